//! `pixl-pipeline`: relighting a photograph, stage by stage, as a library (paper §3.4) — the
//! code behind `pixl relight`, `pixl reconstruct`, `pixl demo` and `pixl studio`.
//!
//! ```text
//! Photo ──► depth ──► Geometry ──► + lights ──► render passes ──► C_T ──► network ──► relit
//! (photo)   (depth)   (reconstruct)  (scene)     (render)                  (relight)
//! ```
//!
//! - [`photo`]: the photo, decoded once, with its focal length ([`exif`]).
//! - [`depth`]: depth files, their kinds and conversion to metres; the [`depth::DepthEstimator`]
//!   trait, with Depth Anything 3 behind it in [`estimators`].
//! - [`reconstruct`]: photo + metric depth (+ material maps) → [`reconstruct::Geometry`], in
//!   memory, written as a scene folder only when asked.
//! - [`normals`]: the mesh's shading normals from a normal map, read from a file or estimated
//!   by a [`normals::NormalsEstimator`] (Marigold Normals in [`estimators`]).
//! - [`lights`]: one light as the user says it ([`lights::LightSpec`]), placed in the scene.
//! - [`render`]: the scene under its lights → passes → C_T.
//! - [`relight`]: the network ([`relight::Network`]: ours, the paper's released checkpoint, or
//!   the bundled weights by default), its memory
//!   plan, and the relit photo at full size.
//! - [`like`]: the target lighting read off another photo instead: its `C_T` from a
//!   [`like::LightingEstimator`] (Marigold-IID-Lighting in [`estimators`]), then the network.
//! - [`job`]: one photo end to end — a [`job::Job`] (photo + [`job::Lighting`]) through the
//!   stages above to the relit photo, intermediates written only when asked.
//! - [`batch`]: many photos in one process — inputs from folders, patterns, lists or a
//!   manifest, a stable shard of them, each a job, resumable through a log.
//! - [`video`]: a clip or an image sequence relit frame by frame through FFmpeg, streamed; a
//!   static camera reconstructed once, a moving one per frame.
//! - [`observe`]: how a caller watches long stages ([`observe::Observer`]).
//!
//! Typed errors ([`PipelineError`]); no stage prints: notes and progress go to the observer.
pub mod batch;
pub mod depth;
pub mod error;
pub mod estimators;
pub mod exif;
pub mod job;
pub mod lights;
pub mod like;
pub mod normals;
pub mod observe;
pub mod photo;
pub mod reconstruct;
pub mod relight;
pub mod render;
pub mod video;

pub use error::{PipelineError, Result};
pub use observe::{Observer, Silent, Stage};
pub use photo::Photo;
