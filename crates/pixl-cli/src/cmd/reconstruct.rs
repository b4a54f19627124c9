//! `pixl reconstruct`: a photo + its depth map (+ optional material maps) → a scene folder with
//! a textured mesh, its textures and a `scene.toml` whose camera reproduces the photo's framing
//! (issue 4, part 2; paper §3.4).
//!
//! The mesh lives in the camera's space (camera at the origin looking down −Z, +Y up; see
//! `pixl_render::depth`), so the scene's camera is the default one with the photo's size and
//! field of view. Maps must have the photo's size (no resampling); depth must be finite (mark
//! missing depth as 0 — its triangles are cut). The mesh reaches the frame's edges (outermost
//! vertices on the image border, not at the border pixels' centres) unless `--pixel-centres`.
use crate::Ctx;
use anyhow::{bail, Context};
use pixl_core::Image;
use pixl_render::depth::{self, DepthMap, Intrinsics, MeshOptions};
use pixl_render::export::{glb, obj, ply};
use pixl_render::scene::{Camera, Color, Material, Object, Scene, Shape, Transform, World};
use std::path::{Path, PathBuf};

/// Vertical field of view assumed when neither `--fov` nor `--focal` is given.
pub const DEFAULT_FOV_DEG: f64 = 50.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MeshFormat {
    Glb,
    Obj,
    Ply,
}

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Example:\n  pixl reconstruct --image photo.png --depth depth.exr --albedo albedo.png --fov 60 -o scene/"
)]
pub struct Args {
    /// The photo (PNG/JPEG/EXR); its size is the camera's.
    #[arg(long)]
    pub image: PathBuf,
    /// Z-depth map in metres (EXR channel Z/Y/R, 16-bit PNG × --depth-scale, or .npy), photo-sized.
    #[arg(long)]
    pub depth: PathBuf,
    /// Albedo map (the mesh's colour texture instead of the photo).
    #[arg(long)]
    pub albedo: Option<PathBuf>,
    /// Roughness map (first channel used).
    #[arg(long)]
    pub roughness: Option<PathBuf>,
    /// Metallic map (first channel used).
    #[arg(long)]
    pub metallic: Option<PathBuf>,
    /// Camera-space normal map (EXR in [-1, 1], or PNG encoding n/2 + 1/2): X right, Y up, Z to the camera.
    #[arg(long)]
    pub normals: Option<PathBuf>,
    /// Vertical field of view in degrees (default 50).
    #[arg(long, conflicts_with = "focal")]
    pub fov: Option<f64>,
    /// Focal length in pixels (principal point at the image centre).
    #[arg(long)]
    pub focal: Option<f64>,
    /// Metres per unit for 16-bit PNG and uint16 .npy depth.
    #[arg(long, default_value_t = depth::DEFAULT_DEPTH_SCALE)]
    pub depth_scale: f32,
    /// Cut triangles whose max/min vertex depth − 1 exceeds this.
    #[arg(long, default_value_t = depth::DEFAULT_MAX_JUMP)]
    pub max_jump: f32,
    /// Keep every N-th pixel in x and y (for big images).
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    /// Put every vertex at its pixel's centre. By default the outermost vertices sit on the
    /// image's edges (at the border pixels' depths), so that the mesh covers the whole frame
    /// and renders of it have no half-pixel rim of background.
    #[arg(long)]
    pub pixel_centres: bool,
    /// Mesh file format.
    #[arg(long, value_enum, default_value_t = MeshFormat::Glb)]
    pub format: MeshFormat,
    /// Output folder (created if missing).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

fn check_size(what: &str, path: &Path, w: usize, h: usize, want: (usize, usize)) -> anyhow::Result<()> {
    if (w, h) != want {
        bail!(
            "{}: {what} is {w}x{h} but the photo is {}x{} (maps must match the photo; resample them first)",
            path.display(),
            want.0,
            want.1
        );
    }
    Ok(())
}

/// Reads a map as stored and checks its size and finiteness.
fn read_map(what: &str, path: &Path, size: (usize, usize)) -> anyhow::Result<Image> {
    let img = pixl_core::io::read_image(path).with_context(|| format!("reading the {what} map"))?;
    check_size(what, path, img.width, img.height, size)?;
    pixl_core::io::ensure_finite(path, &img)?;
    Ok(img)
}

/// A colour texture as an 8-bit sRGB PNG; EXR input is linear and gets encoded.
fn write_color_png(src: &Path, img: &Image, dst: &Path) -> anyhow::Result<()> {
    let rgb = match img.channels {
        1 | 2 => Image::from_fn(img.width, img.height, 3, |x, y, _| img.get(x, y, 0)),
        _ => img.select_channels(0..3),
    };
    let rgb = if pixl_core::io::extension(src) == "exr" {
        rgb.map(pixl_core::image::linear_to_srgb)
    } else {
        rgb
    };
    pixl_core::io::write_png(dst, &rgb, pixl_core::io::PngDepth::Eight)?;
    Ok(())
}

/// A scalar map (first channel) as a 16-bit greyscale PNG, values as stored.
fn write_scalar_png(img: &Image, dst: &Path) -> anyhow::Result<()> {
    let g = img.select_channels(0..1);
    pixl_core::io::write_png(dst, &g, pixl_core::io::PngDepth::Sixteen)?;
    Ok(())
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let photo = pixl_core::io::read_image(&args.image).context("reading the photo")?;
    pixl_core::io::ensure_finite(&args.image, &photo)?;
    let size = (photo.width, photo.height);
    let depth_map: DepthMap = depth::read_depth(&args.depth, args.depth_scale)?;
    check_size("depth map", &args.depth, depth_map.width, depth_map.height, size)?;
    if let Some(i) = depth_map.data.iter().position(|d| !d.is_finite()) {
        let count = depth_map.data.iter().filter(|d| !d.is_finite()).count();
        bail!(
            "{}: {count} non-finite depth values (NaN/Inf), first at x={}, y={}; mark missing depth as 0 instead",
            args.depth.display(),
            i % depth_map.width,
            i / depth_map.width
        );
    }
    let opts = MeshOptions {
        max_jump: args.max_jump,
        stride: args.stride,
        full_frame: !args.pixel_centres,
        ..Default::default()
    };
    if depth_map.count_valid(opts.max_depth) == 0 {
        bail!("{}: no pixel has a positive depth", args.depth.display());
    }
    let intr = match args.focal {
        Some(f) => Intrinsics::from_focal_px(size.0, size.1, f)?,
        None => Intrinsics::from_vfov_deg(size.0, size.1, args.fov.unwrap_or(DEFAULT_FOV_DEG))?,
    };
    let normals = match &args.normals {
        Some(p) => {
            let n = read_map("normal", p, size)?;
            if n.channels < 3 {
                bail!("{}: a normal map needs 3 channels, found {}", p.display(), n.channels);
            }
            // PNG/JPEG store n/2 + 1/2.
            Some(if pixl_core::io::extension(p) == "exr" {
                n
            } else {
                n.map(|v| 2.0 * v - 1.0)
            })
        }
        None => None,
    };
    let albedo = args
        .albedo
        .as_ref()
        .map(|p| read_map("albedo", p, size).map(|m| (p.clone(), m)))
        .transpose()?;
    let roughness = args
        .roughness
        .as_ref()
        .map(|p| read_map("roughness", p, size))
        .transpose()?;
    let metallic = args
        .metallic
        .as_ref()
        .map(|p| read_map("metallic", p, size))
        .transpose()?;

    let mesh = depth::depth_to_mesh(&depth_map, &intr, normals.as_ref(), &opts)?;
    if mesh.indices.is_empty() {
        bail!(
            "{}: every triangle was cut (max jump {}); raise --max-jump",
            args.depth.display(),
            args.max_jump
        );
    }

    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let out = |name: &str| args.out.join(name);
    write_color_png(&args.image, &photo, &out("photo.png"))?;
    let base_tex = match &albedo {
        Some((p, img)) => {
            write_color_png(p, img, &out("albedo.png"))?;
            "albedo.png"
        }
        None => "photo.png",
    };
    let mut material = Material {
        base_color: Color::Rgb([1.0, 1.0, 1.0]),
        base_color_texture: Some(PathBuf::from(base_tex)),
        ..Default::default()
    };
    if let Some(r) = &roughness {
        write_scalar_png(r, &out("roughness.png"))?;
        material.roughness_texture = Some(PathBuf::from("roughness.png"));
    }
    if let Some(m) = &metallic {
        write_scalar_png(m, &out("metallic.png"))?;
        material.metallic_texture = Some(PathBuf::from("metallic.png"));
    }

    let mesh_name = match args.format {
        MeshFormat::Glb => {
            let png = std::fs::read(out(base_tex)).with_context(|| format!("reading back {base_tex}"))?;
            let m = glb::GlbMaterial {
                name: "photo".into(),
                base_color_png: Some(png),
                roughness: material.roughness,
                ..Default::default()
            };
            glb::write_glb(&out("mesh.glb"), &mesh, &m)?;
            "mesh.glb"
        }
        MeshFormat::Obj => {
            let m = obj::ObjMaterial {
                name: "photo".into(),
                diffuse: [1.0; 3],
                texture: Some(base_tex.into()),
                roughness: material.roughness,
                metallic: 0.0,
            };
            obj::write_obj(&out("mesh.obj"), &mesh, Some(&m))?;
            "mesh.obj"
        }
        MeshFormat::Ply => {
            ply::write_ply(&out("mesh.ply"), &mesh)?;
            "mesh.ply"
        }
    };

    let mut camera = Camera::new(size.0 as u32, size.1 as u32, intr.vfov_deg() as f32);
    if args.focal.is_some() {
        camera.fov_y_deg = None;
        camera.focal_px = Some(intr.focal_px as f32);
    }
    let mut scene = Scene::new(camera);
    scene.world = Some(World::default());
    scene.objects.push(Object {
        name: "photo".into(),
        shape: Shape::Mesh {
            path: PathBuf::from(mesh_name),
        },
        transform: Transform::default(),
        material,
    });
    let scene_path = out("scene.toml");
    scene.save(&scene_path)?;
    let grid = |n: usize| (n - 1).div_ceil(args.stride) + 1;
    let possible = 2 * (grid(size.0) - 1) * (grid(size.1) - 1);
    ctx.say(format!(
        "{mesh_name}: {} vertices, {} triangles ({} cut at discontinuities or missing depth) -> {}",
        mesh.positions.len(),
        mesh.num_triangles(),
        possible.saturating_sub(mesh.num_triangles()),
        scene_path.display()
    ));
    Ok(())
}
