//! The estimators the pipeline plugs in: [`Da3Depth`] runs Depth Anything 3 (metric or mono,
//! `pixl_estimate::da3`) as a [`DepthEstimator`]; [`MarigoldLighting`] runs Marigold-IID-Lighting
//! (`pixl_estimate::marigold`) as a [`LightingEstimator`]; [`MarigoldNormalsEstimator`] runs
//! Marigold Normals (`pixl_estimate::marigold::normals`) as a [`NormalsEstimator`]. Where their
//! weights come from (a models folder, the Hugging Face cache, a download with the licence
//! shown) is the caller's business: it hands over the folder that holds them, or the loaded
//! model.
use crate::depth::{DepthEstimator, DepthKind, EstimatedDepth};
use crate::error::{PipelineError, Result};
use crate::like::{Decomposition, LightingEstimator};
use crate::normals::{scene_from_marigold, NormalsEstimator};
use crate::observe::{Observer, Stage};
use candle_core::Device;
use pixl_core::Image;
use pixl_estimate::da3::{Da3, Da3Options, Da3Variant};
use pixl_estimate::marigold::normals::{MarigoldNormals, NormalsOptions};
use pixl_estimate::marigold::{IidPrediction, IidVariant, Marigold};
use pixl_render::depth::DepthMap;
use std::path::Path;

/// The options of a Marigold run (steps, resolution, ensemble, seed), for [`MarigoldLighting`].
pub use pixl_estimate::marigold::MarigoldOptions;

/// Smallest photo side the estimators accept (one 14-pixel ViT patch).
pub const MIN_SIDE: usize = 14;
/// Longest side DA3 processes by default (the official default).
pub const DEFAULT_PROCESS_RES: usize = 504;

/// Checks a DA3 processing resolution.
pub fn check_process_res(r: usize) -> Result<()> {
    if !(MIN_SIDE..=4096).contains(&r) {
        return Err(PipelineError::input(format!(
            "--process-res {r}: must be between {MIN_SIDE} and 4096"
        )));
    }
    Ok(())
}

/// Depth Anything 3 as a [`DepthEstimator`].
pub struct Da3Depth {
    net: Da3,
    /// Longest side the photo is resized to for the network.
    pub process_res: usize,
    /// `da3-metric` / `da3-mono`.
    pub label: String,
}

impl Da3Depth {
    /// Loads the checkpoint in `dir` (the official Hugging Face layout) on `device`; `label`
    /// names it in messages. `want` is the variant asked for: another one is refused.
    pub fn load(dir: &Path, want: Da3Variant, label: &str, device: &Device) -> Result<Da3Depth> {
        let net = Da3::load(dir, device)
            .map_err(|e| PipelineError::from(e).context(format!("loading `{label}` from {}", dir.display())))?;
        if net.variant() != want {
            return Err(PipelineError::input(format!(
                "{}: the checkpoint is DA3 {:?}, but `{label}` was asked for (a config.json of another model?)",
                dir.display(),
                net.variant(),
            )));
        }
        Ok(Da3Depth {
            net,
            process_res: DEFAULT_PROCESS_RES,
            label: label.to_string(),
        })
    }

    pub fn variant(&self) -> Da3Variant {
        self.net.variant()
    }

    /// The full estimate (depth and sky mask as DA3 gives them).
    pub fn estimate_raw(&self, photo: &Image, focal_px: f64) -> Result<pixl_estimate::da3::DepthEstimate> {
        if photo.width < MIN_SIDE || photo.height < MIN_SIDE {
            return Err(PipelineError::input(format!(
                "the photo is {}x{}; depth estimation needs at least {MIN_SIDE}x{MIN_SIDE} pixels",
                photo.width, photo.height
            )));
        }
        let opts = Da3Options {
            process_res: self.process_res,
            focal_px_at_photo: Some(focal_px),
        };
        let est = self
            .net
            .estimate(photo, &opts)
            .map_err(|e| PipelineError::from(e).context(format!("estimating depth with `{}`", self.label)))?;
        let d = &est.depth;
        if (d.width, d.height) != (photo.width, photo.height) || d.channels < 1 {
            return Err(PipelineError::input(format!(
                "`{}` returned a {}x{}x{} depth map for a {}x{} photo",
                self.label, d.width, d.height, d.channels, photo.width, photo.height
            )));
        }
        Ok(est)
    }
}

