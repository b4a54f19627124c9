//! `train.toml`: every setting of a training run, with the paper's values as defaults.
//!
//! ```toml
//! [model]
//! preset = "tiny"            # tiny | small | paper | path to a model config (.toml/.json)
//! init_seed = 0
//! init_weights = "assets/demo-weights/pixl-tiny-synth.safetensors"   # optional: fine-tune from these
//! [data]
//! dataset = "synth:data/synth"   # see pixl_data::open
//! split = "train"
//! cache = true                   # keep decoded images in memory
//! refresh_every = 0              # re-read the data set every N steps and add new scenes (0: never)
//! [data.sampler]
//! long_side = 512
//! coarse_ct = 0.0                # P(condition on `pixl synth --coarse`'s C_T of the pair), 0 = paper
//! coarse_pair_share = 0.0        # P(draw among the pairs that have one, and use it), 0 = paper
//! [optim]
//! batch_size = 4
//! accumulate = 1                 # micro-batches per step (effective batch = batch_size × accumulate)
//! clip_norm = 1.0
//! precision = "f32"              # f32 | bf16 (bf16 compute, f32 master weights; pixl_train::precision)
//! checkpoint = false             # per-block gradient checkpointing (pixl_train::recompute)
//! ema_decay = 0.0                # also keep an exponential moving average of the weights and
//!                                # write it as model-ema.safetensors (0 = off; e.g. 0.999)
//! [optim.schedule]
//! peak_lr = 5e-5
//! [loss]
//! perceptual_weight = 0.2
//! vgg = "vgg16.safetensors"
//! ssim_weight = 0.0              # extra μ·(1 − SSIM) term, not in the paper (0 = off)
//! scale_corrected = 0.0          # share ν of the pixel term taken after the evaluation's
//!                                # per-channel scale correction, not in the paper (0 = off)
//! [augment]
//! enabled = true                 # corrupt C_T with the paper's App. C pipeline
//! coarse = true                  # also the samples on a coarse-reconstruction C_T (false: only
//!                                # those on the target's exact C_T)
//! [run]
//! out_dir = "runs/tiny"
//! steps = 200000
//! max_minutes = 8.0              # optional: stop after this much training time (then the cosine
//!                                # runs over the time, not total_steps)
//! checkpoint_minutes = 2.0       # optional: also checkpoint whenever this much time has passed
//! ```
use crate::error::{Result, TrainError};
use crate::optim::{AdamWConfig, LrSchedule};
use crate::precision::Precision;
use crate::sampler::SamplerConfig;
use pixl_data::Split;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    pub model: ModelSection,
    pub data: DataSection,
    pub optim: OptimSection,
    pub loss: LossSection,
    pub augment: AugmentSection,
    pub run: RunSection,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelSection {
    pub preset: String,
    pub init_seed: u64,
    /// Start from these weights instead of a random initialisation (fine-tuning). The file
    /// (a `pixl` checkpoint) must store the same model config as `preset`; the optimiser
    /// moments and the step still start from zero. Ignored by `--resume`, which restores the
    /// run's own state.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub init_weights: Option<PathBuf>,
}

