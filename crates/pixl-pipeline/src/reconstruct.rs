//! A photo and its metric depth → the coarse scene behind it (paper §3.4): a full-frame triangle
//! mesh in the camera's space (camera at the origin looking down −Z, +Y up; see
//! `pixl_render::depth`), textured with the photo (or an albedo map), with the photo's camera.
//!
//! [`reconstruct`] builds it in memory ([`Geometry`]: the scene holds its mesh and texture
//! images as `pixl_render::scene::Assets`, so it renders without touching the disk);
//! [`Geometry::write`] writes it as a scene folder (`scene.toml`, the mesh as GLB, OBJ or PLY,
//! the textures as PNG) that `pixl render` and Blender read, only when asked.
//!
//! - The mesh reaches the frame's edges (outermost vertices on the image border) unless
//!   `pixel_centres`; triangles are cut at depth jumps (`max_jump`) and where depth is missing.
//! - **Size**: without a stride, the smallest stride giving at most `max_triangles` triangles.
//! - Material maps must have the photo's size and be finite; the albedo (an sRGB PNG/JPEG or a
//!   linear EXR) replaces the photo as the colour texture; roughness and metallic are scalar
//!   textures; a normal map (camera space, in [-1, 1]; read or estimated in [`crate::normals`])
//!   gives the mesh's vertex normals, which the renderer shades with.
use crate::error::{PipelineError, Result};
use crate::observe::Observer;
use crate::photo::Photo;
use pixl_core::io::PngDepth;
use pixl_core::Image;
use pixl_render::depth::{self, DepthMap, Intrinsics, MeshOptions};
use pixl_render::export::{glb, obj, ply};
use pixl_render::scene::{Camera, Color, Material, Object, Scene, Shape, Transform, World};
use pixl_render::Mesh;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Triangle budget that picks the stride when none is given.
pub const DEFAULT_MAX_TRIANGLES: usize = 2_000_000;

/// The files [`Geometry::write`] may write in its folder.
pub const OUTPUT_FILES: &[&str] = &[
    "photo.png",
    "albedo.png",
    "roughness.png",
    "metallic.png",
    "mesh.glb",
    "mesh.obj",
    "mesh.mtl",
    "mesh.ply",
    "scene.toml",
];

/// How the depth becomes a mesh.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshSettings {
    /// Keep every N-th pixel in x and y; `None`: the smallest within `max_triangles`.
    pub stride: Option<usize>,
    pub max_triangles: usize,
    /// Cut triangles whose max/min vertex depth − 1 exceeds this.
    pub max_jump: f32,
    /// Every vertex at its pixel's centre instead of the outermost ones on the image's edges.
    pub pixel_centres: bool,
}

impl Default for MeshSettings {
    fn default() -> Self {
        MeshSettings {
            stride: None,
            max_triangles: DEFAULT_MAX_TRIANGLES,
            max_jump: depth::DEFAULT_MAX_JUMP,
            pixel_centres: false,
        }
    }
}

/// Material maps at the photo's size (each optional).
#[derive(Clone, Debug, Default)]
pub struct Maps {
    /// The colour texture instead of the photo, and whether its values are linear (EXR).
    pub albedo: Option<(Image, bool)>,
    /// First channel used.
    pub roughness: Option<Image>,
    /// First channel used.
    pub metallic: Option<Image>,
    /// Camera-space normals in [-1, 1] (3 channels; X right, Y up, Z towards the camera):
    /// the vertex normals, sampled at each vertex's pixel ([`crate::normals`]).
    pub normals: Option<Image>,
}

/// The mesh file format of a written scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MeshFormat {
    Glb,
    Obj,
    Ply,
}

