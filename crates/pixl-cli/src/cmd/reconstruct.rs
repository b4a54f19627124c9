//! `pixl reconstruct`: a photo + its depth map (+ optional material maps) → a scene folder with
//! a textured mesh, its textures and a `scene.toml` whose camera reproduces the photo's framing
//! (paper §3.4). The work is `pixl_pipeline`'s (photo, depth, reconstruct); this module parses
//! the flags, resolves estimator weights, and prints.
//!
//! - **Without `--depth`** the depth is estimated from the photo with Depth Anything 3 metric
//!   (`da3-metric`; weights as in `pixl models`), sky as missing depth (no mesh: the scene's world
//!   stands in for it).
//! - **Focal length** (camera and metric scale): `--focal`, `--fov`, the photo's EXIF, else 50°
//!   vertical (`pixl_pipeline::exif`).
//! - **`--depth-kind`** / **`--depth-range`**: `pixl_pipeline::depth` (relative depth and
//!   disparity mapped to NEAR,FAR; 0 and negative values are missing depth). A depth map of
//!   another size than the photo is resampled bilinearly to it, with a warning.
//! - **Size**: without `--stride`, the smallest stride giving at most `--max-triangles`
//!   triangles is used (and said).
//! - **Normals** (`--normals`): the mesh's vertex normals from a camera-space normal map, a file
//!   (`pixl estimate normals` writes one) or `marigold` (Marigold Normals run on the photo);
//!   `pixl_pipeline::normals`.
use crate::Ctx;
use anyhow::{bail, Context};
use pixl_core::Image;
use pixl_pipeline::depth::DepthFile;
use pixl_pipeline::estimators::MarigoldNormalsEstimator;
use pixl_pipeline::reconstruct::{Maps, MeshSettings, DEFAULT_MAX_TRIANGLES, OUTPUT_FILES};
use pixl_pipeline::Photo;
use pixl_render::depth::{self, DepthMap};
use std::path::{Path, PathBuf};

/// What the values of a depth file are (`pixl_pipeline::depth::DepthKind`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DepthKind {
    /// Z-depth in metres.
    Metric,
    /// Depth up to an unknown scale and shift (e.g. da3-mono): mapped to --depth-range.
    Relative,
    /// Inverse depth up to an unknown scale and shift (e.g. Depth Anything 2): mapped to --depth-range.
    Disparity,
}

impl From<DepthKind> for pixl_pipeline::depth::DepthKind {
    fn from(k: DepthKind) -> Self {
        match k {
            DepthKind::Metric => Self::Metric,
            DepthKind::Relative => Self::Relative,
            DepthKind::Disparity => Self::Disparity,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MeshFormat {
    Glb,
    Obj,
    Ply,
}

impl From<MeshFormat> for pixl_pipeline::reconstruct::MeshFormat {
    fn from(f: MeshFormat) -> Self {
        match f {
            MeshFormat::Glb => Self::Glb,
            MeshFormat::Obj => Self::Obj,
            MeshFormat::Ply => Self::Ply,
        }
    }
}

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  pixl reconstruct --image photo.jpg -o scene/                    # depth from Depth Anything 3 metric\n  \
pixl reconstruct --image photo.png --depth depth.exr --albedo albedo.png --fov 60 -o scene/\n  \
pixl reconstruct --image photo.jpg --depth disp.png --depth-kind disparity --depth-range 0.5,8 -o scene/\n  \
pixl reconstruct --image photo.jpg --normals marigold -o scene/      # shading normals from Marigold Normals\n  \
pixl reconstruct --image photo.jpg --normals normals.exr -o scene/   # ... or from `pixl estimate normals`\n\n\
Without --depth the weights of da3-metric (with --normals marigold: marigold-normals; with --materials \
marigold: marigold-appearance) are looked up in --models DIR, then the Hugging Face cache, \
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
    /// The mesh's shading normals: a camera-space normal map file (EXR in [-1, 1], or PNG/JPEG
    /// storing n/2 + 1/2; X right, Y up, Z towards the camera), as `pixl estimate normals` writes,
    /// or `marigold` to estimate them from the photo with Marigold Normals (minutes on a CPU; the
    /// time is shown first). A file named `marigold` is given as ./marigold.
    #[arg(long, value_name = "FILE|marigold", value_parser = parse_normals)]
    pub normals: Option<NormalsSource>,
    /// Longest side Marigold processes with --normals marigold (multiple of 8; default 768).
    #[arg(long, value_name = "PX")]
    pub normals_res: Option<usize>,
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
    pub weights: crate::weights::WeightsArgs,
}

/// Where `--normals` comes from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum NormalsSource {
    /// Marigold Normals, run on the photo.
    Marigold,
    /// A normal-map file.
    File(PathBuf),
}

fn parse_normals(s: &str) -> Result<NormalsSource, String> {
    match s {
        "" => Err("give a normal-map file (.exr, .png) or `marigold`".into()),
        "marigold" => Ok(NormalsSource::Marigold),
        path => Ok(NormalsSource::File(PathBuf::from(path))),
    }
}

/// Where the mesh's material maps come from besides the flags that name files.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MaterialSource {
    /// Marigold-IID Appearance (albedo, roughness, metallic).
    Marigold,
}

