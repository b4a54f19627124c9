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
//! The work is `pixl_pipeline::job::run` (photo, depth, reconstruct, lights, render, relight);
//! this module parses the flags, loads the models and prints. Weights: `--weights` (`bundled`, `pixlrelight`
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
use pixl_estimate::hub::Resolved;
use pixl_pipeline::batch::{self, Item, ManifestRow, Setup, Shard};
use pixl_pipeline::depth::{DepthFile, DepthKind};
use pixl_pipeline::estimators::MarigoldLighting;
use pixl_pipeline::job::{self, DepthSource, Job, LightSet, Lighting, LightingKind, Relit};
use pixl_pipeline::lights::{parse_light_words, read_lights_file};
use pixl_pipeline::relight::{gb, Network, DEFAULT_MAX_SIDE};
use pixl_pipeline::video::{self, CameraMotion, VideoJob};
use pixl_pipeline::Photo;
use pixl_render::presets::PRESETS;
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
const NO_LIGHTING: &str = "give the new lighting: --preset NAME, --light 'FLAGS' or --scene lights.toml (or \
                           --intrinsics CT.exr, or --like TARGET.jpg; see --help)";
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
pixl relight photo.jpg --like same-view-other-light.jpg -o relit.png --keep steps/\n  \
pixl relight shots/ --depth-dir depths/ --preset cool-side-flash -o relit/             # a folder: a batch\n  \
pixl relight --manifest jobs.csv -o relit/ --shard auto --shard-count 8                 # one shard of a cluster job\n\n\
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
before_after.png.\n\n\
Many photos: several PHOTOs, a folder (searched recursively), a quoted pattern ('shots/*.jpg'), --inputs\n\
LIST (one path per line) or --manifest FILE (.csv with a header row, or .jsonl: columns photo, preset,\n\
light (several separated by ';'), scene, like, intrinsics, depth; a row without lighting takes the\n\
flags'). -o is then a folder; each output keeps its photo's relative name (extension: --format, else the\n\
photo's). The models are loaded once and the next photo is decoded while the network runs. Every photo's\n\
outcome is a line of OUT/pixl-batch.jsonl; a rerun skips photos done from the same input and set-up\n\
(--force redoes them); a photo that fails is reported and the others go on; the exit code is 1 if any\n\
failed. --shard I/N relights the I-th of N disjoint shares (auto: I from JOB_COMPLETION_INDEX or\n\
SLURM_ARRAY_TASK_ID, N from --shard-count, PIXL_SHARD_COUNT or SLURM_ARRAY_TASK_COUNT).\n\n",
crate::scene_axes_help!()))]
pub struct Args {
    /// The photo to relight (.png, .jpg or .exr); the same as --source. Several photos, a folder
    /// or a quoted pattern make a batch (see below).
    #[arg(value_name = "PHOTO", conflicts_with = "source")]
    pub photo: Vec<PathBuf>,
    /// Source photograph I_S (.png, .jpg or .exr; RGB, values in [0, 1]).
    #[arg(long)]
    pub source: Option<PathBuf>,
    /// Target intrinsics C_T (.exr with albedo.*, shading.* and residual.* channels), at the photo's
    /// size or at the working size. Given, the photo is relit with it (no reconstruction).
    #[arg(long, conflicts_with_all = ["preset", "light", "scene", "depth", "keep"])]
    pub intrinsics: Option<PathBuf>,
    /// Output image (.png: 16-bit; .jpg; .exr: 32-bit float). Its folder must exist. With many
    /// photos, the output folder (created).
    #[arg(short = 'o', long)]
    pub out: PathBuf,
    /// A file listing photos (or folders, or patterns), one per line, relative to its folder.
    #[arg(long, value_name = "LIST")]
    pub inputs: Option<PathBuf>,
    /// A .csv or .jsonl file of photos, each with its own lighting and depth (see below).
    #[arg(long, value_name = "FILE", conflicts_with_all = ["source", "inputs"])]
    pub manifest: Option<PathBuf>,
    /// With many photos: a folder of depth maps named as the photos (same relative path, .exr,
    /// .png or .npy), used as --depth is.
    #[arg(long, value_name = "DIR", conflicts_with = "depth")]
    pub depth_dir: Option<PathBuf>,
    /// With many photos: relight only shard I of N (I/N, 0-based), or `auto` (see below).
    #[arg(long, value_name = "I/N|auto")]
    pub shard: Option<String>,
    /// The number of shards for --shard auto.
    #[arg(long, value_name = "N", requires = "shard")]
    pub shard_count: Option<usize>,
    /// With many photos: the outputs' format (default: each photo's own).
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(["png", "jpg", "exr"]))]
    pub format: Option<String>,
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
    /// A video's camera does not move: reconstruct once from the first frames (default: detected).
    #[arg(long, conflicts_with = "moving")]
    pub r#static: bool,
    /// A video's camera moves: depth and C_T per frame (default: detected).
    #[arg(long)]
    pub moving: bool,
    /// Keep every intermediate in this folder (created; must be empty unless --force).
    #[arg(long, value_name = "DIR")]
    pub keep: Option<PathBuf>,
    /// Allow --keep to write into a folder that has files in it; with many photos, also redo the
    /// photos already done.
    #[arg(long)]
    pub force: bool,
    /// Print a JSON summary on stdout (sizes, planned memory, files written).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub models: crate::weights::WeightsArgs,
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

