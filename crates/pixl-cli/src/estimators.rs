//! The estimators as the commands use them: Depth Anything 3 with its weights resolved on the
//! console ([`estimate_depth`], shared by `pixl estimate depth`, `pixl reconstruct` and `pixl
//! relight`) and a photo read for an estimator ([`read_photo`]).
use crate::weights::WeightsArgs;
use crate::Ctx;
use anyhow::bail;
use pixl_core::Image;
use pixl_estimate::da3::{Da3Variant, DepthEstimate};
use pixl_estimate::hub::{self, Resolved};
use pixl_pipeline::estimators::{Da3Depth, MIN_SIDE};
use pixl_pipeline::exif::Focal;
use pixl_pipeline::Photo;
use std::path::Path;

/// The depth estimators.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum DepthModel {
    /// Metric depth in metres (needs a focal length; see --fov/--focal).
    #[value(name = "da3-metric")]
    Da3Metric,
    /// Relative depth (up to scale).
    #[value(name = "da3-mono")]
    Da3Mono,
}

impl DepthModel {
    pub fn name(self) -> &'static str {
        match self {
            DepthModel::Da3Metric => "da3-metric",
            DepthModel::Da3Mono => "da3-mono",
        }
    }
    pub fn variant(self) -> Da3Variant {
        match self {
            DepthModel::Da3Metric => Da3Variant::Metric,
            DepthModel::Da3Mono => Da3Variant::Mono,
        }
    }
}

/// Reads a photo for an estimator: RGB, finite, at least [`MIN_SIDE`] on each side, sRGB-encoded
/// values in [0, 1] (EXR photos are linear and get encoded).
pub fn read_photo(path: &Path) -> anyhow::Result<Image> {
    let photo = Photo::open(path, None, None)?;
    check_side(&photo)?;
    Ok(photo.srgb().into_owned())
}

/// Refuses a photo smaller than [`MIN_SIDE`] on a side.
pub fn check_side(photo: &Photo) -> anyhow::Result<()> {
    let (w, h) = photo.size();
    if w < MIN_SIDE || h < MIN_SIDE {
        bail!(
            "{}: the photo is {w}x{h}; depth estimation needs at least {MIN_SIDE}x{MIN_SIDE} pixels",
            photo.name()
        );
    }
    Ok(())
}

/// A depth estimate with its provenance.
pub struct Estimated {
    pub estimate: DepthEstimate,
    pub weights: Resolved,
    pub model: DepthModel,
    pub focal: Focal,
}

/// Resolves the weights of `model` (models folder, Hugging Face cache, or a download with the
/// licence shown first) and loads it as the pipeline's depth estimator.
pub fn load_depth_model(
    model: DepthModel,
    process_res: usize,
    device: &str,
    weights: &WeightsArgs,
    ctx: &Ctx,
) -> anyhow::Result<(Da3Depth, Resolved)> {
    let spec = hub::lookup(model.name())?;
    let resolved = crate::weights::resolve(&weights.hub(), spec, ctx)?;
    let device = crate::device::parse_device(device)?;
    tracing::debug!("{}: weights from {}", spec.name, resolved.source);
    let mut net = Da3Depth::load(&resolved.dir, model.variant(), spec.name, &device)?;
    net.process_res = process_res;
    Ok((net, resolved))
}

/// Finds (or downloads) the weights, loads the model, and estimates the photo's depth.
pub fn estimate_depth(
    photo: &Photo,
    model: DepthModel,
    process_res: usize,
    device: &str,
    weights: &WeightsArgs,
    ctx: &Ctx,
) -> anyhow::Result<Estimated> {
    check_side(photo)?;
    let (net, resolved) = load_depth_model(model, process_res, device, weights, ctx)?;
    let estimate = net.estimate_raw(&photo.srgb(), photo.focal.px)?;
    Ok(Estimated {
        estimate,
        weights: resolved,
        model,
        focal: photo.focal,
    })
}
