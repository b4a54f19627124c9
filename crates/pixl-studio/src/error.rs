//! The crate's error type. Every error a request can meet maps to an HTTP status and a
//! one-sentence message (`{"error": "..."}`) that the page shows as it is; the server keeps
//! running after any of them.
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};

#[derive(Debug, thiserror::Error)]
pub enum StudioError {
    /// The request is malformed or asks for something impossible (400).
    #[error("{0}")]
    BadRequest(String),
    /// The request needs something the session does not have yet, e.g. a light id that does not
    /// exist or a result not computed yet (404).
    #[error("{0}")]
    NotFound(String),
    /// An upload or an image over the configured limits (413).
    #[error("{0}")]
    TooLarge(String),
    /// A request the server refuses to serve (another site's page driving it) (403).
    #[error("{0}")]
    Forbidden(String),
    /// A newer request replaced the work this one waited for (409).
    #[error("{0}")]
    Superseded(String),
    /// Rendering, composing, the network or file I/O failed (500).
    #[error("{0}")]
    Internal(String),
    #[error(transparent)]
    Render(#[from] pixl_render::RenderError),
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    #[error(transparent)]
    Depth(#[from] pixl_render::depth::DepthError),
    #[error(transparent)]
    Intrinsics(#[from] pixl_intrinsics::IntrinsicsError),
    #[error(transparent)]
    Model(#[from] pixl_model::CheckpointError),
    #[error(transparent)]
    FullRes(#[from] pixl_model::fullres::FullResError),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
    #[error(transparent)]
    Blender(#[from] pixl_render::blender::BlenderError),
    /// A stage of `pixl_pipeline` failed (boxed: it is large).
    #[error(transparent)]
    Pipeline(Box<pixl_pipeline::PipelineError>),
    #[error("{path}: {source}")]
    Io {
        path: std::path::PathBuf,
        source: std::io::Error,
    },
}

pub type Result<T, E = StudioError> = std::result::Result<T, E>;

impl StudioError {
    /// The HTTP status this error is answered with.
    pub fn status(&self) -> StatusCode {
        match self {
            StudioError::BadRequest(_) | StudioError::Depth(_) => StatusCode::BAD_REQUEST,
            StudioError::NotFound(_) => StatusCode::NOT_FOUND,
            StudioError::Forbidden(_) => StatusCode::FORBIDDEN,
            StudioError::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            StudioError::Superseded(_) => StatusCode::CONFLICT,
            // Scene values and image decoding come from the request.
            StudioError::Render(pixl_render::RenderError::Parse { .. })
            | StudioError::Render(pixl_render::RenderError::Invalid { .. })
            | StudioError::Render(pixl_render::RenderError::UnknownPreset { .. }) => StatusCode::BAD_REQUEST,
            StudioError::Core(pixl_core::CoreError::Decode { .. })
            | StudioError::Core(pixl_core::CoreError::Empty { .. })
            | StudioError::Core(pixl_core::CoreError::UnknownExtension { .. }) => StatusCode::BAD_REQUEST,
            StudioError::Core(pixl_core::CoreError::TooLarge { .. }) => StatusCode::PAYLOAD_TOO_LARGE,
            StudioError::Pipeline(e) if matches!(**e, pixl_pipeline::PipelineError::Input(_)) => {
                StatusCode::BAD_REQUEST
            }
            _ => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    pub(crate) fn io(path: &std::path::Path, source: std::io::Error) -> Self {
        StudioError::Io {
            path: path.to_owned(),
            source,
        }
    }
}

impl From<pixl_pipeline::PipelineError> for StudioError {
    fn from(e: pixl_pipeline::PipelineError) -> Self {
        StudioError::Pipeline(Box::new(e))
    }
}

impl IntoResponse for StudioError {
    fn into_response(self) -> Response {
        let status = self.status();
        if status.is_server_error() {
            tracing::warn!("request failed: {self}");
        }
        (status, axum::Json(serde_json::json!({ "error": self.to_string() }))).into_response()
    }
}
