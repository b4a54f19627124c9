//! Placing lights the way a person describes them: "on that spot of the photo", "from the
//! left", "30° to the right and 45° up" — turned into positions and directions in the scene.
//!
//! Frame ([`SceneFrame`]): metres; the scene's bounds (all objects, meshes loaded) give a centre
//! `c` and a radius `R` (half the diagonal; a 1 m sphere 3 m in front of the camera when the
//! scene is empty, as the presets do). Directions are taken around the world's vertical:
//! `up` = +Y; `forward` = the camera's viewing direction projected onto the horizontal plane;
//! `right` = `forward × up`. For a scene from `pixl reconstruct` (camera at the origin looking
//! down −Z, +Y up) these are the camera's own axes: +X right, +Y up, −Z forward.
//!
//! - [`Side`] / [`toward`]: the unit vector from `c` toward the light for an azimuth and an
//!   elevation in degrees. Azimuth 0° is the camera's side (the light is in front of the scene,
//!   lighting what the camera sees), +90° the right, ±180° behind the scene (backlight), −90°
//!   the left; elevation 0° is level with `c`, +90° straight above. `Side::Front` … `Side::Below`
//!   name the six axis directions.
//! - [`SceneFrame::around`]: `c + distance · toward(az, el)`; [`SceneFrame::default_distance`]
//!   is `1.5 R` (the presets place their lights at 1.5–1.8 R).
//! - [`pick_pixel`]: the surface seen through a pixel of the scene's camera (the photo's pixel,
//!   for a reconstructed scene), traced with the renderer's own intersection code; its normal is
//!   turned to face the camera. [`SceneFrame::default_offset`] (`0.15 ×` the bounds' diagonal) is
//!   how far along that normal a light "at the pixel" is pushed off the surface.
//! - [`power_for_irradiance`]: the power that gives irradiance `E` (W/m²) at distance `d` on a
//!   surface facing the light (point and spot `4π E d²`, area `π E d²` on its axis, sun `E`).
use crate::error::{RenderError, Result};
use crate::math::V3;
use crate::reconstruct::presets::scene_bounds;
use crate::scene::Scene;
use crate::trace::bvh::Ray;
use crate::trace::camera::CameraRays;
use crate::trace::geometry::Geometry;

/// The six directions a person names, as (azimuth, elevation) in degrees.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Side {
    Left,
    Right,
    Above,
    Below,
    Front,
    Behind,
}

impl Side {
    /// Every side and its name, in a fixed order.
    pub const ALL: [(Side, &'static str); 6] = [
        (Side::Left, "left"),
        (Side::Right, "right"),
        (Side::Above, "above"),
        (Side::Below, "below"),
        (Side::Front, "front"),
        (Side::Behind, "behind"),
    ];

    /// Parses a side's name (`left`, `right`, `above`, `below`, `front`, `behind`).
    pub fn parse(name: &str) -> Option<Side> {
        Side::ALL.iter().find(|(_, n)| *n == name).map(|(s, _)| *s)
    }

    /// `(azimuth, elevation)` in degrees (see the module docs).
    pub fn azimuth_elevation(self) -> (f32, f32) {
        match self {
            Side::Front => (0.0, 0.0),
            Side::Right => (90.0, 0.0),
            Side::Behind => (180.0, 0.0),
            Side::Left => (-90.0, 0.0),
            Side::Above => (0.0, 90.0),
            Side::Below => (0.0, -90.0),
        }
    }
}

/// Where the scene is, seen from its camera (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SceneFrame {
    /// Bounds of all objects (`lo`, `hi`), or the default sphere's box when there are none.
    pub lo: [f32; 3],
    pub hi: [f32; 3],
    /// Centre `c` of the bounds.
    pub centre: [f32; 3],
    /// Half the bounds' diagonal, `R`.
    pub radius: f32,
    /// Camera position.
    pub camera: [f32; 3],
    /// Horizontal right, world up, horizontal forward (unit vectors).
    pub right: [f32; 3],
    pub up: [f32; 3],
    pub forward: [f32; 3],
    /// Whether the scene had no geometry (the bounds are the default sphere's).
    pub empty: bool,
}

impl SceneFrame {
    /// The frame of `scene` (loads its meshes to measure the bounds).
    pub fn of(scene: &Scene) -> Result<SceneFrame> {
        let (o, cam_right, cam_up, back) = scene.camera.frame();
        let up = V3::new(0.0, 1.0, 0.0);
        let horizontal = |v: V3| v - up * v.dot(up);
        // Looking straight down, the top of the image is "forward" (as on a map); straight up,
        // the bottom is.
        let mut forward = horizontal(-V3::from_arr(back));
        if forward.length() < 1e-4 {
            forward = horizontal(V3::from_arr(cam_up) * back[1].signum());
        }
        if forward.length() < 1e-4 {
            forward = horizontal(V3::from_arr(cam_right)).cross(up);
        }
        let forward = forward.normalize();
        let right = forward.cross(up).normalize();
        let (lo, hi, empty) = match scene_bounds(scene)? {
            Some((lo, hi)) => (V3::from_arr(lo), V3::from_arr(hi), false),
            None => {
                let c = V3::from_arr(o) - V3::from_arr(back) * 3.0;
                (c - V3::splat(0.5_f32.sqrt()), c + V3::splat(0.5_f32.sqrt()), true)
            }
        };
        let centre = (lo + hi) * 0.5;
        Ok(SceneFrame {
            lo: lo.to_arr(),
            hi: hi.to_arr(),
            centre: centre.to_arr(),
            radius: ((hi - lo) * 0.5).length().max(1e-3),
            camera: o,
            right: right.to_arr(),
            up: up.to_arr(),
            forward: forward.to_arr(),
            empty,
        })
    }

