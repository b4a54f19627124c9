//! [`Lights`]: every light of a scene — its analytic lights, the world and its emissive
//! triangles — built once per render, and what a ray leaving the camera or a surface finds of
//! them: the world's radiance, the cone of a wide sun, the area and sphere lights on its way
//! (lights do not occlude). Choosing one light per shading point is `pick.rs`'s, sampling it
//! `sample.rs`'s.
use super::env::{env_harmonics, env_peak_share, EnvSampler};
use super::kinds::{area_axes, Environment, LightKind};
use super::rect::RectFrame;
use super::sample::SphereCone;
use crate::error::Result;
use crate::math::V3;
use crate::scene::{AreaShape, Light, Scene};
use crate::trace::bvh::Ray;
use crate::trace::geometry::Geometry;
use crate::trace::sampling::Distribution1D;
use crate::trace::texture::Texture;
use std::f32::consts::PI;

pub struct Lights {
    pub lights: Vec<LightKind>,
    /// Scene-wide power estimate of every light (the floor of the per-point choice).
    pub(super) base: Distribution1D,
    /// Lights `0..analytic` are the scene's lights and the world; the rest emissive triangles.
    pub(super) analytic: usize,
    /// Luminance per light (for the per-point weights): point / spot intensity, area radiance,
    /// sun irradiance; unused for the world and triangles.
    pub(super) lum: Vec<f32>,
    /// Emissive triangles: power distribution among them, their summed power weight, their
    /// bounding sphere and total power (luminance).
    pub(super) tri_dist: Distribution1D,
    pub(super) tri_base: f32,
    pub(super) tri_bounds: (V3, f32),
    pub(super) tri_power: f32,
    pub env: Option<Environment>,
    pub(super) env_index: Option<usize>,
    pub(super) env_sampler: Option<EnvSampler>,
    /// The world's luminance to first order: mean radiance `a` and `b` of `L(ω) ≈ a + b·ω`.
    pub(super) env_sh: (f32, V3),
    /// Share of the world's light above its mean radiance, `∫ max(0, L − L̄) / ∫ L` (0 for a
    /// constant world): the part light sampling is needed for (see [`Lights::item_weight`]).
    pub(super) env_peaked: f32,
    area_indices: Vec<usize>,
    /// Suns with an angular size (hit by rays that escape).
    sun_indices: Vec<usize>,
    /// Point and spot lights with a radius (spheres, hit by BSDF rays).
    sphere_indices: Vec<usize>,
    /// The one pick item besides a constant world, if there is only one
    /// ([`Lights::single_item`]).
    pub(super) single: Option<usize>,
}

