//! The page in a real browser: headless Chromium driven through WebDriver (chromedriver, started
//! here on a free loopback port). Skips, saying so, when no Chromium or chromedriver is installed
//! (Debian: `apt-get install -y chromium chromium-driver`; or set PIXL_CHROMIUM and
//! PIXL_CHROMEDRIVER to the binaries). Set PIXL_STUDIO_SCREENSHOT=path.png to keep a screenshot,
//! and PIXL_STUDIO_PHOTO=photo.png to run it on that photo (at a 384-px working size) instead of
//! a 128-px render of the demo scene.
mod common;

use common::*;
use fantoccini::actions::{InputSource, MouseActions, PointerAction, MOUSE_BUTTON_LEFT};
use fantoccini::{ClientBuilder, Locator};
use pixl_studio::{Stage, Studio, StudioConfig};
use serde_json::Value;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn find_binary(env: &str, names: &[&str]) -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(env) {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .flat_map(|d| names.iter().map(move |n| d.join(n)))
        .find(|p| p.is_file())
}

/// Kills chromedriver (and with it the browser) when the test ends, however it ends.
struct Driver(Child);
impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    l.local_addr().expect("addr").port()
}

fn state(addr: SocketAddr) -> Value {
    let (s, v) = http_json(addr, "GET", "/api/state", "");
    assert_eq!(s, 200, "{v}");
    v
}

