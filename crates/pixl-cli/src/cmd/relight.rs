//! `pixl relight`: `Î_T = f_θ(I_S, C_T)` for one photograph of any size (paper §3.2, §3.4).
//!
//! Two forms:
//! - **From a photo, in one command**: `pixl relight photo.jpg --preset NAME -o relit.png`
//!   (and/or `--light 'FLAGS'`, `--scene lights.toml`) runs the inference pipeline of §3.4:
//!   the photo's reconstruction (depth from `--depth`, else Depth Anything 3), in memory → lights
//!   → the native path tracer at the working size → `compose` → the network. The photo is decoded
//!   once; the scene is written only with `--keep DIR`, which keeps every intermediate.
//! - **With a given C_T**: `pixl relight --source photo.png --intrinsics ct.exr -o relit.png`.
//! - **Like a reference photo**: `pixl relight photo.jpg --like target.jpg -o relit.png`: C_T is
//!   the target photo's own (Marigold-IID-Lighting, App. B's rescale, resized to the photo's
//!   size: `pixl_pipeline::like`), as the paper conditions on target photos in training. No
//!   depth, reconstruction or render; `--keep DIR` keeps CT.exr, CT_sheet.png, before_after.png.
//!
//! Any size: the network runs at a working size (long side `--max-side`, default 1024; the
//! paper trains at 512) and its gain and bias are resized bilinearly to the photo and applied
//! there (`pixl_model::fullres`), so the output has the photo's size and detail. A C_T at the
//! photo's size is area-averaged to the working size (one at the working size is used as is).
//! Before any work the output is checked (its extension decides the format, its folder must
//! exist, it must not be an input) and the network's peak memory is planned
//! (`pixl_model::fullres::plan_memory`, plus the full-size photo and output buffers) and refused
//! with the figure if it exceeds `--max-memory` (default: the memory available now). The steps
//! before the network (reconstruction at full size with a stride that keeps the mesh near the
//! working size, the render at the working size) are not in the plan; they finish and free their
//! memory before the network starts.
//!
//! The stages are `pixl_pipeline`'s (photo, depth, reconstruct, render, relight); this module
//! parses the flags, places the lights and prints. Weights: `--weights` (`bundled`, `pixlrelight`
//! or a file; `crate::weights::network_weights`), else the released checkpoint when it is on disk
//! (its licence printed on every run), else the bundled demo weights compiled into the binary (`pixl_pipeline::relight::BUNDLED_WEIGHTS`, 2.8 MB, so they
//! are there after `cargo install` too). Sources: PNG/JPEG as stored values in [0, 1], EXR as
//! stored (values outside [0, 1] clamped with a warning; non-finite refused). Output `.png` 16-bit, `.jpg`,
//! `.exr` f32, written atomically. With freshly initialised weights the output equals the source
//! exactly, at any size.
use crate::Ctx;
use anyhow::{bail, Context};
use indicatif::{ProgressBar, ProgressStyle};
use pixl_core::Image;
use pixl_model::fullres;
use pixl_pipeline::lights::LightSpec;
use pixl_pipeline::relight::{check_budget, ct_at_working_size, gb, Budget, Network, DEFAULT_MAX_SIDE};
use pixl_pipeline::Photo;
use pixl_render::presets::{apply_preset, PRESETS};
use pixl_render::scene::Light;
use pixl_render::Scene;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

/// The flags `--like` (and its own flags) cannot be given with: the other ways of giving the
/// lighting, and those of the reconstruction and render it does without.
const LIKE_CONFLICTS: &[&str] = &[
    "intrinsics",
    "preset",
    "light",
    "scene",
    "depth",
    "fov",
    "focal",
    "spp",
    "bounces",
];
/// Output formats, by extension.
const OUTPUT_EXTS: &[&str] = &["png", "jpg", "jpeg", "exr"];

