//! The coarse 3D scene behind the photo (paper §3.4): where it comes from and how it is built.
//!
//! Three sources, in this order of preference:
//! 1. **A depth map the user gives** (EXR, 16-bit PNG or `.npy`, read by
//!    [`pixl_render::depth::read_depth`]), of one of three kinds ([`DepthKind`]): metric z-depth
//!    in metres; relative depth (known up to scale and shift); or disparity (inverse depth up to
//!    scale and shift). Relative depth and disparity are normalised to `[0, 1]` over their valid
//!    pixels and mapped to `[near, far]` = [`DEPTH_RANGE`] (1 m to 10 m; disparity through `1/d`),
//!    as `pixl reconstruct` does without `--depth-range` (`pixl_pipeline::depth`).
//! 2. **A depth estimator** plugged in through the [`DepthEstimator`] trait of `pixl_pipeline`
//!    (`pixl studio` plugs in Depth Anything 3 when its weights are there, as `pixl relight`
//!    does).
//! 3. **The fallback**, labelled as such: a ground plane and a vertical backdrop fitted to the
//!    photo's frame ([`fallback_depth`]): a level camera at [`FALLBACK_CAMERA_HEIGHT`] above the
//!    ground, the backdrop at [`FALLBACK_BACKDROP`] metres; each pixel sees whichever is closer,
//!    so the two meet at a crease below the horizon (the image's middle row).
//!
//! Each source ends as a z-depth map at the working size, turned into a full-frame triangle mesh
//! ([`pixl_render::depth::depth_to_mesh`], cut at depth jumps) seen by a camera at the origin
//! looking down −Z with the given vertical FOV, textured with the photo itself (sRGB-decoded as
//! albedo, as `pixl reconstruct` does without an albedo map) and given
//! [`pixl_render::reconstruct::estimated_material`]. The files (`mesh.ply`, `albedo.png`,
//! `scene.toml`) go to a folder of the caller's; [`Coarse`] keeps the scene and its BVH for
//! picking surface points and for the quick preview.
//!
//! A scene file can also be opened as it is ([`Coarse::from_scene`]): its objects are the
//! geometry, and the "photo" is its render under its own lights.
use crate::error::{Result, StudioError};
use pixl_core::Image;
use pixl_render::depth::{depth_to_mesh, DepthMap, Intrinsics, MeshOptions};
use pixl_render::geometry::Geometry;
use pixl_render::math::V3;
use pixl_render::scene::{Camera, Color, Object, Scene, Shape, Transform};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Near and far depth (m) that relative depth and disparity are mapped to.
pub const DEPTH_RANGE: (f32, f32) = pixl_pipeline::depth::DEFAULT_DEPTH_RANGE;
/// Height of the fallback's camera above its ground plane (m).
pub const FALLBACK_CAMERA_HEIGHT: f32 = 1.5;
/// Distance of the fallback's backdrop from the camera (m, z-depth).
pub const FALLBACK_BACKDROP: f32 = 6.0;

pub use pixl_pipeline::depth::{DepthEstimator, DepthKind, EstimatedDepth};

/// Where the current geometry came from.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum GeometrySource {
    /// A depth map the user gave.
    Depth { depth_kind: DepthKind, file: String },
    /// The plugged-in estimator.
    Estimator { name: String },
    /// The ground-plane-and-backdrop stand-in.
    Fallback,
    /// A scene file's own objects.
    Scene { file: String },
}

impl GeometrySource {
    /// One sentence for the page.
    pub fn label(&self) -> String {
        match self {
            GeometrySource::Depth { depth_kind, file } => format!(
                "geometry from the depth map {file} ({})",
                match depth_kind {
                    DepthKind::Metric => "metric, metres",
                    DepthKind::Relative => "relative depth mapped to 1-10 m",
                    DepthKind::Disparity => "disparity mapped to 1-10 m",
                }
            ),
            GeometrySource::Estimator { name } => format!("geometry estimated by {name}"),
            GeometrySource::Fallback => format!(
                "FALLBACK GEOMETRY: no depth map and no depth estimator, so the photo is assumed to show a ground \
                 plane {FALLBACK_CAMERA_HEIGHT} m below a level camera and a flat backdrop {FALLBACK_BACKDROP} m away. \
                 Drop a depth map (EXR, 16-bit PNG or .npy) on the page for real geometry."
            ),
            GeometrySource::Scene { file } => format!("geometry of the scene file {file}"),
        }
    }
}

/// The coarse scene and what is derived from it once.
pub struct Coarse {
    /// Camera, objects and world; no lights. Relative paths resolve against `scene.base_dir`.
    pub scene: Scene,
    /// Its triangles and BVH (objects only), for picking and the preview's shadow rays.
    pub geom: Geometry,
    pub source: GeometrySource,
    /// Centre and radius of the geometry's bounding sphere.
    pub centre: [f32; 3],
    pub radius: f32,
}

