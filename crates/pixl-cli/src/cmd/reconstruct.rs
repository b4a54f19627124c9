//! `pixl reconstruct`: a photo + its depth map (+ optional material maps) → a scene folder with
//! a textured mesh, its textures and a `scene.toml` whose camera reproduces the photo's framing
//! (issue 4, part 2; paper §3.4).
//!
//! The mesh lives in the camera's space (camera at the origin looking down −Z, +Y up; see
//! `pixl_render::depth`), so the scene's camera is the default one with the photo's size and
//! field of view. The mesh reaches the frame's edges (outermost vertices on the image border, not
//! at the border pixels' centres) unless `--pixel-centres`.
//!
//! - **Without `--depth`** the depth is estimated from the photo with Depth Anything 3 metric
//!   (`da3-metric`; weights as in `pixl models`), sky as missing depth (no mesh: the scene's world
//!   stands in for it).
//! - **Focal length** (camera and metric scale): `--focal`, `--fov`, the photo's EXIF, else
//!   [`DEFAULT_FOV_DEG`] vertical (see [`super::exif`]).
//! - **`--depth-kind`**: `metric` (metres, as stored); `relative` (depth up to an unknown affine
//!   map: its smallest and largest valid values map linearly to `--depth-range NEAR,FAR`);
//!   `disparity` (inverse depth up to an affine map: largest → NEAR, smallest → FAR, linear in
//!   1/depth). Without `--depth-range` they use [`DEFAULT_DEPTH_RANGE`] with a warning. In every
//!   kind, 0 (and negative) values are missing depth: their triangles are cut.
//! - A depth map of another size than the photo is resampled bilinearly to it (with a warning),
//!   over valid samples only: a pixel whose valid neighbours carry less than half of the weight
//!   stays missing. Depth must be finite. Other maps must have the photo's size.
//! - **Size**: without `--stride`, the smallest stride giving at most `--max-triangles`
//!   triangles is used (and said).
use crate::Ctx;
use anyhow::{bail, Context};
use pixl_core::Image;
use pixl_render::depth::{self, DepthMap, Intrinsics, MeshOptions};
use pixl_render::export::{glb, obj, ply};
use pixl_render::scene::{Camera, Color, Material, Object, Scene, Shape, Transform, World};
use std::path::{Path, PathBuf};

/// Vertical field of view assumed when neither `--fov` nor `--focal` nor EXIF gives one.
pub const DEFAULT_FOV_DEG: f64 = 50.0;
/// Near and far depth (m) that relative depth and disparity map to without `--depth-range`.
pub const DEFAULT_DEPTH_RANGE: (f32, f32) = (1.0, 10.0);
/// Files `reconstruct` may write in its output folder.
const OUTPUT_FILES: &[&str] = &[
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
/// Triangle budget that picks the stride when `--stride` is not given.
pub const DEFAULT_MAX_TRIANGLES: usize = 2_000_000;

/// What the values of a depth file are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DepthKind {
    /// Z-depth in metres.
    Metric,
    /// Depth up to an unknown scale and shift (e.g. da3-mono): mapped to --depth-range.
    Relative,
    /// Inverse depth up to an unknown scale and shift (e.g. Depth Anything 2): mapped to --depth-range.
    Disparity,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MeshFormat {
    Glb,
    Obj,
    Ply,
}

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  pixl reconstruct --image photo.jpg -o scene/                    # depth from Depth Anything 3 metric\n  \
pixl reconstruct --image photo.png --depth depth.exr --albedo albedo.png --fov 60 -o scene/\n  \
pixl reconstruct --image photo.jpg --depth disp.png --depth-kind disparity --depth-range 0.5,8 -o scene/\n\n\
Without --depth the weights of da3-metric are looked up in --models DIR, then the Hugging Face cache, \
then downloaded once (see `pixl models`); --offline never downloads."
)]
pub struct Args {
    /// The photo (PNG/JPEG/EXR); its size is the camera's.
    #[arg(long)]
    pub image: PathBuf,
    /// Z-depth map (EXR channel Z/Y/R, 16-bit PNG × --depth-scale, or .npy). Without it the depth
    /// is estimated from the photo with da3-metric.
    #[arg(long)]
    pub depth: Option<PathBuf>,
    /// What the depth file holds (default metric).
    #[arg(long, value_enum, requires = "depth")]
    pub depth_kind: Option<DepthKind>,
    /// NEAR,FAR in metres for --depth-kind relative/disparity (default 1,10 with a warning).
    #[arg(long, value_name = "NEAR,FAR", requires = "depth")]
    pub depth_range: Option<String>,
    /// Estimate the textures from the photo: `marigold` runs Marigold-IID Appearance for the
    /// albedo, roughness and metallic maps (minutes on a CPU; the time is shown first), so the
    /// photo's own shading is not baked into the colour. Default: the photo is the texture.
    #[arg(long, value_enum, conflicts_with_all = ["albedo", "roughness", "metallic"])]
    pub materials: Option<MaterialSource>,
    /// Longest side Marigold processes with --materials marigold (multiple of 8; default 768).
    #[arg(long, value_name = "PX", requires = "materials")]
    pub materials_res: Option<usize>,
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
    /// Vertical field of view in degrees (else --focal, else the photo's EXIF, else 50).
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
    /// Keep every N-th pixel in x and y (default: the smallest within --max-triangles).
    #[arg(long)]
    pub stride: Option<usize>,
    /// Most triangles when --stride is not given (the stride is raised until the grid fits).
    #[arg(long, default_value_t = DEFAULT_MAX_TRIANGLES)]
    pub max_triangles: usize,
    /// Put every vertex at its pixel's centre. By default the outermost vertices sit on the
    /// image's edges (at the border pixels' depths), so that the mesh covers the whole frame
    /// and renders of it have no half-pixel rim of background.
    #[arg(long)]
    pub pixel_centres: bool,
    /// Mesh file format.
    #[arg(long, value_enum, default_value_t = MeshFormat::Glb)]
    pub format: MeshFormat,
    /// Output folder (created if missing; must be empty unless --force).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Write into an output folder that already has files in it: its scene.toml is replaced,
    /// with the lights it had.
    #[arg(long)]
    pub force: bool,
    /// Print a JSON summary on stdout (even with --quiet) instead of the summary line.
    #[arg(long)]
    pub json: bool,
    /// Longest side the photo is resized to for depth estimation (without --depth).
    #[arg(long, default_value_t = 504)]
    pub process_res: usize,
    /// Device for the estimators (depth, materials): cpu, or cuda[:N] (needs a CUDA build: scripts/cuda-setup.sh; `pixl doctor` lists devices).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    #[command(flatten)]
    pub weights: super::models::WeightsArgs,
}

