//! `pixl-estimate`: the pretrained estimators of the paper's inference pipeline (§3.4), ported to
//! candle and loading their official checkpoints unchanged.
//!
//! - [`da3`] — Depth Anything 3, monocular and metric single-image depth (+ sky mask).
//! - [`marigold`] — Marigold-IID v1.1 Appearance (albedo, roughness, metallicity) and Lighting
//!   (albedo, diffuse shading, non-diffuse residual) intrinsic decompositions.
//! - [`hub`] — where model weights come from: `--models DIR`, the Hugging Face cache, a download.
//! - [`resize`] — the resamplers of the official preprocessing (cv2, PyTorch).
//! - [`error`] — the typed error of this crate ([`EstimateError`]).
pub mod da3;
pub mod error;
pub mod hub;
pub mod marigold;
pub mod resize;

pub use error::EstimateError;
