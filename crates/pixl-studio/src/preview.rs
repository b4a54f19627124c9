//! The quick preview shown while a light moves: direct light only, on the coarse scene's first
//! surfaces, at a small size (long side ≤ [`crate::StudioConfig::preview_side`], 128 by default).
//!
//! [`GBuffer::build`] traces one camera ray through each preview pixel's centre once per geometry
//! and keeps the surface point, its shading normal (turned to face the camera) and its albedo
//! (the material's base colour times its texture, linear). [`shade`] then sums, per pixel,
//! `albedo / π · E` over the lights plus `albedo · L_world`, where the irradiance `E` is, in the
//! scene format's units (`pixl_render::scene`), with `ω` the unit vector to the light, `d` its
//! distance and `n` the normal:
//! - point: `power / 4π · colour · max(0, n·ω) / d²`;
//! - spot: the same times Blender's cone mask `smoothstep((cos θ − cos(½·size)) / (blend · (1 −
//!   cos(½·size))))`, `θ` the angle off the spot's axis;
//! - area: `power / π · colour · max(0, −axis·ω) · max(0, n·ω) / d²` (a small Lambertian emitter);
//! - sun: `strength · colour · max(0, −direction·n)`;
//! - world: a constant radiance `strength · colour` seen over the whole hemisphere (no occlusion).
//!
//! With `shadows`, each light's contribution is kept only when a ray from the surface point
//! (offset along the normal, skipping its own triangle) reaches it unoccluded (suns: along `−direction`). The result is
//! displayed like the path-traced render (Reinhard with auto-exposure, sRGB;
//! [`pixl_core::image::tonemap_reinhard`]). Sizes, soft shadows and interreflections are ignored:
//! it is a guide for placing lights, not a render.
use crate::geometry::Coarse;
use pixl_core::Image;
use pixl_render::bvh::Ray;
use pixl_render::geometry::Geometry;
use pixl_render::math::V3;
use pixl_render::scene::{Light, World};
use rayon::prelude::*;
use std::f32::consts::PI;

/// First-hit surface data at the preview size (row-major).
#[derive(Clone, Debug)]
pub struct GBuffer {
    pub width: usize,
    pub height: usize,
    /// The first surface per pixel; `None` where the ray sees only the background.
    pub px: Vec<Option<Surface>>,
}

/// One pixel's first surface.
#[derive(Clone, Copy, Debug)]
pub struct Surface {
    pub point: V3,
    /// Shading normal, facing the camera.
    pub normal: V3,
    /// Linear base colour.
    pub albedo: V3,
    /// The triangle (shadow rays skip it, as the renderer's do).
    pub prim: u32,
}

impl GBuffer {
    /// Traces the preview's camera rays (long side `max_side`, the camera's aspect) against the
    /// coarse scene.
    pub fn build(coarse: &Coarse, max_side: usize) -> GBuffer {
        let cam = &coarse.scene.camera;
        let (w, h) = pixl_model::fullres::working_size(cam.width as usize, cam.height as usize, max_side.max(1));
        let rays = pixl_render::camera::CameraRays::new(cam, w as u32, h as u32);
        let geom = &coarse.geom;
        let px = (0..w * h)
            .into_par_iter()
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let ray = rays.ray(x as f32 + 0.5, y as f32 + 0.5);
                geom.intersect(&ray, 0.0, f32::INFINITY).map(|hit| {
                    let n = if hit.ns.dot(ray.d) > 0.0 { -hit.ns } else { hit.ns };
                    Surface {
                        point: hit.p,
                        normal: n,
                        albedo: albedo(geom, hit.prim, hit.uv),
                        prim: hit.prim,
                    }
                })
            })
            .collect();
        GBuffer {
            width: w,
            height: h,
            px,
        }
    }
}

/// The base colour at a hit (texture times colour; linear).
fn albedo(geom: &Geometry, prim: u32, uv: [f32; 2]) -> V3 {
    let Some(a) = geom.attrs.get(prim as usize) else {
        return V3::splat(0.5);
    };
    let Some(m) = geom.materials.get(a.material as usize) else {
        return V3::splat(0.5);
    };
    match &m.base_tex {
        Some(t) => m.base * t.sample(uv[0], uv[1]),
        None => m.base,
    }
}

