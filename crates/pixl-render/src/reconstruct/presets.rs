//! The five lighting presets of the paper (§4.2): `cool-side-flash`, `warm-overhead-flash`,
//! `dim-overhead-spot`, `soft-frontal-sun`, `warm-interior-sun`.
//!
//! The paper names the presets but not their parameters; these are ours, chosen to read as the
//! names say. Placement is relative to the scene: `c` and `R` are the centre and radius of the
//! bounding sphere of all objects (a 1 m sphere 3 m in front of the camera if there are none),
//! `right`, `fwd` are the camera's +X and viewing axes, `up` is the world +Y. Powers scale with
//! the squared distance so the target irradiance `E` at `c` is the same at any scene scale
//! (`P = 4π·E·D²` for point and spot lights at distance `D`).
//!
//! | preset | lights |
//! |---|---|
//! | `cool-side-flash` | point, 7500 K, at `c + 1.5R·right + 0.3R·up − 0.6R·fwd`, radius `0.05R`, `E = 4 W/m²` |
//! | `warm-overhead-flash` | point, 3200 K, at `c + 1.6R·up − 0.3R·fwd`, radius `0.05R`, `E = 4 W/m²` |
//! | `dim-overhead-spot` | spot, 3000 K, at `c + 1.8R·up − 0.4R·fwd` aimed at `c`, 35° cone, blend 0.3, `E = 1.5 W/m²` |
//! | `soft-frontal-sun` | sun, 5500 K, from behind and above the camera (travelling `fwd − 0.6·up`), 15° wide, 3 W/m² |
//! | `warm-interior-sun` | sun, 3500 K, low and from the side (travelling `−0.9·right − 0.45·up + 0.3·fwd`), 2° wide, 5 W/m² |
use crate::error::{RenderError, Result};
use crate::math::V3;
use crate::scene::{Color, Light, Scene};
use crate::trace::geometry::shape_mesh;

/// The preset names, in the paper's order.
pub const PRESETS: &[&str] = &[
    "cool-side-flash",
    "warm-overhead-flash",
    "dim-overhead-spot",
    "soft-frontal-sun",
    "warm-interior-sun",
];

/// Axis-aligned bounds of all objects in world space (meshes are loaded), `None` if empty.
pub fn scene_bounds(scene: &Scene) -> Result<Option<([f32; 3], [f32; 3])>> {
    let mut lo = V3::splat(f32::INFINITY);
    let mut hi = V3::splat(f32::NEG_INFINITY);
    for obj in &scene.objects {
        let mesh = shape_mesh(scene, &obj.shape)?;
        let m = obj.transform.to_matrix();
        for p in &mesh.positions {
            let q = V3::new(
                m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2] + m[0][3],
                m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2] + m[1][3],
                m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2] + m[2][3],
            );
            if q.is_finite() {
                lo = lo.min(q);
                hi = hi.max(q);
            }
        }
    }
    Ok(if lo.x <= hi.x {
        Some((lo.to_arr(), hi.to_arr()))
    } else {
        None
    })
}