#[derive(clap::Args, Debug)]
#[command(after_help = concat!("Examples:\n  \
pixl relight photo.jpg --preset warm-overhead-flash -o relit.png                  # depth from Depth Anything 3\n  \
pixl relight photo.jpg --depth depth.exr --preset cool-side-flash -o relit.png --keep steps/\n  \
pixl relight photo.jpg --depth depth.exr --light '--type spot --from left' -o relit.png\n  \
pixl relight photo.jpg --depth depth.exr --light '--at-pixel 640,300' --light '--type sun --azimuth 40 --elevation 50' -o relit.png\n  \
pixl relight photo.jpg --depth depth.exr --scene lights.toml -o relit.png\n  \
pixl relight --source photo.png --intrinsics ct.exr --weights model.safetensors --out relit.png\n  \
pixl relight photo.jpg --like same-view-other-light.jpg -o relit.png --keep steps/\n\n\
From a photo, `pixl relight` runs reconstruct -> lights -> render -> compose -> network. Lights: --preset\n\
(the paper's five), --light 'FLAGS' (one light, the flags of `pixl light add`; repeatable), --scene FILE\n\
(the [[lights]] of a .toml/.json scene file, in the reconstructed scene's coordinates). They add up.\n\
--keep DIR keeps scene/ (mesh, textures, scene.toml with the lights), passes.exr, CT.exr, CT_sheet.png,\n\
render.png and before_after.png.\n\n\
Any size: the network runs with the long side at --max-side (default 1024) and its per-pixel gain and\n\
bias are resized to the photo and applied there: the output has the photo's size and detail. The memory\n\
this needs is checked first; a request that does not fit is refused with the figure.\n\n\
--like TARGET takes the lighting of another photo of the same view instead of lights: the target's C_T\n\
(albedo, diffuse shading, non-diffuse residual) is estimated with Marigold-IID-Lighting\n\
(prs-eth/marigold-iid-lighting-v1-1, licence OpenRAIL++-M; weights from --models DIR, the Hugging Face\n\
cache, or a one-time download of about 2.6 GB, never with --offline), rescaled as the paper's training\n\
targets are (App. B: joint 98th percentile of shading and residual) and resized to the photo's size. No\n\
depth, mesh or render, so no Depth Anything 3 weights. The two photos should show the same view: a target\n\
of another aspect ratio is stretched to the photo's frame (a warning above 3 %). With --like, --keep DIR\n\
keeps CT.exr (at the photo's size: --intrinsics CT.exr gives the same result again), CT_sheet.png and\n\
before_after.png.\n\n",
crate::scene_axes_help!()))]
pub struct Args {
    /// The photo to relight (.png, .jpg or .exr); the same as --source.
    #[arg(value_name = "PHOTO", conflicts_with = "source")]
    pub photo: Option<PathBuf>,
    /// Source photograph I_S (.png, .jpg or .exr; RGB, values in [0, 1]).
    #[arg(long)]
    pub source: Option<PathBuf>,
    /// Target intrinsics C_T (.exr with albedo.*, shading.* and residual.* channels), at the photo's
    /// size or at the working size. Given, the photo is relit with it (no reconstruction).
    #[arg(long, conflicts_with_all = ["preset", "light", "scene", "depth", "keep"])]
    pub intrinsics: Option<PathBuf>,
    /// Output image (.png: 16-bit; .jpg; .exr: 32-bit float). Its folder must exist.
    #[arg(short = 'o', long)]
    pub out: PathBuf,
    #[arg(long, value_name = "bundled|pixlrelight|FILE", help = crate::weights::NETWORK_WEIGHTS_HELP)]
    pub weights: Option<PathBuf>,
    /// Longest side the network works at (the paper trains at 512); the result is applied at the
    /// photo's full size.
    #[arg(long, default_value_t = DEFAULT_MAX_SIDE, value_parser = crate::ctx::at_least_one_usize)]
    pub max_side: usize,
    /// Most memory the network may plan to use, in GB (default: the memory available now).
    #[arg(long, value_name = "GB")]
    pub max_memory: Option<f64>,
    /// Compute dtype of the network.
    #[arg(long, value_enum, default_value_t = crate::args::DtypeArg::F32)]
    pub dtype: crate::args::DtypeArg,
    /// 8-bit matrix products in the network's linear layers (CPU with AVX-512 VNNI; elsewhere a
    /// warning and f32): the network 1.6-1.8x faster at the small and paper sizes, its output
    /// within 59-70 dB PSNR of f32 (BENCHMARKS.md).
    #[arg(long)]
    pub int8: bool,
    /// Device for the network: cpu, or cuda[:N] (needs a CUDA build: scripts/cuda-setup.sh; `pixl doctor` lists devices).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Light the photo with a preset of the paper (§4.2).
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(PRESETS))]
    pub preset: Option<String>,
    /// One light, given by the flags of `pixl light add` in one quoted word, e.g.
    /// '--type spot --from left --power 300'. Repeatable.
    #[arg(long, value_name = "FLAGS", allow_hyphen_values = true)]
    pub light: Vec<String>,
    /// A .toml/.json scene file whose [[lights]] are added (its other tables are ignored);
    /// positions in the reconstructed scene's frame (camera at the origin looking down -Z, metres).
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Depth map of the photo (as `pixl reconstruct --depth`). Without it the depth is estimated
    /// with Depth Anything 3 (weights: --models DIR, the Hugging Face cache, or a download).
    #[arg(long)]
    pub depth: Option<PathBuf>,
    /// What the depth file holds: metric, relative or disparity (as `pixl reconstruct`).
    #[arg(long, requires = "depth")]
    pub depth_kind: Option<String>,
    /// NEAR,FAR in metres for relative depth or disparity (as `pixl reconstruct`).
    #[arg(long, value_name = "NEAR,FAR", requires = "depth")]
    pub depth_range: Option<String>,
    /// Vertical field of view of the photo in degrees (else --focal, else EXIF, else 50).
    #[arg(long, conflicts_with = "focal")]
    pub fov: Option<f64>,
    /// Focal length of the photo in pixels.
    #[arg(long)]
    pub focal: Option<f64>,
    /// Path-tracing samples per pixel of the render C_T is composed from.
    #[arg(long, default_value_t = 64, value_parser = crate::ctx::at_least_one)]
    pub spp: u32,
    /// Maximum bounces of the render.
    #[arg(long, default_value_t = 8)]
    pub bounces: u32,
    /// Random seed of the render (with --like: of Marigold's initial noise).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Relight like this photo: the target lighting is TARGET's (another photo of the same view),
    /// its C_T estimated with Marigold-IID-Lighting (OpenRAIL++-M weights, found or fetched like
    /// `pixl estimate lighting`'s). Instead of --preset/--light/--scene/--intrinsics; needs no depth.
    #[arg(long, value_name = "TARGET", conflicts_with_all = LIKE_CONFLICTS)]
    pub like: Option<PathBuf>,
    /// With --like: longest side Marigold-IID-Lighting sees, a multiple of 8 (default: the
    /// checkpoint's, 768; 512 is about twice as fast on a CPU).
    #[arg(long, value_name = "PX", requires = "like", conflicts_with_all = LIKE_CONFLICTS)]
    pub like_res: Option<usize>,
    /// With --like: Marigold's denoising steps (default 1, as the paper computes C_T from its
    /// training photos; --seed seeds the initial noise).
    #[arg(
        long,
        value_name = "N",
        requires = "like",
        conflicts_with_all = LIKE_CONFLICTS,
        value_parser = crate::ctx::at_least_one_usize
    )]
    pub like_steps: Option<usize>,
    /// Keep every intermediate in this folder (created; must be empty unless --force).
    #[arg(long, value_name = "DIR")]
    pub keep: Option<PathBuf>,
    /// Allow --keep to write into a folder that has files in it.
    #[arg(long, requires = "keep")]
    pub force: bool,
    /// Print a JSON summary on stdout (sizes, planned memory, files written).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub models: crate::weights::WeightsArgs,
}