impl Coarse {
    fn new(scene: Scene, source: GeometrySource) -> Result<Coarse> {
        let geom = Geometry::build(&scene)?;
        if geom.tris.is_empty() {
            return Err(StudioError::BadRequest(
                "the geometry has no triangles (is the depth map empty or all invalid?)".into(),
            ));
        }
        let (c, r) = geom.bounding_sphere();
        Ok(Coarse {
            scene,
            geom,
            source,
            centre: c.to_arr(),
            radius: r,
        })
    }

    /// Geometry from a metric z-depth map at the photo's working size (see the module docs).
    /// `photo` is the working-size photo (its texture); files are written to `dir`.
    pub fn from_depth(
        photo: &Image,
        depth: &DepthMap,
        fov_y_deg: f32,
        source: GeometrySource,
        dir: &Path,
    ) -> Result<Coarse> {
        let (w, h) = (photo.width, photo.height);
        if (depth.width, depth.height) != (w, h) {
            return Err(StudioError::Internal(format!(
                "depth map {}x{} is not at the working size {w}x{h}",
                depth.width, depth.height
            )));
        }
        let intr = Intrinsics::from_vfov_deg(w, h, fov_y_deg as f64)?;
        let opts = MeshOptions {
            full_frame: true,
            ..MeshOptions::default()
        };
        let mesh = depth_to_mesh(depth, &intr, None, &opts)?;
        if mesh.indices.is_empty() {
            return Err(StudioError::BadRequest(
                "the depth map gives no surface (every pixel is invalid: zero, negative or not a number)".into(),
            ));
        }
        std::fs::create_dir_all(dir).map_err(|e| StudioError::io(dir, e))?;
        let mesh_path = dir.join("mesh.ply");
        pixl_render::export::ply::write_ply(&mesh_path, &mesh)
            .map_err(|e| StudioError::Internal(format!("writing {}: {e}", mesh_path.display())))?;
        pixl_core::io::write_png(&dir.join("albedo.png"), photo, pixl_core::io::PngDepth::Sixteen)?;
        let mut scene = Scene::new(Camera::new(w as u32, h as u32, fov_y_deg));
        scene.base_dir = dir.to_owned();
        scene.objects.push(Object {
            name: "reconstruction".into(),
            shape: Shape::Mesh {
                path: PathBuf::from("mesh.ply"),
            },
            transform: Transform::default(),
            material: pixl_render::Material {
                base_color: Color::Rgb([1.0; 3]),
                base_color_texture: Some(PathBuf::from("albedo.png")),
                ..pixl_render::reconstruct::estimated_material()
            },
        });
        scene.save(&dir.join("scene.toml"))?;
        Coarse::new(scene, source)
    }

    /// A scene file's objects as the geometry (lights dropped; the caller keeps them).
    pub fn from_scene(scene: &Scene, file: &str) -> Result<Coarse> {
        let mut s = scene.clone();
        s.lights.clear();
        Coarse::new(s, GeometrySource::Scene { file: file.to_string() })
    }

    /// The surface seen through image point `(u, v)` (fractions of the width and height from
    /// the top-left corner): `(point, normal turned to face the camera)`, or `None` where the
    /// ray meets nothing.
    pub fn pick(&self, u: f32, v: f32) -> Option<([f32; 3], [f32; 3])> {
        let cam = &self.scene.camera;
        let rays = pixl_render::camera::CameraRays::new(cam, cam.width, cam.height);
        let ray = rays.ray(u * cam.width as f32, v * cam.height as f32);
        self.geom.intersect(&ray, 0.0, f32::INFINITY).map(|hit| {
            let n = if hit.ns.dot(ray.d) > 0.0 { -hit.ns } else { hit.ns };
            (hit.p.to_arr(), n.to_arr())
        })
    }

    /// The point at `distance` along the camera ray through `(u, v)` (for a click on the
    /// background) and the direction back to the camera.
    pub fn along_ray(&self, u: f32, v: f32, distance: f32) -> ([f32; 3], [f32; 3]) {
        let cam = &self.scene.camera;
        let rays = pixl_render::camera::CameraRays::new(cam, cam.width, cam.height);
        let ray = rays.ray(u * cam.width as f32, v * cam.height as f32);
        ((ray.o + ray.d * distance).to_arr(), (-ray.d).to_arr())
    }

