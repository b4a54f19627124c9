//! Depth Anything 3, single-image monocular (`da3mono-large`) and metric (`da3metric-large`)
//! depth with a sky score (paper §3.4 "Geometry"), ported from the official code
//! (depth-anything-3 0.1.1) and loading its checkpoints unchanged.
//!
//! Contract of [`Da3::estimate`]: a photo ([`Image`], 1–4 channels, values in [0, 1] as read
//! from an 8-bit PNG/JPEG) → [`DepthEstimate`] at the photo's size: depth (relative for
//! [`Da3Variant::Mono`], metres for [`Da3Variant::Metric`]), the sky score and the sky mask. The
//! pipeline is the official one:
//! [`preprocess`] (cv2 resizes, multiple-of-14 sides, ImageNet normalisation) → [`Da3::forward`]
//! (DINOv2 ViT, [`backbone`], then the DPT head, [`head`]; f32) → the sky rule and metric
//! scaling ([`postprocess`]) → bilinear resize to the photo. [`resize`] holds the resamplers,
//! [`pixl_nn::conv3x3`] and [`pixl_nn::fused`] the CPU kernels (3×3 convolution, fused
//! bias/activation/residual passes, batched attention) that keep the CPU forward parallel.
//!
//! Differences from the official API, all deliberate: the network runs in f32 (the official
//! `DepthAnything3.forward` autocasts the backbone to bf16/fp16); the sky quantile uses every
//! non-sky pixel instead of a random 100 000-pixel sample; the outputs are resized back to the
//! photo (the official API stops at the processed resolution).
//!
//! Files: `config.json` ([`Da3Config::from_json`]) and `model.safetensors` with the official
//! tensor names ([`weights`]), f32, f16 or bf16.
pub mod backbone;
pub mod config;
pub mod head;
pub mod postprocess;
pub mod preprocess;
pub use crate::resize;
pub mod weights;

pub use config::{Da3Arch, Da3Config, Da3HeadConfig, Da3NetConfig};
pub use postprocess::SKY_THRESHOLD;
pub use preprocess::{preprocess, ProcessPlan, DEFAULT_PROCESS_RES};

use crate::error::EstimateError;
use backbone::Backbone;
use candle_core::{Device, Tensor};
use head::DptHead;
use pixl_core::Image;
use std::path::Path;

/// Which released single-view model a checkpoint is (from its `model_name`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Da3Variant {
    /// `da3mono-large`: relative depth.
    Mono,
    /// `da3metric-large`: depth in metres once scaled by the focal length.
    Metric,
}

/// Options of [`Da3::estimate`].
#[derive(Clone, Debug, PartialEq)]
pub struct Da3Options {
    /// Longest side of the network input before rounding to multiples of 14 (official default
    /// 504, [`DEFAULT_PROCESS_RES`]).
    pub process_res: usize,
    /// Focal length in pixels at the photo's resolution (fx = fy), for metric scaling. `None`:
    /// the model's canonical focal, 300 px at the processed resolution, i.e. the network output
    /// unscaled (about an 80° horizontal field of view at 504 px wide). Ignored by mono models.
    pub focal_px_at_photo: Option<f64>,
}

impl Default for Da3Options {
    fn default() -> Self {
        Self {
            process_res: DEFAULT_PROCESS_RES,
            focal_px_at_photo: None,
        }
    }
}

/// Output of [`Da3::estimate`], at the photo's size.
#[derive(Clone, Debug)]
pub struct DepthEstimate {
    /// 1 channel: metres for a metric model, relative depth (not disparity) for a mono model;
    /// sky pixels hold the 0.99 quantile of the other pixels' depth (the official sky rule).
    pub depth: Image,
    /// 1 channel: the sky head's score (ReLU output for the released models; ≥ 0.3 is sky).
    pub sky: Image,
    /// `sky ≥ SKY_THRESHOLD` per pixel, row-major.
    pub sky_mask: Vec<bool>,
    /// Network input size `(width, height)`, multiples of 14.
    pub processed_size: (usize, usize),
    /// Whether `depth` is in metres.
    pub metric: bool,
}

/// A loaded DA3 model.
pub struct Da3 {
    config: Da3Config,
    backbone: Backbone,
    head: DptHead,
    device: Device,
}

impl Da3 {
    /// `dir` holds `config.json` + `model.safetensors` (official layout).
    pub fn load(dir: &Path, device: &Device) -> Result<Self, EstimateError> {
        Self::from_files(&dir.join("config.json"), &dir.join("model.safetensors"), device)
    }

    /// Reads the config, checks the weights' names, shapes and dtypes against it, then builds.
    pub fn from_files(config_json: &Path, weights: &Path, device: &Device) -> Result<Self, EstimateError> {
        let text = std::fs::read_to_string(config_json).map_err(|source| EstimateError::Io {
            path: config_json.to_owned(),
            source,
        })?;
        let config = Da3Config::from_json(&text).map_err(|reason| EstimateError::Config {
            path: config_json.to_owned(),
            reason,
        })?;
        Self::from_config(config, weights, device)
    }

