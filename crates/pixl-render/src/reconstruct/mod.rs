//! Scenes made from a photo, and lights placed in them (paper §3.4, §4.2):
//! - [`depth`]: a depth map + pinhole intrinsics → a textured triangle grid (the mesh of
//!   `pixl reconstruct`);
//! - [`normals`]: camera-space normal maps as files (the mesh's shading normals);
//! - this module: [`coarse_scene`] and [`coarse_scene_textured`], the coarse scene of a source
//!   render (below);
//! - [`placement`]: lights placed as a person describes them (at a pixel of the photo, from a
//!   side, at an angle);
//! - [`presets`]: the paper's five lighting presets, placed relative to the scene's bounds.
//!
//! It builds [`Scene`]s and reads the tracer's [`Film`] and geometry (to place lights on what a
//! pixel sees); nothing in the tracer depends on it.
//!
//! # The coarse scene
//! The coarse scene of the paper's inference (§3.4), built from a render of the *source*: its
//! `Depth` pass becomes a triangle mesh in world space (through the camera; cut at depth
//! discontinuities by [`MeshOptions`]' defaults; reaching the frame's edges) and its `DiffCol`
//! pass the albedo texture — the stand-ins for a monocular depth and albedo estimator. One
//! caller-given material (the "estimated" roughness, specular, metallic) covers the whole mesh;
//! the world is kept, lights are left to the caller. (`DiffCol` is the diffuse closure's
//! albedo, which Cycles' Principled v2 attenuates by the specular coat's reflectance; a template
//! with a specular coat attenuates it once more.)
//!
//! [`coarse_scene_textured`] takes the albedo texture from the caller instead — e.g. the photo
//! itself, as `pixl reconstruct` does when no albedo map is given: the shading and shadows of the
//! source then sit in the "albedo", as they do with a weak albedo estimator.
//!
//! Used by `pixl demo` and by `pixl synth --coarse`, which evaluates the network in this setting.
use crate::error::{RenderError, Result};
use crate::reconstruct::depth::{depth_to_mesh, DepthMap, Intrinsics, MeshOptions};
use crate::scene::{Material, Object, Scene, Shape, Transform};
use crate::trace::film::Film;
use std::path::Path;

pub mod depth;
pub mod normals;
pub mod placement;
pub mod presets;

/// The one material a coarse scene gets when no material estimator is at hand: a mid-rough
/// dielectric (roughness 0.5, Blender's default specular), base colour from the albedo texture.
pub fn estimated_material() -> Material {
    Material {
        roughness: 0.5,
        ..Default::default()
    }
}

/// Writes `dir/mesh.ply` and `dir/albedo.png` (16-bit sRGB) from `source` — a render of `scene`
/// with the `Depth` and `DiffCol` passes — and returns a scene with `scene`'s camera and world,
/// that mesh with `material` whose base colour is replaced by the albedo texture, no lights,
/// files resolving against `dir`. Also saved as `dir/scene.toml`.
pub fn coarse_scene(source: &Film, scene: &Scene, material: &Material, dir: &Path) -> Result<Scene> {
    coarse_scene_textured(source, scene, material, None, dir)
}

