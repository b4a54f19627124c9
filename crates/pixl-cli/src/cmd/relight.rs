//! `pixl relight`: `Î_T = f_θ(I_S, C_T)` for one photograph of any size (paper §3.2, §3.4).
//!
//! Two forms:
//! - **From a photo, in one command**: `pixl relight photo.jpg --preset NAME -o relit.png`
//!   (and/or `--light 'FLAGS'`, `--scene lights.toml`) runs the inference pipeline of §3.4:
//!   `pixl reconstruct` (depth from `--depth`, else Depth Anything 3) → lights → the native path
//!   tracer at the working size → `compose` → the network. `--keep DIR` keeps every intermediate.
//! - **With a given C_T**: `pixl relight --source photo.png --intrinsics ct.exr -o relit.png`.
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
//! Weights: `--weights`, else the bundled demo weights compiled into the binary
//! (`assets/demo-weights/pixl-tiny-synth.safetensors`, 2.8 MB, so they are there after
//! `cargo install` too). Sources: PNG/JPEG as stored values in [0, 1], EXR as stored (values
//! outside [0, 1] clamped with a warning; non-finite refused). Output `.png` 16-bit, `.jpg`,
//! `.exr` f32, written atomically. With freshly initialised weights the output equals the source
//! exactly, at any size.
use super::light::LightSpec;
use crate::Ctx;
use anyhow::{bail, Context};
use candle_core::DType;
use indicatif::{ProgressBar, ProgressStyle};
use pixl_core::Image;
use pixl_intrinsics::compose::{compose, ComposeOptions, PassSet};
use pixl_intrinsics::ct::Ct;
use pixl_model::fullres::{self, MemoryPlan};
use pixl_render::presets::{apply_preset, PRESETS};
use pixl_render::scene::Light;
use pixl_render::{render, RenderOptions, Scene};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

/// The bundled demo weights (a `tiny` model, see `assets/demo-weights/README.md`).
const BUNDLED_WEIGHTS: &[u8] = include_bytes!("../../../../assets/demo-weights/pixl-tiny-synth.safetensors");
const BUNDLED_NAME: &str = "bundled pixl-tiny-synth.safetensors";

/// Default long side of the working size.
pub const DEFAULT_MAX_SIDE: usize = 1024;
/// Output formats, by extension.
const OUTPUT_EXTS: &[&str] = &["png", "jpg", "jpeg", "exr"];

#[derive(clap::Args, Debug)]
#[command(after_help = concat!("Examples:\n  \
pixl relight photo.jpg --preset warm-overhead-flash -o relit.png                  # depth from Depth Anything 3\n  \
pixl relight photo.jpg --depth depth.exr --preset cool-side-flash -o relit.png --keep steps/\n  \
pixl relight photo.jpg --depth depth.exr --light '--type spot --from left' -o relit.png\n  \
pixl relight photo.jpg --depth depth.exr --light '--at-pixel 640,300' --light '--type sun --azimuth 40 --elevation 50' -o relit.png\n  \
pixl relight photo.jpg --depth depth.exr --scene lights.toml -o relit.png\n  \
pixl relight --source photo.png --intrinsics ct.exr --weights model.safetensors --out relit.png\n\n\
From a photo, `pixl relight` runs reconstruct -> lights -> render -> compose -> network. Lights: --preset\n\
(the paper's five), --light 'FLAGS' (one light, the flags of `pixl light add`; repeatable), --scene FILE\n\
(the [[lights]] of a .toml/.json scene file, in the reconstructed scene's coordinates). They add up.\n\
--keep DIR keeps scene/ (mesh, textures, scene.toml with the lights), passes.exr, CT.exr, CT_sheet.png,\n\
render.png and before_after.png.\n\n\
Any size: the network runs with the long side at --max-side (default 1024) and its per-pixel gain and\n\
bias are resized to the photo and applied there: the output has the photo's size and detail. The memory\n\
this needs is checked first; a request that does not fit is refused with the figure.\n\n",
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
    /// Network weights (.safetensors written by `pixl model init` or `pixl train`). Default: the
    /// bundled demo weights (a `tiny` model trained on synthetic scenes).
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// Longest side the network works at (the paper trains at 512); the result is applied at the
    /// photo's full size.
    #[arg(long, default_value_t = DEFAULT_MAX_SIDE, value_parser = crate::ctx::at_least_one_usize)]
    pub max_side: usize,
    /// Most memory the network may plan to use, in GB (default: the memory available now).
    #[arg(long, value_name = "GB")]
    pub max_memory: Option<f64>,
    /// Compute dtype of the network.
    #[arg(long, value_enum, default_value_t = super::bench::DtypeArg::F32)]
    pub dtype: super::bench::DtypeArg,
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
    /// Random seed of the render.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
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
    pub models: super::models::WeightsArgs,
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

