//! The HTTP side: the page's three files (compiled into the binary) and the JSON API (documented
//! in the crate README). Only fixed routes exist — no path from a request ever reaches the file
//! system: images are served from memory by name out of a fixed list, files are written only to
//! the configured output folder under fixed names. Requests that change something are refused
//! when the browser marks them as coming from another site (`Origin`). Work that takes more
//! than a moment runs on tokio's blocking pool; a failure (or a panic) in it becomes a JSON error
//! `{"error": "..."}` with a 4xx/5xx status, and the server goes on.
use crate::error::{Result, StudioError};
use crate::geometry::DepthKind;
use crate::lights::LightPatch;
use crate::session::{Studio, WaitFor};
use axum::body::Bytes;
use axum::extract::rejection::{BytesRejection, JsonRejection};
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use axum::{Json, Router};
use serde::Deserialize;
use serde_json::{json, Value};
use std::time::Duration;

const INDEX_HTML: &str = include_str!("../assets/index.html");
const APP_JS: &str = include_str!("../assets/app.js");
const STYLE_CSS: &str = include_str!("../assets/style.css");

/// Longest wait a request may ask for.
const MAX_WAIT: Duration = Duration::from_secs(120);

/// The router of a studio.
pub fn router(studio: Studio) -> Router {
    // Our own check in the handlers gives the clear message; this bounds what is buffered.
    let limit = studio.config().max_upload_bytes.saturating_add(1);
    Router::new()
        .route("/", get(|| async { asset(INDEX_HTML, "text/html; charset=utf-8") }))
        .route(
            "/app.js",
            get(|| async { asset(APP_JS, "text/javascript; charset=utf-8") }),
        )
        .route(
            "/style.css",
            get(|| async { asset(STYLE_CSS, "text/css; charset=utf-8") }),
        )
        .route("/api/state", get(state))
        .route("/api/wait", get(wait))
        .route("/api/photo", post(photo))
        .route("/api/depth", post(depth))
        .route("/api/lights", get(lights).post(add_light).put(set_lights))
        .route("/api/lights/{id}", put(update_light).delete(delete_light))
        .route("/api/preset", post(preset))
        .route("/api/like", post(like))
        .route("/api/undo", post(undo))
        .route("/api/redo", post(redo))
        .route("/api/image/{name}", get(image))
        .route("/api/scene", get(scene_text).post(load_scene))
        .route("/api/save", post(save))
        .route("/api/export", post(export))
        .route("/api/download/relit.png", get(download_relit))
        .fallback(|| async { StudioError::NotFound("no such page or API route".into()) })
        .layer(axum::middleware::from_fn(same_origin))
        .layer(DefaultBodyLimit::max(limit))
        .with_state(studio)
}

/// Serves `studio` on `listener` until the process ends.
pub async fn serve(studio: Studio, listener: tokio::net::TcpListener) -> std::io::Result<()> {
    axum::serve(listener, router(studio)).await
}

/// Refuses a request that changes something when the browser says it comes from another site
/// (`Origin` not this server): another page open in the same browser cannot drive the session.
async fn same_origin(req: axum::extract::Request, next: axum::middleware::Next) -> Response {
    let changes = !matches!(*req.method(), axum::http::Method::GET | axum::http::Method::HEAD);
    let h = req.headers();
    if changes {
        if let (Some(origin), Some(host)) = (h.get(header::ORIGIN), h.get(header::HOST)) {
            let origin = origin.to_str().unwrap_or("");
            let host = host.to_str().unwrap_or("");
            let from = origin.split_once("://").map(|(_, rest)| rest).unwrap_or(origin);
            if from != host {
                return StudioError::Forbidden(format!(
                    "cross-origin request from {origin} refused (open the studio's own page instead)"
                ))
                .into_response();
            }
        }
    }
    next.run(req).await
}

fn asset(body: &'static str, content_type: &'static str) -> Response {
    let mut r = body.into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static("default-src 'self'; img-src 'self' blob: data:; style-src 'self'; script-src 'self'"),
    );
    r
}

/// Runs `f` on the blocking pool; a panic in it is an error, not a dead server.
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T> + Send + 'static) -> Result<T> {
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| StudioError::Internal(format!("the request failed inside the server: {e}")))?
}

fn body(b: std::result::Result<Bytes, BytesRejection>, limit: usize) -> Result<Bytes> {
    b.map_err(|e| {
        if e.status() == StatusCode::PAYLOAD_TOO_LARGE {
            StudioError::TooLarge(format!(
                "the upload is larger than the limit of {limit} bytes ({} MiB)",
                limit >> 20
            ))
        } else {
            StudioError::BadRequest(format!("cannot read the request body: {e}"))
        }
    })
}

