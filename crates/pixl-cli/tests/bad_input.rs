//! Bad input, everywhere (issue 7): for each kind of bad input, the real `pixl` binary must print
//! one clear message naming the file and the problem, exit non-zero, not panic, and leave no
//! (partial) output file behind. One test per row of the table.
use pixl_core::exrio::{write_exr_channels, ExrChannels};
use pixl_core::io::write_image;
use pixl_core::Image;
use std::path::{Path, PathBuf};
use std::process::Command;

const W: usize = 32;
const H: usize = 24;

struct Fixture {
    dir: tempfile::TempDir,
}

impl Fixture {
    fn new() -> Self {
        Fixture {
            dir: tempfile::tempdir().expect("tempdir"),
        }
    }
    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
    /// A valid 16-bit PNG source.
    fn source(&self) -> PathBuf {
        let p = self.path("src.png");
        let img = Image::from_fn(W, H, 3, |x, y, c| ((x + 2 * y + 5 * c) % 17) as f32 / 16.0);
        write_image(&p, &img).expect("write source");
        p
    }
    /// A valid C_T file of the given size.
    fn ct(&self, name: &str, w: usize, h: usize) -> PathBuf {
        let p = self.path(name);
        let mut ch = ExrChannels::new(w, h);
        for group in ["albedo", "shading", "residual"] {
            for c in ["R", "G", "B"] {
                ch.push(format!("{group}.{c}"), vec![0.5; w * h]).expect("push");
            }
        }
        write_exr_channels(&p, &ch).expect("write ct");
        p
    }
    /// Fresh `tiny` weights, made by the binary itself.
    fn weights(&self) -> PathBuf {
        let p = self.path("w.safetensors");
        let out = pixl(&[
            "model",
            "init",
            "--config",
            "tiny",
            "--seed",
            "0",
            "-o",
            p.to_str().unwrap(),
        ]);
        assert!(
            out.status.success(),
            "model init failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        p
    }
}

fn pixl(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_pixl"))
        .args(args)
        .arg("--quiet")
        .output()
        .expect("run pixl")
}

/// Runs `pixl args`, expects failure whose stderr contains every `needles` (case-insensitive),
/// no panic, and no file at `out`.
fn expect_failure(args: &[&str], needles: &[&str], out: &Path) {
    let o = pixl(args);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "pixl {args:?} succeeded; stderr: {stderr}");
    assert_eq!(
        o.status.code(),
        Some(1),
        "pixl {args:?}: exit {:?}; stderr: {stderr}",
        o.status.code()
    );
    assert!(!stderr.contains("panicked"), "pixl {args:?} panicked: {stderr}");
    let low = stderr.to_lowercase();
    for n in needles {
        assert!(
            low.contains(&n.to_lowercase()),
            "pixl {args:?}: stderr lacks {n:?}: {stderr}"
        );
    }
    assert!(!out.exists(), "pixl {args:?} left an output file {}", out.display());
    if let Some(dir) = out.parent() {
        if let Ok(rd) = std::fs::read_dir(dir) {
            for e in rd.flatten() {
                let n = e.file_name().to_string_lossy().to_string();
                assert!(
                    !n.contains(".tmp-") && !n.contains(".pixl-probe-"),
                    "temporary file left behind: {n}"
                );
            }
        }
    }
}

fn relight_args<'a>(src: &'a str, ct: &'a str, w: &'a str, out: &'a str) -> Vec<&'a str> {
    vec![
        "relight",
        "--source",
        src,
        "--intrinsics",
        ct,
        "--weights",
        w,
        "--out",
        out,
    ]
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// CRC-32 (IEEE), to craft PNG chunks by hand.
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// A PNG that is only a signature and an IHDR announcing `w × h` RGB8 (no pixel data).
fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    let mut v = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = b"IHDR".to_vec();
    chunk.extend_from_slice(&w.to_be_bytes());
    chunk.extend_from_slice(&h.to_be_bytes());
    chunk.extend_from_slice(&[8, 2, 0, 0, 0]);
    v.extend_from_slice(&13u32.to_be_bytes());
    v.extend_from_slice(&chunk);
    v.extend_from_slice(&crc32(&chunk).to_be_bytes());
    v
}