impl Default for ModelSection {
    fn default() -> Self {
        Self {
            preset: "tiny".into(),
            init_seed: 0,
            init_weights: None,
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DataSection {
    pub dataset: String,
    pub split: Split,
    pub cache: bool,
    /// Every this many steps, read the data set again and add the scenes that appeared since
    /// (a set still being made, e.g. a folder of `pixl synth` outputs that grows while the run
    /// reads it); 0 (default): read once. A growing set is not bit-exactly resumable.
    pub refresh_every: u64,
    pub sampler: SamplerConfig,
}

impl Default for DataSection {
    fn default() -> Self {
        Self {
            dataset: String::new(),
            split: Split::Train,
            cache: true,
            refresh_every: 0,
            sampler: SamplerConfig::default(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OptimSection {
    pub batch_size: usize,
    pub accumulate: usize,
    pub clip_norm: f64,
    /// The dtype the network computes in ([`Precision`]); weights and optimiser state stay f32.
    pub precision: Precision,
    /// Recompute each encoder/trunk block in the backward pass instead of keeping its
    /// activations ([`crate::recompute`]): less memory, about one more forward per step.
    pub checkpoint: bool,
    /// Keep an exponential moving average of the weights with this decay
    /// ([`crate::optim::Ema`]), saved with the training state and written as
    /// `model-ema.safetensors` beside `model.safetensors`; 0 (default): none, as in the paper.
    pub ema_decay: f64,
    pub schedule: LrSchedule,
    pub adamw: AdamWConfig,
}

impl Default for OptimSection {
    fn default() -> Self {
        Self {
            batch_size: 4,
            accumulate: 1,
            clip_norm: 1.0,
            precision: Precision::F32,
            checkpoint: false,
            ema_decay: 0.0,
            schedule: LrSchedule::default(),
            adamw: AdamWConfig::default(),
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LossSection {
    /// λ of eq. 5 (paper: 0.2). 0 trains with L1 only and needs no VGG file.
    pub perceptual_weight: f64,
    /// torchvision VGG16 weights (safetensors) for the perceptual term.
    pub vgg: Option<PathBuf>,
    /// μ of an extra `μ · (1 − SSIM)` term (not in the paper; 0 = off). `pixl_train::loss`.
    pub ssim_weight: f64,
    /// ν in `[0, 1]`: the pixel term becomes `(1 − ν)·L1 + ν·L1` of the scale-corrected output
    /// (not in the paper; 0 = off). `pixl_train::loss`.
    pub scale_corrected: f64,
}

impl Default for LossSection {
    fn default() -> Self {
        Self {
            perceptual_weight: 0.2,
            vgg: None,
            ssim_weight: 0.0,
            scale_corrected: 0.0,
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AugmentSection {
    /// Corrupt C_T on the fly with the paper's App. C pipeline (`pixl_intrinsics::augment`).
    pub enabled: bool,
    /// Also corrupt the samples conditioned on a coarse-reconstruction C_T (`[data.sampler]
    /// coarse_ct`, `coarse_pair_share`). The pipeline imitates the artifacts of the inference
    /// setting on a clean C_T; a coarse C_T already carries the real ones. `false` corrupts only
    /// the samples with the target's exact C_T (each keeps its random draws either way).
    pub coarse: bool,
}

impl Default for AugmentSection {
    fn default() -> Self {
        Self {
            enabled: true,
            coarse: true,
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunSection {
    pub out_dir: PathBuf,
    /// Train until this many optimiser steps have been taken.
    pub steps: u64,
    /// Seed of data order, crops, flips and C_T corruption.
    pub seed: u64,
    pub log_every: u64,
    pub sample_every: u64,
    pub checkpoint_every: u64,
    /// Stop after this many minutes of training (counted from the first step; the step under way
    /// finishes). With it, the learning rate's cosine runs over this time instead of
    /// `[optim.schedule] total_steps` ([`crate::optim::LrSchedule::lr_at_progress`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_minutes: Option<f64>,
    /// Also write a checkpoint whenever this many minutes have passed since the last one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub checkpoint_minutes: Option<f64>,
}

impl Default for RunSection {
    fn default() -> Self {
        Self {
            out_dir: PathBuf::from("runs/pixl"),
            steps: 200_000,
            seed: 0,
            log_every: 10,
            sample_every: 1000,
            checkpoint_every: 1000,
            max_minutes: None,
            checkpoint_minutes: None,
        }
    }
}

impl TrainConfig {
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| TrainError::io(path, e))?;
        let cfg: TrainConfig = toml::from_str(&text).map_err(|e| TrainError::File {
            path: path.to_owned(),
            reason: e.to_string(),
        })?;
        Ok(cfg)
    }

    pub fn to_toml(&self) -> Result<String> {
        toml::to_string_pretty(self).map_err(|e| TrainError::Config(e.to_string()))
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |m: &str| Err(TrainError::Config(m.to_string()));
        if self.data.dataset.is_empty() {
            return bad("[data] dataset is empty (e.g. dataset = \"synth:data/synth\")");
        }
        if self.optim.batch_size == 0 || self.optim.accumulate == 0 {
            return bad("[optim] batch_size and accumulate must be at least 1");
        }
        if self.optim.clip_norm.is_nan() || self.optim.clip_norm <= 0.0 {
            return bad("[optim] clip_norm must be positive");
        }
        if !(self.optim.ema_decay >= 0.0 && self.optim.ema_decay < 1.0) {
            return bad("[optim] ema_decay must be a number in [0, 1) (0: no average; e.g. 0.999)");
        }
        if self.loss.perceptual_weight < 0.0 {
            return bad("[loss] perceptual_weight must be >= 0");
        }
        if !(self.loss.ssim_weight >= 0.0 && self.loss.ssim_weight.is_finite()) {
            return bad("[loss] ssim_weight must be a finite number >= 0");
        }
        if !(0.0..=1.0).contains(&self.loss.scale_corrected) {
            return bad("[loss] scale_corrected must be a number in [0, 1] (the share of the scale-corrected L1)");
        }
        if self.loss.perceptual_weight > 0.0 && self.loss.vgg.is_none() {
            return bad(
                "[loss] perceptual_weight > 0 needs VGG16 weights: set vgg = \"vgg16.safetensors\" (torchvision layout, \
                 e.g. --vgg) or train with L1 only via perceptual_weight = 0 (--perceptual-weight 0)",
            );
        }
        if self.run.checkpoint_every == 0 || self.run.log_every == 0 || self.run.sample_every == 0 {
            return bad("[run] log_every, sample_every and checkpoint_every must be at least 1");
        }
        for (key, v) in [
            ("max_minutes", self.run.max_minutes),
            ("checkpoint_minutes", self.run.checkpoint_minutes),
        ] {
            if let Some(v) = v {
                if !(v.is_finite() && v > 0.0) {
                    return Err(TrainError::Config(format!(
                        "[run] {key} must be a positive number of minutes (got {v})"
                    )));
                }
            }
        }
        self.data.sampler.validate()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `[augment]`: both keys default to on (old run configs keep their meaning) and read back.
    #[test]
    fn augment_section_defaults_and_reads() {
        let cfg: TrainConfig = toml::from_str("").unwrap();
        assert_eq!((cfg.augment.enabled, cfg.augment.coarse), (true, true));
        let cfg: TrainConfig = toml::from_str("[augment]\ncoarse = false").unwrap();
        assert_eq!((cfg.augment.enabled, cfg.augment.coarse), (true, false));
        let again: TrainConfig = toml::from_str(&cfg.to_toml().unwrap()).unwrap();
        assert_eq!(again.augment, cfg.augment);
        assert!(toml::from_str::<TrainConfig>("[augment]\ncoarse_ct = false").is_err());
    }
}