/// The coarse scene of a photo, in memory.
#[derive(Clone, Debug)]
pub struct Geometry {
    /// Camera, world and the object `photo`, whose mesh (`mesh.glb`) and textures (`photo.png`
    /// or `albedo.png`, `roughness.png`, `metallic.png`) the scene holds in memory
    /// (`scene.assets`) under the names [`Geometry::write`] writes them with.
    pub scene: Scene,
    pub mesh: Arc<Mesh>,
    /// The colour texture (RGB, sRGB-encoded) and the scalar textures, by file name.
    pub textures: Vec<(String, Arc<Image>, PngDepth)>,
    pub intrinsics: Intrinsics,
    pub stride: usize,
    /// Triangles the grid could have had at this stride.
    pub possible_triangles: usize,
}

/// Samples per axis and triangles of the grid for a stride (as `depth_to_mesh` builds it).
pub fn grid_triangles(w: usize, h: usize, stride: usize) -> usize {
    let grid = |n: usize| (n - 1).div_ceil(stride) + 1;
    2 * (grid(w) - 1) * (grid(h) - 1)
}

/// The smallest stride whose grid has at most `max` triangles.
pub fn auto_stride(w: usize, h: usize, max: usize) -> usize {
    let mut s = 1;
    while grid_triangles(w, h, s) > max && s < w.max(h) {
        s += 1;
    }
    s
}

/// Checks that a map has the photo's size and finite values.
pub fn check_map(what: &str, name: &str, img: &Image, size: (usize, usize)) -> Result<()> {
    if (img.width, img.height) != size {
        return Err(PipelineError::input(format!(
            "{name}: {what} is {}x{} but the photo is {}x{} (maps must match the photo; resample them first)",
            img.width, img.height, size.0, size.1
        )));
    }
    if let Some((n, x, y, c)) = img.find_non_finite() {
        return Err(PipelineError::input(format!(
            "{name}: {n} non-finite values in the {what} map, first at x={x}, y={y}, channel {c}"
        )));
    }
    Ok(())
}

/// An image as an RGB colour texture (grey maps widened), sRGB-encoded.
fn color_texture(img: &Image, linear: bool) -> Image {
    let rgb = match img.channels {
        1 | 2 => Image::from_fn(img.width, img.height, 3, |x, y, _| img.get(x, y, 0)),
        _ => img.select_channels(0..3),
    };
    if linear {
        rgb.map(pixl_core::image::linear_to_srgb)
    } else {
        rgb
    }
}