#[test]
fn corrupt_png_source() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bad = f.path("bad.png");
    std::fs::write(&bad, b"\x89PNG\r\n\x1a\nthis is not a png").unwrap();
    expect_failure(&relight_args(s(&bad), s(&ct), s(&w), s(&out)), &["bad.png"], &out);
}

#[test]
fn truncated_png_source() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bytes = std::fs::read(&src).unwrap();
    let cut = f.path("cut.png");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    expect_failure(&relight_args(s(&cut), s(&ct), s(&w), s(&out)), &["cut.png"], &out);
}

#[test]
fn truncated_jpeg_source() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let jpg = f.path("src.jpg");
    write_image(&jpg, &Image::from_fn(W, H, 3, |x, y, _| ((x * y) % 7) as f32 / 7.0)).unwrap();
    let bytes = std::fs::read(&jpg).unwrap();
    let cut = f.path("cut.jpg");
    std::fs::write(&cut, &bytes[..bytes.len() / 3]).unwrap();
    expect_failure(&relight_args(s(&cut), s(&ct), s(&w), s(&out)), &["cut.jpg"], &out);
}

#[test]
fn truncated_exr_intrinsics() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bytes = std::fs::read(&ct).unwrap();
    let cut = f.path("cut.exr");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    expect_failure(&relight_args(s(&src), s(&cut), s(&w), s(&out)), &["cut.exr"], &out);
}

#[test]
fn intrinsics_with_wrong_channels() {
    let f = Fixture::new();
    let (src, w, out) = (f.source(), f.weights(), f.path("out.png"));
    let rgb = f.path("rgb.exr");
    write_image(&rgb, &Image::new(W, H, 3)).unwrap();
    expect_failure(
        &relight_args(s(&src), s(&rgb), s(&w), s(&out)),
        &["rgb.exr", "albedo"],
        &out,
    );
}

#[test]
fn nan_in_source() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let mut img = Image::new(W, H, 3);
    img.set(3, 2, 1, f32::NAN);
    img.set(4, 2, 0, f32::INFINITY);
    let nan = f.path("nan.exr");
    write_image(&nan, &img).unwrap();
    expect_failure(
        &relight_args(s(&nan), s(&ct), s(&w), s(&out)),
        &["nan.exr", "non-finite", "2 "],
        &out,
    );
}

#[test]
fn nan_in_intrinsics() {
    let f = Fixture::new();
    let (src, w, out) = (f.source(), f.weights(), f.path("out.png"));
    let p = f.path("ctnan.exr");
    let mut ch = ExrChannels::new(W, H);
    for group in ["albedo", "shading", "residual"] {
        for c in ["R", "G", "B"] {
            let mut v = vec![0.5; W * H];
            if group == "shading" && c == "G" {
                v[5] = f32::NAN;
            }
            ch.push(format!("{group}.{c}"), v).unwrap();
        }
    }
    write_exr_channels(&p, &ch).unwrap();
    expect_failure(&relight_args(s(&src), s(&p), s(&w), s(&out)), &["ctnan.exr"], &out);
}

#[test]
fn zero_sized_image() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let p = f.path("empty.png");
    std::fs::write(&p, png_header_only(0, 0)).unwrap();
    expect_failure(&relight_args(s(&p), s(&ct), s(&w), s(&out)), &["empty.png"], &out);
}

#[test]
fn absurd_image_header_is_refused_before_allocating() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let p = f.path("huge.png");
    std::fs::write(&p, png_header_only(200_000, 200_000)).unwrap();
    expect_failure(
        &relight_args(s(&p), s(&ct), s(&w), s(&out)),
        &["huge.png", "200000x200000"],
        &out,
    );
}

#[test]
fn source_and_intrinsics_differ_in_size() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("small.exr", W / 2, H), f.weights(), f.path("out.png"));
    expect_failure(
        &relight_args(s(&src), s(&ct), s(&w), s(&out)),
        &["32x24", "16x24"],
        &out,
    );
}

#[test]
fn truncated_weights() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bytes = std::fs::read(&w).unwrap();
    let cut = f.path("cut.safetensors");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    expect_failure(
        &relight_args(s(&src), s(&ct), s(&cut), s(&out)),
        &["cut.safetensors"],
        &out,
    );
}