/// Reads a map as stored and checks its size and finiteness.
fn read_map(what: &str, path: &Path, size: (usize, usize)) -> anyhow::Result<Image> {
    let img = pixl_core::io::read_image(path).with_context(|| format!("reading the {what} map"))?;
    pixl_pipeline::reconstruct::check_map(what, &path.display().to_string(), &img, size)?;
    Ok(img)
}

/// The photo's metric depth at its size: from `--depth`, else estimated with da3-metric.
fn depth_of(args: &Args, photo: &Photo, ctx: &Ctx) -> anyhow::Result<DepthMap> {
    let size = photo.size();
    let Some(path) = &args.depth else {
        pixl_pipeline::estimators::check_process_res(args.process_res)?;
        ctx.say(format!(
            "no --depth: estimating depth with da3-metric (focal {:.1} px from {})",
            photo.focal.px, photo.focal.source
        ));
        let est = crate::estimators::estimate_depth(
            photo,
            crate::estimators::DepthModel::Da3Metric,
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
        return Ok(DepthMap::new(
            size.0,
            size.1,
            pixl_pipeline::estimators::depth_without_sky(&est.estimate),
        )?);
    };
    let how = DepthFile {
        kind: args.depth_kind.unwrap_or(DepthKind::Metric).into(),
        range: args
            .depth_range
            .as_deref()
            .map(pixl_pipeline::depth::parse_range)
            .transpose()?,
        scale: args.depth_scale,
    };
    Ok(pixl_pipeline::depth::read_depth_file(path, &how, size)?)
}

/// The photo's normals with Marigold Normals (`--normals marigold`), in the scene's frame.
fn marigold_normals(args: &Args, photo: &Photo, ctx: &Ctx) -> anyhow::Result<Image> {
    let (m, resolved) = crate::normals::load(&args.device, &args.weights, ctx)?;
    let flags = crate::normals::MarigoldNormalsArgs {
        res: args.normals_res,
        ..Default::default()
    };
    let opts = flags.options(false);
    let (w, h) = photo.size();
    crate::normals::announce(&m, w, h, &opts)?;
    let (steps, res) = m.resolve(&opts)?;
    let est = MarigoldNormalsEstimator::new(m, opts, crate::normals::MODEL);
    let normals = pixl_pipeline::normals::estimate_normals(&est, photo, &crate::ctx::Bars::new(ctx))?;
    ctx.say(format!(
        "normals from {} ({steps} steps at {res} px; weights: {} from {})",
        crate::normals::MODEL,
        resolved.spec.licence,
        resolved.source
    ));
    Ok(normals)
}

/// The material maps of the flags (`--albedo`, `--roughness`, `--metallic`, `--normals`) or of
/// Marigold-IID Appearance (`--materials marigold`).
fn maps_of(args: &Args, photo: &Photo, ctx: &Ctx) -> anyhow::Result<Maps> {
    let size = photo.size();
    let normals = match &args.normals {
        Some(NormalsSource::File(p)) => {
            Some(pixl_pipeline::normals::read_normals(p, size).context("reading the normal map")?)
        }
        Some(NormalsSource::Marigold) => Some(marigold_normals(args, photo, ctx)?),
        None => None,
    };
    if args.materials == Some(MaterialSource::Marigold) {
        let (m, resolved) = crate::iid::load(
            pixl_estimate::marigold::IidVariant::Appearance,
            &args.device,
            &args.weights,
            ctx,
        )?;
        let iid = crate::iid::IidArgs {
            res: args.materials_res,
            ..Default::default()
        };
        let pred = crate::iid::run(&m, &photo.srgb(), &iid, "materials", ctx)?;
        let mats = pixl_pipeline::estimators::Materials::from_prediction(&pred)?;
        ctx.say(format!(
            "materials from marigold-appearance ({} steps at {}x{}; weights: {} from {})",
            pred.steps, pred.processed_size.0, pred.processed_size.1, resolved.spec.licence, resolved.source
        ));
        // The linear albedo is written as an sRGB texture, as an EXR albedo map would be.
        return Ok(Maps {
            albedo: Some((mats.albedo_linear, true)),
            roughness: Some(mats.roughness),
            metallic: Some(mats.metallic),
            normals,
        });
    }
    Ok(Maps {
        albedo: args
            .albedo
            .as_ref()
            .map(|p| read_map("albedo", p, size).map(|m| (m, pixl_core::io::extension(p) == "exr")))
            .transpose()?,
        roughness: args
            .roughness
            .as_ref()
            .map(|p| read_map("roughness", p, size))
            .transpose()?,
        metallic: args
            .metallic
            .as_ref()
            .map(|p| read_map("metallic", p, size))
            .transpose()?,
        normals,
    })
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    let started = std::time::Instant::now();
    // An existing scene (with the lights someone placed) is replaced only with --force; none of
    // the files written may be an input.
    let mut inputs: Vec<&Path> = vec![&args.image];
    inputs.extend(args.depth.as_deref());
    inputs.extend(
        [&args.albedo, &args.roughness, &args.metallic]
            .into_iter()
            .flatten()
            .map(PathBuf::as_path),
    );
    if let Some(NormalsSource::File(p)) = &args.normals {
        inputs.push(p);
    }
    if args.normals_res.is_some() && args.normals != Some(NormalsSource::Marigold) {
        bail!("--normals-res sets Marigold's resolution: it needs --normals marigold");
    }
    pixl_core::output::check_output_dir(&args.out, args.force, OUTPUT_FILES, &inputs)?;
    if args.max_triangles < 2 {
        bail!("--max-triangles {}: must be at least 2", args.max_triangles);
    }
    if args.stride == Some(0) {
        bail!("--stride must be at least 1");
    }
    if let Some(r) = &args.depth_range {
        pixl_pipeline::depth::parse_range(r)?;
    }
    let photo = Photo::open(&args.image, args.focal, args.fov)?;
    let size = photo.size();
    if size.0 < 2 || size.1 < 2 {
        bail!(
            "{}: the photo is {}x{}; a mesh needs at least 2x2 pixels",
            args.image.display(),
            size.0,
            size.1
        );
    }
    let depth_map = depth_of(&args, &photo, ctx)?;
    let maps = maps_of(&args, &photo, ctx)?;
    let settings = MeshSettings {
        stride: args.stride,
        max_triangles: args.max_triangles,
        max_jump: args.max_jump,
        pixel_centres: args.pixel_centres,
    };
    let bars = crate::ctx::Bars::new(ctx);
    let depth_name = args
        .depth
        .as_ref()
        .map(|p| p.display().to_string())
        .unwrap_or_else(|| "the estimated depth".into());
    let geometry = pixl_pipeline::reconstruct::reconstruct(&photo, &depth_map, &depth_name, &maps, &settings, &bars)?;

    // What this run creates is removed again if it fails.
    let mut created = pixl_core::output::Provisional::new();
    created.create_dir_all(&args.out)?;
    let scene_path = geometry.write(&args.out, args.format.into(), &[])?;
    let mesh_name = match args.format {
        MeshFormat::Glb => "mesh.glb",
        MeshFormat::Obj => "mesh.obj",
        MeshFormat::Ply => "mesh.ply",
    };
    let mesh = &geometry.mesh;
    ctx.say(format!(
        "{mesh_name}: {} vertices, {} triangles ({} cut at discontinuities or missing depth) -> {}",
        mesh.positions.len(),
        mesh.num_triangles(),
        geometry.triangles_cut(),
        scene_path.display()
    ));
    if args.json {
        let intr = &geometry.intrinsics;
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
            "focal_source": photo.focal.source.to_string(),
            "stride": geometry.stride,
            "vertices": mesh.positions.len(),
            "triangles": mesh.num_triangles(),
            "triangles_cut": geometry.triangles_cut(),
            "materials": match args.materials {
                Some(MaterialSource::Marigold) => "marigold-appearance",
                None if args.albedo.is_some() => "maps",
                None => "photo",
            },
            "normals": match &args.normals {
                Some(NormalsSource::Marigold) => Some(crate::normals::MODEL),
                Some(NormalsSource::File(_)) => Some("file"),
                None => None,
            },
            "seconds": started.elapsed().as_secs_f64(),
        }))?;
    }
    created.keep();
    Ok(())
}
