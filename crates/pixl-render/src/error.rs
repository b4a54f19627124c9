//! Typed errors of `pixl-render`. Every variant that concerns a file names it.
use std::path::PathBuf;

pub type Result<T, E = RenderError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// A scene file that does not parse (TOML or JSON); `message` carries the line and column.
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    /// A scene that parses but is not valid (negative power, missing mesh file, ...).
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
    /// A scene file that cannot be written.
    #[error("{path}: cannot write scene: {message}")]
    Write { path: PathBuf, message: String },
    /// An unknown preset name.
    #[error("unknown lighting preset {name:?} (known: {known})")]
    UnknownPreset { name: String, known: String },
    /// Bad render options or an unrenderable scene.
    #[error("{0}")]
    Options(String),
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
}
