//! Marigold-IID on the command line, shared by `pixl estimate materials|lighting`,
//! `pixl reconstruct --materials marigold` and `pixl prepare-targets`: the flags ([`IidArgs`]),
//! loading a checkpoint of the right variant ([`load`]: the wrong variant is one clear error),
//! the time it will take shown up front, and a progress bar per UNet step and decode ([`run`]).
use crate::weights::WeightsArgs;
use crate::Ctx;
use anyhow::{bail, Context};
use pixl_core::Image;
use pixl_estimate::hub::{self, Resolved};
use pixl_estimate::marigold::{IidPrediction, IidVariant, Marigold, MarigoldOptions};

/// The options of one Marigold-IID run (the model and device flags come with the command).
#[derive(clap::Args, Debug, Clone)]
pub struct IidArgs {
    /// Longest side the network sees, a multiple of 8 (default: the checkpoint's, 768; 512 is
    /// about twice as fast on a CPU and a little blurrier).
    #[arg(long = "res", value_name = "PX")]
    pub res: Option<usize>,
    /// Denoising steps (default: the checkpoint's, 4).
    #[arg(long, value_parser = crate::ctx::at_least_one_usize)]
    pub steps: Option<usize>,
    /// Predictions combined per pixel by their median (each one costs a full run; 1 = none).
    #[arg(long, default_value_t = 1, value_parser = crate::ctx::at_least_one_usize)]
    pub ensemble: usize,
    /// Seed of the initial noise (the same seed gives the same maps).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write each map's uncertainty, the ensemble's spread as diffusers computes it (median
    /// absolute deviation), as `uncertainty-<map>.exr` beside the output (needs --ensemble ≥ 2).
    #[arg(long)]
    pub uncertainty: bool,
}

impl Default for IidArgs {
    fn default() -> Self {
        Self {
            res: None,
            steps: None,
            ensemble: 1,
            seed: 0,
            uncertainty: false,
        }
    }
}

impl IidArgs {
    pub fn options(&self) -> MarigoldOptions {
        MarigoldOptions {
            steps: self.steps,
            ensemble: self.ensemble,
            resolution: self.res,
            seed: self.seed,
            uncertainty: self.uncertainty,
            ..Default::default()
        }
    }
}

/// The registry name of a variant's released checkpoint.
pub fn model_name(v: IidVariant) -> &'static str {
    match v {
        IidVariant::Appearance => "marigold-appearance",
        IidVariant::Lighting => "marigold-lighting",
    }
}

fn describe(v: Option<IidVariant>, names: &[&str]) -> String {
    match v {
        Some(IidVariant::Appearance) => format!("Marigold-IID Appearance ({})", names.join(", ")),
        Some(IidVariant::Lighting) => format!("Marigold-IID Lighting ({})", names.join(", ")),
        None => format!("targets {}", names.join(", ")),
    }
}

/// Finds (or downloads) the weights of `variant` and loads them; a checkpoint of the other
/// variant is refused with both target lists named.
pub fn load(
    variant: IidVariant,
    device: &str,
    weights: &WeightsArgs,
    ctx: &Ctx,
) -> anyhow::Result<(Marigold, Resolved)> {
    let spec = hub::lookup(model_name(variant))?;
    let hub = weights.hub();
    let resolved = crate::weights::resolve(&hub, spec, ctx)?;
    let device = crate::device::parse_device(device)?;
    let m = Marigold::load(&resolved.dir, &device)
        .with_context(|| format!("loading `{}` from {}", spec.name, resolved.dir.display()))?;
    if m.variant() != Some(variant) {
        bail!(
            "{}: this checkpoint predicts {}, but this command needs {} ({}); is it the other Marigold-IID model?",
            resolved.dir.display(),
            describe(m.variant(), &m.pipeline().target_names()),
            describe(Some(variant), variant.target_names()),
            spec.name
        );
    }
    Ok((m, resolved))
}

/// Decomposes one photo, with the expected time said first and a progress bar.
pub fn run(m: &Marigold, photo: &Image, args: &IidArgs, label: &str, ctx: &Ctx) -> anyhow::Result<IidPrediction> {
    let opts = args.options();
    announce(m, photo.width, photo.height, &opts, label)?;
    let pb = ctx.progress(1, label);
    let pred = m.predict(photo, &opts, &mut |p| {
        pb.set_length(p.total as u64);
        pb.set_position(p.done as u64);
    })?;
    pb.finish_and_clear();
    Ok(pred)
}

/// Writes each map's uncertainty (if computed) as `<prefix>uncertainty-<map>.exr`.
pub fn write_uncertainty(pred: &IidPrediction, prefix: &str) -> anyhow::Result<()> {
    for (t, img) in &pred.uncertainty {
        pixl_core::io::write_image(format!("{prefix}uncertainty-{}.exr", t.name).as_ref(), img)?;
    }
    Ok(())
}

/// Logs how long decomposing a `width × height` photo with `opts` will take (measured
/// throughput, BENCHMARKS.md); refuses options the checkpoint cannot run.
pub fn announce(m: &Marigold, width: usize, height: usize, opts: &MarigoldOptions, label: &str) -> anyhow::Result<()> {
    let (steps, res) = m.resolve(opts)?;
    log_expected_time(label, res, steps, opts.ensemble, m.approx_tflop(width, height, opts));
    Ok(())
}

/// Logs the expected time of a Marigold run of `tflop` TFLOP (`None`: nothing to say) on this
/// process's CPU threads (`RAYON_NUM_THREADS`, else all cores). Shared by every Marigold model:
/// they run the same UNet.
pub fn log_expected_time(label: &str, res: usize, steps: usize, members: usize, tflop: Option<f64>) {
    let threads = std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|v| v.parse::<usize>().ok())
        .filter(|n| *n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));
    if let Some(tflop) = tflop {
        // Measured (BENCHMARKS.md, 2 threads, Xeon): 0.085 TFLOP/s per thread for materials at
        // 768 px × 4 steps, 0.09–0.10 at 512 px × 1 step (materials, normals); the lower figure.
        let secs = tflop / (0.085 * threads.max(1) as f64);
        tracing::info!(
            "{label}: {res} px, {steps} steps × {members} member(s): about {} on {threads} CPU threads (≈{tflop:.0} TFLOP)",
            human_duration(secs)
        );
    }
}

fn human_duration(secs: f64) -> String {
    if secs < 90.0 {
        format!("{secs:.0} s")
    } else {
        format!("{:.0} min", secs / 60.0)
    }
}
