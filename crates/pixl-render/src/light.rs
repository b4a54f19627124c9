//! Lights for the tracer, in Cycles' units (see [`crate::scene`]): point, spot, area
//! (rectangle / disk), sun, the world, and emissive triangles. One light is picked per shading
//! point in proportion to an estimate of its power; the sample returns the incident radiance
//! (or, for delta lights, the radiance-equivalent `I/d²` or irradiance) and the pdf including
//! the pick probability.
//!
//! - Point: intensity `I = P·color / 4π`. With a radius `r` it is a sphere, as in Cycles: seen as
//!   a disk of radiance `I / (π r²)` (the same irradiance `I cos θ / d²` wherever the sphere is
//!   wholly above the horizon), light-sampled uniformly in the cone it subtends and hit by BSDF
//!   rays; when that cone is too narrow for f32 (`1 − cos θmax < 1e-5`) or the shading point is
//!   inside, the sample point is jittered on a facing disk of the radius (light sampling only).
//! - Spot: point intensity (a sphere with a radius, as above) masked by
//!   `smoothstep(0, 1, (cos θ − cos(size/2)) / ((1 − cos(size/2))·blend))`
//!   (hard edge for `blend = 0`), not renormalised to the cone.
//! - Area: one-sided Lambertian, radiance `P·color / (π A)`, emitting along its direction; its
//!   local X (`size`) is `normalize(d × Y)` (or +X when `d ∥ Y`), local Y is `(−d) × X`.
//! - Sun: irradiance `strength·color` on a surface facing it; with an angular diameter of at
//!   least ~0.16° (Blender's default is 0.526°) a cone of uniform radiance `E / Ω` (`Ω = 2π(1 −
//!   cos(angle/2))`, directions sampled uniformly in it), below that a delta light of
//!   irradiance `E` (directions still spread over the cone).
//! - World: radiance `strength·color` (× texel), sampled uniformly over the sphere.
//! - Emissive triangles: two-sided, radiance = the material's emission, sampled by area.
//!
//! Point and spot lights without a radius, and a sun below ~0.16°, are invisible to camera and BSDF
//! rays (delta lights, sampled only by next-event estimation). Area lights, sphere (point / spot
//! with a radius) lights, emissive triangles, the world and a wider sun are hit by BSDF
//! rays (the sun only by rays that escape the scene, as
//! in Cycles — so smooth glass and mirrors show its glint) and combined with light sampling by
//! MIS (power heuristic). No light is seen by camera rays except emissive triangles, the
//! world, and area and sphere (point / spot with a radius) lights marked `visible_to_camera`
//! (sphere lights then show their radiance `I / (π r²)`, spot-masked, wherever a camera ray
//! hits the sphere, as in Cycles). Lights do not occlude.
use crate::bvh::Ray;
use crate::error::Result;
use crate::geometry::Geometry;
use crate::math::{Frame, V3};
use crate::sampling::{concentric_disk, uniform_cone, uniform_sphere, uniform_triangle, Distribution1D};
use crate::scene::{AreaShape, Light, Scene};
use crate::texture::Texture;
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

/// A light sample at a shading point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Incident radiance (delta lights: `I/d²` or irradiance), before the BSDF.
    pub li: V3,
    pub wi: V3,
    /// Distance to the sampled point (`INFINITY` for sun and world).
    pub dist: f32,
    /// Solid-angle pdf including the pick probability (delta lights: the pick probability).
    pub pdf: f32,
    pub delta: bool,
}

pub struct Lights {
    pub lights: Vec<LightKind>,
    dist: Distribution1D,
    pub env: Option<Environment>,
    env_index: Option<usize>,
    area_indices: Vec<usize>,
    /// Suns with an angular size (hit by rays that escape).
    sun_indices: Vec<usize>,
    /// Point and spot lights with a radius (spheres, hit by BSDF rays).
    sphere_indices: Vec<usize>,
}

fn smoothstep(x: f32) -> f32 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

/// The cone a sphere light of centre `c` and radius `r` subtends from `x`, when it is worth
/// sampling as one: `x` outside the sphere and the cone not so narrow that `1 − cos θmax` is
/// lost in f32 (then the light is treated as a point, by light sampling alone).
struct SphereCone {
    /// Unit direction from `x` to the centre, and the distance.
    axis: V3,
    dist: f32,
    cos_max: f32,
    /// Solid angle `2π (1 − cos θmax)`.
    omega: f32,
}

