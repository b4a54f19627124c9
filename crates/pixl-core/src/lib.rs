//! `pixl-core`: what every stage of pixlrelight shares and none owns.
//!
//! - [`image`]: an interleaved `f32` image ([`Image`]), the one in-memory picture type.
//! - [`io`]: reading PNG / JPEG / EXR into an [`Image`] and writing them back, with a size guard
//!   that refuses absurd headers before allocating, and *atomic* writes (temporary file, fsync,
//!   rename) so a failed or interrupted command never leaves a half-written output.
//! - [`exrio`]: named-channel OpenEXR read/write (multi-part and single-part, f16/f32/u32), the
//!   layer under C_T files and Cycles render-pass files.
//! - [`output`]: checks of output files and folders made before any work (format from the
//!   extension, folder writable, output ≠ input, `--force` for a non-empty folder), and the
//!   registry of live temporary paths that a signal handler removes on interruption.
//! - [`resample`]: resizing an [`Image`]: a tent filter with optional crop (training crops) and
//!   the exact area average (the network's working size).
//! - [`passes`]: the Cycles render-pass names, short (`DiffDir`) and long (`Diffuse Direct`),
//!   shared by the renderer (writer) and the compositor (reader).
//! - [`rng`]: a small, serialisable, splittable PRNG so every random draw in the project is
//!   reproducible from `(seed, stream)` and training can resume bit-exactly.
pub mod error;
pub mod exrio;
pub mod image;
pub mod io;
pub mod output;
pub mod passes;
pub mod resample;
pub mod rng;

pub use error::{CoreError, Result};
pub use image::Image;
pub use rng::Rng;