#[test]
fn garbage_weights() {
    let f = Fixture::new();
    let (src, ct, out) = (f.source(), f.ct("ct.exr", W, H), f.path("out.png"));
    let g = f.path("garbage.safetensors");
    std::fs::write(&g, b"\xff\xff\xff\xff\xff\xff\xff\x7fnot json at all").unwrap();
    expect_failure(
        &relight_args(s(&src), s(&ct), s(&g), s(&out)),
        &["garbage.safetensors"],
        &out,
    );
}

/// Rewrites one tensor of a safetensors file: `shape` and `dtype` as given, data zero-filled.
fn rewrite_tensor(src: &Path, dst: &Path, shape: Option<Vec<usize>>, dtype: Option<&str>) -> String {
    let bytes = std::fs::read(src).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let data = &bytes[8 + n..];
    let mut map = header.as_object().unwrap().clone();
    let meta = map.remove("__metadata__");
    let mut names: Vec<String> = map.keys().cloned().collect();
    names.sort();
    let victim = names
        .iter()
        .find(|k| k.ends_with(".weight") && k.contains("fuse"))
        .unwrap_or(&names[0])
        .clone();
    let mut out_header = serde_json::Map::new();
    if let Some(m) = meta {
        out_header.insert("__metadata__".into(), m);
    }
    let mut out_data = Vec::new();
    for name in &names {
        let t = &map[name];
        let mut dt = t["dtype"].as_str().unwrap().to_string();
        let mut sh: Vec<usize> = t["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect();
        let off: Vec<usize> = t["data_offsets"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect();
        let mut chunk = data[off[0]..off[1]].to_vec();
        if name == &victim {
            if let Some(s) = &shape {
                sh = s.clone();
            }
            if let Some(d) = dtype {
                dt = d.to_string();
            }
            let size = match dt.as_str() {
                "F64" | "I64" => 8,
                "F32" | "I32" => 4,
                _ => 2,
            };
            chunk = vec![0u8; sh.iter().product::<usize>() * size];
        }
        let start = out_data.len();
        out_data.extend_from_slice(&chunk);
        out_header.insert(
            name.clone(),
            serde_json::json!({"dtype": dt, "shape": sh, "data_offsets": [start, out_data.len()]}),
        );
    }
    let mut h = serde_json::to_vec(&serde_json::Value::Object(out_header)).unwrap();
    while !h.len().is_multiple_of(8) {
        h.push(b' ');
    }
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&h);
    out.extend_from_slice(&out_data);
    std::fs::write(dst, out).unwrap();
    victim
}

#[test]
fn weights_with_a_wrong_shape() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bad = f.path("shape.safetensors");
    let victim = rewrite_tensor(&w, &bad, Some(vec![3, 5]), None);
    expect_failure(
        &relight_args(s(&src), s(&ct), s(&bad), s(&out)),
        &["shape.safetensors", &victim],
        &out,
    );
}

#[test]
fn weights_with_a_wrong_dtype() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bad = f.path("dtype.safetensors");
    let bytes = std::fs::read(&w).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    let first = header
        .as_object()
        .unwrap()
        .iter()
        .find(|(k, _)| *k != "__metadata__")
        .unwrap();
    let shape: Vec<usize> = first.1["shape"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect();
    let victim = rewrite_tensor(&w, &bad, Some(shape.clone()), Some("I32"));
    let _ = victim;
    expect_failure(
        &relight_args(s(&src), s(&ct), s(&bad), s(&out)),
        &["dtype.safetensors"],
        &out,
    );
}

#[test]
fn missing_input() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let missing = f.path("no-such-photo.png");
    expect_failure(
        &relight_args(s(&missing), s(&ct), s(&w), s(&out)),
        &["no-such-photo.png", "not found"],
        &out,
    );
}

#[test]
fn unwritable_output_directory() {
    let f = Fixture::new();
    let (src, ct, w) = (f.source(), f.ct("ct.exr", W, H), f.weights());
    // A directory that cannot exist: its parent is a regular file (root ignores permission bits).
    let blocker = f.path("a-file");
    std::fs::write(&blocker, b"x").unwrap();
    let out = blocker.join("out.png");
    expect_failure(&relight_args(s(&src), s(&ct), s(&w), s(&out)), &["out.png"], &out);
}