impl Lights {
    /// Collects the scene's lights and marks emissive triangles in `geom`.
    pub fn build(scene: &Scene, geom: &mut Geometry) -> Result<Lights> {
        let (_, radius) = geom.bounding_sphere();
        let mut lights = Vec::new();
        let mut power = Vec::new();
        let mut area_indices = Vec::new();
        let mut sun_indices = Vec::new();
        let mut sphere_indices = Vec::new();
        let mut lum = Vec::new();
        for l in &scene.lights {
            let color = V3::from_arr(l.color().rgb());
            let dir = l
                .direction()
                .map(V3::from_arr)
                .unwrap_or(V3::new(0.0, -1.0, 0.0))
                .normalize();
            match l {
                Light::Point {
                    position,
                    power: p,
                    radius,
                    visible_to_camera,
                    ..
                } => {
                    let intensity = color * (*p / (4.0 * PI));
                    if *radius > 0.0 {
                        sphere_indices.push(lights.len());
                    }
                    lights.push(LightKind::Point {
                        p: V3::from_arr(*position),
                        intensity,
                        radius: *radius,
                        camera: *visible_to_camera && *radius > 0.0,
                    });
                    power.push(p * color.luminance());
                    lum.push(intensity.luminance());
                }
                Light::Spot {
                    position,
                    power: p,
                    spot_size_deg,
                    blend,
                    radius,
                    visible_to_camera,
                    ..
                } => {
                    let intensity = color * (*p / (4.0 * PI));
                    let cos_half = (0.5 * spot_size_deg.to_radians()).cos();
                    let smooth = (1.0 - cos_half) * blend;
                    if *radius > 0.0 {
                        sphere_indices.push(lights.len());
                    }
                    lights.push(LightKind::Spot {
                        p: V3::from_arr(*position),
                        dir,
                        intensity,
                        radius: *radius,
                        cos_half,
                        smooth,
                        camera: *visible_to_camera && *radius > 0.0,
                    });
                    power.push(p * color.luminance());
                    lum.push(intensity.luminance());
                }
                Light::Area {
                    position,
                    shape,
                    power: p,
                    visible_to_camera,
                    ..
                } => {
                    let (sx, sy) = l.area_size().unwrap_or((1.0, 1.0));
                    let disk = matches!(shape, AreaShape::Disk | AreaShape::Ellipse);
                    let area = if disk { PI * 0.25 * sx * sy } else { sx * sy };
                    let (x, y) = area_axes(dir);
                    area_indices.push(lights.len());
                    lights.push(LightKind::Area {
                        c: V3::from_arr(*position),
                        ex: x * (0.5 * sx),
                        ey: y * (0.5 * sy),
                        n: dir,
                        disk,
                        frame: RectFrame::new(x * sx, y * sy),
                        radiance: color * (*p / (PI * area)),
                        area,
                        camera: *visible_to_camera,
                    });
                    power.push(p * color.luminance());
                    lum.push((color * (*p / (PI * area))).luminance());
                }
                Light::Sun {
                    strength, angle_deg, ..
                } => {
                    let cos_max = (0.5 * angle_deg.to_radians()).cos().min(1.0 - 1e-7);
                    // Ω of exactly the cone that is sampled and hit-tested (`cos ≥ cos_max`, in
                    // f32). Below ~0.16° (1 − cos_max < 4e-6) a direction's rounding (~1e-7) is
                    // no longer small against the cone, so such a sun stays a delta light.
                    let one_minus = 1.0 - cos_max as f64;
                    let omega = if one_minus >= 4e-6 {
                        sun_indices.push(lights.len());
                        (2.0 * std::f64::consts::PI * one_minus) as f32
                    } else {
                        0.0
                    };
                    lights.push(LightKind::Sun {
                        dir,
                        irradiance: color * *strength,
                        cos_max,
                        omega,
                    });
                    power.push(strength * color.luminance() * PI * radius * radius);
                    lum.push((color * *strength).luminance());
                }
            }
        }
        let mut env = None;
        let mut env_index = None;
        let mut env_sampler = None;
        let mut env_sh = (0.0, V3::ZERO);
        let mut env_peaked = 0.0;
        if let Some(w) = &scene.world {
            let image = match &w.image {
                Some(p) => Some(Texture::load_color(&scene.resolve(p))?),
                None => None,
            };
            let radiance = match image {
                Some(_) => V3::splat(w.strength),
                None => V3::from_arr(w.color.rgb()) * w.strength,
            };
            let mean = match &image {
                Some(t) => {
                    let img = t.image();
                    let n = (img.width * img.height).max(1) as f32;
                    img.data
                        .chunks_exact(3)
                        .fold(V3::ZERO, |a, p| a + V3::new(p[0], p[1], p[2]))
                        / n
                }
                None => V3::ONE,
            };
            let e = Environment {
                radiance,
                image,
                rotation: w.rotation_deg.to_radians(),
            };
            let lum_mean = (radiance * mean).luminance();
            if lum_mean > 0.0 {
                env_index = Some(lights.len());
                lights.push(LightKind::Env);
                power.push(2.0 * PI * PI * radius * radius * lum_mean);
                lum.push(lum_mean);
                match &e.image {
                    Some(tex) => {
                        env_sampler = EnvSampler::new(tex, e.rotation);
                        env_sh = env_harmonics(tex, e.rotation, radiance.luminance());
                        env_peaked = env_peak_share(tex);
                    }
                    None => env_sh = (lum_mean, V3::ZERO),
                }
            }
            env = Some(e);
        }
        let analytic = lights.len();
        let mut tri_power = Vec::new();
        let (mut lo, mut hi) = (V3::splat(f32::INFINITY), V3::splat(f32::NEG_INFINITY));
        for (prim, a) in geom.attrs.iter_mut().enumerate() {
            let em = geom.materials[a.material as usize].emission;
            if em.max_comp() > 0.0 {
                a.light = lights.len() as u32;
                lights.push(LightKind::Tri {
                    prim: prim as u32,
                    radiance: em,
                });
                let tri = &geom.tris[prim];
                for q in [tri.point(0.0, 0.0), tri.point(1.0, 0.0), tri.point(0.0, 1.0)] {
                    lo = lo.min(q);
                    hi = hi.max(q);
                }
                let w = 2.0 * PI * a.area * em.luminance();
                power.push(w);
                tri_power.push(w);
            }
        }
        let base = Distribution1D::new(&power);
        let tri_dist = Distribution1D::new(&tri_power);
        let tri_base = (analytic..lights.len()).map(|i| base.pmf(i)).sum();
        let tri_bounds = if tri_power.is_empty() {
            (V3::ZERO, 0.0)
        } else {
            ((lo + hi) * 0.5, (hi - lo).length() * 0.5)
        };
        let mut lights = Lights {
            lights,
            base,
            analytic,
            lum,
            tri_base,
            tri_bounds,
            tri_power: tri_dist.total,
            tri_dist,
            env,
            env_index,
            env_sampler,
            env_sh,
            env_peaked,
            area_indices,
            sun_indices,
            sphere_indices,
            single: None,
        };
        lights.single = lights.find_single_item();
        Ok(lights)
    }

