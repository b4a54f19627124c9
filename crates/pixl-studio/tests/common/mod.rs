//! Shared test helpers: a small configuration, synthetic photos, a server on a free loopback
//! port, and a minimal HTTP/1.1 client over `TcpStream` (requests only to 127.0.0.1).
#![allow(dead_code)]
use pixl_studio::{Stage, Studio, StudioConfig};
use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::Path;
use std::time::Duration;

/// A configuration small enough for a test to render and relight in well under a second.
pub fn small_config(out: &Path) -> StudioConfig {
    StudioConfig {
        work_side: 64,
        preview_side: 32,
        stages: vec![Stage { side: 32, spp: 1 }, Stage { side: 64, spp: 2 }],
        max_bounces: 1,
        settle_ms: 10,
        max_upload_bytes: 1 << 20,
        max_pixels: 1_000_000,
        out_dir: out.to_owned(),
        ..StudioConfig::default()
    }
}

/// A `w × h` PNG: a smooth gradient with a darker square, so every region differs.
pub fn photo_png(w: u32, h: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(w, h, |x, y| {
        let inside = x > w / 3 && x < 2 * w / 3 && y > h / 3 && y < 2 * h / 3;
        let base = [60 + (120 * x / w) as u8, 80 + (100 * y / h) as u8, 140];
        if inside {
            image::Rgb(base.map(|c| c / 2))
        } else {
            image::Rgb(base)
        }
    });
    let mut out = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .expect("encoding a test PNG");
    out
}

/// Decodes PNG bytes to RGB8.
pub fn decode(png: &[u8]) -> image::RgbImage {
    image::load_from_memory(png).expect("a PNG").to_rgb8()
}

/// Runs `studio` on a free 127.0.0.1 port in a background thread; returns the address.
pub fn spawn_server(studio: Studio) -> SocketAddr {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("a runtime");
        rt.block_on(async move {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
            tx.send(listener.local_addr().expect("addr")).expect("send");
            let _ = pixl_studio::serve(studio, listener).await;
        });
    });
    rx.recv_timeout(Duration::from_secs(10)).expect("the server started")
}

/// One HTTP/1.1 request (`Connection: close`); returns the status and the body.
pub fn http(addr: SocketAddr, method: &str, path: &str, body: &[u8]) -> (u16, Vec<u8>) {
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_secs(60))).expect("timeout");
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).expect("write");
    s.write_all(body).expect("write body");
    let mut raw = Vec::new();
    let _ = s.read_to_end(&mut raw);
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").expect("a response head");
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    let status: u16 = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .expect("a status code");
    let mut body = raw[split + 4..].to_vec();
    if head.to_ascii_lowercase().contains("transfer-encoding: chunked") {
        body = dechunk(&body);
    }
    (status, body)
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    while let Some(eol) = b.windows(2).position(|w| w == b"\r\n") {
        let n = usize::from_str_radix(String::from_utf8_lossy(&b[..eol]).trim(), 16).unwrap_or(0);
        if n == 0 {
            break;
        }
        out.extend_from_slice(&b[eol + 2..eol + 2 + n]);
        b = &b[eol + 2 + n + 2..];
    }
    out
}

/// [`http`] with a JSON answer.
pub fn http_json(addr: SocketAddr, method: &str, path: &str, body: &str) -> (u16, serde_json::Value) {
    let (status, bytes) = http(addr, method, path, body.as_bytes());
    let v =
        serde_json::from_slice(&bytes).unwrap_or_else(|_| serde_json::json!({"raw": String::from_utf8_lossy(&bytes)}));
    (status, v)
}
