//! Bad input, everywhere: for each kind of bad input, the real `pixl` binary must print
//! one clear message naming the file and the problem, exit non-zero, not panic, and leave no
//! (partial) output file behind. One test per kind of bad input.
mod common;
use common::{
    assert_no_temp_files, pixl_q, png_header_only, relight_args, s, sphere_scene, tiny_weights, truncated_copy,
    write_ct_channels, write_file, write_image,
};
use pixl_core::Image;
use std::path::{Path, PathBuf};

const W: usize = 32;
const H: usize = 24;

struct Fixture {
    dir: tempfile::TempDir,
}

impl Fixture {
    fn new() -> Self {
        Fixture { dir: common::tempdir() }
    }
    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
    /// A valid 16-bit PNG source.
    fn source(&self) -> PathBuf {
        let img = Image::from_fn(W, H, 3, |x, y, c| ((x + 2 * y + 5 * c) % 17) as f32 / 16.0);
        write_image(&self.path("src.png"), &img)
    }
    /// A valid C_T file of the given size.
    fn ct(&self, name: &str, w: usize, h: usize) -> PathBuf {
        write_ct_channels(&self.path(name), w, h, |_, _| vec![0.5; w * h])
    }
    /// Fresh `tiny` weights, made by the binary itself.
    fn weights(&self) -> PathBuf {
        tiny_weights(&self.path("w.safetensors"), 0)
    }
}

/// Runs `pixl args --quiet`, expects failure whose stderr contains every `needles`
/// (case-insensitive), no panic, no file at `out`, and no temporary file beside it.
fn expect_failure(args: &[&str], needles: &[&str], out: &Path) {
    pixl_q(args).fails_ignoring_case(needles);
    assert!(!out.exists(), "pixl {args:?} left an output file {}", out.display());
    if let Some(dir) = out.parent() {
        assert_no_temp_files(dir);
    }
}

/// `pixl relight` of `src` with `ct` and `w` into `out` is refused with `needles`.
fn relight_fails(src: &Path, ct: &Path, w: &Path, out: &Path, needles: &[&str]) {
    expect_failure(&relight_args(src, ct, w, out), needles, out);
}

#[test]
fn corrupt_png_source() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bad = write_file(&f.path("bad.png"), b"\x89PNG\r\n\x1a\nthis is not a png");
    relight_fails(&bad, &ct, &w, &out, &["bad.png"]);
}

#[test]
fn truncated_png_source() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let cut = truncated_copy(&src, &f.path("cut.png"), 2);
    relight_fails(&cut, &ct, &w, &out, &["cut.png"]);
}

#[test]
fn truncated_jpeg_source() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let jpg = write_image(
        &f.path("src.jpg"),
        &Image::from_fn(W, H, 3, |x, y, _| ((x * y) % 7) as f32 / 7.0),
    );
    let cut = truncated_copy(&jpg, &f.path("cut.jpg"), 3);
    relight_fails(&cut, &ct, &w, &out, &["cut.jpg"]);
}

#[test]
fn truncated_exr_intrinsics() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let cut = truncated_copy(&ct, &f.path("cut.exr"), 2);
    relight_fails(&src, &cut, &w, &out, &["cut.exr"]);
}

#[test]
fn intrinsics_with_wrong_channels() {
    let f = Fixture::new();
    let (src, w, out) = (f.source(), f.weights(), f.path("out.png"));
    let rgb = write_image(&f.path("rgb.exr"), &Image::new(W, H, 3));
    relight_fails(&src, &rgb, &w, &out, &["rgb.exr", "albedo"]);
}

#[test]
fn nan_in_source() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let mut img = Image::new(W, H, 3);
    img.set(3, 2, 1, f32::NAN);
    img.set(4, 2, 0, f32::INFINITY);
    let nan = write_image(&f.path("nan.exr"), &img);
    relight_fails(&nan, &ct, &w, &out, &["nan.exr", "non-finite", "2 "]);
}

