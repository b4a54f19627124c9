//! The JSON API without a browser: routing and safety (through `tower::ServiceExt::oneshot` and
//! through a real loopback socket), limits, errors, concurrency, and the pipeline's results.
mod common;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use common::*;
use pixl_studio::{Studio, WaitFor};
use serde_json::{json, Value};
use std::time::Duration;
use tower::ServiceExt;

async fn call(router: &axum::Router, method: &str, uri: &str, body: Vec<u8>) -> (StatusCode, Vec<u8>) {
    let req = Request::builder()
        .method(method)
        .uri(uri)
        .header("content-type", "application/json")
        .body(Body::from(body))
        .expect("a request");
    let res = router.clone().oneshot(req).await.expect("infallible");
    let status = res.status();
    let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.expect("a body");
    (status, bytes.to_vec())
}

fn error_of(bytes: &[u8]) -> String {
    let v: Value = serde_json::from_slice(bytes).expect("a JSON error");
    v["error"].as_str().expect("an error message").to_string()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serves_its_own_files_and_refuses_path_traversal() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    let router = pixl_studio::router(studio.clone());
    let (s, page) = call(&router, "GET", "/", vec![]).await;
    assert_eq!(s, StatusCode::OK);
    let page = String::from_utf8(page).unwrap();
    assert!(page.contains("/app.js") && page.contains("/style.css"), "{page}");
    // No resource from elsewhere (no CDN).
    assert!(!page.contains("http://") && !page.contains("https://"));
    for asset in ["/app.js", "/style.css"] {
        assert_eq!(call(&router, "GET", asset, vec![]).await.0, StatusCode::OK, "{asset}");
    }
    // Nothing outside the fixed routes, however the path is spelled.
    for evil in [
        "/../Cargo.toml",
        "/../../../../etc/passwd",
        "/%2e%2e/%2e%2e/etc/passwd",
        "/assets/index.html",
        "/src/lib.rs",
        "/api/image/..%2F..%2FCargo.toml",
        "/api/image/../../Cargo.toml",
        "/api/image/%2Fetc%2Fpasswd",
        "/api/download/..%2Fscene.toml",
    ] {
        let (s, body) = call(&router, "GET", evil, vec![]).await;
        assert_eq!(s, StatusCode::NOT_FOUND, "{evil}");
        assert!(!String::from_utf8_lossy(&body).contains("root:"), "{evil}");
    }
    // An image name outside the list is refused with the list; a known one not made yet is 404.
    let (s, body) = call(&router, "GET", "/api/image/secret.png", vec![]).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    assert!(error_of(&body).contains("relit"), "{}", error_of(&body));
    assert_eq!(
        call(&router, "GET", "/api/image/relit.png", vec![]).await.0,
        StatusCode::NOT_FOUND
    );

    // The same through a real socket, where the request line carries the raw path.
    let addr = spawn_server(studio);
    for evil in ["/../Cargo.toml", "/api/image/../../../Cargo.toml", "//etc/passwd"] {
        let (s, body) = http(addr, "GET", evil, b"");
        assert!(s == 404 || s == 400, "{evil}: {s}");
        assert!(!String::from_utf8_lossy(&body).contains("[workspace]"), "{evil}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversize_uploads_and_images_are_refused_with_a_clear_message() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    let router = pixl_studio::router(studio);
    // Bytes over the 1 MiB limit of the small configuration.
    let (s, body) = call(&router, "POST", "/api/photo?name=big.png", vec![0u8; (1 << 20) + 10]).await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE);
    let e = error_of(&body);
    assert!(e.contains("limit") && e.contains("1 MiB"), "{e}");
    // A small file that declares more pixels than allowed (1 M): refused from its header.
    let big = photo_png(1200, 1000);
    assert!(big.len() < 1 << 20);
    let (s, body) = call(&router, "POST", "/api/photo?name=wide.png", big).await;
    assert_eq!(s, StatusCode::PAYLOAD_TOO_LARGE);
    let e = error_of(&body);
    assert!(e.contains("1200x1000") && e.contains("1000000 pixels"), "{e}");
    // The server goes on: a good photo loads.
    let (s, body) = call(&router, "POST", "/api/photo?name=ok.png", photo_png(80, 60)).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(v["photo"]["width"], 80);
    assert_eq!(v["photo"]["work"], json!([64, 48]));
    assert_eq!(v["geometry"]["fallback"], true);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_errors_and_the_server_continues() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    let router = pixl_studio::router(studio.clone());
    // Lights before a photo.
    let (s, body) = call(&router, "POST", "/api/lights", br#"{"kind":"point"}"#.to_vec()).await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert!(error_of(&body).contains("photo"), "{}", error_of(&body));
    // Not an image.
    let (s, body) = call(
        &router,
        "POST",
        "/api/photo?name=x.png",
        b"not an image at all".to_vec(),
    )
    .await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert!(error_of(&body).contains("x.png"));
    call(&router, "POST", "/api/photo?name=p.png", photo_png(80, 60)).await;
    let cases: &[(&str, &str, &str, StatusCode, &str)] = &[
        ("POST", "/api/lights", "{not json", StatusCode::BAD_REQUEST, "JSON"),
        (
            "POST",
            "/api/lights",
            r#"{"kind":"laser"}"#,
            StatusCode::BAD_REQUEST,
            "laser",
        ),
        ("POST", "/api/lights", r#"{"powr":3}"#, StatusCode::BAD_REQUEST, "powr"),
        (
            "POST",
            "/api/lights",
            r#"{"power":-3}"#,
            StatusCode::BAD_REQUEST,
            "power",
        ),
        (
            "POST",
            "/api/lights",
            r#"{"anchor":[2,0]}"#,
            StatusCode::BAD_REQUEST,
            "anchor",
        ),
        ("PUT", "/api/lights/999", r#"{"power":3}"#, StatusCode::NOT_FOUND, "999"),
        (
            "PUT",
            "/api/lights/abc",
            r#"{"power":3}"#,
            StatusCode::BAD_REQUEST,
            "light id",
        ),
        ("DELETE", "/api/lights/999", "", StatusCode::NOT_FOUND, "999"),
        (
            "POST",
            "/api/preset",
            r#"{"name":"disco"}"#,
            StatusCode::BAD_REQUEST,
            "disco",
        ),
        (
            "POST",
            "/api/depth?name=d.exr&kind=sideways",
            "x",
            StatusCode::BAD_REQUEST,
            "sideways",
        ),
        ("POST", "/api/depth?name=d.txt", "x", StatusCode::BAD_REQUEST, "d.txt"),
        (
            "POST",
            "/api/depth?name=d.exr",
            "not an exr",
            StatusCode::BAD_REQUEST,
            "d.exr",
        ),
        (
            "POST",
            "/api/scene",
            "[camera]\nwidth = -1",
            StatusCode::BAD_REQUEST,
            "width",
        ),
        (
            "POST",
            "/api/export?what=everything",
            "",
            StatusCode::BAD_REQUEST,
            "everything",
        ),
        ("GET", "/api/wait?what=soon", "", StatusCode::BAD_REQUEST, "soon"),
    ];
    for (method, uri, body, want, says) in cases {
        let (s, got) = call(&router, method, uri, body.as_bytes().to_vec()).await;
        assert_eq!(s, *want, "{method} {uri}: {}", String::from_utf8_lossy(&got));
        let e = error_of(&got);
        assert!(e.contains(says), "{method} {uri}: {e:?} should mention {says:?}");
    }
    // Another site's page cannot drive the session; the studio's own page can.
    for (origin, want) in [
        ("http://evil.example", StatusCode::FORBIDDEN),
        ("http://127.0.0.1:8765", StatusCode::OK),
    ] {
        let req = Request::builder()
            .method("POST")
            .uri("/api/undo")
            .header("host", "127.0.0.1:8765")
            .header("origin", origin)
            .body(Body::empty())
            .unwrap();
        let res = router.clone().oneshot(req).await.unwrap();
        assert_eq!(res.status(), want, "{origin}");
    }
    // Nothing above changed the session: no light, no history.
    assert!(studio.lights().is_empty());
    let st = studio.state_json();
    assert_eq!(st["can_undo"], false);
    // And it still works.
    let (s, body) = call(
        &router,
        "POST",
        "/api/lights",
        br#"{"kind":"spot","anchor":[0.5,0.5]}"#.to_vec(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    assert_eq!(studio.lights().len(), 1);
}

#[test]
fn concurrent_light_updates_keep_a_consistent_state() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    studio.load_photo_bytes(&photo_png(80, 60), "p.png").unwrap();
    let addr = spawn_server(studio.clone());
    let (s, v) = http_json(addr, "POST", "/api/lights", r#"{"kind":"point","anchor":[0.3,0.4]}"#);
    assert_eq!(s, 200, "{v}");
    let id = v["light"]["id"].as_u64().unwrap();
    let gen0 = studio.state_json()["generation"].as_u64().unwrap();
    // 6 clients × 8 updates, each setting power and size together (size = power / 1000) and
    // moving the anchor: whatever the interleaving, every state must pair them.
    let threads: Vec<_> = (0..6)
        .map(|t| {
            std::thread::spawn(move || {
                for k in 0..8 {
                    let p = (t * 8 + k + 1) as f32;
                    let body = json!({"power": p, "size": p / 1000.0, "anchor": [0.1 + 0.01 * p, 0.5]}).to_string();
                    let (s, v) = http_json(addr, "PUT", &format!("/api/lights/{id}"), &body);
                    assert_eq!(s, 200, "{v}");
                    let l = &v["light"];
                    assert!(
                        (l["size"].as_f64().unwrap() - l["power"].as_f64().unwrap() / 1000.0).abs() < 1e-6,
                        "{l}"
                    );
                }
            })
        })
        .collect();
    // Meanwhile, read the state over and over: always one light, always consistent.
    for _ in 0..20 {
        let (s, v) = http_json(addr, "GET", "/api/state", "");
        assert_eq!(s, 200);
        let ls = v["lights"].as_array().unwrap();
        assert_eq!(ls.len(), 1);
        let (p, sz) = (ls[0]["power"].as_f64().unwrap(), ls[0]["size"].as_f64().unwrap());
        assert!(
            p > 0.0 && (sz - p / 1000.0).abs() < 1e-6 || sz > 0.0 && p > 4.0,
            "{}",
            ls[0]
        );
    }
    for t in threads {
        t.join().unwrap();
    }
    let st = studio.state_json();
    assert_eq!(
        st["generation"].as_u64().unwrap(),
        gen0 + 48,
        "one generation per change"
    );
    let l = &studio.lights()[0];
    assert!((l.size - l.power / 1000.0).abs() < 1e-6);
    assert!((l.anchor.unwrap()[0] - (0.1 + 0.01 * l.power)).abs() < 1e-5, "{l:?}");
    // Every change is one undo step (none was sent with coalesce): 48 + the add.
    let mut undos = 0;
    while studio.undo().unwrap() {
        undos += 1;
    }
    assert_eq!(undos, 49);
    assert!(studio.lights().is_empty());
}

/// Column (0..1) of the brightest preview pixel.
fn brightest_u(png: &[u8]) -> f32 {
    let img = decode(png);
    let (mut best, mut bx) = (-1i32, 0);
    for (x, _, p) in img.enumerate_pixels() {
        let l = p.0.iter().map(|c| *c as i32).sum::<i32>();
        if l > best {
            best = l;
            bx = x;
        }
    }
    (bx as f32 + 0.5) / img.width() as f32
}

#[test]
fn previews_renders_presets_history_and_files_follow_the_lights() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    studio.load_photo_bytes(&photo_png(80, 60), "p.png").unwrap();
    // A small point light close to the backdrop on the left: the preview's brightest column is
    // near its anchor; dragged right, the brightest column follows.
    let add: pixl_studio::LightPatch =
        serde_json::from_value(json!({"kind": "point", "anchor": [0.2, 0.3], "distance": 0.3})).unwrap();
    let l = studio.add_light(&add).unwrap();
    assert!(studio.wait(WaitFor::Preview, None, Duration::from_secs(5)));
    let (g1, p1) = studio.image_png("preview").unwrap();
    assert!((brightest_u(&p1) - 0.2).abs() < 0.1, "{}", brightest_u(&p1));
    assert!(
        studio.wait(WaitFor::Final, None, Duration::from_secs(60)),
        "the final render came"
    );
    let (_, relit1) = studio.image_png("relit").unwrap();
    let (_, render1) = studio.image_png("render").unwrap();
    for name in ["albedo", "shading", "residual"] {
        let (_, png) = studio.image_png(name).unwrap();
        assert_eq!(decode(&png).dimensions(), (64, 48), "{name}");
    }
    let mv: pixl_studio::LightPatch = serde_json::from_value(json!({"anchor": [0.8, 0.3]})).unwrap();
    studio.update_light(l.id, &mv).unwrap();
    let (g2, p2) = studio.image_png("preview").unwrap();
    assert!(g2 > g1);
    assert!((brightest_u(&p2) - 0.8).abs() < 0.1, "{}", brightest_u(&p2));
    assert!(studio.wait(WaitFor::Final, None, Duration::from_secs(60)));
    let (_, relit2) = studio.image_png("relit").unwrap();
    let (_, render2) = studio.image_png("render").unwrap();
    assert_ne!(decode(&render1), decode(&render2), "the render follows the light");
    assert_ne!(decode(&relit1), decode(&relit2), "the relit photo follows the light");

    // Presets replace the lights; undo brings the moved light back, redo the preset.
    for p in pixl_render::presets::PRESETS {
        let ls = studio.apply_preset(p).unwrap();
        assert!(!ls.is_empty() && ls.iter().all(|l| l.name.starts_with(p)), "{p}");
    }
    for _ in 0..5 {
        assert!(studio.undo().unwrap());
    }
    let back = studio.lights();
    assert_eq!(back.len(), 1);
    assert_eq!(back[0].anchor, Some([0.8, 0.3]));
    assert!(studio.redo().unwrap());
    assert!(studio.lights()[0].name.starts_with("cool-side-flash"));

    // Save: the CLI's scene format, loadable with its files, holding the lights.
    let path = studio.save_scene().unwrap();
    let scene = pixl_render::Scene::load(&path).unwrap();
    assert_eq!(scene.lights.len(), 1);
    assert_eq!(scene.objects.len(), 1);
    // Exports: the relit photo at its full size, C_T, a Blender script.
    let relit = studio.export("relit", Duration::from_secs(60)).unwrap();
    let img = pixl_core::io::read_rgb(&relit[0]).unwrap();
    assert_eq!((img.width, img.height), (80, 60));
    let ct = studio.export("ct", Duration::from_secs(60)).unwrap();
    let ct = pixl_intrinsics::ct::read_ct(&ct[0]).unwrap();
    assert_eq!((ct.width(), ct.height()), (64, 48));
    let bl = studio.export("blender", Duration::from_secs(5)).unwrap();
    assert!(bl[0].is_file() && std::fs::read_to_string(&bl[0]).unwrap().contains("bpy"));
}

/// A little-endian float32 `.npy` of shape `(h, w)`.
fn npy(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> Vec<u8> {
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({h}, {w}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for y in 0..h {
        for x in 0..w {
            out.extend_from_slice(&f(x, y).to_le_bytes());
        }
    }
    out
}

#[test]
fn a_depth_map_replaces_the_fallback_and_anchored_lights_follow() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    studio.load_photo_bytes(&photo_png(80, 60), "p.png").unwrap();
    let add: pixl_studio::LightPatch =
        serde_json::from_value(json!({"kind": "point", "anchor": [0.5, 0.25], "distance": 0.5})).unwrap();
    let before = studio.add_light(&add).unwrap();
    // Fallback: the upper half sees the backdrop at 6 m (z), the light 0.5 m in front of it.
    assert!((before.position[2] + 5.5).abs() < 0.05, "{:?}", before.position);
    // A flat wall at 2 m, at another size than the photo (resampled).
    let wall = npy(40, 30, |_, _| 2.0);
    let addr = spawn_server(studio.clone());
    let (s, v) = {
        let (s, b) = http(addr, "POST", "/api/depth?name=wall.npy&kind=metric", &wall);
        (s, serde_json::from_slice::<Value>(&b).unwrap())
    };
    assert_eq!(s, 200, "{v}");
    assert_eq!(v["geometry"]["fallback"], false);
    assert_eq!(v["geometry"]["source"]["kind"], "depth");
    let after = studio.lights()[0].clone();
    assert!((after.position[2] + 1.5).abs() < 1e-3, "{:?}", after.position);
    // Disparity: a constant map says nothing about depth, so it lies in the middle of the range
    // (as `pixl reconstruct` places it): t = 1/2 in 1/z between 1/10 and 1/1 m, z = 1/0.55 m.
    let (s, b) = http(addr, "POST", "/api/depth?name=d.npy&kind=disparity", &wall);
    assert_eq!(s, 200, "{}", String::from_utf8_lossy(&b));
    let l = studio.lights()[0].clone();
    assert!((l.position[2] + (1.0 / 0.55 - 0.5)).abs() < 1e-3, "{:?}", l.position);
    // All invalid: refused, the geometry stays.
    let (s, b) = http(addr, "POST", "/api/depth?name=bad.npy", &npy(4, 3, |_, _| 0.0));
    assert_eq!(s, 400);
    assert!(
        String::from_utf8_lossy(&b).contains("no valid pixel"),
        "{}",
        String::from_utf8_lossy(&b)
    );
    assert_eq!(studio.lights()[0].position, l.position);
}

#[test]
fn a_scene_file_opens_with_its_lights() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    let demo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo/scene.toml");
    studio.open_scene_file(&demo).unwrap();
    let want = pixl_render::Scene::load(&demo).unwrap();
    let st = studio.state_json();
    assert_eq!(st["geometry"]["source"]["kind"], "scene");
    // Its lights, and its world as an environment light.
    let lights = studio.lights();
    assert_eq!(lights.len(), want.lights.len() + 1);
    let scene = studio.scene().unwrap();
    assert_eq!(
        scene.lights,
        want.lights
            .iter()
            .map(|l| {
                let mut l = l.clone();
                // Directions are stored resolved.
                if let pixl_render::Light::Area { direction, look_at, .. } = &mut l {
                    *direction = Some(want.lights[0].direction().unwrap());
                    *look_at = None;
                }
                l
            })
            .collect::<Vec<_>>()
    );
    assert_eq!(
        scene.world.as_ref().map(|w| w.color.rgb()),
        want.world.as_ref().map(|w| {
            let c = w.color.rgb();
            [c[0] * w.strength, c[1] * w.strength, c[2] * w.strength]
        })
    );
}

/// A JPEG of `w`×`h` stored pixels tagged with EXIF orientation 6 ("rotate 90° clockwise to
/// view"): viewers show it `h`×`w`.
fn sideways_jpeg(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, _| image::Rgb([(255 * x / w) as u8, 90, 140]));
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 95)
        .encode_image(&img)
        .unwrap();
    // APP1 "Exif": little-endian TIFF header, one IFD entry: 0x0112 Orientation, SHORT, 1, 6.
    let mut app1 = b"Exif\0\0II*\0\x08\0\0\0".to_vec();
    app1.extend_from_slice(&1u16.to_le_bytes());
    app1.extend_from_slice(&[0x12, 0x01, 3, 0, 1, 0, 0, 0, 6, 0, 0, 0]);
    app1.extend_from_slice(&0u32.to_le_bytes());
    let mut out = jpeg[..2].to_vec();
    out.extend_from_slice(&[0xFF, 0xE1]);
    out.extend_from_slice(&((app1.len() + 2) as u16).to_be_bytes());
    out.extend_from_slice(&app1);
    out.extend_from_slice(&jpeg[2..]);
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sideways_phone_photo_is_shown_upright() {
    let out = tempfile::tempdir().unwrap();
    let studio = Studio::new(small_config(out.path())).unwrap();
    let router = pixl_studio::router(studio);
    let (s, body) = call(&router, "POST", "/api/photo?name=phone.jpg", sideways_jpeg(80, 60)).await;
    assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&body));
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(
        (v["photo"]["width"].clone(), v["photo"]["height"].clone()),
        (json!(60), json!(80))
    );
}