impl SphereCone {
    fn new(c: V3, r: f32, x: V3) -> Option<SphereCone> {
        if !(r > 0.0) {
            return None;
        }
        let to = c - x;
        let dist = to.length();
        if !(dist > r * 1.0001) {
            return None;
        }
        let sin2 = (r / dist) * (r / dist);
        let cos_max = (1.0 - sin2).max(0.0).sqrt();
        // 1 − cos θmax = sin² / (1 + cos), without cancellation.
        let one_minus = sin2 / (1.0 + cos_max);
        if one_minus < 1e-5 {
            return None;
        }
        Some(SphereCone {
            axis: to / dist,
            dist,
            cos_max,
            omega: 2.0 * PI * one_minus,
        })
    }
}

impl LightKind {
    /// A spot light's cone mask for the direction `from_light` (light → shading point,
    /// any length); 1 for every other light.
    fn spot_mask(&self, from_light: V3) -> f32 {
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

impl Lights {
    /// Collects the scene's lights and marks emissive triangles in `geom`.
    pub fn build(scene: &Scene, geom: &mut Geometry) -> Result<Lights> {
        let (_, radius) = geom.bounding_sphere();
        let mut lights = Vec::new();
        let mut power = Vec::new();
        let mut area_indices = Vec::new();
        let mut sun_indices = Vec::new();
        let mut sphere_indices = Vec::new();
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
                        radiance: color * (*p / (PI * area)),
                        area,
                        camera: *visible_to_camera,
                    });
                    power.push(p * color.luminance());
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
                }
            }
        }
        let mut env = None;
        let mut env_index = None;
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
            let lum = (radiance * mean).luminance();
            if lum > 0.0 {
                env_index = Some(lights.len());
                lights.push(LightKind::Env);
                power.push(2.0 * PI * PI * radius * radius * lum);
            }
            env = Some(e);
        }
        for (prim, a) in geom.attrs.iter_mut().enumerate() {
            let em = geom.materials[a.material as usize].emission;
            if em.max_comp() > 0.0 {
                a.light = lights.len() as u32;
                lights.push(LightKind::Tri {
                    prim: prim as u32,
                    radiance: em,
                });
                power.push(2.0 * PI * a.area * em.luminance());
            }
        }
        let dist = Distribution1D::new(&power);
        Ok(Lights {
            lights,
            dist,
            env,
            env_index,
            area_indices,
            sun_indices,
            sphere_indices,
        })
    }

    pub fn is_empty(&self) -> bool {
        self.dist.is_empty()
    }

    /// Probability of picking light `i`.
    pub fn pick_pmf(&self, i: usize) -> f32 {
        self.dist.pmf(i)
    }

    /// Samples one light for the shading point `p`.
    #[inline(always)]
    pub fn sample(&self, geom: &Geometry, p: V3, u_pick: f32, u1: f32, u2: f32) -> Option<LightSample> {
        if self.dist.is_empty() {
            return None;
        }
        let (i, _) = self.dist.sample(u_pick);
        let pick = self.dist.pmf(i);
        if pick <= 0.0 {
            return None;
        }
        let towards = |q: V3| {
            let d = q - p;
            let dist = d.length();
            (d / dist, dist)
        };
        match &self.lights[i] {
            LightKind::Point {
                p: lp,
                intensity,
                radius,
                ..
            }
            | LightKind::Spot {
                p: lp,
                intensity,
                radius,
                ..
            } => {
                let light = &self.lights[i];
                let mask = light.spot_mask(p - *lp);
                if mask <= 0.0 {
                    return None;
                }
                if let Some(cone) = SphereCone::new(*lp, *radius, p) {
                    // A sphere light: a direction uniform in the cone it subtends.
                    let wi = Frame::new(cone.axis).to_world(uniform_cone(u1, u2, cone.cos_max));
                    let b = cone.dist * wi.dot(cone.axis);
                    let dist = b - (radius * radius - (cone.dist * cone.dist - b * b)).max(0.0).sqrt();
                    return Some(LightSample {
                        li: *intensity / (PI * radius * radius) * mask,
                        wi,
                        dist,
                        pdf: pick / cone.omega,
                        delta: false,
                    });
                }
                // A point (or a sphere too small or too close to sample as one): the position
                // jittered on a disk of the radius facing the shading point.
                let mut q = *lp;
                if *radius > 0.0 {
                    let f = Frame::new((p - *lp).normalize());
                    let (dx, dy) = concentric_disk(u1, u2);
                    q = q + f.t * (dx * radius) + f.b * (dy * radius);
                }
                let (wi, dist) = towards(q);
                if !(dist > 0.0) {
                    return None;
                }
                Some(LightSample {
                    li: *intensity / (dist * dist) * mask,
                    wi,
                    dist,
                    pdf: pick,
                    delta: true,
                })
            }
            LightKind::Area {
                c,
                ex,
                ey,
                n,
                disk,
                radiance,
                area,
                ..
            } => {
                let (a, b) = if *disk {
                    concentric_disk(u1, u2)
                } else {
                    (2.0 * u1 - 1.0, 2.0 * u2 - 1.0)
                };
                let q = *c + *ex * a + *ey * b;
                let (wi, dist) = towards(q);
                let cos_l = -wi.dot(*n);
                if !(cos_l > 0.0 && dist > 0.0) {
                    return None;
                }
                Some(LightSample {
                    li: *radiance,
                    wi,
                    dist,
                    pdf: pick * dist * dist / (cos_l * area),
                    delta: false,
                })
            }
            LightKind::Sun {
                dir,
                irradiance,
                cos_max,
                omega,
            } => {
                let f = Frame::new(-*dir);
                let wi = f.to_world(uniform_cone(u1, u2, *cos_max));
                let (li, pdf, delta) = if *omega > 0.0 {
                    (*irradiance / *omega, pick / *omega, false)
                } else {
                    (*irradiance, pick, true)
                };
                Some(LightSample {
                    li,
                    wi,
                    dist: f32::INFINITY,
                    pdf,
                    delta,
                })
            }
            LightKind::Env => {
                let env = self.env.as_ref()?;
                let wi = uniform_sphere(u1, u2);
                Some(LightSample {
                    li: env.eval(wi),
                    wi,
                    dist: f32::INFINITY,
                    pdf: pick / (4.0 * PI),
                    delta: false,
                })
            }
            LightKind::Tri { prim, radiance } => {
                let tri = &geom.tris[*prim as usize];
                let (b1, b2) = uniform_triangle(u1, u2);
                let q = tri.point(b1, b2);
                let a = &geom.attrs[*prim as usize];
                let (wi, dist) = towards(q);
                let cos_l = wi.dot(a.ng).abs();
                if !(cos_l > 0.0 && dist > 0.0) {
                    return None;
                }
                Some(LightSample {
                    li: *radiance,
                    wi,
                    dist,
                    pdf: pick * dist * dist / (cos_l * a.area),
                    delta: false,
                })
            }
        }
    }

    /// The world's radiance along `d` and the light-sampling pdf of that direction.
    #[inline]
    pub fn env_hit(&self, d: V3) -> Option<(V3, f32)> {
        let env = self.env.as_ref()?;
        let pdf = self.env_index.map(|i| self.dist.pmf(i) / (4.0 * PI)).unwrap_or(0.0);
        Some((env.eval(d), pdf))
    }

    /// Suns with a cone (see the module docs) a ray escaping the scene along `d` sees: calls `f(radiance,
    /// light_pdf)` for each.
    #[inline(always)]
    pub fn sun_hits(&self, d: V3, mut f: impl FnMut(V3, f32)) {
        for &i in &self.sun_indices {
            if let LightKind::Sun {
                dir,
                irradiance,
                cos_max,
                omega,
            } = &self.lights[i]
            {
                if -d.dot(*dir) >= *cos_max {
                    f(*irradiance / *omega, self.dist.pmf(i) / *omega);
                }
            }
        }
    }

    /// Light-sampling pdf (solid angle) of an emissive triangle hit at distance `t` with
    /// `|cos|` between the ray and its normal.
    pub fn tri_pdf(&self, geom: &Geometry, prim: u32, t: f32, cos_l: f32) -> f32 {
        let a = &geom.attrs[prim as usize];
        if a.light == u32::MAX || cos_l <= 0.0 {
            return 0.0;
        }
        self.dist.pmf(a.light as usize) * t * t / (cos_l * a.area)
    }

    /// Area and sphere lights hit by `ray` before `tmax`: calls `f(radiance, light_pdf, t)`
    /// for each (lights do not occlude, so every one on the way counts).
    #[inline(always)]
    pub fn area_hits(&self, ray: &Ray, tmax: f32, f: impl FnMut(V3, f32, f32)) {
        self.area_hits_if(ray, tmax, false, f)
    }

    /// [`Lights::area_hits`] for a camera ray: only the area and sphere lights visible to the
    /// camera (the light pdf passed to `f` is then meaningless: no MIS at the camera).
    #[inline(always)]
    pub fn camera_area_hits(&self, ray: &Ray, tmax: f32, f: impl FnMut(V3, f32, f32)) {
        self.area_hits_if(ray, tmax, true, f)
    }

    #[inline(always)]
    fn area_hits_if(&self, ray: &Ray, tmax: f32, camera_ray: bool, mut f: impl FnMut(V3, f32, f32)) {
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
                    let pdf = self.dist.pmf(i) * t * t / (-denom * area);
                    f(*radiance, pdf, t);
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
                f(radiance, 0.0, t);
                continue;
            }
            // Only where light sampling samples the sphere as a cone (else it is a point).
            let Some(cone) = SphereCone::new(*c, *radius, ray.o) else {
                continue;
            };
            f(radiance, self.dist.pmf(i) / cone.omega, t);
        }
    }
}