/// The network, its config, and where it came from.
struct Network {
    model: pixl_model::PixlRelight,
    cfg: pixl_model::Config,
    name: String,
    /// Bytes of the 8-bit weight copies (`--int8`; 0 otherwise), held beside the f32 weights.
    int8_bytes: u64,
}

fn load_network(
    ctx: &Ctx,
    weights: Option<&Path>,
    dtype: DType,
    device: &candle_core::Device,
    int8: bool,
) -> anyhow::Result<Network> {
    if int8 {
        crate::device::check_int8(device, dtype)?;
    }
    let sp = spinner(ctx, "loading the weights");
    let (cfg, mut model, name) = match weights {
        Some(w) => {
            let (cfg, model) = pixl_model::load(w, device, dtype)?;
            (cfg, model, w.display().to_string())
        }
        None => {
            let (cfg, model) = pixl_model::load_bytes(Path::new(BUNDLED_NAME), BUNDLED_WEIGHTS, device, dtype)?;
            (cfg, model, BUNDLED_NAME.to_string())
        }
    };
    if int8 {
        match model.quantize_int8()? {
            0 => tracing::warn!("--int8: this CPU has no AVX-512 VNNI; the network runs in f32"),
            n => tracing::info!("--int8: {n} linear layers quantized to 8 bits"),
        }
    }
    sp.finish_and_clear();
    tracing::info!(
        "weights: {name} ({} parameters, patch {})",
        cfg.param_count(),
        cfg.patch
    );
    let int8_bytes = model.int8_bytes();
    Ok(Network {
        model,
        cfg,
        name,
        int8_bytes,
    })
}

/// Bytes of memory available now (Linux `MemAvailable`), if known.
fn available_memory() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

fn gb(bytes: u64) -> String {
    format!("{:.2} GB", bytes as f64 / 1e9)
}

/// What relighting a `w × h` photo at `max_side` costs: the working size, the network's plan,
/// the 8-bit weight copies (`--int8`), and the full-size buffers (the photo in f32 and the
/// encoded output, `full_bytes_per_px`).
struct Budget {
    work: (usize, usize),
    plan: MemoryPlan,
    int8: u64,
    full: u64,
}

impl Budget {
    fn new(net: &Network, dtype: DType, size: (usize, usize), max_side: usize, full_bytes_per_px: u64) -> Self {
        let work = fullres::working_size(size.0, size.1, max_side);
        Budget {
            work,
            plan: fullres::plan_memory(&net.cfg, dtype, work.0, work.1),
            int8: net.int8_bytes,
            full: full_bytes_per_px * (size.0 * size.1) as u64,
        }
    }

    /// The network's planned peak with its 8-bit weight copies.
    fn network(&self) -> u64 {
        self.plan.peak_bytes() + self.int8
    }

    fn total(&self) -> u64 {
        self.network() + self.full
    }
}