fn write_output(ctx: &Ctx, path: &Path, img: &Image) -> anyhow::Result<()> {
    let sp = spinner(ctx, &format!("writing {}", path.display()));
    pixl_core::io::write_image(path, img)?;
    sp.finish_and_clear();
    Ok(())
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    let photo = match (args.photo.as_slice(), &args.source) {
        _ if is_batch(&args) => return run_batch(&args, ctx),
        ([p], _) | ([], Some(p)) if video::is_video(p) => return run_video(&args, p, ctx),
        ([p], _) | ([], Some(p)) => p.clone(),
        _ => bail!("give the photo: `pixl relight photo.jpg --preset NAME -o relit.png` (see --help)"),
    };
    if args.shard.is_some() || args.format.is_some() || args.depth_dir.is_some() {
        bail!("--shard, --format and --depth-dir are for many photos (a folder, a pattern, --inputs or --manifest)");
    }
    let mut inputs: Vec<&Path> = vec![&photo];
    for p in [&args.intrinsics, &args.weights, &args.depth, &args.scene, &args.like]
        .into_iter()
        .flatten()
    {
        inputs.push(p);
    }
    pixl_core::output::check_output(&args.out, OUTPUT_EXTS, &inputs)?;
    let lights = light_set(&args)?;
    if lights.is_empty() && args.intrinsics.is_none() && args.like.is_none() {
        bail!(NO_LIGHTING);
    }
    let like = args.like.as_deref().map(like_target).transpose()?;
    if let Some(dir) = &args.keep {
        let kept = if args.like.is_some() { job::KEPT_LIKE } else { job::KEPT };
        pixl_core::output::check_output_dir(dir, args.force, kept, &inputs)?;
    }
    let device = crate::device::parse_device(&args.device)?;
    let net = load_network(ctx, &args, &device)?;
    let photo = read_photo(ctx, &args, &photo)?;
    let size = photo.size();
    let max_memory = max_memory(&args)?;
    // Refused before any estimator is loaded.
    let kind = match (&args.intrinsics, &args.like) {
        (Some(_), _) => LightingKind::Intrinsics,
        (None, Some(_)) => LightingKind::Like,
        (None, None) => LightingKind::Lights,
    };
    job::check(&net, size, args.max_side, max_memory, kind)?;
    let job = |lighting| Job {
        photo,
        lighting,
        max_side: args.max_side,
        render: render_settings(&args),
        max_memory,
        keep: args.keep.clone(),
    };
    let bars = crate::ctx::Bars::new(ctx);
    let (relit, like) = if let Some(path) = &args.intrinsics {
        (job::run(&net, job(Lighting::Intrinsics(path)), &device, &bars)?, None)
    } else if let Some((target_path, target)) = &like {
        let (estimator, resolved) = like_estimator(&args, Some(target), ctx)?;
        let lighting = Lighting::Like {
            target,
            estimator: &estimator,
        };
        let relit = job::run(&net, job(lighting), &device, &bars)?;
        let info = like_info(&args, target_path, &relit, &estimator, &resolved, ctx);
        (relit, Some(info))
    } else {
        let da3;
        let depth = match &args.depth {
            Some(path) => DepthSource::File {
                path: path.clone(),
                how: depth_file(&args)?,
            },
            None => {
                da3 = load_da3(&args, ctx)?;
                DepthSource::Estimate(&da3)
            }
        };
        let lighting = Lighting::Lights { lights: &lights, depth };
        (job::run(&net, job(lighting), &device, &bars)?, None)
    };
    write_output(ctx, &args.out, &relit.image)?;
    report(ctx, &args, &net, size, &relit, like)
}