/// DA3's depth with sky (and anything non-finite or ≤ 0) as 0 = missing.
pub fn depth_without_sky(est: &pixl_estimate::da3::DepthEstimate) -> Vec<f32> {
    let d = &est.depth;
    (0..d.width * d.height)
        .map(|i| {
            let v = d.data[i * d.channels];
            let sky = est.sky_mask.get(i).copied().unwrap_or(false);
            if sky || !v.is_finite() || v <= 0.0 {
                0.0
            } else {
                v
            }
        })
        .collect()
}

impl DepthEstimator for Da3Depth {
    fn name(&self) -> String {
        match self.net.variant() {
            Da3Variant::Metric => format!("Depth Anything 3 metric ({})", self.label),
            Da3Variant::Mono => format!("Depth Anything 3 relative ({})", self.label),
        }
    }

    fn estimate(&self, photo: &Image, focal_px: f64) -> Result<EstimatedDepth> {
        let est = self.estimate_raw(photo, focal_px)?;
        let sky = est.sky_mask.iter().filter(|s| **s).count();
        let (w, h) = (photo.width, photo.height);
        Ok(EstimatedDepth {
            depth: DepthMap::new(w, h, depth_without_sky(&est))?,
            kind: if est.metric {
                DepthKind::Metric
            } else {
                DepthKind::Relative
            },
            sky_fraction: sky as f64 / (w * h).max(1) as f64,
        })
    }
}

/// Marigold-IID-Lighting (`prs-eth/marigold-iid-lighting-v1-1`, OpenRAIL++-M) as a
/// [`LightingEstimator`]: its albedo, diffuse shading and non-diffuse residual are linear, the
/// paper's A, S, R.
pub struct MarigoldLighting {
    net: Marigold,
    /// Steps, resolution, ensemble and seed of every decomposition.
    pub options: MarigoldOptions,
    /// How the checkpoint is named in messages (`marigold-lighting`).
    pub label: String,
}

impl MarigoldLighting {
    /// Wraps a loaded checkpoint; one of another variant (Appearance) is refused.
    pub fn new(net: Marigold, options: MarigoldOptions, label: &str) -> Result<MarigoldLighting> {
        if net.variant() != Some(IidVariant::Lighting) {
            return Err(PipelineError::input(format!(
                "`{label}` predicts {}, not Marigold-IID Lighting's albedo, shading and residual",
                net.pipeline().target_names().join(", ")
            )));
        }
        Ok(MarigoldLighting {
            net,
            options,
            label: label.to_string(),
        })
    }

    /// Loads the checkpoint in `dir` (the official diffusers layout) on `device`.
    pub fn load(dir: &Path, options: MarigoldOptions, label: &str, device: &Device) -> Result<MarigoldLighting> {
        let net = Marigold::load(dir, device)
            .map_err(|e| PipelineError::from(e).context(format!("loading `{label}` from {}", dir.display())))?;
        Self::new(net, options, label)
    }

    pub fn model(&self) -> &Marigold {
        &self.net
    }
}

impl Decomposition {
    /// From a Marigold-IID-Lighting prediction (its `albedo`, `shading` and `residual` maps).
    pub fn from_prediction(p: &IidPrediction) -> Result<Decomposition> {
        let get = |n: &str| {
            p.get(n)
                .cloned()
                .ok_or_else(|| PipelineError::input(format!("the prediction has no {n} map")))
        };
        Ok(Decomposition {
            albedo: get("albedo")?,
            shading: get("shading")?,
            residual: get("residual")?,
        })
    }
}

