//! Typed errors of `pixl-eval`. Every variant names the file, pair or method it is about.
use std::path::PathBuf;

pub type Result<T, E = EvalError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error(transparent)]
    Metric(#[from] crate::metrics::MetricError),
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// Opening the dataset, reading an image or its target intrinsics. (Not boxed: it is about
    /// the size of the inline `Pair` variant.)
    #[error(transparent)]
    Data(#[from] pixl_data::DataError),
    // Other foreign errors are boxed: they are large and would make every `Result` here large.
    #[error(transparent)]
    Core(Box<pixl_core::CoreError>),
    #[error(transparent)]
    Checkpoint(Box<pixl_model::CheckpointError>),
    #[error(transparent)]
    Lpips(Box<crate::lpips::LpipsError>),
    #[error("{path}, line {line}: {reason}")]
    Pairs { path: PathBuf, line: usize, reason: String },
    #[error("pair {scene}/{source_name} -> {target}: {reason}")]
    Pair {
        scene: String,
        source_name: String,
        target: String,
        reason: String,
    },
    #[error("method {method}: {reason}")]
    Method { method: String, reason: String },
    #[error("unknown baseline {0:?} (expected identity, compose, compose-reinhard or compose-camera)")]
    UnknownBaseline(String),
    #[error("nothing to evaluate: {0}")]
    Empty(String),
}

macro_rules! boxed_from {
    ($($variant:ident: $ty:ty),*) => {$(
        impl From<$ty> for EvalError {
            fn from(e: $ty) -> Self {
                EvalError::$variant(Box::new(e))
            }
        }
    )*};
}
boxed_from!(
    Core: pixl_core::CoreError,
    Checkpoint: pixl_model::CheckpointError,
    Lpips: crate::lpips::LpipsError
);