/// Parses `--light` words with the flags of `pixl light add`.
#[derive(clap::Parser, Debug)]
#[command(name = "--light", no_binary_name = true, disable_help_flag = true)]
struct LightWords {
    #[command(flatten)]
    spec: LightSpec,
}

/// Parses one `--light` value (whitespace-separated flags).
pub fn parse_light(words: &str) -> anyhow::Result<LightSpec> {
    let parsed = <LightWords as clap::Parser>::try_parse_from(words.split_whitespace()).map_err(|e| {
        let text = e.render().to_string();
        let first = text
            .lines()
            .next()
            .unwrap_or("")
            .trim_start_matches("error: ")
            .to_string();
        anyhow::anyhow!("--light '{words}': {first}")
    })?;
    if !parsed.spec.is_given() {
        bail!("--light '{words}': give the light's flags, e.g. '--type spot --from left'");
    }
    parsed.spec.check().with_context(|| format!("--light '{words}'"))?;
    Ok(parsed.spec)
}

/// The `[[lights]]` of a scene-like file; everything else in it is ignored.
#[derive(serde::Deserialize)]
struct LightsFile {
    #[serde(default)]
    lights: Vec<Light>,
}

/// Reads the lights of `--scene FILE` and validates them.
pub fn read_lights(path: &Path) -> anyhow::Result<Vec<Light>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let file: LightsFile = match pixl_core::io::extension(path).as_str() {
        "toml" => toml::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?,
        "json" => serde_json::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?,
        other => bail!(
            "{}: a lights file must be .toml or .json, not {other:?}",
            path.display()
        ),
    };
    if file.lights.is_empty() {
        bail!("{}: no [[lights]] in it", path.display());
    }
    let mut probe = Scene::new(pixl_render::Camera::new(1, 1, 50.0));
    probe.lights = file.lights.clone();
    probe
        .validate()
        .map_err(|e| anyhow::anyhow!("{}: {}", path.display(), e.to_string().trim_start_matches("<scene>: ")))?;
    Ok(file.lights)
}