impl LightingEstimator for MarigoldLighting {
    fn name(&self) -> String {
        format!("Marigold-IID Lighting ({})", self.label)
    }

    fn decompose(&self, photo: &Image, observer: &dyn Observer) -> Result<Decomposition> {
        let pred = self
            .net
            .predict(photo, &self.options, &mut |p| {
                observer.progress(Stage::Intrinsics, p.done as u64, p.total as u64)
            })
            .map_err(PipelineError::from)?;
        Decomposition::from_prediction(&pred)
    }
}

/// Marigold Normals (`prs-eth/marigold-normals-v1-1`, Apache-2.0) as a [`NormalsEstimator`]:
/// its camera-frame normals are given in the scene's frame ([`scene_from_marigold`]).
pub struct MarigoldNormalsEstimator {
    net: MarigoldNormals,
    /// Steps, resolution, ensemble, reduction and seed of every estimate.
    pub options: NormalsOptions,
    /// How the checkpoint is named in messages (`marigold-normals`).
    pub label: String,
}

impl MarigoldNormalsEstimator {
    pub fn new(net: MarigoldNormals, options: NormalsOptions, label: &str) -> MarigoldNormalsEstimator {
        MarigoldNormalsEstimator {
            net,
            options,
            label: label.to_string(),
        }
    }

    /// Loads the checkpoint in `dir` (the official diffusers layout) on `device`; an IID
    /// checkpoint is refused.
    pub fn load(dir: &Path, options: NormalsOptions, label: &str, device: &Device) -> Result<MarigoldNormalsEstimator> {
        let net = MarigoldNormals::load(dir, device)
            .map_err(|e| PipelineError::from(e).context(format!("loading `{label}` from {}", dir.display())))?;
        Ok(Self::new(net, options, label))
    }

    pub fn model(&self) -> &MarigoldNormals {
        &self.net
    }
}

impl NormalsEstimator for MarigoldNormalsEstimator {
    fn name(&self) -> String {
        format!("Marigold Normals ({})", self.label)
    }

    fn estimate(&self, photo: &Image, observer: &dyn Observer) -> Result<Image> {
        let pred = self
            .net
            .predict(photo, &self.options, &mut |p| {
                observer.progress(Stage::Normals, p.done as u64, p.total as u64)
            })
            .map_err(PipelineError::from)?;
        Ok(scene_from_marigold(&pred.normals))
    }
}

/// Estimated materials at the photo's size (Marigold-IID-Appearance): linear albedo (RGB),
/// roughness and metallic (one channel each).
pub struct Materials {
    pub albedo_linear: Image,
    pub roughness: Image,
    pub metallic: Image,
}

impl Materials {
    /// From an Appearance prediction: albedo is sRGB-encoded (decoded here), the material map
    /// holds roughness in R and metallicity in G.
    pub fn from_prediction(p: &IidPrediction) -> Result<Self> {
        let get = |n: &str, what: &str| {
            p.get(n)
                .ok_or_else(|| PipelineError::input(format!("the prediction has no {what}")))
        };
        let albedo = get("albedo", "albedo")?;
        let material = get("material", "material map")?;
        let (w, h) = (albedo.width, albedo.height);
        Ok(Self {
            albedo_linear: albedo.map(|v| pixl_core::image::srgb_to_linear(v.clamp(0.0, 1.0))),
            roughness: Image::from_fn(w, h, 1, |x, y, _| material.get(x, y, 0).clamp(0.0, 1.0)),
            metallic: Image::from_fn(w, h, 1, |x, y, _| material.get(x, y, 1).clamp(0.0, 1.0)),
        })
    }
}

/// `C_T` of a photo from a Lighting prediction at its size (App. B's rescale), and τ.
pub fn ct_from_lighting(p: &IidPrediction) -> Result<(pixl_intrinsics::ct::Ct, f32)> {
    let d = Decomposition::from_prediction(p)?;
    crate::like::ct_from_decomposition(&d, (d.albedo.width, d.albedo.height))
}
