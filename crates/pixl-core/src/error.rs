//! Typed errors for file I/O and image validation. Every variant names the file it is about.
use std::path::PathBuf;

pub type Result<T, E = CoreError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    #[error("{path}: file not found")]
    NotFound { path: PathBuf },
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a readable {format} file: {reason}")]
    Decode {
        path: PathBuf,
        format: &'static str,
        reason: String,
    },
    #[error("{path}: cannot write {format}: {reason}")]
    Encode {
        path: PathBuf,
        format: &'static str,
        reason: String,
    },
    #[error("{path}: unsupported file extension (expected one of {expected})")]
    UnknownExtension { path: PathBuf, expected: &'static str },
    #[error("{path}: image is empty ({width}x{height})")]
    Empty { path: PathBuf, width: usize, height: usize },
    #[error("{path}: image header announces {width}x{height}, over the limit of {limit} pixels; refusing to allocate")]
    TooLarge {
        path: PathBuf,
        width: usize,
        height: usize,
        limit: usize,
    },
    #[error("{path}: expected {expected} channels, found {found}")]
    Channels {
        path: PathBuf,
        expected: String,
        found: String,
    },
    #[error("{path}: {count} non-finite values (NaN/Inf); first at x={x}, y={y}, channel {channel}")]
    NonFinite {
        path: PathBuf,
        count: usize,
        x: usize,
        y: usize,
        channel: String,
    },
    #[error("{0}")]
    Invalid(String),
}

impl CoreError {
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        let path = path.into();
        if source.kind() == std::io::ErrorKind::NotFound {
            CoreError::NotFound { path }
        } else {
            CoreError::Io { path, source }
        }
    }
}
