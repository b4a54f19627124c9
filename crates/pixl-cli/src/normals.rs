//! Marigold Normals on the command line, shared by `pixl estimate normals` and
//! `pixl reconstruct --normals marigold`: the flags ([`MarigoldNormalsArgs`]), loading the checkpoint
//! (`marigold-normals`; an IID checkpoint in its place is one clear error: [`load`]), and the
//! time it will take shown up front ([`announce`]).
use crate::weights::WeightsArgs;
use crate::Ctx;
use anyhow::Context;
use pixl_estimate::hub::{self, Resolved};
use pixl_estimate::marigold::normals::{MarigoldNormals, NormalsOptions, NormalsReduction};

/// The registry name of the released checkpoint.
pub const MODEL: &str = "marigold-normals";

/// How an ensemble's members are combined per pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Reduction {
    /// The member nearest in angle to the members' mean normal (diffusers' default).
    Closest,
    /// The members' mean normal.
    Mean,
}

/// The options of one Marigold Normals run (the model and device flags come with the command).
#[derive(clap::Args, Debug, Clone)]
pub struct MarigoldNormalsArgs {
    /// Longest side the network sees, a multiple of 8 (default: the checkpoint's, 768; 512 is
    /// about twice as fast on a CPU and a little blurrier).
    #[arg(long = "res", value_name = "PX")]
    pub res: Option<usize>,
    /// Denoising steps (default: the checkpoint's, 4).
    #[arg(long, value_parser = crate::ctx::at_least_one_usize)]
    pub steps: Option<usize>,
    /// Predictions combined per pixel (each one costs a full run; 1 = none).
    #[arg(long, default_value_t = 1, value_parser = crate::ctx::at_least_one_usize)]
    pub ensemble: usize,
    /// How an ensemble is combined per pixel.
    #[arg(long, value_enum, default_value_t = Reduction::Closest)]
    pub reduction: Reduction,
    /// Seed of the initial noise (the same seed gives the same normals).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

impl Default for MarigoldNormalsArgs {
    fn default() -> Self {
        Self {
            res: None,
            steps: None,
            ensemble: 1,
            reduction: Reduction::Closest,
            seed: 0,
        }
    }
}

impl MarigoldNormalsArgs {
    pub fn options(&self, uncertainty: bool) -> NormalsOptions {
        NormalsOptions {
            steps: self.steps,
            ensemble: self.ensemble,
            resolution: self.res,
            reduction: match self.reduction {
                Reduction::Closest => NormalsReduction::Closest,
                Reduction::Mean => NormalsReduction::Mean,
            },
            seed: self.seed,
            uncertainty,
        }
    }
}

/// Finds (or downloads) the weights of `marigold-normals` and loads them; a checkpoint of
/// another Marigold pipeline is refused, naming what it predicts.
pub fn load(device: &str, weights: &WeightsArgs, ctx: &Ctx) -> anyhow::Result<(MarigoldNormals, Resolved)> {
    let spec = hub::lookup(MODEL)?;
    let resolved = crate::weights::resolve(&weights.hub(), spec, ctx)?;
    let device = crate::device::parse_device(device)?;
    let m = MarigoldNormals::load(&resolved.dir, &device)
        .with_context(|| format!("loading `{}` from {}", spec.name, resolved.dir.display()))?;
    Ok((m, resolved))
}

/// Logs how long estimating a `width × height` photo's normals with `opts` will take
/// ([`crate::iid::log_expected_time`]); refuses options the checkpoint cannot run.
pub fn announce(m: &MarigoldNormals, width: usize, height: usize, opts: &NormalsOptions) -> anyhow::Result<()> {
    let (steps, res) = m.resolve(opts)?;
    crate::iid::log_expected_time(
        "normals",
        res,
        steps,
        opts.ensemble,
        m.approx_tflop(width, height, opts),
    );
    Ok(())
}