    pub fn is_empty(&self) -> bool {
        self.base.is_empty()
    }

    /// The world's radiance along `d`.
    #[inline]
    pub fn env_hit(&self, d: V3) -> Option<V3> {
        Some(self.env.as_ref()?.eval(d))
    }

    /// Suns with a cone (see the module docs) a ray escaping the scene along `d` sees: calls
    /// `f(radiance, light, direction_pdf)` for each (the pdf without the pick probability).
    #[inline(always)]
    pub fn sun_hits(&self, d: V3, mut f: impl FnMut(V3, usize, f32)) {
        for &i in &self.sun_indices {
            if let LightKind::Sun {
                dir,
                irradiance,
                cos_max,
                omega,
            } = &self.lights[i]
            {
                if -d.dot(*dir) >= *cos_max {
                    f(*irradiance / *omega, i, 1.0 / *omega);
                }
            }
        }
    }

    /// Area and sphere lights hit by `ray` before `tmax`: calls `f(radiance, light,
    /// direction_pdf, t)` for each, the pdf without the pick probability, for area lights the
    /// pdf of sampling by area (see [`Lights::area_dir_pdf`]) (lights do not occlude, so every
    /// one on the way counts).
    #[inline(always)]
    pub fn area_hits(&self, ray: &Ray, tmax: f32, f: impl FnMut(V3, usize, f32, f32)) {
        self.area_hits_if(ray, tmax, false, f)
    }

    /// [`Lights::area_hits`] for a camera ray: only the area and sphere lights visible to the
    /// camera (the pdf passed to `f` is then meaningless: no MIS at the camera).
    #[inline(always)]
    pub fn camera_area_hits(&self, ray: &Ray, tmax: f32, f: impl FnMut(V3, usize, f32, f32)) {
        self.area_hits_if(ray, tmax, true, f)
    }

    #[inline(always)]
    fn area_hits_if(&self, ray: &Ray, tmax: f32, camera_ray: bool, mut f: impl FnMut(V3, usize, f32, f32)) {
        for &i in &self.area_indices {
            if let LightKind::Area {
                c,
                ex,
                ey,
                n,
                disk,
                radiance,
                area,
                camera,
                ..
            } = &self.lights[i]
            {
                if camera_ray && !camera {
                    continue;
                }
                let denom = ray.d.dot(*n);
                if denom >= 0.0 {
                    continue; // back side or parallel: one-sided emitter
                }
                let t = (*c - ray.o).dot(*n) / denom;
                if !(t > 1e-5 && t < tmax) {
                    continue;
                }
                let q = ray.o + ray.d * t - *c;
                let a = q.dot(*ex) / ex.dot(*ex);
                let b = q.dot(*ey) / ey.dot(*ey);
                let inside = if *disk {
                    a * a + b * b <= 1.0
                } else {
                    a.abs() <= 1.0 && b.abs() <= 1.0
                };
                if inside {
                    f(*radiance, i, t * t / (-denom * area), t);
                }
            }
        }
        for &i in &self.sphere_indices {
            let light = &self.lights[i];
            let (LightKind::Point {
                p: c,
                intensity,
                radius,
                camera,
            }
            | LightKind::Spot {
                p: c,
                intensity,
                radius,
                camera,
                ..
            }) = light
            else {
                continue;
            };
            if camera_ray && !camera {
                continue;
            }
            let oc = ray.o - *c;
            let b = oc.dot(ray.d);
            let disc = b * b - (oc.dot(oc) - radius * radius);
            if disc < 0.0 {
                continue;
            }
            let t = -b - disc.sqrt();
            if !(t > 1e-5 && t < tmax) {
                continue;
            }
            let mask = light.spot_mask(oc);
            if !(mask > 0.0) {
                continue;
            }
            let radiance = *intensity / (PI * radius * radius) * mask;
            if camera_ray {
                // The camera sees the sphere wherever its rays hit it (no MIS to match).
                f(radiance, i, 0.0, t);
                continue;
            }
            // Only where light sampling samples the sphere as a cone (else it is a point).
            let Some(cone) = SphereCone::new(*c, *radius, ray.o) else {
                continue;
            };
            f(radiance, i, 1.0 / cone.omega, t);
        }
    }
}