#[test]
fn nan_in_intrinsics() {
    let f = Fixture::new();
    let (src, w, out) = (f.source(), f.weights(), f.path("out.png"));
    let p = write_ct_channels(&f.path("ctnan.exr"), W, H, |group, c| {
        let mut v = vec![0.5; W * H];
        if group == "shading" && c == "G" {
            v[5] = f32::NAN;
        }
        v
    });
    relight_fails(&src, &p, &w, &out, &["ctnan.exr"]);
}

#[test]
fn zero_sized_image() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let p = write_file(&f.path("empty.png"), png_header_only(0, 0));
    relight_fails(&p, &ct, &w, &out, &["empty.png"]);
}

#[test]
fn absurd_image_header_is_refused_before_allocating() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let p = write_file(&f.path("huge.png"), png_header_only(200_000, 200_000));
    relight_fails(&p, &ct, &w, &out, &["huge.png", "200000x200000"]);
}

#[test]
fn source_and_intrinsics_differ_in_size() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("small.exr", W / 2, H), f.weights(), f.path("out.png"));
    relight_fails(&src, &ct, &w, &out, &["32x24", "16x24"]);
}

#[test]
fn truncated_weights() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let cut = truncated_copy(&w, &f.path("cut.safetensors"), 2);
    relight_fails(&src, &ct, &cut, &out, &["cut.safetensors"]);
}

#[test]
fn garbage_weights() {
    let f = Fixture::new();
    let (src, ct, out) = (f.source(), f.ct("ct.exr", W, H), f.path("out.png"));
    let g = write_file(
        &f.path("garbage.safetensors"),
        b"\xff\xff\xff\xff\xff\xff\xff\x7fnot json at all",
    );
    relight_fails(&src, &ct, &g, &out, &["garbage.safetensors"]);
}

/// The JSON header of a safetensors file, and its data.
fn safetensors_parts(bytes: &[u8]) -> (serde_json::Value, &[u8]) {
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    (serde_json::from_slice(&bytes[8..8 + n]).unwrap(), &bytes[8 + n..])
}

/// The unsigned integers of a JSON array.
fn usizes(v: &serde_json::Value) -> Vec<usize> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as usize)
        .collect()
}

/// Rewrites one tensor of a safetensors file: `shape` and `dtype` as given, data zero-filled.
fn rewrite_tensor(src: &Path, dst: &Path, shape: Option<Vec<usize>>, dtype: Option<&str>) -> String {
    let bytes = std::fs::read(src).unwrap();
    let (header, data) = safetensors_parts(&bytes);
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
        let mut sh = usizes(&t["shape"]);
        let off = usizes(&t["data_offsets"]);
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
    write_file(dst, out);
    victim
}

#[test]
fn weights_with_a_wrong_shape() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bad = f.path("shape.safetensors");
    let victim = rewrite_tensor(&w, &bad, Some(vec![3, 5]), None);
    relight_fails(&src, &ct, &bad, &out, &["shape.safetensors", &victim]);
}

#[test]
fn weights_with_a_wrong_dtype() {
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let bad = f.path("dtype.safetensors");
    let bytes = std::fs::read(&w).unwrap();
    let (header, _) = safetensors_parts(&bytes);
    let first = header
        .as_object()
        .unwrap()
        .iter()
        .find(|(k, _)| *k != "__metadata__")
        .unwrap();
    let shape = usizes(&first.1["shape"]);
    rewrite_tensor(&w, &bad, Some(shape), Some("I32"));
    relight_fails(&src, &ct, &bad, &out, &["dtype.safetensors"]);
}

