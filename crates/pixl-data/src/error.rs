//! Typed errors of `pixl-data`. Every variant names the spec, dataset root or file it is about;
//! the messages are user-facing (the CLI prints them as they are).
use std::path::PathBuf;

pub type Result<T, E = DataError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// An image or C_T file could not be read or decoded.
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    /// A C_T file is not a valid C_T.
    #[error(transparent)]
    Intrinsics(#[from] pixl_intrinsics::IntrinsicsError),
    /// A directory or manifest could not be read.
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    /// A `KIND:ROOT` spec that does not parse.
    #[error("dataset spec {spec:?}: {reason}")]
    Spec { spec: String, reason: String },
    /// A dataset that parses but holds nothing usable.
    #[error("dataset {root}: {reason}")]
    Dataset { root: PathBuf, reason: String },
    /// A split name other than `train`, `test` or `all`.
    #[error("invalid configuration: unknown split {0:?} (expected train, test or all)")]
    UnknownSplit(String),
    /// An image with neither exact nor cached target intrinsics.
    #[error(
        "{image}: no target intrinsics C_T: expected the cached file {expected} beside the image. \
         Produce it with `pixl prepare-targets --dataset KIND:ROOT` (Marigold-IID Lighting), with \
         `pixl compose` from render passes, or with any decomposer writing a C_T EXR \
         (`pixl intrinsics` describes the format)"
    )]
    MissingIntrinsics { image: PathBuf, expected: PathBuf },
    /// A dataset file (e.g. a `pixl synth` manifest) that is readable but wrong.
    #[error("{path}: {reason}")]
    File { path: PathBuf, reason: String },
}

impl DataError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        DataError::Io {
            path: path.into(),
            source,
        }
    }
}