    /// Where world point `p` lands in the image, as `(u, v)` fractions, if it is in front of
    /// the camera.
    pub fn project(&self, p: [f32; 3]) -> Option<[f32; 2]> {
        let cam = &self.scene.camera;
        let (o, r, u, b) = cam.frame();
        let d = V3::from_arr(p) - V3::from_arr(o);
        let z = -d.dot(V3::from_arr(b));
        if z.is_nan() || z <= 1e-6 {
            return None;
        }
        let f = cam.focal_for_height(cam.height);
        let (cx, cy) = cam
            .principal_px
            .map(|[x, y]| (x, y))
            .unwrap_or((0.5 * cam.width as f32, 0.5 * cam.height as f32));
        let x = cx + f * d.dot(V3::from_arr(r)) / z;
        let y = cy - f * d.dot(V3::from_arr(u)) / z;
        let uv = [x / cam.width as f32, y / cam.height as f32];
        uv.iter().all(|c| c.is_finite()).then_some(uv)
    }
}

/// Metric z-depth at `w × h` from a map of `kind` (resampled bilinearly over its valid pixels,
/// relative depth and disparity mapped to [`DEPTH_RANGE`]; `pixl_pipeline::depth`). Errors when
/// no pixel is valid.
pub fn metric_at(depth: &DepthMap, kind: DepthKind, w: usize, h: usize) -> Result<DepthMap> {
    let mut d = depth.clone();
    pixl_pipeline::depth::to_metric(&mut d, kind, DEPTH_RANGE);
    let d = pixl_pipeline::depth::resize_depth(&d, w, h).map_err(|e| StudioError::Internal(e.to_string()))?;
    if !d.data.iter().any(|v| *v > 0.0) {
        return Err(StudioError::BadRequest(
            "the depth map has no valid pixel (all are zero, negative or not a number)".into(),
        ));
    }
    Ok(d)
}

/// The fallback's z-depth at every pixel of a `w × h` image with vertical FOV `fov_y_deg`
/// (see the module docs): `min(backdrop, height / (−ray_y))` for rays pointing down, else the
/// backdrop, where the ray through pixel centre `(x, y)` is `((x − W/2)/f, −(y − H/2)/f, −1)`
/// per unit of z-depth.
pub fn fallback_depth(w: usize, h: usize, fov_y_deg: f32) -> Result<DepthMap> {
    let f = 0.5 * h as f32 / (0.5 * fov_y_deg.to_radians()).tan();
    let mut data = Vec::with_capacity(w * h);
    for y in 0..h {
        let dy = -((y as f32 + 0.5) - 0.5 * h as f32) / f;
        let d = if dy < 0.0 {
            (FALLBACK_CAMERA_HEIGHT / -dy).min(FALLBACK_BACKDROP)
        } else {
            FALLBACK_BACKDROP
        };
        data.extend(std::iter::repeat_n(d, w));
    }
    Ok(DepthMap::new(w, h, data)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metric_at_maps_kinds_and_refuses_an_empty_map() {
        let d = DepthMap::new(3, 1, vec![2.0, 4.0, 6.0]).unwrap();
        assert_eq!(
            metric_at(&d, DepthKind::Relative, 3, 1).unwrap().data,
            vec![1.0, 5.5, 10.0]
        );
        let disp = metric_at(&d, DepthKind::Disparity, 3, 1).unwrap();
        assert!((disp.data[0] - 10.0).abs() < 1e-5 && (disp.data[2] - 1.0).abs() < 1e-5);
        assert!((disp.data[1] - 1.0 / 0.55).abs() < 1e-5, "{:?}", disp.data);
        let metric = metric_at(&DepthMap::new(2, 1, vec![0.0, 3.0]).unwrap(), DepthKind::Metric, 2, 1).unwrap();
        assert_eq!(metric.data, vec![0.0, 3.0]);
        assert!(metric_at(&DepthMap::new(1, 1, vec![f32::NAN]).unwrap(), DepthKind::Metric, 1, 1).is_err());
    }

    #[test]
    fn fallback_meets_the_ground_where_the_backdrop_is_as_far() {
        // 60° FOV, 100 rows: f = 50 / tan 30°. The bottom row's ray falls by 49.5/f per metre.
        let d = fallback_depth(4, 100, 60.0).unwrap();
        let f = 50.0 / 30f32.to_radians().tan();
        assert_eq!(d.get(0, 0), FALLBACK_BACKDROP);
        let bottom = FALLBACK_CAMERA_HEIGHT / (49.5 / f);
        assert!((d.get(2, 99) - bottom).abs() < 1e-4, "{} vs {bottom}", d.get(2, 99));
        // Continuous: no step bigger than 10 % between neighbouring rows.
        for y in 1..100 {
            let (a, b) = (d.get(0, y - 1), d.get(0, y));
            assert!((a / b - 1.0).abs() < 0.1, "row {y}: {a} {b}");
        }
    }
}
