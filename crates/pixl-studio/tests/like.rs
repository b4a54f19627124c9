//! "Light like this photo" through the JSON API (`POST /api/like`, the `like` image and state):
//! refused with a clear message without an estimator or a photo; with Marigold-IID-Lighting (the
//! tiny random checkpoint of `fixtures/marigold/lighting`) the served image is exactly the
//! library's `pixl_pipeline::like::target_ct` → network on the photo at the working size; a
//! reference of another frame shape is reported; a bad upload is refused; a new photo clears it.
mod common;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use common::*;
use pixl_pipeline::estimators::{MarigoldLighting, MarigoldOptions};
use pixl_pipeline::like::{target_ct, LIKE_STEPS};
use pixl_studio::{Studio, StudioConfig};
use serde_json::Value;
use std::sync::Arc;
use tower::ServiceExt;

async fn call(router: &axum::Router, method: &str, uri: &str, body: Vec<u8>) -> (StatusCode, Vec<u8>) {
    let req = Request::builder()
        .method(method)
        .uri(uri)
        .body(Body::from(body))
        .expect("a request");
    let res = router.clone().oneshot(req).await.expect("infallible");
    let status = res.status();
    let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.expect("a body");
    (status, bytes.to_vec())
}

fn json(bytes: &[u8]) -> Value {
    serde_json::from_slice(bytes).expect("JSON")
}

/// A `w × h` PNG whose colours differ from [`photo_png`]'s: another "lighting".
fn reference_png(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([
            200 - (150 * x / w) as u8,
            90 + (60 * y / h) as u8,
            40 + (30 * (x + y) / (w + h)) as u8,
        ])
    });
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .expect("encoding a test PNG");
    out
}

fn rgb(png: &[u8]) -> pixl_core::Image {
    let img = image::load_from_memory(png).expect("a PNG").to_rgb32f();
    let (w, h) = img.dimensions();
    pixl_core::Image::from_vec(w as usize, h as usize, 3, img.into_raw()).expect("an image")
}

fn marigold() -> Arc<MarigoldLighting> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/marigold/lighting");
    let opts = MarigoldOptions {
        steps: Some(LIKE_STEPS),
        resolution: Some(32),
        ..Default::default()
    };
    Arc::new(MarigoldLighting::load(&dir, opts, "marigold-lighting", &candle_core::Device::Cpu).expect("the fixture"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_an_estimator_light_like_is_refused_with_how_to_get_one() {
    let out = tempfile::tempdir().unwrap();
    let router = pixl_studio::router(Studio::new(small_config(out.path())).unwrap());
    let (_, st) = call(&router, "GET", "/api/state", vec![]).await;
    assert_eq!(json(&st)["can_like"], false);
    call(&router, "POST", "/api/photo?name=p.png", photo_png(80, 60)).await;
    let (s, body) = call(&router, "POST", "/api/like?name=r.png", reference_png(80, 60)).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    let e = json(&body)["error"].as_str().unwrap_or_default().to_string();
    assert!(
        e.contains("Marigold-IID-Lighting") && e.contains("marigold-lighting"),
        "{e}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn light_like_a_reference_photo_serves_the_librarys_result() {
    let out = tempfile::tempdir().unwrap();
    let est = marigold();
    let config = StudioConfig {
        lighting: Some(est.clone()),
        ..small_config(out.path())
    };
    let studio = Studio::new(config).unwrap();
    let router = pixl_studio::router(studio);
    let reference = reference_png(80, 60);

    // Before a photo: a clear 400.
    let (s, body) = call(&router, "POST", "/api/like?name=ref.png", reference.clone()).await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert!(json(&body)["error"]
        .as_str()
        .unwrap_or_default()
        .contains("load a photo"));

    let photo = photo_png(80, 60);
    let (s, _) = call(&router, "POST", "/api/photo?name=p.png", photo.clone()).await;
    assert_eq!(s, StatusCode::OK);
    let (s, body) = call(&router, "POST", "/api/like?name=ref.png", reference.clone()).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    let v = json(&body);
    let like = &v["like"];
    assert_eq!((like["width"].as_u64(), like["height"].as_u64()), (Some(64), Some(48)));
    assert_eq!(like["reference"], "ref.png");
    assert_eq!(like["aspect_differs"], false);
    assert_eq!(v["state"]["like"]["id"], like["id"]);
    assert_eq!(v["state"]["can_like"], true);
    // The lights, their history and the generation are untouched.
    assert_eq!(v["state"]["lights"].as_array().map(Vec::len), Some(0));
    assert_eq!(v["state"]["can_undo"], false);

    // The served image is the library's computation on the same inputs, byte for byte.
    let (s, png) = call(&router, "GET", "/api/image/like.png", vec![]).await;
    assert_eq!(s, StatusCode::OK);
    let work = pixl_core::resample::area_resize(&rgb(&photo), 64, 48).unwrap();
    let ct = target_ct(est.as_ref(), &rgb(&reference), (64, 48), &pixl_pipeline::Silent).unwrap();
    let (_, model) = pixl_model::load_bytes(
        std::path::Path::new(pixl_pipeline::relight::BUNDLED_NAME),
        pixl_pipeline::relight::BUNDLED_WEIGHTS,
        &candle_core::Device::Cpu,
        candle_core::DType::F32,
    )
    .unwrap();
    let (gain, bias) = pixl_studio::pipeline::gain_bias(&model, &work, &ct.ct).unwrap();
    let mut expected = work.clone();
    pixl_model::fullres::apply_gain_bias(&mut expected, &gain, &bias, 64, 48).unwrap();
    assert_eq!(png, pixl_studio::pipeline::png_bytes(&expected).unwrap());
    // …and it is not the photo: the bundled network changes it under this C_T.
    assert_ne!(
        decode(&png).into_raw(),
        decode(&pixl_studio::pipeline::png_bytes(&work).unwrap()).into_raw()
    );

    // A reference of another frame shape: stretched, and said so.
    let (s, body) = call(&router, "POST", "/api/like?name=wide.png", reference_png(120, 40)).await;
    assert_eq!(s, StatusCode::OK);
    let like = &json(&body)["like"];
    assert_eq!(like["aspect_differs"], true);
    assert_eq!(like["reference_size"], serde_json::json!([120, 40]));

    // Not an image: 400, and the last result stays.
    let (s, body) = call(&router, "POST", "/api/like?name=x.png", b"not an image".to_vec()).await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert!(json(&body)["error"].as_str().unwrap_or_default().contains("x.png"));
    let (s, _) = call(&router, "GET", "/api/image/like.png", vec![]).await;
    assert_eq!(s, StatusCode::OK);

    // A new photo clears the result.
    call(&router, "POST", "/api/photo?name=q.png", photo_png(60, 60)).await;
    let (_, st) = call(&router, "GET", "/api/state", vec![]).await;
    assert!(json(&st)["like"].is_null());
    let (s, _) = call(&router, "GET", "/api/image/like.png", vec![]).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
}
