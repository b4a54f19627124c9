//! `pixl-train`: training PIXLRelight on paired multi-illumination data (paper §3.3, App. A, C).
//!
//! - [`data`]: dataset loaders (MIIW, BigTime, VIDIT, a generic folder, our synthetic renders),
//!   target-intrinsics lookup, and the pair sampler (same crop / resize / flip for source, target
//!   and C_T; no photometric augmentation).
pub mod data;
pub mod error;

pub use error::{Result, TrainError};