fn scene_with_light(f: &Fixture, light: &str) -> PathBuf {
    let p = f.path("scene.toml");
    let text = format!(
        "[camera]\nwidth = 16\nheight = 16\nfov_y_deg = 40.0\nposition = [0.0, 0.0, 3.0]\n\n\
         [[objects]]\nshape = {{ type = \"sphere\", radius = 1.0 }}\n\n{light}\n"
    );
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn scene_with_unknown_light_type() {
    let f = Fixture::new();
    let scene = scene_with_light(
        &f,
        "[[lights]]\ntype = \"laser\"\nposition = [0.0, 2.0, 0.0]\npower = 10.0",
    );
    let out = f.path("passes.exr");
    expect_failure(
        &["render", s(&scene), "--spp", "1", "-o", s(&out)],
        &["scene.toml", "laser"],
        &out,
    );
}

#[test]
fn scene_with_negative_power() {
    let f = Fixture::new();
    let scene = scene_with_light(
        &f,
        "[[lights]]\ntype = \"point\"\nposition = [0.0, 2.0, 0.0]\npower = -5.0",
    );
    let out = f.path("passes.exr");
    expect_failure(
        &["render", s(&scene), "--spp", "1", "-o", s(&out)],
        &["scene.toml", "power"],
        &out,
    );
}

#[test]
fn scene_with_missing_mesh() {
    let f = Fixture::new();
    let p = f.path("scene.toml");
    std::fs::write(
        &p,
        "[camera]\nwidth = 16\nheight = 16\nfov_y_deg = 40.0\n\n[[objects]]\nshape = { type = \"mesh\", path = \"gone.glb\" }\n",
    )
    .unwrap();
    let out = f.path("passes.exr");
    expect_failure(&["render", s(&p), "--spp", "1", "-o", s(&out)], &["gone.glb"], &out);
}

#[test]
fn compose_with_corrupt_passes() {
    let f = Fixture::new();
    let bad = f.path("passes.exr");
    std::fs::write(&bad, b"v/1\x01garbage garbage garbage").unwrap();
    let out = f.path("ct.exr");
    expect_failure(&["compose", s(&bad), "-o", s(&out)], &["passes.exr"], &out);
}

#[test]
fn good_input_succeeds_and_round_trips() {
    // The control row: with valid inputs the same command succeeds, and fresh weights return
    // the source exactly (the zero-initialised modulation head).
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let o = pixl(&relight_args(s(&src), s(&ct), s(&w), s(&out)));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let a = pixl_core::io::read_rgb(&src).unwrap();
    let b = pixl_core::io::read_rgb(&out).unwrap();
    assert_eq!(a, b);
}

/// `relight --device`: an unknown device, a malformed ordinal, and CUDA where this build or
/// machine has none are refused with a message saying why, before anything is written.
#[test]
fn relight_on_an_unavailable_device() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    for (device, message) in [
        ("tpu", "expected cpu or cuda"),
        ("cuda0", "expected cpu or cuda[:N]"),
        ("cuda:x", "bad CUDA ordinal"),
    ] {
        let mut args = relight_args(s(&src), s(&ct), s(&w), s(&out));
        args.extend(["--device", device]);
        expect_failure(&args, &["--device", message], &out);
    }
    // What `pixl doctor` says about CUDA decides the message for `--device cuda:0`.
    let doctor = pixl(&["doctor", "--json"]);
    assert!(doctor.status.success(), "{}", String::from_utf8_lossy(&doctor.stderr));
    let report: serde_json::Value = serde_json::from_slice(&doctor.stdout).unwrap();
    assert_eq!(report["cuda"]["compiled"], cfg!(feature = "cuda"));
    let expected = if !cfg!(feature = "cuda") {
        Some("CUDA is not available in this build")
    } else if report["cuda"]["unavailable"].is_string() {
        Some("no CUDA device")
    } else {
        None
    };
    if let Some(message) = expected {
        let mut args = relight_args(s(&src), s(&ct), s(&w), s(&out));
        args.extend(["--device", "cuda:0"]);
        expect_failure(&args, &["--device cuda:0", message], &out);
    }
    let mut args = relight_args(s(&src), s(&ct), s(&w), s(&out));
    args.extend(["--device", "cuda:99"]);
    expect_failure(
        &args,
        &["--device cuda:99", expected.unwrap_or("no CUDA device 99")],
        &out,
    );
    // The same arguments on the CPU work (the failures above are the device's alone).
    let mut args = relight_args(s(&src), s(&ct), s(&w), s(&out));
    args.extend(["--device", "cpu"]);
    let o = pixl(&args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.is_file());
}