/// Builds the coarse scene of `photo` from its metric `depth` (at the photo's size; 0 =
/// missing; `depth_name` names it in errors: its file, or "the estimated depth") and optional
/// `maps` (see the module docs). Notes for the user (the stride chosen) go to `observer`.
pub fn reconstruct(
    photo: &Photo,
    depth: &DepthMap,
    depth_name: &str,
    maps: &Maps,
    settings: &MeshSettings,
    observer: &dyn Observer,
) -> Result<Geometry> {
    let size = photo.size();
    if size.0 < 2 || size.1 < 2 {
        return Err(PipelineError::input(format!(
            "{}: the photo is {}x{}; a mesh needs at least 2x2 pixels",
            photo.name(),
            size.0,
            size.1
        )));
    }
    if (depth.width, depth.height) != size {
        return Err(PipelineError::input(format!(
            "{depth_name} is {}x{} but the photo is {}x{}",
            depth.width, depth.height, size.0, size.1
        )));
    }
    if settings.max_triangles < 2 {
        return Err(PipelineError::input(format!(
            "--max-triangles {}: must be at least 2",
            settings.max_triangles
        )));
    }
    let stride = match settings.stride {
        Some(0) => return Err(PipelineError::input("--stride must be at least 1")),
        Some(s) => {
            let n = grid_triangles(size.0, size.1, s);
            if n > settings.max_triangles {
                tracing::warn!(
                    "--stride {s} gives up to {n} triangles (more than --max-triangles {})",
                    settings.max_triangles
                );
            }
            s
        }
        None => {
            let s = auto_stride(size.0, size.1, settings.max_triangles);
            if s > 1 {
                observer.note(&format!(
                    "stride {s} (every {s}th pixel): a {}x{} photo at stride 1 would give {} triangles, \
more than --max-triangles {}; pass --stride 1 to keep them all",
                    size.0,
                    size.1,
                    grid_triangles(size.0, size.1, 1),
                    settings.max_triangles
                ));
            }
            s
        }
    };
    let opts = MeshOptions {
        max_jump: settings.max_jump,
        stride,
        full_frame: !settings.pixel_centres,
        ..Default::default()
    };
    if depth.count_valid(opts.max_depth) == 0 {
        return Err(PipelineError::input(format!(
            "{depth_name}: no pixel has a positive depth"
        )));
    }
    let intr = Intrinsics::from_focal_px(size.0, size.1, photo.focal.px)?;
    let mesh = depth::depth_to_mesh(depth, &intr, maps.normals.as_ref(), &opts)?;
    if mesh.indices.is_empty() {
        return Err(no_triangle_error(depth, depth_name, &opts, size, stride));
    }

    let mut textures = Vec::new();
    let base_tex = match &maps.albedo {
        Some((img, linear)) => {
            textures.push((
                "albedo.png".to_string(),
                Arc::new(color_texture(img, *linear)),
                PngDepth::Eight,
            ));
            "albedo.png"
        }
        None => {
            textures.push((
                "photo.png".to_string(),
                Arc::new(color_texture(&photo.image, photo.linear)),
                PngDepth::Eight,
            ));
            "photo.png"
        }
    };
    let mut material = Material {
        base_color: Color::Rgb([1.0, 1.0, 1.0]),
        base_color_texture: Some(PathBuf::from(base_tex)),
        ..Default::default()
    };
    for (name, map, slot) in [
        ("roughness.png", &maps.roughness, &mut material.roughness_texture),
        ("metallic.png", &maps.metallic, &mut material.metallic_texture),
    ] {
        if let Some(m) = map {
            textures.push((name.to_string(), Arc::new(m.select_channels(0..1)), PngDepth::Sixteen));
            *slot = Some(PathBuf::from(name));
        }
    }
    let mut camera = Camera::new(size.0 as u32, size.1 as u32, intr.vfov_deg() as f32);
    if photo.focal.source == crate::exif::FocalSource::Flag {
        camera.fov_y_deg = None;
        camera.focal_px = Some(intr.focal_px as f32);
    }
    let mut scene = Scene::new(camera);
    scene.world = Some(World::default());
    scene.objects.push(Object {
        name: "photo".into(),
        shape: Shape::Mesh {
            path: PathBuf::from("mesh.glb"),
        },
        transform: Transform::default(),
        material,
    });
    let mesh = Arc::new(mesh);
    scene.assets.meshes.insert(PathBuf::from("mesh.glb"), mesh.clone());
    for (name, img, _) in &textures {
        scene.assets.images.insert(PathBuf::from(name), img.clone());
    }
    Ok(Geometry {
        scene,
        mesh,
        textures,
        intrinsics: intr,
        stride,
        possible_triangles: grid_triangles(size.0, size.1, stride),
    })
}

/// Why no triangle survived: a grid too coarse for the image, missing depth, or depth jumps.
fn no_triangle_error(
    depth: &DepthMap,
    depth_name: &str,
    opts: &MeshOptions,
    size: (usize, usize),
    stride: usize,
) -> PipelineError {
    let c = depth::cut_counts(depth, opts);
    let total = c.missing_depth + c.depth_jump;
    if c.grid.0 < 2 || c.grid.1 < 2 || (stride > 1 && total < 32) {
        return PipelineError::input(format!(
            "--stride {stride} leaves a {}x{} grid of samples ({total} triangles, none kept) on a {}x{} photo; use a smaller --stride",
            c.grid.0, c.grid.1, size.0, size.1
        ));
    }
    if c.missing_depth >= c.depth_jump {
        return PipelineError::input(format!(
            "{depth_name}: no triangle has valid depth at all three corners ({} of {} lack depth); check the depth map (0, negative and beyond-far values count as missing)",
            c.missing_depth, total
        ));
    }
    PipelineError::input(format!(
        "{depth_name}: every triangle was cut at a depth jump over --max-jump {} ({} of {}; at --stride {stride} neighbouring samples are {stride} pixels apart); raise --max-jump{}",
        opts.max_jump,
        c.depth_jump,
        total,
        if stride > 1 { " or lower --stride" } else { "" }
    ))
}

