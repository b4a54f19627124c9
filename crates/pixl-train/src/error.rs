//! Typed errors of `pixl-train`. Every variant names the file or setting it is about.
use std::path::PathBuf;

pub type Result<T, E = TrainError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// Opening a dataset, reading its images or their target intrinsics.
    #[error(transparent)]
    Data(#[from] pixl_data::DataError),
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
    #[error("invalid configuration: {0}")]
    Config(String),
    #[error(transparent)]
    Intrinsics(#[from] pixl_intrinsics::IntrinsicsError),
    #[error(transparent)]
    Model(#[from] pixl_model::CheckpointError),
    #[error("tensor error: {0}")]
    Candle(#[from] candle_core::Error),
    #[error("{0}")]
    Other(String),
}

impl TrainError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        TrainError::Io {
            path: path.into(),
            source,
        }
    }
}
