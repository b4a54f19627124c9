//! `pixl model` / `pixl relight` / `pixl bench model` through the real binary: fresh weights
//! return the source exactly (16-bit PNG and f32 EXR, odd size), `model info` totals.
use pixl_core::Image;
use pixl_intrinsics::ct::{write_ct, Ct};
use std::path::Path;
use std::process::Command;

fn pixl(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_pixl"))
        .args(args)
        .arg("--quiet")
        .output()
        .expect("run pixl")
}

fn ok(args: &[&str]) -> String {
    let o = pixl(args);
    assert!(
        o.status.success(),
        "pixl {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).to_string()
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

#[test]
fn fresh_weights_return_png_and_exr_sources_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (37, 21); // odd size: padding and cropping are exercised
    let w_path = dir.path().join("w.safetensors");
    ok(&["model", "init", "--config", "tiny", "--seed", "3", "-o", s(&w_path)]);
    let ct = Ct::new(
        Image::from_fn(w, h, 3, |x, _, c| 0.2 + 0.1 * c as f32 + 0.01 * x as f32),
        Image::from_fn(w, h, 3, |_, y, _| 0.5 + 0.05 * y as f32),
        Image::from_fn(w, h, 3, |x, y, _| 0.01 * ((x + y) % 3) as f32),
    )
    .unwrap();
    let ct_path = dir.path().join("ct.exr");
    write_ct(&ct_path, &ct).unwrap();
    // 16-bit PNG values k/65535, including both ends of the range.
    let png = Image::from_fn(w, h, 3, |x, y, c| {
        ((x * 977 + y * 131 + c * 17) % 65536) as f32 / 65535.0
    });
    let exr = Image::from_fn(w, h, 3, |x, y, c| {
        ((x * 7 + y * 3 + c) % 101) as f32 / 101.0 + 1e-7 * x as f32
    });
    for (name, img) in [("src.png", &png), ("src.exr", &exr)] {
        let src = dir.path().join(name);
        pixl_core::io::write_image(&src, img).unwrap();
        let out = dir.path().join(format!("out-{name}"));
        ok(&[
            "relight",
            "--source",
            s(&src),
            "--intrinsics",
            s(&ct_path),
            "--weights",
            s(&w_path),
            "--out",
            s(&out),
        ]);
        let a = pixl_core::io::read_rgb(&src).unwrap();
        let b = pixl_core::io::read_rgb(&out).unwrap();
        assert_eq!((a.width, a.height), (b.width, b.height));
        let same = a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same, "{name}: output differs from the source");
    }
}

#[test]
fn model_info_paper_total_is_in_the_papers_range() {
    let out = ok(&["model", "info", "--config", "paper", "--json"]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let total = v["total"].as_u64().unwrap();
    assert!((600_000_000..760_000_000).contains(&total), "{total}");
    let sum: u64 = v["modules"]
        .as_object()
        .unwrap()
        .values()
        .map(|n| n.as_u64().unwrap())
        .sum();
    assert_eq!(sum, total);
    for m in ["src_encoder", "cond_encoder", "fuse", "trunk", "head", "modulation"] {
        assert!(v["modules"][m].as_u64().unwrap() > 0, "{m}");
    }
}

#[test]
fn bench_rejects_a_bad_size() {
    let o = pixl(&["bench", "model", "--config", "tiny", "--size", "512by512"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("WIDTHxHEIGHT"));
}