impl Geometry {
    /// Writes the scene folder `dir` (created if missing): the textures as PNG, the mesh in
    /// `format`, and `scene.toml` (with `lights`); returns the scene file's path. Files are
    /// written atomically; the caller decides whether `dir` may hold files already.
    pub fn write(&self, dir: &Path, format: MeshFormat, lights: &[pixl_render::Light]) -> Result<PathBuf> {
        std::fs::create_dir_all(dir).map_err(|e| PipelineError::io(dir, e))?;
        for (name, img, depth) in &self.textures {
            pixl_core::io::write_png(&dir.join(name), img, *depth)?;
        }
        let base_tex = self.textures.first().map(|t| t.0.as_str()).unwrap_or("photo.png");
        let roughness = self.scene.objects.first().map(|o| o.material.roughness).unwrap_or(0.5);
        let mesh_name = match format {
            MeshFormat::Glb => {
                // The colour texture's PNG, as written above.
                let png = match self.textures.first() {
                    Some((_, img, depth)) => {
                        pixl_core::io::encode_png(img, *depth, pixl_core::io::PngCompression::Default)?
                    }
                    None => return Err(PipelineError::input("the geometry has no colour texture")),
                };
                let m = glb::GlbMaterial {
                    name: "photo".into(),
                    base_color_png: Some(png),
                    roughness,
                    ..Default::default()
                };
                glb::write_glb(&dir.join("mesh.glb"), &self.mesh, &m)?;
                "mesh.glb"
            }
            MeshFormat::Obj => {
                let m = obj::ObjMaterial {
                    name: "photo".into(),
                    diffuse: [1.0; 3],
                    texture: Some(base_tex.into()),
                    roughness,
                    metallic: 0.0,
                };
                obj::write_obj(&dir.join("mesh.obj"), &self.mesh, Some(&m))?;
                "mesh.obj"
            }
            MeshFormat::Ply => {
                ply::write_ply(&dir.join("mesh.ply"), &self.mesh)?;
                "mesh.ply"
            }
        };
        let mut scene = self.scene.clone();
        scene.assets = Default::default();
        for o in scene.objects.iter_mut() {
            o.shape = Shape::Mesh {
                path: PathBuf::from(mesh_name),
            };
        }
        scene.lights = lights.to_vec();
        let path = dir.join("scene.toml");
        scene.save(&path)?;
        Ok(path)
    }

    /// Triangles cut at discontinuities or missing depth.
    pub fn triangles_cut(&self) -> usize {
        self.possible_triangles.saturating_sub(self.mesh.num_triangles())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stride_keeps_the_triangle_budget() {
        // A 6 MP photo: 12 M triangles at stride 1.
        let (w, h) = (3000, 2000);
        assert_eq!(grid_triangles(w, h, 1), 2 * 2999 * 1999);
        let s = auto_stride(w, h, DEFAULT_MAX_TRIANGLES);
        assert!(grid_triangles(w, h, s) <= DEFAULT_MAX_TRIANGLES);
        assert!(grid_triangles(w, h, s - 1) > DEFAULT_MAX_TRIANGLES);
        assert_eq!(s, 3);
        assert_eq!(auto_stride(8, 6, DEFAULT_MAX_TRIANGLES), 1);
        assert_eq!(auto_stride(2, 2, 2), 1);
    }
}
