//! Typed errors for file I/O, output checks and image validation. Every variant names the file
//! it is about.
//!
//! Each message states its cause once: no variant exposes an inner error through
//! [`std::error::Error::source`] while also printing it, so a caller that prints the whole chain
//! (`anyhow`'s `{:#}`) does not repeat the operating system's words.
use std::path::PathBuf;

pub type Result<T, E = CoreError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum CoreError {
    #[error("{path}: file not found")]
    NotFound { path: PathBuf },
    /// An operating-system error on `path`; the message is the OS's own, printed once.
    #[error("{path}: {cause}")]
    Io { path: PathBuf, cause: std::io::Error },
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
    /// An output path whose extension is not one the command writes.
    #[error("{path}: cannot write this kind of file here (the output must end in {expected})")]
    OutputExtension { path: PathBuf, expected: String },
    /// An output path that cannot be written (missing or unwritable folder, a folder in the way).
    #[error("{path}: {reason}")]
    Output { path: PathBuf, reason: String },
    /// An output that is also one of the command's inputs.
    #[error("{path}: the output is the input {input}; write to another file")]
    OutputIsInput { path: PathBuf, input: PathBuf },
    /// An existing output folder that would be replaced without `--force`.
    #[error("{path}: {what} already exists; pass --force to replace it, or choose another folder")]
    Exists { path: PathBuf, what: String },
    #[error("{0}")]
    Invalid(String),
}

impl CoreError {
    pub fn io(path: impl Into<PathBuf>, cause: std::io::Error) -> Self {
        let path = path.into();
        if cause.kind() == std::io::ErrorKind::NotFound {
            CoreError::NotFound { path }
        } else {
            CoreError::Io { path, cause }
        }
    }
}
