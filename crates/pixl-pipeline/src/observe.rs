//! How a caller watches the pipeline: an [`Observer`] hears of every long stage (its name and
//! progress) and of the notes a user should read (which estimator ran, what was assumed). The
//! CLI draws progress bars and prints the notes; the studio and tests use [`Silent`].
//!
//! Every method has a default that does nothing, and all may be called from worker threads.

/// A stage of the pipeline that can take a while.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Estimating the photo's depth.
    Depth,
    /// Building the mesh and textures.
    Reconstruct,
    /// Estimating a photo's intrinsics (albedo, shading, residual; progress: denoising steps
    /// and decodes).
    Intrinsics,
    /// Estimating a photo's surface normals (progress: denoising steps and decodes).
    Normals,
    /// Path-tracing the passes (progress: rows).
    Render,
    /// The network (progress: its blocks).
    Network,
    /// A video's frames (progress: frames written).
    Frames,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Depth => "depth",
            Stage::Reconstruct => "reconstruct",
            Stage::Intrinsics => "intrinsics",
            Stage::Normals => "normals",
            Stage::Render => "rendering",
            Stage::Network => "network",
            Stage::Frames => "frames",
        }
    }
}

pub trait Observer: Sync {
    /// `stage` started; `total` units of progress are coming (0: unknown).
    fn begin(&self, _stage: Stage, _total: u64) {}
    /// `done` of `total` units of `stage` are finished.
    fn progress(&self, _stage: Stage, _done: u64, _total: u64) {}
    /// `stage` ended (successfully or not).
    fn end(&self, _stage: Stage) {}
    /// A line a user should read.
    fn note(&self, _line: &str) {}
}

/// Watches nothing.
pub struct Silent;

impl Observer for Silent {}
