//! `pixl studio PHOTO` without a depth map, through the running server's HTTP API: with Depth
//! Anything 3 weights on disk (the tiny randomly initialised fixture in `fixtures/da3/tiny`) the
//! geometry is estimated, as `pixl relight` estimates it; without them it is the labelled
//! fallback. No test touches the network (a private HOME, `--offline`).
mod common;
use common::{cmd_in, repo_path, write_image};
use pixl_core::Image;
use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;
use std::process::{Child, Stdio};

/// The studio's process, killed when dropped.
struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Starts `pixl studio` with `args` on a free port and returns it with the address it prints.
fn start(home: &Path, args: &[&std::ffi::OsStr]) -> (Server, String) {
    let mut c = cmd_in(home);
    c.arg("studio").args(args).args(["--port", "0", "--offline"]);
    let mut child = c.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let out = child.stdout.take().unwrap();
    let mut lines = BufReader::new(out).lines();
    let mut said = Vec::new();
    let url = loop {
        match lines.next() {
            Some(Ok(l)) if l.starts_with("http://") => break l,
            Some(Ok(l)) => said.push(l),
            _ => {
                let mut err = String::new();
                if let Some(mut e) = child.stderr.take() {
                    let _ = e.read_to_string(&mut err);
                }
                panic!("pixl studio printed no address; stdout {said:?}, stderr {err}");
            }
        }
    };
    // Keep draining stdout so the server never blocks on a full pipe.
    std::thread::spawn(move || for _ in lines {});
    let addr = url.trim_start_matches("http://").trim_end_matches('/').to_string();
    (Server(child), addr)
}

/// `GET path` on `addr`, the body as JSON.
fn get_json(addr: &str, path: &str) -> serde_json::Value {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let body = text.split("\r\n\r\n").nth(1).unwrap_or("");
    serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {text}"))
}

fn photo(dir: &Path) -> std::path::PathBuf {
    let img = Image::from_fn(56, 42, 3, |x, y, c| ((x * 7 + y * 13 + c * 29) % 64) as f32 / 63.0);
    write_image(&dir.join("photo.png"), &img)
}

#[test]
fn studio_estimates_depth_with_da3_when_its_weights_are_there_and_falls_back_labelled_otherwise() {
    let t = tempfile::tempdir().unwrap();
    let p = photo(t.path());
    // A models folder with the tiny checkpoint as `da3-mono` (the fixture is a mono model).
    let models = t.path().join("models");
    let own = models.join("da3-mono");
    std::fs::create_dir_all(&own).unwrap();
    for f in ["config.json", "model.safetensors"] {
        std::fs::copy(repo_path("fixtures/da3/tiny").join(f), own.join(f)).unwrap();
    }
    let (server, addr) = start(t.path(), &[p.as_os_str(), "--models".as_ref(), models.as_os_str()]);
    let state = get_json(&addr, "/api/state");
    let g = &state["geometry"];
    assert_eq!(g["fallback"], false, "{state}");
    assert_eq!(g["source"]["kind"], "estimator", "{state}");
    assert!(g["label"].as_str().unwrap().contains("Depth Anything 3"), "{state}");
    drop(server);

    // No weights anywhere: the stand-in, said so.
    let empty = t.path().join("no-models");
    std::fs::create_dir_all(&empty).unwrap();
    let (server, addr) = start(t.path(), &[p.as_os_str(), "--models".as_ref(), empty.as_os_str()]);
    let state = get_json(&addr, "/api/state");
    assert_eq!(state["geometry"]["fallback"], true, "{state}");
    assert!(
        state["geometry"]["label"].as_str().unwrap().contains("FALLBACK"),
        "{state}"
    );
    drop(server);
}

/// `POST path` with `body` on `addr`: the status and the body as JSON.
fn post_json(addr: &str, path: &str, body: &[u8]) -> (u16, serde_json::Value) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    write!(
        s,
        "POST {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n\r\n",
        body.len()
    )
    .unwrap();
    s.write_all(body).unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let status = text.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    let body = text.split("\r\n\r\n").nth(1).unwrap_or("");
    (
        status,
        serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {text}")),
    )
}

#[test]
fn studio_lights_like_a_photo_when_marigold_lighting_is_on_disk_and_says_how_otherwise() {
    let t = tempfile::tempdir().unwrap();
    let p = photo(t.path());
    let reference = std::fs::read(write_image(
        &t.path().join("ref.png"),
        &Image::from_fn(56, 42, 3, |x, _, c| [0.8, 0.5, 0.2][c] * x as f32 / 56.0),
    ))
    .unwrap();
    let models = t.path().join("models");
    common::copy_dir(
        &repo_path("fixtures/marigold/lighting"),
        &models.join("marigold-lighting"),
    );
    let (server, addr) = start(t.path(), &[p.as_os_str(), "--models".as_ref(), models.as_os_str()]);
    assert_eq!(get_json(&addr, "/api/state")["can_like"], true);
    let (status, v) = post_json(&addr, "/api/like?name=ref.png", &reference);
    assert_eq!(status, 200, "{v}");
    assert_eq!(v["like"]["reference"], "ref.png", "{v}");
    assert!(v["like"]["estimator"]
        .as_str()
        .unwrap_or_default()
        .contains("Marigold-IID Lighting"));
    drop(server);

    // Without the weights: off, and the request says how to get them.
    let empty = t.path().join("no-models");
    std::fs::create_dir_all(&empty).unwrap();
    let (server, addr) = start(t.path(), &[p.as_os_str(), "--models".as_ref(), empty.as_os_str()]);
    assert_eq!(get_json(&addr, "/api/state")["can_like"], false);
    let (status, v) = post_json(&addr, "/api/like?name=ref.png", &reference);
    assert_eq!(status, 404, "{v}");
    assert!(
        v["error"]
            .as_str()
            .unwrap_or_default()
            .contains("pixl models fetch marigold-lighting"),
        "{v}"
    );
    drop(server);
}