/// Plans the memory and refuses a request that does not fit `--max-memory`, naming the figure
/// and a `--max-side` that fits.
fn check_budget(args: &Args, net: &Network, size: (usize, usize), per_px: u64) -> anyhow::Result<Budget> {
    let dtype: DType = args.dtype.into();
    let budget = Budget::new(net, dtype, size, args.max_side, per_px);
    let (limit, whence) = match args.max_memory {
        Some(g) if g.is_finite() && g > 0.0 => ((g * 1e9) as u64, "--max-memory"),
        Some(g) => bail!("--max-memory {g}: must be a positive number of GB"),
        None => match available_memory() {
            Some(b) => (b, "available now"),
            None => (u64::MAX, "unknown"),
        },
    };
    let (stage, _) = budget.plan.peak();
    tracing::info!(
        "working size {}x{} ({} tokens): planned peak {} ({stage}) + {} for the full-size image",
        budget.work.0,
        budget.work.1,
        budget.plan.tokens,
        gb(budget.network()),
        gb(budget.full)
    );
    if budget.total() > limit {
        // The largest --max-side (a multiple of 64, or 16 at the least) that fits.
        let mut fits = None;
        let mut side = args.max_side.min(size.0.max(size.1));
        while side > 16 {
            side = if side > 64 { (side - 1) / 64 * 64 } else { 16 };
            let b = Budget::new(net, dtype, size, side, per_px);
            if b.total() <= limit {
                fits = Some((side, b.total()));
                break;
            }
        }
        let hint = match fits {
            Some((s, bytes)) => format!("lower --max-side (e.g. --max-side {s} needs about {})", gb(bytes)),
            None => "even the smallest working size does not fit; free memory".to_string(),
        };
        bail!(
            "relighting this {}x{} photo at a working size of {}x{} (--max-side {}) needs about {} \
             (network peak {} in the {stage}, over {} tokens; full-size image {}), more than the {} {whence}; {hint}, \
             or raise --max-memory",
            size.0,
            size.1,
            budget.work.0,
            budget.work.1,
            args.max_side,
            gb(budget.total()),
            gb(budget.network()),
            budget.plan.tokens,
            gb(budget.full),
            gb(limit),
        );
    }
    Ok(budget)
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

/// A bar that redraws its elapsed time while a long step runs.
fn ticking(bar: ProgressBar) -> ProgressBar {
    if !bar.is_hidden() {
        bar.enable_steady_tick(std::time::Duration::from_millis(250));
    }
    bar
}

/// Reads the photo (RGB, finite, clamped to [0, 1]) with a spinner.
fn read_photo(ctx: &Ctx, path: &Path) -> anyhow::Result<Image> {
    let sp = spinner(ctx, &format!("reading {}", path.display()));
    let photo = clamp_to_unit(pixl_core::io::read_rgb_finite(path)?, path);
    sp.finish_and_clear();
    Ok(photo)
}

/// The paper's source is in [0, 1]; EXR sources may exceed it. Clamped values are reported.
fn clamp_to_unit(img: Image, path: &Path) -> Image {
    let outside = img.data.iter().filter(|v| !(0.0..=1.0).contains(*v)).count();
    if outside == 0 {
        return img;
    }
    tracing::warn!(
        "{}: {outside} values outside [0, 1] clamped (the network expects I_S in [0, 1])",
        path.display()
    );
    img.map(|v| v.clamp(0.0, 1.0))
}

/// Planar `9 × wh × ww` C_T at the working size: area-averaged from the photo's size, or as is.
fn ct_at_working_size(ct: &Ct, work: (usize, usize)) -> anyhow::Result<Vec<f32>> {
    if (ct.width(), ct.height()) == work {
        return Ok(ct.to_chw());
    }
    let mut out = Vec::with_capacity(9 * work.0 * work.1);
    for group in ct.groups() {
        out.extend(fullres::area_resize_to_chw(group, work.0, work.1)?);
    }
    Ok(out)
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
    let bar = ticking(ctx.progress(1, &format!("network {}x{}", work.0, work.1)));
    let mut progress = |done: usize, total: usize, _stage: &str| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    };
    let relit = fullres::relight_full(&net.model, photo, ct_work, work, device, &mut progress).context("relighting")?;
    bar.finish_and_clear();
    Ok(relit)
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
    for p in [&args.intrinsics, &args.weights, &args.depth, &args.scene]
        .into_iter()
        .flatten()
    {
        inputs.push(p);
    }
    pixl_core::output::check_output(&args.out, OUTPUT_EXTS, &inputs)?;
    if args.intrinsics.is_some() {
        return run_with_intrinsics(&args, &photo, ctx);
    }
    run_pipeline(&args, &photo, ctx)
}

