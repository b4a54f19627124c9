//! The light kinds of the tracer, in Cycles' units, as [`Lights::build`](super::Lights::build)
//! makes them from the scene: each kind's parameters, and what it emits — the world's radiance
//! along a direction ([`Environment::eval`]), a spot's cone mask, an area light's axes. Their
//! definitions and units: the module docs of [`super`].
use super::rect::RectFrame;
use crate::math::V3;
use crate::trace::texture::Texture;
use std::f32::consts::PI;

#[derive(Clone, Debug)]
pub enum LightKind {
    Point {
        p: V3,
        intensity: V3,
        radius: f32,
        /// The sphere is seen by camera rays (needs a radius).
        camera: bool,
    },
    Spot {
        p: V3,
        dir: V3,
        intensity: V3,
        radius: f32,
        cos_half: f32,
        smooth: f32,
        camera: bool,
    },
    Area {
        c: V3,
        ex: V3,
        ey: V3,
        n: V3,
        disk: bool,
        /// Unit edge directions and full edge lengths (for [`RectView`](super::rect::RectView)).
        frame: RectFrame,
        radiance: V3,
        area: f32,
        /// Seen by camera rays (else only by rays that scattered).
        camera: bool,
    },
    Sun {
        dir: V3,
        irradiance: V3,
        cos_max: f32,
        /// Solid angle of the cone (0: a delta light).
        omega: f32,
    },
    Env,
    Tri {
        prim: u32,
        radiance: V3,
    },
}

/// The world: constant radiance or an equirectangular image times a strength.
#[derive(Clone, Debug)]
pub struct Environment {
    pub radiance: V3,
    pub image: Option<Texture>,
    pub rotation: f32,
}

impl Environment {
    /// Radiance arriving from direction `-d` (i.e. seen looking along `d`).
    pub fn eval(&self, d: V3) -> V3 {
        match &self.image {
            None => self.radiance,
            Some(tex) => {
                let (s, c) = (-self.rotation).sin_cos();
                let d = V3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z);
                let u = 0.5 - (-d.z).atan2(d.x) / (2.0 * PI);
                let v = 0.5 + d.y.atan2((d.x * d.x + d.z * d.z).sqrt()) / PI;
                self.radiance * tex.sample(u, 1.0 - v)
            }
        }
    }
}

fn smoothstep(x: f32) -> f32 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

impl LightKind {
    /// A spot light's cone mask for the direction `from_light` (light → shading point,
    /// any length); 1 for every other light.
    pub(super) fn spot_mask(&self, from_light: V3) -> f32 {
        match self {
            LightKind::Spot {
                dir, cos_half, smooth, ..
            } => {
                let cos_a = dir.dot(from_light.normalize());
                if *smooth > 0.0 {
                    smoothstep((cos_a - cos_half) / smooth)
                } else if cos_a > *cos_half {
                    1.0
                } else {
                    0.0
                }
            }
            _ => 1.0,
        }
    }
}

/// The local X axis of an area light travelling along `d` (see module docs).
pub fn area_axes(d: V3) -> (V3, V3) {
    let x = d.cross(V3::new(0.0, 1.0, 0.0));
    let x = if x.length() < 1e-6 {
        V3::new(1.0, 0.0, 0.0)
    } else {
        x.normalize()
    };
    let y = (-d).cross(x).normalize();
    (x, y)
}
