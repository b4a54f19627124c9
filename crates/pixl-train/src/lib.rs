//! `pixl-train`: training PIXLRelight on paired multi-illumination data (paper §3.3, App. A, C).
//!
//! - [`sampler`]: the pair sampler over the scenes of a [`pixl_data`] dataset (same crop / resize
//!   / flip for source, target and C_T; no photometric augmentation).
//! - [`synth`]: `pixl synth`, the synthetic multi-illumination sets ([`pixl_data::Synth`] reads them).
//! - [`optim`]: AdamW (decay exemptions), the warm-up + cosine schedule, global-norm clipping.
//! - [`loss`]: L1 + λ·VGG16 perceptual (feature L1).
//! - [`config`]: the `train.toml` settings.
//! - [`trainer`]: the loop (accumulation, C_T corruption, logs, sample grids, checkpoints).
//! - [`precision`]: bf16 compute over f32 master weights.
//! - [`recompute`]: the micro-batch loss/gradient, plain or with per-block gradient checkpointing.
//! - [`state`]: the resumable checkpoint file (bit-exact resume on CPU).
pub mod config;
pub mod error;
pub mod loss;
pub mod optim;
pub mod precision;
pub mod recompute;
pub mod sampler;
pub mod state;
pub mod synth;
pub mod trainer;

pub use config::TrainConfig;
pub use error::{Result, TrainError};
pub use trainer::{StepReport, Trainer};
