//! `pixl-intrinsics`: the intrinsic bridge between renders and the network.
//!
//! - [`ct`]: C_T = [A; S; R] (paper §3.1, eq. 1), in memory ([`ct::Ct`]) and on disk (one EXR,
//!   channels `albedo.R/G/B`, `shading.R/G/B`, `residual.R/G/B`).
//! - [`compose`]: C_T from Cycles render passes, exactly as paper App. B (joint p98 rescale).
//! - [`preview`]: contact sheets (A | S | R | A⊙S+R) for a person to look at.
//! - [`augment`]: the conditioning corruption pipeline of paper App. C (Table 4), candle ops.
//!
//! Errors are typed ([`IntrinsicsError`]) and name the file, pass and location involved.
pub mod augment;
pub mod compose;
pub mod ct;
pub mod error;
pub mod preview;

pub use error::{IntrinsicsError, Result};
