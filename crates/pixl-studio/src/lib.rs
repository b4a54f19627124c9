//! `pixl-studio`: place lights on a photograph in the browser and watch it relight.
//!
//! A local web server (axum on tokio) holds one session ([`Studio`]): a photo, its coarse 3D
//! geometry ([`geometry`]: a depth map, a pluggable [`geometry::DepthEstimator`], or a labelled
//! ground-and-backdrop fallback), the lights ([`lights`]) and their undo history. Every change
//! gives a quick direct-light preview at once ([`preview`], ≤ 128 px); when the lights settle, a
//! background thread path-traces the coarse scene progressively, composes `C_T` and runs the
//! network ([`pipeline`]), superseded by any newer change. "Light like this photo" relights the
//! photo with the lighting of an uploaded reference photo instead, through a pluggable
//! [`LightingEstimator`] (`pixl_pipeline::like`). The page (plain HTML/CSS/JS, compiled in) and
//! the JSON API are in [`api`]; the API is documented in the crate README.
pub mod api;
pub mod error;
pub mod geometry;
pub mod lights;
pub mod pipeline;
pub mod preview;
pub mod session;

pub use api::{router, serve};
pub use error::{Result, StudioError};
pub use geometry::{DepthEstimator, DepthKind, EstimatedDepth};
pub use lights::{LightKind, LightPatch, StudioLight};
pub use pipeline::Stage;
pub use pixl_pipeline::like::LightingEstimator;
pub use session::{Studio, StudioConfig, WaitFor};
