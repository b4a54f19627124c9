//! `pixl-eval`: the evaluation of paper §4.1 — PSNR / SSIM / LPIPS after a per-image, per-channel
//! least-squares scale correction, at native target resolution; the timing protocol (2 warm-ups,
//! 5 timed runs, forward pass only); the identity and compose baselines; report tables.
//!
//! - [`timing`]: [`time_runs`], [`Timing`].
//! - [`metrics`]: [`scale_correct`], [`psnr`], [`ssim`] (pure functions on [`pixl_core::Image`]).
//! - [`lpips`]: LPIPS v0.1 ([`Lpips`]) over [`pixl_nn::backbones`].
//! - [`baselines`]: the [`Method`] trait, [`Identity`], [`Compose`], [`ModelMethod`].
//! - [`response`]: the light-response score ([`light_response`]): how much of a change of light
//!   shows up in relit images, without ground truth.
//! - [`grid`]: the patch-grid score ([`patch_grid_amplitude`]): the RMS of an image's pattern
//!   repeating with the network's patch period.
//! - [`html`]: a self-contained HTML report of image panels and tables (`pixl demo`'s).
//! - [`run`]: pair lists and [`run_eval`].
//! - [`report`]: `results.md` / `results.json` / `per_pair.csv`.
//! - [`temporal`]: flicker of a clip ([`temporal::temporal_noise`]) and of a relit clip relative to
//!   its source ([`temporal::added_flicker`]).
//! - [`sheet`]: the contact sheet of the first pairs ([`contact_sheet`]).
pub mod baselines;
pub mod error;
pub mod grid;
pub mod html;
pub mod lpips;
pub mod metrics;
pub mod report;
pub mod response;
pub mod run;
pub mod sheet;
pub mod temporal;
pub mod timing;

pub use baselines::{compose_baseline, parse_baselines, Compose, Identity, Method, ModelMethod};
pub use error::{EvalError, Result};
pub use grid::patch_grid_amplitude;
pub use lpips::{Lpips, LpipsError, LpipsNet};
pub use metrics::{psnr, scale_correct, ssim, MetricError};
pub use report::write_reports;
pub use response::{light_response, LightResponse, ResponseSums};
pub use run::{
    default_pairs, read_pairs, run_eval, run_response, EvalOptions, EvalReport, MethodSummary, Pair, PairScore,
    ResponseCase, ResponseSummary,
};
pub use sheet::{contact_sheet, sheet_columns, SheetRow};
pub use timing::{time_runs, Timing, DEFAULT_RUNS, DEFAULT_WARMUPS};