    /// Builds `config` with the weights of `weights`.
    pub fn from_config(config: Da3Config, weights: &Path, device: &Device) -> Result<Self, EstimateError> {
        config.validate().map_err(|reason| EstimateError::Config {
            path: weights.to_owned(),
            reason,
        })?;
        let vb = weights::load(&config, weights, device)?;
        Self::from_var_builder(config, vb, device)
    }

    /// Builds from any `VarBuilder` holding the official names (e.g. random weights for a
    /// benchmark). Names and shapes are checked as the tensors are read.
    pub fn from_var_builder(
        config: Da3Config,
        vb: candle_nn::VarBuilder,
        device: &Device,
    ) -> Result<Self, EstimateError> {
        config.validate().map_err(EstimateError::Input)?;
        let backbone = Backbone::new(&config, vb.pp("model").pp("backbone").pp("pretrained"))?;
        let head = DptHead::new(&config, vb.pp("model").pp("head"))?;
        Ok(Self {
            config,
            backbone,
            head,
            device: device.clone(),
        })
    }

    /// Mono or metric.
    pub fn variant(&self) -> Da3Variant {
        self.config.variant()
    }

    /// The architecture.
    pub fn config(&self) -> &Da3Config {
        &self.config
    }

    /// The device the weights live on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The backbone's linear layers as 8-bit products on CPUs with AVX-512 VNNI
    /// ([`pixl_nn::int8`]); returns how many (0 elsewhere). Measured on random weights of the
    /// released architecture only (`examples/bench_da3 --int8`): the released weights' depth
    /// under it has not been checked.
    pub fn quantize_int8(&mut self) -> Result<usize, EstimateError> {
        Ok(self.backbone.quantize_int8()?)
    }

    /// Backbone features for a preprocessed `(B, 3, H, W)` batch: four `(B, N, C)` tensors.
    pub fn forward_features(&self, xs: &Tensor) -> Result<Vec<Tensor>, EstimateError> {
        Ok(self.backbone.forward_features(xs)?)
    }

    /// The position embedding used for a `(gh, gw)` patch grid, `(1, 1 + gh·gw, C)`.
    pub fn pos_embed_for(&self, gh: usize, gw: usize) -> Result<Tensor, EstimateError> {
        Ok(self.backbone.pos_embed_for(gh, gw)?)
    }

    /// The network on a preprocessed `(B, 3, H, W)` batch: raw depth `exp(logits)` and the sky
    /// score, each `(B, H, W)`, before the sky rule.
    pub fn forward(&self, xs: &Tensor) -> Result<(Tensor, Tensor), EstimateError> {
        let (_, _, h, w) = xs.dims4()?;
        let p = self.backbone.patch();
        if h % p != 0 || w % p != 0 || h == 0 || w == 0 {
            return Err(EstimateError::Input(format!(
                "network input {w}x{h} is not a multiple of the patch size {p}"
            )));
        }
        let feats = self.backbone.forward_features(xs)?;
        Ok(self.head.forward(&feats, h / p, w / p)?)
    }

    /// The official preprocessing of `photo` on this model's device: `(1, 3, H, W)` and sizes.
    pub fn preprocess(&self, photo: &Image, process_res: usize) -> Result<(Tensor, ProcessPlan), EstimateError> {
        preprocess(photo, process_res, &self.device)
    }

    /// Depth and sky of one photo at its own size (see the module docs for the pipeline).
    pub fn estimate(&self, photo: &Image, opts: &Da3Options) -> Result<DepthEstimate, EstimateError> {
        if let Some(f) = opts.focal_px_at_photo {
            if !(f.is_finite() && f > 0.0) {
                return Err(EstimateError::Input(format!(
                    "focal length {f} px must be positive and finite"
                )));
            }
        }
        let (xs, plan) = self.preprocess(photo, opts.process_res)?;
        let (depth, sky) = self.forward(&xs)?;
        let (w, h) = plan.processed;
        let mut depth = depth.flatten_all()?.to_vec1::<f32>()?;
        let sky = sky.flatten_all()?.to_vec1::<f32>()?;
        postprocess::apply_sky_rule(&mut depth, &sky)?;
        let metric = self.variant() == Da3Variant::Metric;
        if metric {
            if let Some(f) = opts.focal_px_at_photo {
                let s = postprocess::metric_scale(f, plan.photo, plan.processed) as f32;
                depth.iter_mut().for_each(|d| *d *= s);
            }
        }
        let (pw, ph) = plan.photo;
        let to_photo = |v: Vec<f32>| -> Result<Image, EstimateError> {
            let t = Tensor::from_vec(v, (1, 1, h, w), &Device::Cpu)?;
            let t = resize::bilinear_half_pixel(&t, ph, pw)?;
            Ok(Image::from_vec(pw, ph, 1, t.flatten_all()?.to_vec1::<f32>()?)?)
        };
        let depth = to_photo(depth)?;
        let sky = to_photo(sky)?;
        let sky_mask = sky.data.iter().map(|&s| s >= SKY_THRESHOLD).collect();
        Ok(DepthEstimate {
            depth,
            sky,
            sky_mask,
            processed_size: plan.processed,
            metric,
        })
    }
}