fn load_network(ctx: &Ctx, args: &Args, device: &candle_core::Device) -> anyhow::Result<Network> {
    if args.int8 {
        crate::device::check_int8(device, args.dtype.into())?;
    }
    let choice = args.weights.as_deref().map(|p| p.to_string_lossy().into_owned());
    let weights = crate::weights::network_weights(choice.as_deref(), &args.models, ctx)?;
    let sp = spinner(ctx, "loading the weights");
    let net = Network::load(weights.as_deref(), args.dtype.into(), device, args.int8);
    sp.finish_and_clear();
    let net = net?;
    if net.licence.is_some() {
        // Always shown (even under --quiet): the weights restrict how the output may be used.
        eprintln!("{}", net.describe());
    }
    Ok(net)
}

/// `--max-memory` in bytes, checked.
fn max_memory(args: &Args) -> anyhow::Result<Option<u64>> {
    match args.max_memory {
        Some(g) if g.is_finite() && g > 0.0 => Ok(Some((g * 1e9) as u64)),
        Some(g) => bail!("--max-memory {g}: must be a positive number of GB"),
        None => Ok(None),
    }
}

/// A spinner for a step that may take more than a second (hidden under --quiet or without a terminal).
fn spinner(ctx: &Ctx, msg: &str) -> ProgressBar {
    if ctx.quiet || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let pb = ProgressBar::new_spinner();
    if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} {elapsed}") {
        pb.set_style(style);
    }
    pb.set_message(msg.to_string());
    pb.enable_steady_tick(std::time::Duration::from_millis(120));
    pb
}

/// Reads the photo (decoded once; RGB, finite, clamped to [0, 1]) with a spinner.
fn read_photo(ctx: &Ctx, args: &Args, path: &Path) -> anyhow::Result<Photo> {
    let sp = spinner(ctx, &format!("reading {}", path.display()));
    let photo = Photo::open(path, args.focal, args.fov);
    sp.finish_and_clear();
    Ok(photo?)
}

/// Runs the network at the working size and applies its result to the full-size photo, with a
/// progress bar over its blocks.
fn run_network(
    ctx: &Ctx,
    net: &Network,
    photo: Image,
    ct_work: &[f32],
    work: (usize, usize),
    device: &candle_core::Device,
) -> anyhow::Result<Image> {
    let bars = crate::ctx::Bars::new(ctx);
    Ok(pixl_pipeline::relight::relight(
        net, photo, ct_work, work, device, &bars,
    )?)
}