    /// Unit vector from the centre toward a light at `azimuth_deg`, `elevation_deg`.
    pub fn toward(&self, azimuth_deg: f32, elevation_deg: f32) -> [f32; 3] {
        let (az, el) = (azimuth_deg.to_radians(), elevation_deg.to_radians());
        let (r, u, f) = (
            V3::from_arr(self.right),
            V3::from_arr(self.up),
            V3::from_arr(self.forward),
        );
        let horizontal = f * -az.cos() + r * az.sin();
        (horizontal * el.cos() + u * el.sin()).normalize().to_arr()
    }

    /// `c + distance · toward(azimuth, elevation)`.
    pub fn around(&self, azimuth_deg: f32, elevation_deg: f32, distance: f32) -> [f32; 3] {
        (V3::from_arr(self.centre) + V3::from_arr(self.toward(azimuth_deg, elevation_deg)) * distance).to_arr()
    }

    /// `1.5 R`.
    pub fn default_distance(&self) -> f32 {
        1.5 * self.radius
    }

    /// `0.15 ×` the bounds' diagonal (`0.3 R`).
    pub fn default_offset(&self) -> f32 {
        0.3 * self.radius
    }
}

/// The surface seen through a pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelHit {
    /// The point on the surface (world space, metres).
    pub point: [f32; 3],
    /// Unit shading normal, turned to face the camera.
    pub normal: [f32; 3],
    /// Distance from the camera along the ray.
    pub distance: f32,
}

/// The surface seen through image point `(x, y)` of the scene's camera (pixel units of its
/// `width × height` image, `(0, 0)` the top-left corner, a pixel's centre at `+0.5`): the closest
/// hit of the camera ray against every object's triangles (the renderer's BVH), or `None` where
/// the ray sees only the background. Errors for a point outside the image.
pub fn pick_pixel(scene: &Scene, x: f32, y: f32) -> Result<Option<PixelHit>> {
    let (w, h) = (scene.camera.width, scene.camera.height);
    if !(x.is_finite() && y.is_finite() && (0.0..=w as f32).contains(&x) && (0.0..=h as f32).contains(&y)) {
        return Err(RenderError::Options(format!(
            "pixel ({x}, {y}) is outside the {w}x{h} image (x in 0..{w}, y in 0..{h}, from the top-left corner)"
        )));
    }
    let geometry = Geometry::build(scene)?;
    let rays = CameraRays::new(&scene.camera, w, h);
    let ray: Ray = rays.ray(x, y);
    Ok(geometry.intersect(&ray, 0.0, f32::INFINITY).map(|hit| {
        let n = if hit.ns.dot(ray.d) > 0.0 { -hit.ns } else { hit.ns };
        PixelHit {
            point: hit.p.to_arr(),
            normal: n.to_arr(),
            distance: hit.t,
        }
    }))
}

/// A light's kind, for [`power_for_irradiance`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Emitter {
    Point,
    Spot,
    Area,
    Sun,
}