fn smoothstep(x: f32) -> f32 {
    let t = x.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Linear radiance of the preview (3 channels; see the module docs).
pub fn shade(g: &GBuffer, geom: &Geometry, lights: &[Light], world: Option<&World>, shadows: bool) -> Image {
    let env = world
        .map(|w| V3::from_arr(w.color.rgb()) * w.strength)
        .unwrap_or(V3::ZERO);
    // Per light, once: its colour (a blackbody integrates a spectrum) and axis.
    let prepared: Vec<(&Light, V3, V3)> = lights
        .iter()
        .map(|l| {
            (
                l,
                V3::from_arr(l.color().rgb()),
                V3::from_arr(l.direction().unwrap_or([0.0, -1.0, 0.0])),
            )
        })
        .collect();
    let mut out = Image::new(g.width, g.height, 3);
    out.data.par_chunks_mut(3).zip(g.px.par_iter()).for_each(|(o, s)| {
        let Some(Surface {
            point: p,
            normal: n,
            albedo: a,
            prim,
        }) = *s
        else {
            o.copy_from_slice(&env.to_arr());
            return;
        };
        // Shadow rays leave the surface's own triangle (skipped) from a point nudged off it.
        let origin = p + n * (1e-4 * (1.0 + p.length()));
        let visible = |d: V3, tmax: f32| {
            if !shadows {
                return true;
            }
            let mut ray = Ray::new(origin, d);
            ray.skip = prim;
            !geom.occluded(&ray, 1e-4, tmax)
        };
        let mut e = V3::ZERO;
        for &(l, c, axis) in &prepared {
            match l {
                Light::Point { position, power, .. } | Light::Spot { position, power, .. } => {
                    let to = V3::from_arr(*position) - p;
                    let d2 = to.dot(to);
                    if d2.is_nan() || d2 <= 1e-12 {
                        continue;
                    }
                    let w = to / d2.sqrt();
                    let cos = n.dot(w);
                    if cos <= 0.0 {
                        continue;
                    }
                    let mut k = power / (4.0 * PI) * cos / d2;
                    if let Light::Spot {
                        spot_size_deg, blend, ..
                    } = l
                    {
                        let cos_half = (0.5 * spot_size_deg.to_radians()).cos();
                        let t = axis.dot(-w);
                        let spread = blend * (1.0 - cos_half);
                        let mask = if t < cos_half {
                            0.0
                        } else if spread > 0.0 {
                            smoothstep((t - cos_half) / spread)
                        } else {
                            1.0
                        };
                        k *= mask;
                    }
                    if k > 0.0 && visible(w, d2.sqrt() * (1.0 - 1e-4)) {
                        e += c * k;
                    }
                }
                Light::Area { position, power, .. } => {
                    let to = V3::from_arr(*position) - p;
                    let d2 = to.dot(to);
                    if d2.is_nan() || d2 <= 1e-12 {
                        continue;
                    }
                    let w = to / d2.sqrt();
                    let k = power / PI * axis.dot(-w).max(0.0) * n.dot(w).max(0.0) / d2;
                    if k > 0.0 && visible(w, d2.sqrt() * (1.0 - 1e-4)) {
                        e += c * k;
                    }
                }
                Light::Sun { strength, .. } => {
                    let w = -axis;
                    let cos = n.dot(w);
                    if cos > 0.0 && visible(w, f32::INFINITY) {
                        e += c * (strength * cos);
                    }
                }
            }
        }
        let r = a * e * (1.0 / PI) + a * env;
        o.copy_from_slice(&r.to_arr());
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_render::scene::{Camera, Color, Material, Object, Scene, Shape, Transform};

    /// A grey wall 2 m in front of the camera, lit by one point light 1 m in front of its
    /// centre: the centre pixel's radiance is `albedo/π · P/(4π) / 1²`.
    #[test]
    fn point_light_on_a_wall_by_hand() {
        let mut s = Scene::new(Camera::new(9, 9, 40.0));
        s.objects.push(Object {
            name: "wall".into(),
            shape: Shape::Quad { size: [10.0, 10.0] },
            transform: Transform {
                translate: [0.0, 0.0, -2.0],
                ..Default::default()
            },
            material: Material::diffuse([0.5, 0.5, 0.5]),
        });
        let coarse = crate::geometry::Coarse::from_scene(&s, "wall").unwrap();
        let g = GBuffer::build(&coarse, 9);
        assert_eq!((g.width, g.height), (9, 9));
        let light = Light::Point {
            name: String::new(),
            position: [0.0, 0.0, -1.0],
            power: 100.0,
            radius: 0.0,
            color: Color::Rgb([1.0, 1.0, 1.0]),
            visible_to_camera: false,
        };
        let img = shade(&g, &coarse.geom, &[light], None, true);
        let want = 0.5 / PI * 100.0 / (4.0 * PI);
        assert!(
            (img.get(4, 4, 0) - want).abs() < 1e-4 * want,
            "{} vs {want}",
            img.get(4, 4, 0)
        );
        // Behind the wall the light is blocked by the wall itself (cos < 0 and occluded).
        let behind = Light::Point {
            name: String::new(),
            position: [0.0, 0.0, -3.0],
            power: 100.0,
            radius: 0.0,
            color: Color::Rgb([1.0, 1.0, 1.0]),
            visible_to_camera: false,
        };
        let dark = shade(&g, &coarse.geom, &[behind], None, true);
        assert_eq!(dark.get(4, 4, 0), 0.0);
        // A sun straight onto the wall: albedo/π · strength.
        let sun = Light::Sun {
            name: String::new(),
            direction: Some([0.0, 0.0, -1.0]),
            strength: 3.0,
            angle_deg: 0.5,
            color: Color::Rgb([1.0, 1.0, 1.0]),
        };
        let lit = shade(&g, &coarse.geom, &[sun], None, true);
        assert!((lit.get(0, 0, 1) - 0.5 / PI * 3.0).abs() < 1e-5);
    }
}