fn write_output(ctx: &Ctx, path: &Path, img: &Image) -> anyhow::Result<()> {
    let sp = spinner(ctx, &format!("writing {}", path.display()));
    pixl_core::io::write_image(path, img)?;
    sp.finish_and_clear();
    Ok(())
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    let photo = match (&args.photo, &args.source) {
        (Some(p), _) | (None, Some(p)) => p.clone(),
        (None, None) => bail!("give the photo: `pixl relight photo.jpg --preset NAME -o relit.png` (see --help)"),
    };
    let mut inputs: Vec<&Path> = vec![&photo];
    for p in [&args.intrinsics, &args.weights, &args.depth, &args.scene, &args.like]
        .into_iter()
        .flatten()
    {
        inputs.push(p);
    }
    pixl_core::output::check_output(&args.out, OUTPUT_EXTS, &inputs)?;
    if args.intrinsics.is_some() {
        return run_with_intrinsics(&args, &photo, ctx);
    }
    if let Some(target) = &args.like {
        return run_like(&args, &photo, target, ctx);
    }
    run_pipeline(&args, &photo, ctx)
}

/// `--source PHOTO --intrinsics CT`.
fn run_with_intrinsics(args: &Args, photo_path: &Path, ctx: &Ctx) -> anyhow::Result<()> {
    let ct_path = args.intrinsics.as_deref().unwrap_or(Path::new(""));
    let device = crate::device::parse_device(&args.device)?;
    let net = load_network(ctx, args, &device)?;
    let photo = read_photo(ctx, args, photo_path)?.image;
    let size = (photo.width, photo.height);
    let work = fullres::working_size(size.0, size.1, args.max_side);
    let ct = pixl_intrinsics::ct::read_ct(ct_path)?;
    let ct_size = (ct.width(), ct.height());
    if ct_size != size && ct_size != work {
        bail!(
            "source {} is {}x{} but intrinsics {} are {}x{}; give C_T at the photo's size or at the working size {}x{} (--max-side {})",
            photo_path.display(),
            size.0,
            size.1,
            ct_path.display(),
            ct_size.0,
            ct_size.1,
            work.0,
            work.1,
            args.max_side
        );
    }
    // Full size: the photo (f32), the encoded output, and a full-size C_T (9 f32 + its EXR decode).
    let per_px = 12 + 8 + if ct_size == size { 72 } else { 0 };
    let budget = check_budget(&net, size, args.max_side, per_px, max_memory(args)?)?;
    let ct_work = ct_at_working_size(&ct, budget.work)?;
    drop(ct);
    let relit = run_network(ctx, &net, photo, &ct_work, budget.work, &device)?;
    write_output(ctx, &args.out, &relit)?;
    report(ctx, args, &net, size, &budget, &[], None)
}

fn report(
    ctx: &Ctx,
    args: &Args,
    net: &Network,
    size: (usize, usize),
    budget: &Budget,
    kept: &[PathBuf],
    like: Option<serde_json::Value>,
) -> anyhow::Result<()> {
    if args.json {
        let mut v = serde_json::json!({
            "output": args.out.display().to_string(),
            "width": size.0,
            "height": size.1,
            "working_width": budget.work.0,
            "working_height": budget.work.1,
            "tokens": budget.plan.tokens,
            "planned_network_bytes": budget.network(),
            "planned_peak_stage": budget.plan.peak().0,
            "planned_full_size_bytes": budget.full,
            "weights": net.name,
            "kept": kept.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
        });
        if let (Some(like), serde_json::Value::Object(m)) = (like, &mut v) {
            m.insert("like".into(), like);
        }
        return ctx.print_json(&v);
    }
    ctx.say(format!(
        "wrote {} ({}x{}; network at {}x{}, planned peak {})",
        args.out.display(),
        size.0,
        size.1,
        budget.work.0,
        budget.work.1,
        gb(budget.total())
    ));
    Ok(())
}