/// Power (W; sun: strength in W/m²) that gives irradiance `e` W/m² at distance `d` m on a
/// surface facing the light: point and spot `4π e d²` (intensity `P/4π`), area `π e d²` (on its
/// axis, for an emitter small next to `d`: radiance `P/(πA)` times solid angle `A/d²`), sun `e`.
pub fn power_for_irradiance(kind: Emitter, e: f32, d: f32) -> f32 {
    use std::f32::consts::PI;
    match kind {
        Emitter::Point | Emitter::Spot => 4.0 * PI * e * d * d,
        Emitter::Area => PI * e * d * d,
        Emitter::Sun => e,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Camera, Material, Object, Shape, Transform};

    /// A 4 m × 3 m wall 3 m in front of a camera at the origin (a reconstructed photo's frame).
    fn wall() -> Scene {
        let mut s = Scene::new(Camera::new(40, 30, 60.0));
        s.objects.push(Object {
            name: "wall".into(),
            shape: Shape::Quad { size: [4.0, 3.0] },
            transform: Transform {
                translate: [0.0, 0.0, -3.0],
                ..Default::default()
            },
            material: Material::default(),
        });
        s
    }

    fn close(a: [f32; 3], b: [f32; 3], tol: f32) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    #[test]
    fn frame_of_a_reconstructed_scene_is_the_cameras() {
        let f = SceneFrame::of(&wall()).unwrap();
        assert!(close(f.right, [1.0, 0.0, 0.0], 1e-6));
        assert!(close(f.up, [0.0, 1.0, 0.0], 1e-6));
        assert!(close(f.forward, [0.0, 0.0, -1.0], 1e-6));
        assert!(close(f.centre, [0.0, 0.0, -3.0], 1e-6));
        assert!((f.radius - 2.5).abs() < 1e-6, "{}", f.radius); // half of the 4 × 3 diagonal
                                                                // The six sides, by hand.
        let c = [0.0, 0.0, -3.0];
        let d = 2.0;
        for (side, want) in [
            (Side::Left, [-2.0, 0.0, -3.0]),
            (Side::Right, [2.0, 0.0, -3.0]),
            (Side::Above, [0.0, 2.0, -3.0]),
            (Side::Below, [0.0, -2.0, -3.0]),
            (Side::Front, [0.0, 0.0, -1.0]),
            (Side::Behind, [0.0, 0.0, -5.0]),
        ] {
            let (az, el) = side.azimuth_elevation();
            assert!(
                close(f.around(az, el, d), want, 1e-5),
                "{side:?}: {:?}",
                f.around(az, el, d)
            );
        }
        // 30° to the right of the camera's side, 45° up: by hand.
        let (a, e) = (30f32.to_radians(), 45f32.to_radians());
        let want = [
            c[0] + d * e.cos() * a.sin(),
            c[1] + d * e.sin(),
            c[2] + d * e.cos() * a.cos(),
        ];
        assert!(close(f.around(30.0, 45.0, d), want, 1e-5));
        assert_eq!(Side::parse("behind"), Some(Side::Behind));
        assert_eq!(Side::parse("up"), None);
    }

    #[test]
    fn a_tilted_camera_keeps_above_vertical() {
        let mut s = wall();
        s.camera.position = [0.0, 2.0, 1.0];
        s.camera.look_at = Some([0.0, 0.0, -3.0]);
        let f = SceneFrame::of(&s).unwrap();
        assert!(close(f.forward, [0.0, 0.0, -1.0], 1e-6));
        assert!(close(f.toward(0.0, 90.0), [0.0, 1.0, 0.0], 1e-6));
        // Looking straight down: forward is where the top of the image points.
        s.camera.position = [0.0, 5.0, -3.0];
        s.camera.look_at = Some([0.0, 0.0, -3.0]);
        s.camera.up = [0.0, 0.0, -1.0];
        let f = SceneFrame::of(&s).unwrap();
        assert!(close(f.forward, [0.0, 0.0, -1.0], 1e-5), "{:?}", f.forward);
    }

    #[test]
    fn pick_pixel_finds_the_wall_by_hand() {
        let s = wall();
        // The centre of the image: straight ahead, 3 m.
        let hit = pick_pixel(&s, 20.0, 15.0).unwrap().unwrap();
        assert!(close(hit.point, [0.0, 0.0, -3.0], 1e-5), "{hit:?}");
        assert!(close(hit.normal, [0.0, 0.0, 1.0], 1e-5));
        assert!((hit.distance - 3.0).abs() < 1e-5);
        // Pixel (30.5, 5.5): focal = 15 / tan(30°); the ray meets z = −3 at x = 3·10.5/f, y = 3·9.5/f.
        let f = 15.0 / 30f32.to_radians().tan();
        let hit = pick_pixel(&s, 30.5, 5.5).unwrap().unwrap();
        assert!(close(hit.point, [3.0 * 10.5 / f, 3.0 * 9.5 / f, -3.0], 1e-4), "{hit:?}");
        // The corner pixel sees past the wall (its half-width at 3 m is 2 m; the image's is
        // 3·tan(30°)·40/30 ≈ 2.31 m).
        assert!(pick_pixel(&s, 0.5, 15.0).unwrap().is_none());
        // Outside the image.
        let e = pick_pixel(&s, 41.0, 3.0).unwrap_err().to_string();
        assert!(e.contains("outside the 40x30 image"), "{e}");
        // Seen from behind, the normal still faces the camera.
        let mut back = wall();
        back.objects[0].transform.rotate_deg = [0.0, 180.0, 0.0];
        let hit = pick_pixel(&back, 20.0, 15.0).unwrap().unwrap();
        assert!(close(hit.normal, [0.0, 0.0, 1.0], 1e-5), "{hit:?}");
    }

    #[test]
    fn powers_give_the_asked_irradiance() {
        use std::f32::consts::PI;
        // A point light of power P: intensity P/4π, irradiance P/(4π d²).
        let p = power_for_irradiance(Emitter::Point, 4.0, 2.0);
        assert!((p / (4.0 * PI * 4.0) - 4.0).abs() < 1e-5);
        assert_eq!(power_for_irradiance(Emitter::Sun, 3.0, 100.0), 3.0);
        assert!((power_for_irradiance(Emitter::Area, 1.0, 1.0) - PI).abs() < 1e-6);
    }
}