/// Where the mesh's material maps come from besides the flags that name files.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MaterialSource {
    /// Marigold-IID Appearance (albedo, roughness, metallic).
    Marigold,
}

/// Parses `NEAR,FAR` (metres, 0 < NEAR < FAR).
pub fn parse_range(s: &str) -> anyhow::Result<(f32, f32)> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let nums: Option<Vec<f32>> = parts.iter().map(|p| p.parse::<f32>().ok()).collect();
    match nums.as_deref() {
        Some(&[near, far]) if near.is_finite() && far.is_finite() && 0.0 < near && near < far => Ok((near, far)),
        _ => bail!("--depth-range {s:?}: expected NEAR,FAR in metres with 0 < NEAR < FAR, e.g. 0.5,8"),
    }
}

/// Maps relative depth or disparity to metres in `[near, far]` (see the module docs); values
/// ≤ 0 stay 0 (missing). `Metric` leaves the map unchanged.
pub fn to_metric(map: &mut DepthMap, kind: DepthKind, (near, far): (f32, f32)) {
    if kind == DepthKind::Metric {
        return;
    }
    let valid = |v: f32| v.is_finite() && v > 0.0;
    let (lo, hi) = map
        .data
        .iter()
        .copied()
        .filter(|v| valid(*v))
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if lo > hi {
        return;
    }
    let (lo, hi) = (lo as f64, hi as f64);
    let (near, far) = (near as f64, far as f64);
    // A constant map: everything at the middle of the range.
    let t_of = |v: f64| if hi > lo { (v - lo) / (hi - lo) } else { 0.5 };
    for v in map.data.iter_mut() {
        if !valid(*v) {
            *v = 0.0;
            continue;
        }
        let t = t_of(*v as f64);
        *v = match kind {
            DepthKind::Relative => near + t * (far - near),
            // Largest disparity = nearest.
            _ => 1.0 / (1.0 / far + t * (1.0 / near - 1.0 / far)),
        } as f32;
    }
}