/// Polls `f` every 50 ms until it returns `Some`, or fails after `secs` seconds.
async fn until<T>(secs: u64, what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let end = Instant::now() + Duration::from_secs(secs);
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < end, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn image(addr: SocketAddr, name: &str) -> image::RgbImage {
    let (s, b) = http(addr, "GET", &format!("/api/image/{name}.png"), b"");
    assert_eq!(s, 200, "{name}: {}", String::from_utf8_lossy(&b));
    decode(&b)
}

/// Mean absolute difference of two images of one size, in 8-bit levels.
fn diff(a: &image::RgbImage, b: &image::RgbImage) -> f64 {
    assert_eq!(a.dimensions(), b.dimensions());
    let n = a.as_raw().len() as f64;
    a.as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| (*x as f64 - *y as f64).abs())
        .sum::<f64>()
        / n
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn place_drag_preset_and_save_in_headless_chromium() {
    let (Some(chromium), Some(driver)) = (
        find_binary("PIXL_CHROMIUM", &["chromium", "chromium-browser", "google-chrome"]),
        find_binary("PIXL_CHROMEDRIVER", &["chromedriver"]),
    ) else {
        eprintln!(
            "SKIPPED place_drag_preset_and_save_in_headless_chromium: no chromium and chromedriver on PATH \
             (apt-get install -y chromium chromium-driver, or set PIXL_CHROMIUM / PIXL_CHROMEDRIVER)"
        );
        return;
    };

    // The photo: the bundled demo scene rendered at 128 px wide, or PIXL_STUDIO_PHOTO.
    let (png, name, side) = match std::env::var_os("PIXL_STUDIO_PHOTO") {
        Some(p) => (std::fs::read(&p).unwrap(), "photo.png", 384),
        None => {
            let demo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo/scene.toml");
            let scene = pixl_render::Scene::load(&demo).unwrap();
            let opts = pixl_render::RenderOptions {
                spp: 4,
                width: Some(128),
                ..Default::default()
            };
            let photo = pixl_render::render(&scene, &opts, &|_, _| {}).unwrap().combined_srgb();
            (
                pixl_studio::pipeline::png_bytes(&photo).unwrap(),
                "demo-render.png",
                128,
            )
        }
    };
    let full = decode(&png);
    let (work_w, _) = pixl_model::fullres::working_size(full.width() as usize, full.height() as usize, side);
    let out = tempfile::tempdir().unwrap();
    let config = StudioConfig {
        work_side: side,
        preview_side: 64,
        stages: vec![Stage { side: side / 2, spp: 1 }, Stage { side, spp: 4 }],
        max_bounces: 2,
        settle_ms: 60,
        out_dir: out.path().to_owned(),
        ..StudioConfig::default()
    };
    let studio = Studio::new(config).unwrap();
    studio.load_photo_bytes(&png, name).unwrap();
    let addr = spawn_server(studio);

    // chromedriver on a free port, and a fresh browser profile.
    let port = free_port();
    let profile = tempfile::tempdir().unwrap();
    let _driver = Driver(
        Command::new(&driver)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("starting chromedriver"),
    );
    until(20, "chromedriver to listen", || {
        std::net::TcpStream::connect(("127.0.0.1", port)).ok()
    })
    .await;
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        serde_json::json!({
            "binary": chromium,
            "args": [
                "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--window-size=1300,900",
                format!("--user-data-dir={}", profile.path().display()),
            ],
        }),
    );
    let connector = hyper_util::client::legacy::connect::HttpConnector::new();
    let c = ClientBuilder::new(connector)
        .capabilities(caps)
        .connect(&format!("http://127.0.0.1:{port}"))
        .await
        .expect("a WebDriver session");

    let url = format!("http://{addr}/");
    c.goto(&url).await.unwrap();
    // The photo shows.
    let photo_el = c.wait().for_element(Locator::Id("before")).await.unwrap();
    let mut loaded = false;
    for _ in 0..100 {
        let w = c
            .execute("return document.getElementById('before').naturalWidth", vec![])
            .await
            .unwrap();
        if w.as_u64().unwrap_or(0) == work_w as u64 {
            loaded = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(loaded, "the photo did not load in the page");
    let _ = photo_el;
    // No light yet: nothing covers the photo (no black overlay while there is nothing to show).
    let over = c
        .execute(
            "const a = document.getElementById('after'); return [a.getAttribute('src'), getComputedStyle(a).visibility]",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(
        over,
        serde_json::json!([null, "hidden"]),
        "the photo is covered before any light"
    );

    // Click the photo's centre: a point light anchored there.
    let gen0 = state(addr)["generation"].as_u64().unwrap();
    c.find(Locator::Id("markers"))
        .await
        .expect("the marker layer")
        .click()
        .await
        .expect("a click on the photo");
    let light = until(10, "a light after the click", || {
        let s = state(addr);
        let ls = s["lights"].as_array()?.clone();
        (ls.len() == 1).then(|| ls[0].clone())
    })
    .await;
    let u0 = light["anchor"][0].as_f64().unwrap();
    assert!((u0 - 0.5).abs() < 0.05, "{light}");
    assert_eq!(light["kind"], "point");
    // Preview for the click, then the final relit image.
    let s1 = until(20, "the final render after the click", || {
        let s = state(addr);
        let r = &s["rendered"];
        (r["final"] == true && r["generation"] == s["generation"] && s["generation"].as_u64()? > gen0).then_some(s)
    })
    .await;
    let preview1 = image(addr, "preview");
    let relit1 = image(addr, "relit");
    // The page shows the relit image over the photo.
    until(10, "the page to show the relit image", || Some(())).await;
    let mut kind = String::new();
    for _ in 0..100 {
        kind = c
            .execute("return document.getElementById('after').dataset.kind", vec![])
            .await
            .unwrap()
            .as_str()
            .unwrap_or("")
            .to_string();
        if kind == "relit-final" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(kind, "relit-final");

    // Drag the marker a third of the width to the left, in small steps.
    let marker = c.wait().for_element(Locator::Css(".marker")).await.unwrap();
    let (_, _, width, _) = c.find(Locator::Id("markers")).await.unwrap().rectangle().await.unwrap();
    let mut drag = MouseActions::new("mouse".into())
        .then(PointerAction::MoveToElement {
            element: marker,
            duration: None,
            x: 0.0,
            y: 0.0,
        })
        .then(PointerAction::Down {
            button: MOUSE_BUTTON_LEFT,
        });
    for _ in 0..8 {
        drag = drag.then(PointerAction::MoveBy {
            duration: Some(Duration::from_millis(40)),
            x: -width / 24.0,
            y: 0.0,
        });
    }
    drag = drag.then(PointerAction::Up {
        button: MOUSE_BUTTON_LEFT,
    });
    c.perform_actions(drag).await.expect("the drag gestures");
    let moved = until(10, "the light to follow the drag", || {
        let s = state(addr);
        let u = s["lights"][0]["anchor"][0].as_f64()?;
        ((u0 - u - 1.0 / 3.0).abs() < 0.05).then_some(s)
    })
    .await;
    assert!(moved["generation"].as_u64() > s1["generation"].as_u64());
    // The drag was one undo step (the moves coalesced), plus the click.
    // The preview changed, then the relit image.
    let preview2 = image(addr, "preview");
    assert!(
        diff(&preview1, &preview2) > 0.5,
        "the preview did not change: {}",
        diff(&preview1, &preview2)
    );
    until(20, "the final render after the drag", || {
        let s = state(addr);
        let r = &s["rendered"];
        (r["final"] == true
            && r["generation"] == s["generation"]
            && s["generation"].as_u64()? >= moved["generation"].as_u64()?)
        .then_some(())
    })
    .await;
    let relit2 = image(addr, "relit");
    assert!(
        diff(&relit1, &relit2) > 0.05,
        "the relit image did not change: {}",
        diff(&relit1, &relit2)
    );

    // Undo the drag in the page: the light goes back to the centre in one step.
    c.find(Locator::Id("undo")).await.unwrap().click().await.unwrap();
    until(10, "undo to restore the click position", || {
        let u = state(addr)["lights"][0]["anchor"][0].as_f64()?;
        ((u - u0).abs() < 1e-6).then_some(())
    })
    .await;

    // A preset, one click.
    c.find(Locator::Id("preset-warm-overhead-flash"))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
    until(10, "the preset's lights", || {
        let s = state(addr);
        let ls = s["lights"].as_array()?.clone();
        (ls.len() == 1 && ls[0]["name"].as_str()?.starts_with("warm-overhead-flash")).then_some(())
    })
    .await;

    // Save: a scene file the CLI can load, holding the preset's light.
    c.find(Locator::Id("save")).await.unwrap().click().await.unwrap();
    let saved = out.path().join("scene.toml");
    until(10, "scene.toml", || saved.is_file().then_some(())).await;
    let scene = pixl_render::Scene::load(&saved).unwrap();
    assert_eq!(scene.lights.len(), 1);
    assert!(
        scene.lights[0].name().starts_with("warm-overhead-flash"),
        "{:?}",
        scene.lights
    );
    // The page said where it saved (its status line moves on to render progress at once, so
    // read the record it keeps, polling: the file can land before the reply is handled).
    let end = Instant::now() + Duration::from_secs(10);
    loop {
        let el = c.find(Locator::Id("status")).await.unwrap();
        let said = el.attr("data-saved").await.unwrap();
        if said.as_deref().is_some_and(|p| p.ends_with("scene.toml")) {
            break;
        }
        assert!(Instant::now() < end, "the page never reported the save: {said:?}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // The screenshot, once the relit image for the preset shows.
    until(20, "the final render of the preset", || {
        let s = state(addr);
        (s["rendered"]["final"] == true && s["rendered"]["generation"] == s["generation"]).then_some(())
    })
    .await;
    tokio::time::sleep(Duration::from_millis(800)).await;
    if let Some(path) = std::env::var_os("PIXL_STUDIO_SCREENSHOT") {
        let shot = c.screenshot().await.unwrap();
        std::fs::write(&path, shot).unwrap();
        eprintln!("screenshot written to {}", PathBuf::from(path).display());
    }
    // No error was shown.
    let err_hidden = c
        .execute("return document.getElementById('error').hidden", vec![])
        .await
        .unwrap();
    assert_eq!(err_hidden, Value::Bool(true), "the page shows an error");
    c.close().await.unwrap();
}