#[test]
fn missing_input() {
    let f = Fixture::new();
    let (ct, w, out) = (f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    let missing = f.path("no-such-photo.png");
    relight_fails(&missing, &ct, &w, &out, &["no-such-photo.png", "not found"]);
}

#[test]
fn unwritable_output_directory() {
    let f = Fixture::new();
    let (src, ct, w) = (f.source(), f.ct("ct.exr", W, H), f.weights());
    // A directory that cannot exist: its parent is a regular file (root ignores permission bits).
    let blocker = write_file(&f.path("a-file"), b"x");
    let out = blocker.join("out.png");
    relight_fails(&src, &ct, &w, &out, &["out.png"]);
}

/// `pixl render` of the scene `text` (written as scene.toml) is refused with `needles`.
fn render_fails(f: &Fixture, text: &str, needles: &[&str]) {
    let scene = write_file(&f.path("scene.toml"), text);
    let out = f.path("passes.exr");
    expect_failure(&["render", s(&scene), "--spp", "1", "-o", s(&out)], needles, &out);
}

/// A 16 × 16 view of a sphere lit by `light`.
fn scene_with_light(light: &str) -> String {
    sphere_scene(16, 16, &format!("\n{light}\n"))
}

#[test]
fn scene_with_unknown_light_type() {
    let light = "[[lights]]\ntype = \"laser\"\nposition = [0.0, 2.0, 0.0]\npower = 10.0";
    render_fails(&Fixture::new(), &scene_with_light(light), &["scene.toml", "laser"]);
}

#[test]
fn scene_with_negative_power() {
    let light = "[[lights]]\ntype = \"point\"\nposition = [0.0, 2.0, 0.0]\npower = -5.0";
    render_fails(&Fixture::new(), &scene_with_light(light), &["scene.toml", "power"]);
}

#[test]
fn scene_with_missing_mesh() {
    render_fails(
        &Fixture::new(),
        "[camera]\nwidth = 16\nheight = 16\nfov_y_deg = 40.0\n\n[[objects]]\nshape = { type = \"mesh\", path = \"gone.glb\" }\n",
        &["gone.glb"],
    );
}

#[test]
fn compose_with_corrupt_passes() {
    let f = Fixture::new();
    let bad = write_file(&f.path("passes.exr"), b"v/1\x01garbage garbage garbage");
    let out = f.path("ct.exr");
    expect_failure(&["compose", s(&bad), "-o", s(&out)], &["passes.exr"], &out);
}

#[test]
fn good_input_succeeds_and_round_trips() {
    // The control row: with valid inputs the same command succeeds, and fresh weights return
    // the source exactly (the zero-initialised modulation head).
    let f = Fixture::new();
    let (src, ct, w, out) = (f.source(), f.ct("ct.exr", W, H), f.weights(), f.path("out.png"));
    pixl_q(&relight_args(&src, &ct, &w, &out)).ok();
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
    let on = |device: &'static str| {
        let mut args = relight_args(&src, &ct, &w, &out);
        args.extend(["--device", device]);
        args
    };
    for (device, message) in [
        ("tpu", "expected cpu or cuda"),
        ("cuda0", "expected cpu or cuda[:N]"),
        ("cuda:x", "bad CUDA ordinal"),
    ] {
        expect_failure(&on(device), &["--device", message], &out);
    }
    // What `pixl doctor` says about CUDA decides the message for `--device cuda:0`.
    let report = pixl_q(&["doctor", "--json"]).ok().json();
    assert_eq!(report["cuda"]["compiled"], cfg!(feature = "cuda"));
    let expected = if !cfg!(feature = "cuda") {
        Some("CUDA is not available in this build")
    } else if report["cuda"]["unavailable"].is_string() {
        Some("no CUDA device")
    } else {
        None
    };
    if let Some(message) = expected {
        expect_failure(&on("cuda:0"), &["--device cuda:0", message], &out);
    }
    expect_failure(
        &on("cuda:99"),
        &["--device cuda:99", expected.unwrap_or("no CUDA device 99")],
        &out,
    );
    // The same arguments on the CPU work (the failures above are the device's alone).
    pixl_q(&on("cpu")).ok();
    assert!(out.is_file());
}