/// Bilinear resampling of a depth map to `w` × `h` (pixel centres aligned), over valid samples
/// only: a pixel whose valid neighbours carry less than half the weight is missing (0).
pub fn resize_depth(src: &DepthMap, w: usize, h: usize) -> anyhow::Result<DepthMap> {
    let axis = |dst: usize, n: usize, i: usize| -> (usize, usize, f64) {
        let s = ((i as f64 + 0.5) * n as f64 / dst as f64 - 0.5).clamp(0.0, (n - 1) as f64);
        let i0 = s.floor() as usize;
        (i0, (i0 + 1).min(n - 1), s - i0 as f64)
    };
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        let (y0, y1, fy) = axis(h, src.height, y);
        for x in 0..w {
            let (x0, x1, fx) = axis(w, src.width, x);
            let taps = [
                (x0, y0, (1.0 - fx) * (1.0 - fy)),
                (x1, y0, fx * (1.0 - fy)),
                (x0, y1, (1.0 - fx) * fy),
                (x1, y1, fx * fy),
            ];
            let (mut sum, mut wsum) = (0.0f64, 0.0f64);
            for (sx, sy, wt) in taps {
                let d = src.get(sx, sy);
                if d.is_finite() && d > 0.0 {
                    sum += wt * d as f64;
                    wsum += wt;
                }
            }
            if wsum >= 0.5 {
                out[y * w + x] = (sum / wsum) as f32;
            }
        }
    }
    Ok(DepthMap::new(w, h, out)?)
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
    let ctx = &ctx.for_json(args.json);
    let started = std::time::Instant::now();
    // An existing scene (with the lights someone placed) is replaced only with --force; none of
    // the files written may be an input.
    let mut inputs: Vec<&Path> = vec![&args.image];
    inputs.extend(args.depth.as_deref());
    inputs.extend(
        [&args.albedo, &args.roughness, &args.metallic, &args.normals]
            .into_iter()
            .flatten()
            .map(PathBuf::as_path),
    );
    pixl_core::output::check_output_dir(&args.out, args.force, OUTPUT_FILES, &inputs)?;
    if args.max_triangles < 2 {
        bail!("--max-triangles {}: must be at least 2", args.max_triangles);
    }
    if args.stride == Some(0) {
        bail!("--stride must be at least 1");
    }
    let range = args.depth_range.as_deref().map(parse_range).transpose()?;
    let photo = pixl_core::io::read_image(&args.image).context("reading the photo")?;
    pixl_core::io::ensure_finite(&args.image, &photo)?;
    let size = (photo.width, photo.height);
    if size.0 < 2 || size.1 < 2 {
        bail!(
            "{}: the photo is {}x{}; a mesh needs at least 2x2 pixels",
            args.image.display(),
            size.0,
            size.1
        );
    }
    let focal = super::exif::photo_focal(&args.image, size.0, size.1, args.focal, args.fov)?;
    let (depth_map, depth_name): (DepthMap, String) = match &args.depth {
        Some(path) => (read_depth_arg(&args, path, size, range)?, path.display().to_string()),
        None => {
            super::estimate::check_process_res(args.process_res)?;
            let rgb = super::estimate::read_photo(&args.image)?;
            ctx.say(format!(
                "no --depth: estimating depth with da3-metric (focal {:.1} px from {})",
                focal.px, focal.source
            ));
            let est = super::estimate::estimate_depth(
                &rgb,
                super::estimate::DepthModel::Da3Metric,
                focal,
                args.process_res,
                &args.device,
                &args.weights,
                ctx,
            )?;
            let sky = est.estimate.sky_mask.iter().filter(|s| **s).count();
            ctx.say(format!(
                "depth from da3-metric (weights: {} from {}); {:.1} % sky left to the world",
                est.weights.spec.licence,
                est.weights.source,
                100.0 * sky as f64 / (size.0 * size.1) as f64
            ));
            (
                DepthMap::new(size.0, size.1, est.depth_without_sky())?,
                "the estimated depth".to_string(),
            )
        }
    };
    let stride = match args.stride {
        Some(s) => {
            let n = grid_triangles(size.0, size.1, s);
            if n > args.max_triangles {
                tracing::warn!(
                    "--stride {s} gives up to {n} triangles (more than --max-triangles {})",
                    args.max_triangles
                );
            }
            s
        }
        None => {
            let s = auto_stride(size.0, size.1, args.max_triangles);
            if s > 1 {
                ctx.say(format!(
                    "stride {s} (every {s}th pixel): a {}x{} photo at stride 1 would give {} triangles, \
more than --max-triangles {}; pass --stride 1 to keep them all",
                    size.0,
                    size.1,
                    grid_triangles(size.0, size.1, 1),
                    args.max_triangles
                ));
            }
            s
        }
    };
    let opts = MeshOptions {
        max_jump: args.max_jump,
        stride,
        full_frame: !args.pixel_centres,
        ..Default::default()
    };
    if depth_map.count_valid(opts.max_depth) == 0 {
        bail!("{depth_name}: no pixel has a positive depth");
    }
    let intr = Intrinsics::from_focal_px(size.0, size.1, focal.px)?;
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
    let (albedo, roughness, metallic) = match args.materials {
        Some(MaterialSource::Marigold) => {
            let rgb = super::estimate::read_photo(&args.image)?;
            let (m, resolved) = super::iid::load(
                pixl_estimate::marigold::IidVariant::Appearance,
                &args.device,
                &args.weights,
                ctx,
            )?;
            let iid = super::iid::IidArgs {
                res: args.materials_res,
                ..Default::default()
            };
            let pred = super::iid::run(&m, &rgb, &iid, "materials", ctx)?;
            let mats = super::estimate::Materials::from_prediction(&pred)?;
            ctx.say(format!(
                "materials from marigold-appearance ({} steps at {}x{}; weights: {} from {})",
                pred.steps, pred.processed_size.0, pred.processed_size.1, resolved.spec.licence, resolved.source
            ));
            // The linear albedo is written as an sRGB texture, as an EXR albedo map would be.
            (
                Some((PathBuf::from("albedo.exr"), mats.albedo_linear)),
                Some(mats.roughness),
                Some(mats.metallic),
            )
        }
        None => (
            args.albedo
                .as_ref()
                .map(|p| read_map("albedo", p, size).map(|m| (p.clone(), m)))
                .transpose()?,
            args.roughness
                .as_ref()
                .map(|p| read_map("roughness", p, size))
                .transpose()?,
            args.metallic
                .as_ref()
                .map(|p| read_map("metallic", p, size))
                .transpose()?,
        ),
    };

    let mesh = depth::depth_to_mesh(&depth_map, &intr, normals.as_ref(), &opts)?;
    if mesh.indices.is_empty() {
        // Name the cause that cut the most: a grid too coarse for the image, missing depth, or
        // depth jumps.
        let c = depth::cut_counts(&depth_map, &opts);
        let total = c.missing_depth + c.depth_jump;
        if c.grid.0 < 2 || c.grid.1 < 2 || (stride > 1 && total < 32) {
            bail!(
                "--stride {stride} leaves a {}x{} grid of samples ({total} triangles, none kept) on a {}x{} photo; use a smaller --stride",
                c.grid.0,
                c.grid.1,
                size.0,
                size.1
            );
        }
        if c.missing_depth >= c.depth_jump {
            bail!(
                "{depth_name}: no triangle has valid depth at all three corners ({} of {} lack depth); check the depth map (0, negative and beyond-far values count as missing)",
                c.missing_depth,
                total
            );
        }
        bail!(
            "{depth_name}: every triangle was cut at a depth jump over --max-jump {} ({} of {}; at --stride {stride} neighbouring samples are {stride} pixels apart); raise --max-jump{}",
            args.max_jump,
            c.depth_jump,
            total,
            if stride > 1 { " or lower --stride" } else { "" }
        );
    }

    // What this run creates is removed again if it fails.
    let mut created = pixl_core::output::Provisional::new();
    created.create_dir_all(&args.out)?;
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
    if focal.source == super::exif::FocalSource::Flag {
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
    let possible = grid_triangles(size.0, size.1, stride);
    ctx.say(format!(
        "{mesh_name}: {} vertices, {} triangles ({} cut at discontinuities or missing depth) -> {}",
        mesh.positions.len(),
        mesh.num_triangles(),
        possible.saturating_sub(mesh.num_triangles()),
        scene_path.display()
    ));
    if args.json {
        ctx.print_json(&serde_json::json!({
            "image": args.image,
            "depth": args.depth,
            "output": args.out,
            "scene": scene_path,
            "mesh": args.out.join(mesh_name),
            "width": size.0,
            "height": size.1,
            "focal_px": intr.focal_px,
            "fov_y_deg": intr.vfov_deg(),
            "focal_source": focal.source.to_string(),
            "stride": stride,
            "vertices": mesh.positions.len(),
            "triangles": mesh.num_triangles(),
            "triangles_cut": possible.saturating_sub(mesh.num_triangles()),
            "materials": match args.materials {
                Some(MaterialSource::Marigold) => "marigold-appearance",
                None if args.albedo.is_some() => "maps",
                None => "photo",
            },
            "seconds": started.elapsed().as_secs_f64(),
        }))?;
    }
    created.keep();
    Ok(())
}