/// The lights of preset `name` for `scene` (see the module table).
pub fn preset_lights(scene: &Scene, name: &str) -> Result<Vec<Light>> {
    let (o, right, _up_cam, back) = scene.camera.frame();
    let (o, right, fwd) = (V3::from_arr(o), V3::from_arr(right), -V3::from_arr(back));
    let up = V3::new(0.0, 1.0, 0.0);
    let (c, r) = match scene_bounds(scene)? {
        Some((lo, hi)) => {
            let (lo, hi) = (V3::from_arr(lo), V3::from_arr(hi));
            ((lo + hi) * 0.5, ((hi - lo) * 0.5).length().max(1e-3))
        }
        None => (o + fwd * 3.0, 1.0),
    };
    let named = |s: &str| format!("{name}/{s}");
    let point = |pos: V3, kelvin: f32, e: f32, light: &str| {
        let d = (pos - c).length();
        Light::Point {
            name: named(light),
            position: pos.to_arr(),
            power: 4.0 * std::f32::consts::PI * e * d * d,
            radius: 0.05 * r,
            color: Color::Blackbody { kelvin },
            visible_to_camera: false,
        }
    };
    let lights = match name {
        "cool-side-flash" => vec![point(
            c + right * (1.5 * r) + up * (0.3 * r) - fwd * (0.6 * r),
            7500.0,
            4.0,
            "flash",
        )],
        "warm-overhead-flash" => vec![point(c + up * (1.6 * r) - fwd * (0.3 * r), 3200.0, 4.0, "flash")],
        "dim-overhead-spot" => {
            let pos = c + up * (1.8 * r) - fwd * (0.4 * r);
            let d = (pos - c).length();
            vec![Light::Spot {
                name: named("spot"),
                position: pos.to_arr(),
                direction: None,
                look_at: Some(c.to_arr()),
                power: 4.0 * std::f32::consts::PI * 1.5 * d * d,
                spot_size_deg: 35.0,
                blend: 0.3,
                radius: 0.02 * r,
                color: Color::Blackbody { kelvin: 3000.0 },
                visible_to_camera: false,
            }]
        }
        "soft-frontal-sun" => vec![Light::Sun {
            name: named("sun"),
            direction: Some((fwd - up * 0.6).normalize().to_arr()),
            strength: 3.0,
            angle_deg: 15.0,
            color: Color::Blackbody { kelvin: 5500.0 },
        }],
        "warm-interior-sun" => vec![Light::Sun {
            name: named("sun"),
            direction: Some((right * -0.9 - up * 0.45 + fwd * 0.3).normalize().to_arr()),
            strength: 5.0,
            angle_deg: 2.0,
            color: Color::Blackbody { kelvin: 3500.0 },
        }],
        _ => {
            return Err(RenderError::UnknownPreset {
                name: name.to_string(),
                known: PRESETS.join(", "),
            })
        }
    };
    Ok(lights)
}

/// Adds preset `name`'s lights to `scene`, replacing its existing lights when `replace`.
pub fn apply_preset(scene: &mut Scene, name: &str, replace: bool) -> Result<()> {
    let lights = preset_lights(scene, name)?;
    if replace {
        scene.lights.clear();
    }
    scene.lights.extend(lights);
    scene.validate()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Camera, Material, Object, Shape, Transform};

    fn scene() -> Scene {
        let mut cam = Camera::new(32, 24, 50.0);
        cam.position = [0.0, 1.0, 6.0];
        cam.look_at = Some([0.0, 1.0, 0.0]);
        let mut s = Scene::new(cam);
        s.objects.push(Object {
            name: "box".into(),
            shape: Shape::Cuboid { size: [2.0, 2.0, 2.0] },
            transform: Transform {
                translate: [0.0, 1.0, 0.0],
                ..Default::default()
            },
            material: Material::default(),
        });
        s
    }

    #[test]
    fn every_preset_applies_and_point_power_gives_target_irradiance() {
        for name in PRESETS {
            let mut s = scene();
            apply_preset(&mut s, name, true).unwrap();
            assert!(!s.lights.is_empty(), "{name}");
            apply_preset(&mut s, name, false).unwrap();
            assert_eq!(s.lights.len() % 2, 0);
        }
        let mut s = scene();
        apply_preset(&mut s, "warm-overhead-flash", true).unwrap();
        // Irradiance facing the light at the box centre (0, 1, 0): P / (4π d²) = 4 W/m².
        if let Light::Point { position, power, .. } = &s.lights[0] {
            let d2: f32 = position
                .iter()
                .zip([0.0, 1.0, 0.0])
                .map(|(a, b)| (a - b) * (a - b))
                .sum();
            let e = power / (4.0 * std::f32::consts::PI * d2);
            assert!((e - 4.0).abs() < 1e-3, "{e}");
            assert!(position[1] > 2.0, "overhead: {position:?}");
        } else {
            panic!("expected a point light");
        }
        let e = apply_preset(&mut scene(), "disco", true).unwrap_err().to_string();
        assert!(e.contains("disco") && e.contains("cool-side-flash"), "{e}");
    }
}