/// The files `--keep` writes directly in its folder.
const KEPT: &[&str] = &[
    "scene",
    "passes.exr",
    "CT.exr",
    "CT_sheet.png",
    "render.png",
    "before_after.png",
];

/// The photo's metric depth at its size: `--depth` (of `--depth-kind`), else Depth Anything 3.
fn depth_of(args: &Args, photo: &Photo, ctx: &Ctx) -> anyhow::Result<pixl_render::depth::DepthMap> {
    let Some(path) = &args.depth else {
        let est = crate::estimators::estimate_depth(
            photo,
            crate::estimators::DepthModel::Da3Metric,
            pixl_pipeline::estimators::DEFAULT_PROCESS_RES,
            "cpu",
            &args.models,
            ctx,
        )
        .context(
            "reconstructing the scene without --depth (pass --depth FILE with a depth map of the photo, or make \
             Depth Anything 3's weights available: `pixl models fetch da3-metric`, or --models DIR holding them)",
        )?;
        let (w, h) = photo.size();
        return Ok(pixl_render::depth::DepthMap::new(
            w,
            h,
            pixl_pipeline::estimators::depth_without_sky(&est.estimate),
        )?);
    };
    let kind = match args.depth_kind.as_deref() {
        None => pixl_pipeline::depth::DepthKind::Metric,
        Some(k) => pixl_pipeline::depth::DepthKind::parse(k)
            .with_context(|| format!("--depth-kind {k:?}: give metric, relative or disparity"))?,
    };
    let how = pixl_pipeline::depth::DepthFile {
        kind,
        range: args
            .depth_range
            .as_deref()
            .map(pixl_pipeline::depth::parse_range)
            .transpose()?,
        ..Default::default()
    };
    pixl_pipeline::depth::read_depth_file(path, &how, photo.size()).context("reconstructing the scene")
}

