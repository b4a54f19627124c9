//! `pixl-eval`: the evaluation of paper §4.1 — PSNR / SSIM / LPIPS after a per-channel
//! least-squares scale correction, the timing protocol (2 warm-ups, 5 timed runs), baselines and
//! report tables.
pub mod timing;

pub use timing::{time_runs, Timing, DEFAULT_RUNS, DEFAULT_WARMUPS};
pub mod metrics;

pub use metrics::{psnr, scale_correct, ssim, MetricError};
pub mod lpips;

pub use lpips::{Lpips, LpipsError, LpipsNet};
