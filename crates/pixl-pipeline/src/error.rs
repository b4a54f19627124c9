//! [`PipelineError`]: everything a pipeline stage can refuse or fail with. Bad input says what
//! is wrong and how to fix it ([`PipelineError::Input`]); failures of the stages below keep
//! their own typed errors as the source.
use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// The input cannot be used as given; the message names it and what to do.
    #[error("{0}")]
    Input(String),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    #[error(transparent)]
    Render(#[from] pixl_render::RenderError),
    #[error(transparent)]
    Depth(#[from] pixl_render::depth::DepthError),
    #[error(transparent)]
    MeshIo(#[from] pixl_render::export::MeshIoError),
    #[error(transparent)]
    FullRes(#[from] pixl_model::fullres::FullResError),
    #[error(transparent)]
    Intrinsics(#[from] pixl_intrinsics::IntrinsicsError),
    #[error(transparent)]
    Checkpoint(#[from] pixl_model::checkpoint::CheckpointError),
    #[error(transparent)]
    Official(#[from] pixl_model::official::OfficialError),
    #[error(transparent)]
    Estimate(#[from] pixl_estimate::EstimateError),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    /// A stage failed; the message says which and why.
    #[error("{context}: {source}")]
    Stage {
        context: String,
        source: Box<PipelineError>,
    },
}

impl PipelineError {
    /// Bad input, with a message for the user.
    pub fn input(msg: impl Into<String>) -> Self {
        PipelineError::Input(msg.into())
    }

    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        PipelineError::Io {
            path: path.into(),
            source,
        }
    }

    /// This error, said to have happened while doing `context`.
    pub fn context(self, context: impl Into<String>) -> Self {
        PipelineError::Stage {
            context: context.into(),
            source: Box::new(self),
        }
    }
}

pub type Result<T, E = PipelineError> = std::result::Result<T, E>;