/// The lights of `--preset`, `--light` and `--scene`, parsed and checked before any work.
fn light_set(args: &Args) -> anyhow::Result<LightSet> {
    let placed = args
        .light
        .iter()
        .map(|w| Ok((w.clone(), parse_light_words(w)?)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let fixed = args.scene.as_deref().map(read_lights_file).transpose()?;
    let set = LightSet {
        preset: args.preset.clone(),
        placed,
        fixed: fixed.unwrap_or_default(),
    };
    if args.depth.is_some() {
        depth_file(args)?;
    }
    Ok(set)
}

/// How to read `--depth` (`--depth-kind`, `--depth-range`).
fn depth_file(args: &Args) -> anyhow::Result<DepthFile> {
    let kind = match args.depth_kind.as_deref() {
        None => DepthKind::Metric,
        Some(k) => {
            DepthKind::parse(k).with_context(|| format!("--depth-kind {k:?}: give metric, relative or disparity"))?
        }
    };
    let range = args
        .depth_range
        .as_deref()
        .map(pixl_pipeline::depth::parse_range)
        .transpose()?;
    Ok(DepthFile {
        kind,
        range,
        ..Default::default()
    })
}

/// `--like TARGET`, read and checked before any model is loaded.
fn like_target(path: &Path) -> anyhow::Result<(PathBuf, Image)> {
    let target = pixl_pipeline::like::read_target(path).with_context(|| format!("--like {}", path.display()))?;
    Ok((path.to_owned(), target))
}

/// Marigold-IID-Lighting for `--like`, its weights found or fetched.
fn like_estimator(args: &Args, target: Option<&Image>, ctx: &Ctx) -> anyhow::Result<(MarigoldLighting, Resolved)> {
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
    if let Some(t) = target {
        crate::iid::announce(&m, t.width, t.height, &opts, "target intrinsics")?;
    }
    Ok((MarigoldLighting::new(m, opts, resolved.spec.name)?, resolved))
}

/// The `like` record of the JSON summary (and its line on the console).
fn like_info(
    args: &Args,
    target: &Path,
    relit: &Relit,
    estimator: &MarigoldLighting,
    resolved: &Resolved,
    ctx: &Ctx,
) -> serde_json::Value {
    let Some(ct) = &relit.like else {
        return serde_json::Value::Null;
    };
    if !args.json {
        ctx.say(format!(
            "lighting of {} ({}x{}) by {}; weights {} ({}), from {}",
            target.display(),
            ct.target_size.0,
            ct.target_size.1,
            ct.estimator,
            resolved.spec.repo,
            resolved.spec.licence,
            resolved.source
        ));
    }
    serde_json::json!({
        "target": target.display().to_string(),
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
    })
}

fn report(
    ctx: &Ctx,
    args: &Args,
    net: &Network,
    size: (usize, usize),
    relit: &Relit,
    like: Option<serde_json::Value>,
) -> anyhow::Result<()> {
    let budget = &relit.budget;
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
            "kept": relit.kept.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
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

/// Depth Anything 3 (metric) for photos without a depth map.
fn load_da3(args: &Args, ctx: &Ctx) -> anyhow::Result<pixl_pipeline::estimators::Da3Depth> {
    let model = crate::estimators::DepthModel::Da3Metric;
    let res = pixl_pipeline::estimators::DEFAULT_PROCESS_RES;
    Ok(
        crate::estimators::load_depth_model(model, res, "cpu", &args.models, ctx)
            .context(
                "reconstructing the scene without --depth (pass --depth FILE with a depth map of the photo, or make \
             Depth Anything 3's weights available: `pixl models fetch da3-metric`, or --models DIR holding them)",
            )?
            .0,
    )
}

/// Whether the photos make a batch: several, a folder, a pattern, a list or a manifest.
fn is_batch(args: &Args) -> bool {
    args.photo.len() > 1
        || args.inputs.is_some()
        || args.manifest.is_some()
        || args
            .photo
            .first()
            .is_some_and(|p| p.is_dir() || batch::is_pattern(&p.to_string_lossy()))
}

/// A manifest row's own lighting, if it gives one.
fn row_setup(row: &ManifestRow, lights: &LightSet) -> anyhow::Result<Option<Setup>> {
    if let Some(p) = &row.intrinsics {
        return Ok(Some(Setup::Intrinsics(p.clone())));
    }
    if let Some(p) = &row.like {
        return Ok(Some(Setup::Like(p.clone())));
    }
    if let Some(p) = row.preset.as_deref().filter(|p| !PRESETS.contains(p)) {
        bail!("preset {p:?}: not one of {}", PRESETS.join(", "));
    }
    let placed = row
        .lights
        .iter()
        .map(|w| Ok((w.clone(), parse_light_words(w)?)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let fixed = row
        .scene
        .as_deref()
        .map(read_lights_file)
        .transpose()?
        .unwrap_or_default();
    let own = LightSet {
        preset: row.preset.clone(),
        placed,
        fixed,
    };
    let lights = if own.is_empty() { lights.clone() } else { own };
    Ok((!lights.is_empty()).then_some(Setup::Lights { lights, depth: None }))
}

/// Many photos (see --help): the items listed and checked, the models loaded once, then
/// `pixl_pipeline::batch::run`.
fn run_batch(args: &Args, ctx: &Ctx) -> anyhow::Result<()> {
    if args.depth.is_some() {
        bail!("--depth names one photo's depth map; with many photos give --depth-dir DIR (maps named as the photos)");
    }
    if args.out.is_file() || OUTPUT_EXTS.contains(&pixl_core::io::extension(&args.out).as_str()) {
        bail!("-o {}: with many photos -o is a folder", args.out.display());
    }
    let shard = match &args.shard {
        Some(s) => Shard::parse(s, args.shard_count, &|v| std::env::var(v).ok())?,
        None => Shard::ALL,
    };
    let lights = light_set(args)?;
    let common = match (&args.intrinsics, &args.like) {
        (Some(p), _) => Some(Setup::Intrinsics(p.clone())),
        (None, Some(p)) => Some(Setup::Like(p.clone())),
        (None, None) => (!lights.is_empty()).then(|| Setup::Lights {
            lights: lights.clone(),
            depth: None,
        }),
    };
    let rows: Vec<(batch::Input, Option<ManifestRow>)> = match &args.manifest {
        Some(m) => batch::read_manifest(m)?
            .into_iter()
            .map(|(i, r)| (i, Some(r)))
            .collect(),
        None => batch::list_inputs(&args.photo, args.inputs.as_deref())?
            .into_iter()
            .map(|i| (i, None))
            .collect(),
    };
    let mut items = Vec::with_capacity(rows.len());
    for (input, row) in rows {
        let name = input.path.display().to_string();
        let own = row
            .as_ref()
            .map(|r| row_setup(r, &lights))
            .transpose()
            .with_context(|| name.clone())?;
        let mut setup = own
            .flatten()
            .or_else(|| common.clone())
            .with_context(|| format!("{name}: {NO_LIGHTING}"))?;
        if let Setup::Lights { depth, .. } = &mut setup {
            *depth = row
                .and_then(|r| r.depth)
                .or_else(|| args.depth_dir.as_deref().and_then(|d| batch::depth_in(d, &input.rel)));
        }
        let output = batch::output_for(&args.out, &input.rel, args.format.as_deref());
        if pixl_core::output::same_file(&output, &input.path) {
            bail!("{name}: its output would be the photo itself; give another -o or --format");
        }
        items.push(Item { input, setup, output });
    }
    let needs_depth = items
        .iter()
        .any(|i| matches!(i.setup, Setup::Lights { depth: None, .. }));
    let needs_like = items.iter().any(|i| matches!(i.setup, Setup::Like(_)));

    let device = crate::device::parse_device(&args.device)?;
    let net = load_network(ctx, args, &device)?;
    let da3 = needs_depth.then(|| load_da3(args, ctx)).transpose()?;
    let like = needs_like.then(|| like_estimator(args, None, ctx)).transpose()?;
    let opts = batch::Options {
        out_dir: args.out.clone(),
        shard,
        force: args.force,
        max_side: args.max_side,
        render: render_settings(args),
        max_memory: max_memory(args)?,
        keep: args.keep.clone(),
        depth_file: if args.depth_dir.is_some() {
            depth_file(args)?
        } else {
            DepthFile::default()
        },
        depth: da3.as_ref().map(|d| d as &dyn pixl_pipeline::depth::DepthEstimator),
        lighting: like
            .as_ref()
            .map(|(m, _)| m as &dyn pixl_pipeline::like::LightingEstimator),
        focal_px: args.focal,
        fov_deg: args.fov,
        settings: format!(
            "{} {:?} int8={} max_side={} spp={} bounces={} seed={} like_steps={:?} like_res={:?} depth_kind={:?} \
             depth_range={:?}",
            net.name,
            args.dtype,
            args.int8,
            args.max_side,
            args.spp,
            args.bounces,
            args.seed,
            args.like_steps,
            args.like_res,
            args.depth_kind,
            args.depth_range
        ),
    };
    let bars = crate::ctx::Bars::new(ctx);
    let s = batch::run(&net, &device, items, &opts, &bars)?;
    if args.json {
        ctx.print_json(&serde_json::json!({
            "total": s.total, "done": s.done, "skipped": s.skipped, "failed": s.failed,
            "seconds": s.seconds, "log": s.log.display().to_string(),
            "shard": [shard.index, shard.count], "network_loads": Network::loads(),
        }))?;
    } else {
        ctx.say(format!(
            "{} photos: {} relit, {} already done, {} failed in {:.1} s (log: {})",
            s.total,
            s.done,
            s.skipped,
            s.failed,
            s.seconds,
            s.log.display()
        ));
    }
    if s.failed > 0 {
        bail!(
            "{} of {} photos failed; their errors are in {}",
            s.failed,
            s.total,
            s.log.display()
        );
    }
    Ok(())
}

/// `pixl relight CLIP --preset … -o OUT.mp4` (or image sequences): `pixl_pipeline::video`.
fn run_video(args: &Args, input: &Path, ctx: &Ctx) -> anyhow::Result<()> {
    if args.like.is_some() || args.intrinsics.is_some() || args.keep.is_some() {
        bail!("--like, --intrinsics and --keep are for photos; relight a clip with --preset, --light or --scene");
    }
    video::check_output(&args.out, input)?;
    let lights = light_set(args)?;
    if lights.is_empty() {
        bail!("give the new lighting: --preset NAME, --light 'FLAGS' or --scene lights.toml");
    }
    let ff = video::Ffmpeg::find()?;
    video::probe(&ff, input)?;
    let device = crate::device::parse_device(&args.device)?;
    let net = load_network(ctx, args, &device)?;
    let da3;
    let depth = match &args.depth {
        Some(path) => DepthSource::File {
            path: path.clone(),
            how: depth_file(args)?,
        },
        None => {
            da3 = load_da3(args, ctx)?;
            DepthSource::Estimate(&da3)
        }
    };
    let camera = match (args.r#static, args.moving) {
        (true, _) => CameraMotion::Static,
        (_, true) => CameraMotion::Moving,
        _ => CameraMotion::Auto,
    };
    let job = VideoJob {
        input: input.to_owned(),
        output: args.out.clone(),
        lights: &lights,
        depth,
        camera,
        max_side: args.max_side,
        render: render_settings(args),
        max_memory: max_memory(args)?,
        focal_px: args.focal,
        fov_deg: args.fov,
    };
    let start = std::time::Instant::now();
    let bars = crate::ctx::Bars::new(ctx);
    let v = video::relight_video(&ff, &net, job, &device, &bars)?;
    let secs = start.elapsed().as_secs_f64();
    if args.json {
        return ctx.print_json(&serde_json::json!({
            "output": args.out.display().to_string(), "frames": v.frames, "width": v.info.width,
            "height": v.info.height, "fps": v.info.fps(), "audio": v.info.audio, "static_camera": v.static_camera,
            "working_width": v.work.0, "working_height": v.work.1, "seconds": secs, "weights": net.name,
        }));
    }
    ctx.say(format!(
        "wrote {} ({} frames of {}x{} in {secs:.1} s, {:.2} frames/s; network at {}x{})",
        args.out.display(),
        v.frames,
        v.info.width,
        v.info.height,
        v.frames as f64 / secs.max(1e-9),
        v.work.0,
        v.work.1
    ));
    Ok(())
}

/// `--spp`, `--bounces`, `--seed`.
fn render_settings(args: &Args) -> pixl_pipeline::render::RenderSettings {
    pixl_pipeline::render::RenderSettings {
        spp: args.spp,
        bounces: args.bounces,
        seed: args.seed,
    }
}
