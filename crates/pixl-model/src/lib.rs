//! `pixl-model`: the PIXLRelight network (paper §3.2–3.3) on candle, its configuration and its
//! checkpoints.
//!
//! One file per paragraph of §3.2: [`vit`] (source encoder), [`convnext`] (intrinsics
//! encoder), [`fusion`] (per-location fusion), [`trunk`] (self-attention trunk with registers
//! and 2D RoPE), [`dpt`] (DPT head), [`modulation`] (gain/bias output, Eq. 4). [`model`]
//! assembles them; [`fullres`] runs it at a working resolution and applies its gain and bias to
//! a photo of any size; [`config`] holds the presets; [`checkpoint`] builds, saves and loads weights
//! (safetensors, PyTorch-style names, config in the metadata — see the crate README); [`parts`]
//! splits a weights file into parts of bounded size (optionally as f16/bf16) and joins them back;
//! [`official`] loads the paper's released checkpoint unchanged through a rename table (data) and
//! inspects any weights file against it.
pub mod checkpoint;
pub mod config;
pub mod convnext;
pub mod dpt;
pub mod fullres;
pub mod fusion;
mod layers;
pub mod model;
pub mod modulation;
pub mod official;
pub mod parts;
pub mod trunk;
pub mod vit;

pub use checkpoint::{
    build_inference, build_trainable, freeze, load, load_bytes, load_into_varmap, read_config, save, save_tensors,
    CheckpointError,
};
pub use config::{Config, ConfigError};
pub use model::PixlRelight;
