//! Typed errors of `pixl-intrinsics`. Every variant names what it is about: the file or pass
//! set, the pass or channel, and the values involved.
use pixl_core::CoreError;

pub type Result<T, E = IntrinsicsError> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum IntrinsicsError {
    /// File I/O, decoding, size guard, non-finite values in a C_T file.
    #[error(transparent)]
    Core(#[from] CoreError),
    /// A C_T file lacks some of its nine channels.
    #[error(
        "{path}: not a C_T file: missing channel(s) {missing} (expected albedo.R/G/B, shading.R/G/B, residual.R/G/B; found {found})"
    )]
    MissingCtChannels {
        path: String,
        missing: String,
        found: String,
    },
    /// The three images of a C_T disagree in size or are not RGB.
    #[error("invalid C_T: {0}")]
    InvalidCt(String),
    /// A required diffuse pass is absent.
    #[error(
        "{source_name}: required pass(es) missing: {missing} (compose needs DiffCol, DiffDir, DiffInd; found: {found})"
    )]
    MissingPasses {
        source_name: String,
        missing: String,
        found: String,
    },
    /// Several view layers hold passes and none was chosen.
    #[error("{source_name}: several view layers hold render passes ({layers}); choose one with --layer")]
    AmbiguousLayer { source_name: String, layers: String },
    /// The chosen view layer does not exist.
    #[error("{source_name}: view layer `{layer}` not found; available: {layers}")]
    UnknownLayer {
        source_name: String,
        layer: String,
        layers: String,
    },
    /// No render pass at all was recognised.
    #[error("{source_name}: no Cycles render passes found ({detail})")]
    NoPasses { source_name: String, detail: String },
    /// A pass lacks one of its R, G, B channels.
    #[error("{source_name}: pass {pass} lacks channel(s) {missing}")]
    PassChannels {
        source_name: String,
        pass: String,
        missing: String,
    },
    /// Passes of different sizes.
    #[error("{source_name}: pass {pass} is {width}x{height}, but {first} is {first_width}x{first_height}; all passes must share one size")]
    SizeMismatch {
        source_name: String,
        pass: String,
        width: usize,
        height: usize,
        first: String,
        first_width: usize,
        first_height: usize,
    },
    /// NaN/Inf in the passes (without `sanitize`).
    #[error(
        "{source_name}: {count} non-finite value(s) (NaN/Inf) in the render passes; first in pass {pass} at x={x}, y={y}, channel {channel} (use --sanitize to replace them with 0)"
    )]
    NonFinitePasses {
        source_name: String,
        count: usize,
        pass: String,
        x: usize,
        y: usize,
        channel: String,
    },
    /// Bad argument to a library call (batch shape, seeds, config).
    #[error("{0}")]
    Invalid(String),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}