/// `--source PHOTO --intrinsics CT`.
fn run_with_intrinsics(args: &Args, photo_path: &Path, ctx: &Ctx) -> anyhow::Result<()> {
    let ct_path = args.intrinsics.as_deref().unwrap_or(Path::new(""));
    let device = crate::device::parse_device(&args.device)?;
    let net = load_network(ctx, args.weights.as_deref(), args.dtype.into(), &device, args.int8)?;
    let photo = read_photo(ctx, photo_path)?;
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
    let budget = check_budget(args, &net, size, per_px)?;
    let ct_work = ct_at_working_size(&ct, budget.work)?;
    drop(ct);
    let relit = run_network(ctx, &net, photo, &ct_work, budget.work, &device)?;
    write_output(ctx, &args.out, &relit)?;
    report(ctx, args, &net, size, &budget, &[])
}

fn report(
    ctx: &Ctx,
    args: &Args,
    net: &Network,
    size: (usize, usize),
    budget: &Budget,
    kept: &[PathBuf],
) -> anyhow::Result<()> {
    if args.json {
        return ctx.print_json(&serde_json::json!({
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
        }));
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

/// Reconstruct's flags from ours, parsed by its own clap definition (so its defaults and new
/// flags apply unchanged).
fn reconstruct_args(args: &Args, photo: &Path, out: &Path, stride: usize) -> anyhow::Result<super::reconstruct::Args> {
    #[derive(clap::Parser)]
    #[command(no_binary_name = true)]
    struct Wrap {
        #[command(flatten)]
        a: super::reconstruct::Args,
    }
    let mut argv: Vec<std::ffi::OsString> = vec!["--image".into(), photo.into(), "--out".into(), out.into()];
    let mut flag = |name: &str, value: Option<std::ffi::OsString>| {
        if let Some(v) = value {
            argv.push(name.into());
            argv.push(v);
        }
    };
    flag("--depth", args.depth.as_ref().map(|p| p.into()));
    flag("--depth-kind", args.depth_kind.as_ref().map(|s| s.into()));
    flag("--depth-range", args.depth_range.as_ref().map(|s| s.into()));
    flag("--fov", args.fov.map(|v| v.to_string().into()));
    flag("--focal", args.focal.map(|v| v.to_string().into()));
    flag("--models", args.models.models.as_ref().map(|p| p.into()));
    flag("--stride", Some(stride.to_string().into()));
    // The scene folder is ours (a fresh temporary folder, or --keep's, checked there).
    argv.push("--force".into());
    if args.models.offline {
        argv.push("--offline".into());
    }
    let w = <Wrap as clap::Parser>::try_parse_from(argv).map_err(|e| {
        anyhow::anyhow!(
            "reconstruct: {}",
            e.render()
                .to_string()
                .lines()
                .next()
                .unwrap_or("")
                .trim_start_matches("error: ")
        )
    })?;
    Ok(w.a)
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

/// From a photo: reconstruct → lights → render → compose → network.
fn run_pipeline(args: &Args, photo_path: &Path, ctx: &Ctx) -> anyhow::Result<()> {
    // Everything that can be checked without work, first.
    let specs = args
        .light
        .iter()
        .map(|w| parse_light(w))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let file_lights = args.scene.as_deref().map(read_lights).transpose()?;
    if args.preset.is_none() && specs.is_empty() && file_lights.is_none() {
        bail!("give the new lighting: --preset NAME, --light 'FLAGS' or --scene lights.toml (or --intrinsics CT.exr; see --help)");
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
    let net = load_network(ctx, args.weights.as_deref(), args.dtype.into(), &device, args.int8)?;
    let photo = read_photo(ctx, photo_path)?;
    let size = (photo.width, photo.height);
    let budget = check_budget(args, &net, size, 12 + 8)?;
    let work = budget.work;

    // 1. Reconstruct, into --keep DIR/scene or a folder removed at the end.
    let mut provisional = pixl_core::output::Provisional::new();
    let root = match &args.keep {
        Some(dir) => {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            dir.clone()
        }
        None => {
            let tmp = std::env::temp_dir().join(format!(
                "pixl-relight-{}-{}",
                std::process::id(),
                std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_nanos())
                    .unwrap_or(0)
            ));
            provisional.create_dir_all(&tmp)?;
            tmp
        }
    };
    let scene_dir = root.join("scene");
    // The mesh needs no more vertices than the render has pixels.
    let stride = size.0.max(size.1).div_ceil(work.0.max(work.1)).max(1);
    let rargs = reconstruct_args(args, photo_path, &scene_dir, stride)?;
    // (Depth estimation shows its own progress.)
    let sp = match &args.depth {
        Some(_) => spinner(ctx, "reconstructing the scene"),
        None => ProgressBar::hidden(),
    };
    let reconstructed = super::reconstruct::run(rargs, ctx);
    sp.finish_and_clear();
    reconstructed.with_context(|| {
        if args.depth.is_none() {
            "reconstructing the scene without --depth (pass --depth FILE with a depth map of the photo, or make \
             Depth Anything 3's weights available: `pixl models fetch da3-metric`, or --models DIR holding them)"
                .to_string()
        } else {
            "reconstructing the scene".to_string()
        }
    })?;

    // 2. Lights.
    let scene_path = scene_dir.join("scene.toml");
    let mut scene = Scene::load(&scene_path)?;
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
    scene.save(&scene_path)?;

    // 3. Render at the working size.
    let opts = RenderOptions {
        spp: args.spp,
        width: Some(work.0 as u32),
        height: Some(work.1 as u32),
        seed: args.seed,
        max_bounces: args.bounces,
    };
    let bar = ticking(ctx.progress(work.1 as u64, "rendering"));
    let film = render(&scene, &opts, &|done, _total| bar.set_position(done as u64))
        .with_context(|| format!("rendering {}", scene_path.display()))?;
    bar.finish_and_clear();
    drop(scene);

    // 4. Compose C_T.
    let passes = PassSet::from_exr_channels(&film.to_exr_channels(), None)?;
    let composed = compose(&passes, &ComposeOptions::default())?;
    drop(passes);
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

    // 5. The network, applied at full size.
    let before = args
        .keep
        .as_ref()
        .map(|_| fullres::area_resize_to_chw(&photo, work.0, work.1))
        .transpose()?;
    let relit = run_network(ctx, &net, photo, &ct_work, work, &device)?;
    write_output(ctx, &args.out, &relit)?;
    if let (Some(dir), Some(before)) = (&args.keep, before) {
        let after = fullres::area_resize_to_chw(&relit, work.0, work.1)?;
        let a = Image::from_chw(work.0, work.1, 3, &before)?;
        let b = Image::from_chw(work.0, work.1, 3, &after)?;
        let pair = Image::hstack(&[&a, &b])?;
        let path = dir.join("before_after.png");
        pixl_core::io::write_png(&path, &pair, pixl_core::io::PngDepth::Eight)?;
        kept.push(path);
        ctx.say(format!("intermediates in {}", dir.display()));
    }
    drop(provisional);
    report(ctx, args, &net, size, &budget, &kept)
}