/// From a photo: reconstruct → lights → render → compose → network. The photo is decoded once.
fn run_pipeline(args: &Args, photo_path: &Path, ctx: &Ctx) -> anyhow::Result<()> {
    // Everything that can be checked without work, first.
    let specs = args
        .light
        .iter()
        .map(|w| parse_light(w))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let file_lights = args.scene.as_deref().map(read_lights).transpose()?;
    if args.preset.is_none() && specs.is_empty() && file_lights.is_none() {
        bail!(
            "give the new lighting: --preset NAME, --light 'FLAGS' or --scene lights.toml (or --intrinsics CT.exr, \
             or --like TARGET.jpg; see --help)"
        );
    }
    if let Some(k) = &args.depth_kind {
        if pixl_pipeline::depth::DepthKind::parse(k).is_none() {
            bail!("--depth-kind {k:?}: give metric, relative or disparity");
        }
    }
    if let Some(r) = &args.depth_range {
        pixl_pipeline::depth::parse_range(r)?;
    }
    if let Some(dir) = &args.keep {
        let mut inputs: Vec<&Path> = vec![photo_path];
        inputs.extend(
            [&args.depth, &args.scene, &args.weights]
                .into_iter()
                .flatten()
                .map(|p| p.as_path()),
        );
        pixl_core::output::check_output_dir(dir, args.force, KEPT, &inputs)?;
    }
    let device = crate::device::parse_device(&args.device)?;
    let net = load_network(ctx, args, &device)?;
    let photo = read_photo(ctx, args, photo_path)?;
    let size = photo.size();
    let budget = check_budget(&net, size, args.max_side, 12 + 8, max_memory(args)?)?;
    let work = budget.work;
    let bars = crate::ctx::Bars::new(ctx);

    // 1. Reconstruct: the mesh needs no more vertices than the render has pixels.
    let depth = depth_of(args, &photo, ctx)?;
    let sp = spinner(ctx, "reconstructing the scene");
    let settings = pixl_pipeline::reconstruct::MeshSettings {
        stride: Some(size.0.max(size.1).div_ceil(work.0.max(work.1)).max(1)),
        ..Default::default()
    };
    let depth_name = match &args.depth {
        Some(p) => p.display().to_string(),
        None => "the estimated depth".to_string(),
    };
    let geometry = pixl_pipeline::reconstruct::reconstruct(
        &photo,
        &depth,
        &depth_name,
        &pixl_pipeline::reconstruct::Maps::default(),
        &settings,
        &bars,
    );
    sp.finish_and_clear();
    let geometry = geometry.context("reconstructing the scene")?;
    drop(depth);

    // 2. Lights, on the scene in memory (its mesh and texture are not written unless --keep).
    let mut scene = geometry.scene.clone();
    scene.lights.clear();
    if let Some(p) = &args.preset {
        apply_preset(&mut scene, p, false)?;
    }
    for (words, spec) in args.light.iter().zip(&specs) {
        let (light, notes) = spec.build(&scene).with_context(|| format!("--light '{words}'"))?;
        for n in notes {
            ctx.say(n);
        }
        scene.lights.push(light);
    }
    if let Some(lights) = file_lights {
        scene.lights.extend(lights);
    }
    scene.validate()?;
    let scene_name = match &args.keep {
        Some(dir) => {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            let path = geometry.write(
                &dir.join("scene"),
                pixl_pipeline::reconstruct::MeshFormat::Glb,
                &scene.lights,
            )?;
            path.display().to_string()
        }
        None => "the reconstructed scene".to_string(),
    };
    drop(geometry);

    // 3. Render at the working size and compose C_T.
    let settings = pixl_pipeline::render::RenderSettings {
        spp: args.spp,
        bounces: args.bounces,
        seed: args.seed,
    };
    let (film, composed) = pixl_pipeline::render::render_intrinsics(&scene, work, &settings, &bars)
        .with_context(|| format!("rendering {scene_name}"))?;
    drop(scene);
    let ct = composed.ct;
    let mut kept = Vec::new();
    if let Some(dir) = &args.keep {
        let sp = spinner(ctx, "writing the intermediates");
        film.write_exr(&dir.join("passes.exr"))?;
        pixl_core::io::write_png(
            &dir.join("render.png"),
            &film.combined_srgb(),
            pixl_core::io::PngDepth::Eight,
        )?;
        pixl_intrinsics::ct::write_ct(&dir.join("CT.exr"), &ct)?;
        let sheet = pixl_intrinsics::preview::preview_sheet(&ct)?;
        pixl_core::io::write_png(&dir.join("CT_sheet.png"), &sheet, pixl_core::io::PngDepth::Eight)?;
        sp.finish_and_clear();
        kept.extend(KEPT[..5].iter().map(|n| dir.join(n)));
    }
    drop(film);
    let ct_work = ct_at_working_size(&ct, work)?;
    drop(ct);

    // 4. The network, applied at full size.
    let photo = photo.image;
    let before = args
        .keep
        .as_ref()
        .map(|_| pixl_core::resample::area_resize(&photo, work.0, work.1))
        .transpose()?;
    let relit = run_network(ctx, &net, photo, &ct_work, work, &device)?;
    write_output(ctx, &args.out, &relit)?;
    if let (Some(dir), Some(before)) = (&args.keep, before) {
        let after = pixl_core::resample::area_resize(&relit, work.0, work.1)?;
        let pair = Image::hstack(&[&before, &after])?;
        let path = dir.join("before_after.png");
        pixl_core::io::write_png(&path, &pair, pixl_core::io::PngDepth::Eight)?;
        kept.push(path);
        ctx.say(format!("intermediates in {}", dir.display()));
    }
    report(ctx, args, &net, size, &budget, &kept, None)
}

/// The files `--keep` writes with `--like`.
const KEPT_LIKE: &[&str] = &["CT.exr", "CT_sheet.png", "before_after.png"];