fn json_body<T>(b: std::result::Result<Json<T>, JsonRejection>) -> Result<T> {
    b.map(|Json(v)| v)
        .map_err(|e| StudioError::BadRequest(format!("bad JSON: {}", e.body_text())))
}

async fn state(State(s): State<Studio>) -> Json<Value> {
    Json(s.state_json())
}

#[derive(Deserialize)]
struct WaitQuery {
    /// `preview`, `render` (or `relit`: any stage) or `final`.
    what: Option<String>,
    generation: Option<u64>,
    timeout_ms: Option<u64>,
}

async fn wait(
    State(s): State<Studio>,
    q: std::result::Result<Query<WaitQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<Value>> {
    let Query(q) = q.map_err(|e| StudioError::BadRequest(e.body_text()))?;
    let what = match q.what.as_deref() {
        None => WaitFor::Final,
        Some(w) => WaitFor::parse(w)
            .ok_or_else(|| StudioError::BadRequest(format!("what={w:?}: give preview, render, relit or final")))?,
    };
    let timeout = Duration::from_millis(q.timeout_ms.unwrap_or(30_000)).min(MAX_WAIT);
    let s2 = s.clone();
    let ready = blocking(move || Ok(s2.wait(what, q.generation, timeout))).await?;
    Ok(Json(json!({"ready": ready, "state": s.state_json()})))
}

#[derive(Deserialize)]
struct NameQuery {
    name: Option<String>,
    kind: Option<String>,
}

async fn photo(
    State(s): State<Studio>,
    q: Query<NameQuery>,
    b: std::result::Result<Bytes, BytesRejection>,
) -> Result<Json<Value>> {
    let bytes = body(b, s.config().max_upload_bytes)?;
    let name = q.name.clone().unwrap_or_else(|| "photo".into());
    let s2 = s.clone();
    blocking(move || s2.load_photo_bytes(&bytes, &name)).await?;
    Ok(Json(s.state_json()))
}

async fn depth(
    State(s): State<Studio>,
    q: Query<NameQuery>,
    b: std::result::Result<Bytes, BytesRejection>,
) -> Result<Json<Value>> {
    let bytes = body(b, s.config().max_upload_bytes)?;
    let name = q.name.clone().unwrap_or_else(|| "depth.exr".into());
    let kind = match q.kind.as_deref() {
        None => DepthKind::Metric,
        Some(k) => DepthKind::parse(k)
            .ok_or_else(|| StudioError::BadRequest(format!("kind={k:?}: give metric, relative or disparity")))?,
    };
    let s2 = s.clone();
    blocking(move || s2.load_depth_bytes(&bytes, &name, kind)).await?;
    Ok(Json(s.state_json()))
}

/// "Light like this photo": the body is the reference photo (PNG or JPEG).
async fn like(
    State(s): State<Studio>,
    q: Query<NameQuery>,
    b: std::result::Result<Bytes, BytesRejection>,
) -> Result<Json<Value>> {
    let bytes = body(b, s.config().max_upload_bytes)?;
    let name = q.name.clone().unwrap_or_else(|| "reference".into());
    let s2 = s.clone();
    let like = blocking(move || s2.relight_like_bytes(&bytes, &name)).await?;
    Ok(Json(json!({"like": like, "state": s.state_json()})))
}

async fn lights(State(s): State<Studio>) -> Json<Value> {
    Json(json!({ "lights": s.lights() }))
}

async fn add_light(
    State(s): State<Studio>,
    b: std::result::Result<Json<LightPatch>, JsonRejection>,
) -> Result<Json<Value>> {
    let patch = json_body(b)?;
    let s2 = s.clone();
    let light = blocking(move || s2.add_light(&patch)).await?;
    Ok(Json(json!({"light": light, "state": s.state_json()})))
}

async fn set_lights(
    State(s): State<Studio>,
    b: std::result::Result<Json<Vec<LightPatch>>, JsonRejection>,
) -> Result<Json<Value>> {
    let patches = json_body(b)?;
    let s2 = s.clone();
    blocking(move || s2.set_lights(&patches)).await?;
    Ok(Json(s.state_json()))
}

async fn update_light(
    State(s): State<Studio>,
    id: std::result::Result<Path<u64>, axum::extract::rejection::PathRejection>,
    b: std::result::Result<Json<LightPatch>, JsonRejection>,
) -> Result<Json<Value>> {
    let Path(id) = id.map_err(|e| StudioError::BadRequest(format!("light id: {}", e.body_text())))?;
    let patch = json_body(b)?;
    let s2 = s.clone();
    let light = blocking(move || s2.update_light(id, &patch)).await?;
    Ok(Json(json!({"light": light, "state": s.state_json()})))
}

async fn delete_light(
    State(s): State<Studio>,
    id: std::result::Result<Path<u64>, axum::extract::rejection::PathRejection>,
) -> Result<Json<Value>> {
    let Path(id) = id.map_err(|e| StudioError::BadRequest(format!("light id: {}", e.body_text())))?;
    let s2 = s.clone();
    blocking(move || s2.delete_light(id)).await?;
    Ok(Json(s.state_json()))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PresetBody {
    name: String,
}

async fn preset(
    State(s): State<Studio>,
    b: std::result::Result<Json<PresetBody>, JsonRejection>,
) -> Result<Json<Value>> {
    let p = json_body(b)?;
    let s2 = s.clone();
    blocking(move || s2.apply_preset(&p.name)).await?;
    Ok(Json(s.state_json()))
}

async fn undo(State(s): State<Studio>) -> Result<Json<Value>> {
    let s2 = s.clone();
    let changed = blocking(move || s2.undo()).await?;
    Ok(Json(json!({"changed": changed, "state": s.state_json()})))
}

async fn redo(State(s): State<Studio>) -> Result<Json<Value>> {
    let s2 = s.clone();
    let changed = blocking(move || s2.redo()).await?;
    Ok(Json(json!({"changed": changed, "state": s.state_json()})))
}

async fn image(State(s): State<Studio>, Path(name): Path<String>) -> Result<Response> {
    let stem = name.strip_suffix(".png").unwrap_or(&name).to_string();
    let (generation, png) = s.image_png(&stem)?;
    png_response(png, Some(generation), None)
}

fn png_response(png: Vec<u8>, generation: Option<u64>, attachment: Option<&str>) -> Result<Response> {
    let mut r = png.into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    if let Some(g) = generation {
        if let Ok(v) = HeaderValue::from_str(&g.to_string()) {
            h.insert("x-pixl-generation", v);
        }
    }
    if let Some(name) = attachment {
        if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"{name}\"")) {
            h.insert(header::CONTENT_DISPOSITION, v);
        }
    }
    Ok(r)
}

