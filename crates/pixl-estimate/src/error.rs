//! Typed errors of the estimators. Every variant names what it is about: the file, the tensor,
//! the config key or the input size.
use std::path::PathBuf;

pub type Result<T, E = EstimateError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum EstimateError {
    /// A file could not be read.
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// A `config.json` that does not parse, or describes a model this port does not implement.
    #[error("{path}: {reason}")]
    Config { path: PathBuf, reason: String },
    /// A weight file that is not a readable safetensors file.
    #[error("{path}: not a readable safetensors file: {reason}")]
    Weights { path: PathBuf, reason: String },
    /// A tensor the model needs is absent from the weight file.
    #[error("{path}: tensor `{name}` is missing (expected shape {expected:?})")]
    MissingTensor {
        path: PathBuf,
        name: String,
        expected: Vec<usize>,
    },
    /// A tensor has the wrong shape.
    #[error("{path}: tensor `{name}` has shape {found:?}, expected {expected:?}")]
    TensorShape {
        path: PathBuf,
        name: String,
        expected: Vec<usize>,
        found: Vec<usize>,
    },
    /// A tensor has a dtype the loader does not accept (f32, f16, bf16 are accepted).
    #[error("{path}: tensor `{name}` has dtype {dtype}, expected f32, f16 or bf16")]
    TensorDtype { path: PathBuf, name: String, dtype: String },
    /// A tensor the model does not use is present (a checkpoint of another model, or a renamed key).
    #[error("{path}: unexpected tensor `{name}` (not part of this model)")]
    UnexpectedTensor { path: PathBuf, name: String },
    /// Bad input to an estimator (empty image, wrong channel count, non-finite values, bad option).
    #[error("{0}")]
    Input(String),
    /// A feature that is declared but not available yet.
    #[error("not implemented: {0}")]
    Unimplemented(&'static str),
    /// An image error from `pixl-core`.
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    /// An error from the tensor library.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}