/// [`coarse_scene`] with `texture` (sRGB in [0, 1], 3 channels, the render's size) as the albedo
/// texture instead of the `DiffCol` pass when given.
pub fn coarse_scene_textured(
    source: &Film,
    scene: &Scene,
    material: &Material,
    texture: Option<&pixl_core::Image>,
    dir: &Path,
) -> Result<Scene> {
    let missing = |pass: &str| RenderError::Options(format!("the source render has no {pass} pass"));
    let depth = source.pass_ref("Depth").ok_or_else(|| missing("Depth"))?;
    let texture = match texture {
        Some(t) => {
            if (t.width, t.height, t.channels) != (depth.width, depth.height, 3) {
                return Err(RenderError::Options(format!(
                    "albedo texture is {}x{}x{}, the render {}x{}x3",
                    t.width, t.height, t.channels, depth.width, depth.height
                )));
            }
            t.map(|v| v.clamp(0.0, 1.0))
        }
        None => {
            let albedo = source.pass_ref("DiffCol").ok_or_else(|| missing("DiffCol"))?;
            albedo.map(|v| pixl_core::image::linear_to_srgb(v.clamp(0.0, 1.0)))
        }
    };
    std::fs::create_dir_all(dir).map_err(|e| RenderError::Write {
        path: dir.to_owned(),
        message: e.to_string(),
    })?;
    let (w, h) = (depth.width, depth.height);
    let depth_error =
        |e: crate::reconstruct::depth::DepthError| RenderError::Options(format!("coarse reconstruction: {e}"));
    let intr = Intrinsics::from_focal_px(w, h, scene.camera.focal_for_height(h as u32) as f64).map_err(depth_error)?;
    let depth_map = DepthMap::new(w, h, depth.data.clone()).map_err(depth_error)?;
    let opts = MeshOptions {
        full_frame: true,
        ..MeshOptions::default()
    };
    let mesh = depth_to_mesh(&depth_map, &intr, None, &opts).map_err(depth_error)?;
    let mesh_path = dir.join("mesh.ply");
    crate::io::export::ply::write_ply(&mesh_path, &mesh).map_err(|e| RenderError::Write {
        path: mesh_path.clone(),
        message: e.to_string(),
    })?;
    pixl_core::io::write_png(&dir.join("albedo.png"), &texture, pixl_core::io::PngDepth::Sixteen)?;
    let (o, r, u, b) = scene.camera.frame();
    let cam_to_world = [
        [r[0], u[0], b[0], o[0]],
        [r[1], u[1], b[1], o[1]],
        [r[2], u[2], b[2], o[2]],
        [0.0, 0.0, 0.0, 1.0],
    ];
    let mut coarse = Scene::new(scene.camera.clone());
    coarse.world = scene.world.clone();
    coarse.base_dir = dir.to_owned();
    coarse.objects.push(Object {
        name: "reconstruction".into(),
        shape: Shape::Mesh {
            path: "mesh.ply".into(),
        },
        transform: Transform {
            matrix: Some(cam_to_world),
            ..Default::default()
        },
        material: Material {
            base_color: crate::scene::Color::Rgb([1.0; 3]),
            base_color_texture: Some("albedo.png".into()),
            ..material.clone()
        },
    });
    coarse.save(&dir.join("scene.toml"))?;
    Ok(coarse)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Camera, Color, Light, World};
    use crate::trace::integrator::{render, RenderOptions};

    /// A uniform diffuse wall (no specular coat) filling the view, lit by a sun and a constant
    /// world — its coarse scene (a planar depth mesh with the DiffCol texture and the wall's
    /// material otherwise) must render to the same image means.
    #[test]
    fn coarse_scene_of_a_wall_renders_like_the_wall() {
        let mut cam = Camera::new(32, 24, 50.0);
        cam.position = [0.3, 0.2, 6.0];
        cam.look_at = Some([0.0, 0.0, 0.0]);
        let mut scene = Scene::new(cam);
        let estimated = Material {
            roughness: 0.5,
            specular_ior_level: 0.0,
            ..Default::default()
        };
        scene.objects.push(Object {
            name: "wall".into(),
            shape: Shape::Quad { size: [40.0, 40.0] },
            transform: Transform::default(),
            material: Material {
                base_color: Color::Rgb([0.6, 0.4, 0.3]),
                ..estimated.clone()
            },
        });
        scene.lights.push(Light::Sun {
            name: "sun".into(),
            direction: Some([-0.3, -0.4, -1.0]),
            strength: 3.0,
            angle_deg: 0.5,
            color: Color::Rgb([1.0, 1.0, 1.0]),
        });
        scene.world = Some(World {
            color: Color::Rgb([0.2, 0.2, 0.25]),
            strength: 1.0,
            image: None,
            rotation_deg: 0.0,
        });
        let opts = RenderOptions {
            spp: 16,
            ..RenderOptions::default()
        };
        let source = render(&scene, &opts, &|_, _| {}).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let mut coarse = coarse_scene(&source, &scene, &estimated, dir.path()).unwrap();
        assert!(coarse.lights.is_empty());
        assert!(dir.path().join("mesh.ply").is_file() && dir.path().join("albedo.png").is_file());
        // Reloading the saved scene.toml gives the same scene.
        assert_eq!(Scene::load(&dir.path().join("scene.toml")).unwrap().objects.len(), 1);
        coarse.lights = scene.lights.clone();
        let relit = render(&coarse, &opts, &|_, _| {}).unwrap();
        for pass in ["DiffCol", "DiffDir", "Combined"] {
            let mean = |f: &Film| {
                let d = &f.pass_ref(pass).unwrap().data;
                d.iter().map(|v| *v as f64).sum::<f64>() / d.len() as f64
            };
            let (a, b) = (mean(&source), mean(&relit));
            assert!(a > 0.01 && b.is_finite(), "{pass}: {a} {b}");
            assert!((a - b).abs() / a < 0.01, "{pass}: source {a} vs coarse {b}");
        }
        // A caller-given texture replaces DiffCol: a uniform sRGB 0.5 "photo" gives the coarse
        // scene a diffuse colour of srgb_to_linear(0.5) = 0.2140 (the material has no specular
        // coat, so DiffCol is the base colour itself).
        let photo = pixl_core::Image::new(32, 24, 3).map(|_| 0.5);
        let mut textured = coarse_scene_textured(&source, &scene, &estimated, Some(&photo), dir.path()).unwrap();
        textured.lights = scene.lights.clone();
        let film = render(&textured, &opts, &|_, _| {}).unwrap();
        let d = &film.pass_ref("DiffCol").unwrap().data;
        let mean = d.iter().map(|v| *v as f64).sum::<f64>() / d.len() as f64;
        let want = ((0.5f64 + 0.055) / 1.055).powf(2.4);
        assert!((mean - want).abs() / want < 0.01, "DiffCol {mean} vs {want}");
        let wrong = pixl_core::Image::new(16, 24, 3);
        assert!(coarse_scene_textured(&source, &scene, &estimated, Some(&wrong), dir.path()).is_err());
    }
}