async fn scene_text(State(s): State<Studio>) -> Result<Response> {
    let text = s.scene_toml()?;
    let mut r = text.into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/toml; charset=utf-8"),
    );
    Ok(r)
}

#[derive(Deserialize)]
struct FormatQuery {
    format: Option<String>,
}

async fn load_scene(
    State(s): State<Studio>,
    q: Query<FormatQuery>,
    b: std::result::Result<Bytes, BytesRejection>,
) -> Result<Json<Value>> {
    let bytes = body(b, s.config().max_upload_bytes)?;
    let text = String::from_utf8(bytes.to_vec())
        .map_err(|_| StudioError::BadRequest("the scene file is not UTF-8 text".into()))?;
    let json = match q.format.as_deref() {
        None | Some("toml") => false,
        Some("json") => true,
        Some(f) => return Err(StudioError::BadRequest(format!("format={f:?}: give toml or json"))),
    };
    let s2 = s.clone();
    blocking(move || s2.load_lights_from_scene_text(&text, json)).await?;
    Ok(Json(s.state_json()))
}

async fn save(State(s): State<Studio>) -> Result<Json<Value>> {
    let s2 = s.clone();
    let path = blocking(move || s2.save_scene()).await?;
    Ok(Json(json!({"path": path})))
}

#[derive(Deserialize)]
struct ExportQuery {
    what: String,
    timeout_ms: Option<u64>,
}

async fn export(
    State(s): State<Studio>,
    q: std::result::Result<Query<ExportQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<Value>> {
    let Query(q) = q.map_err(|e| {
        StudioError::BadRequest(format!(
            "{} (give ?what=relit, ct, blender, scene or video)",
            e.body_text()
        ))
    })?;
    let timeout = Duration::from_millis(q.timeout_ms.unwrap_or(60_000)).min(MAX_WAIT);
    let s2 = s.clone();
    let paths = blocking(move || s2.export(&q.what, timeout)).await?;
    Ok(Json(json!({"paths": paths})))
}

async fn download_relit(State(s): State<Studio>) -> Result<Response> {
    let s2 = s.clone();
    let png = blocking(move || {
        let img = s2.relit_full(Duration::from_secs(60))?;
        crate::pipeline::png_bytes(&img)
    })
    .await?;
    png_response(png, None, Some("relit.png"))
}