/// Reads `--depth`, checks it, converts its kind to metres and resamples it to the photo's size.
fn read_depth_arg(
    args: &Args,
    path: &Path,
    size: (usize, usize),
    range: Option<(f32, f32)>,
) -> anyhow::Result<DepthMap> {
    let mut map: DepthMap = depth::read_depth(path, args.depth_scale)?;
    if let Some(i) = map.data.iter().position(|d| !d.is_finite()) {
        let count = map.data.iter().filter(|d| !d.is_finite()).count();
        bail!(
            "{}: {count} non-finite depth values (NaN/Inf), first at x={}, y={}; mark missing depth as 0 instead",
            path.display(),
            i % map.width,
            i / map.width
        );
    }
    let kind = args.depth_kind.unwrap_or(DepthKind::Metric);
    if kind == DepthKind::Metric {
        if range.is_some() {
            tracing::warn!("--depth-range is ignored for metric depth");
        }
    } else {
        let r = match range {
            Some(r) => r,
            None => {
                let (near, far) = DEFAULT_DEPTH_RANGE;
                tracing::warn!(
                    "{}: {kind:?} depth without --depth-range: mapping it to {near}-{far} m (the default); \
pass --depth-range NEAR,FAR for the scene's real scale",
                    path.display()
                );
                DEFAULT_DEPTH_RANGE
            }
        };
        to_metric(&mut map, kind, r);
    }
    if (map.width, map.height) != size {
        tracing::warn!(
            "{}: the depth map is {}x{} but the photo is {}x{}; resampling it bilinearly to the photo",
            path.display(),
            map.width,
            map.height,
            size.0,
            size.1
        );
        map = resize_depth(&map, size.0, size.1)?;
    }
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_and_disparity_map_to_the_range() {
        let mut m = DepthMap::new(4, 1, vec![2.0, 4.0, 6.0, 0.0]).unwrap();
        to_metric(&mut m, DepthKind::Relative, (1.0, 5.0));
        assert_eq!(m.data, vec![1.0, 3.0, 5.0, 0.0]);
        // Disparity: 6 (largest) → near 1 m, 2 → far 5 m, 4 → halfway in 1/d: 1/(0.2 + 0.4) m.
        let mut m = DepthMap::new(4, 1, vec![2.0, 4.0, 6.0, -1.0]).unwrap();
        to_metric(&mut m, DepthKind::Disparity, (1.0, 5.0));
        let want = [5.0, 1.0 / 0.6, 1.0, 0.0];
        for (a, b) in m.data.iter().zip(want) {
            assert!((*a as f64 - b).abs() < 1e-6, "{:?}", m.data);
        }
        let mut m = DepthMap::new(2, 1, vec![7.0, 7.0]).unwrap();
        to_metric(&mut m, DepthKind::Relative, (2.0, 4.0));
        assert_eq!(m.data, vec![3.0, 3.0]);
        assert_eq!(parse_range(" 0.5, 8").unwrap(), (0.5, 8.0));
        for bad in ["8,0.5", "0,1", "1", "a,b", "1,2,3", "1,inf"] {
            assert!(parse_range(bad).is_err(), "{bad}");
        }
    }

    /// Against a naive bilinear interpolation of a linear ramp (exact for bilinear), and the
    /// missing-sample rule.
    #[test]
    fn resize_is_bilinear_over_valid_samples() {
        let (sw, sh) = (4usize, 3usize);
        let f = |x: f64, y: f64| 1.0 + 0.5 * x + 0.25 * y;
        let src = DepthMap::new(
            sw,
            sh,
            (0..sw * sh)
                .map(|i| f((i % sw) as f64, (i / sw) as f64) as f32)
                .collect(),
        )
        .unwrap();
        let (w, h) = (7usize, 5usize);
        let out = resize_depth(&src, w, h).unwrap();
        for y in 0..h {
            for x in 0..w {
                let sx = ((x as f64 + 0.5) * sw as f64 / w as f64 - 0.5).clamp(0.0, (sw - 1) as f64);
                let sy = ((y as f64 + 0.5) * sh as f64 / h as f64 - 0.5).clamp(0.0, (sh - 1) as f64);
                assert!((out.get(x, y) as f64 - f(sx, sy)).abs() < 1e-5, "({x},{y})");
            }
        }
        // 2x1 → 4x1 with the right sample missing: x=0,1 see mostly the left sample; x=2,3 mostly
        // the missing one and stay missing.
        let src = DepthMap::new(2, 1, vec![3.0, 0.0]).unwrap();
        let out = resize_depth(&src, 4, 1).unwrap();
        assert_eq!(out.data, vec![3.0, 3.0, 0.0, 0.0]);
    }

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
