//! Typed errors of `pixl-train`. Every variant names the file or setting it is about.
use std::path::PathBuf;

pub type Result<T, E = TrainError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("dataset spec {spec:?}: {reason}")]
    Spec { spec: String, reason: String },
    #[error("dataset {root}: {reason}")]
    Dataset { root: PathBuf, reason: String },
    #[error(
        "{image}: no target intrinsics C_T: expected the cached file {expected} beside the image. \
         Produce it with `pixl compose` from render passes, or with an external intrinsic decomposer \
         (e.g. Marigold-IID-Lighting) writing a C_T EXR (`pixl intrinsics` describes the format)"
    )]
    MissingIntrinsics { image: PathBuf, expected: PathBuf },
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