/// `PHOTO --like TARGET`: the target's C_T from Marigold-IID-Lighting → the network. Both photos
/// are read and the network's memory planned before the estimator's weights are looked up;
/// nothing is written until the relit image exists.
fn run_like(args: &Args, photo_path: &Path, target_path: &Path, ctx: &Ctx) -> anyhow::Result<()> {
    if let Some(dir) = &args.keep {
        let mut inputs: Vec<&Path> = vec![photo_path, target_path];
        inputs.extend(args.weights.as_deref());
        pixl_core::output::check_output_dir(dir, args.force, KEPT_LIKE, &inputs)?;
    }
    let device = crate::device::parse_device(&args.device)?;
    let photo = read_photo(ctx, args, photo_path)?;
    let target =
        pixl_pipeline::like::read_target(target_path).with_context(|| format!("--like {}", target_path.display()))?;
    let net = load_network(ctx, args, &device)?;
    let size = photo.size();
    // Full size: the photo (f32), the encoded output, the target's C_T at the photo's size (9 f32)
    // and one of its maps being resized.
    let budget = check_budget(&net, size, args.max_side, 12 + 8 + 36 + 12, max_memory(args)?)?;
    let work = budget.work;

    let opts = pixl_estimate::marigold::MarigoldOptions {
        steps: Some(args.like_steps.unwrap_or(pixl_pipeline::like::LIKE_STEPS)),
        resolution: args.like_res,
        seed: args.seed,
        ..Default::default()
    };
    let (m, resolved) = crate::iid::load(
        pixl_estimate::marigold::IidVariant::Lighting,
        &args.device,
        &args.models,
        ctx,
    )
    .context(
        "--like needs Marigold-IID-Lighting's weights (`pixl models fetch marigold-lighting`, or --models DIR \
         holding them)",
    )?;
    crate::iid::announce(&m, target.width, target.height, &opts, "target intrinsics")?;
    let estimator = pixl_pipeline::estimators::MarigoldLighting::new(m, opts, resolved.spec.name)?;

    let before = args
        .keep
        .as_ref()
        .map(|_| pixl_core::resample::area_resize(&photo.image, work.0, work.1))
        .transpose()?;
    let bars = crate::ctx::Bars::new(ctx);
    let liked = pixl_pipeline::like::relight_like(&net, photo, &target, &estimator, work, &device, &bars)?;
    drop(target);
    write_output(ctx, &args.out, &liked.relit)?;

    let ct = &liked.ct;
    let mut kept = Vec::new();
    if let (Some(dir), Some(before)) = (&args.keep, before) {
        let sp = spinner(ctx, "writing the intermediates");
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        pixl_intrinsics::ct::write_ct(&dir.join("CT.exr"), &ct.ct)?;
        let sheet = pixl_intrinsics::preview::preview_sheet(&ct.ct)?;
        pixl_core::io::write_png(&dir.join("CT_sheet.png"), &sheet, pixl_core::io::PngDepth::Eight)?;
        let after = pixl_core::resample::area_resize(&liked.relit, work.0, work.1)?;
        let pair = Image::hstack(&[&before, &after])?;
        pixl_core::io::write_png(&dir.join("before_after.png"), &pair, pixl_core::io::PngDepth::Eight)?;
        sp.finish_and_clear();
        kept.extend(KEPT_LIKE.iter().map(|n| dir.join(n)));
        ctx.say(format!("intermediates in {}", dir.display()));
    }
    let like = serde_json::json!({
        "target": target_path.display().to_string(),
        "target_width": ct.target_size.0,
        "target_height": ct.target_size.1,
        "aspect_mismatch": ct.aspect_mismatch,
        "tau": ct.tau,
        "estimator": ct.estimator,
        "steps": estimator.options.steps,
        "resolution": estimator.options.resolution,
        "seed": args.seed,
        "weights": {
            "dir": resolved.dir.display().to_string(),
            "source": resolved.source.to_string(),
            "licence": resolved.spec.licence,
        },
    });
    if !args.json {
        ctx.say(format!(
            "lighting of {} ({}x{}) by {}; weights {} ({}), from {}",
            target_path.display(),
            ct.target_size.0,
            ct.target_size.1,
            ct.estimator,
            resolved.spec.repo,
            resolved.spec.licence,
            resolved.source
        ));
    }
    report(ctx, args, &net, size, &budget, &kept, Some(like))
}
