//! `pixl model` / `pixl relight` / `pixl bench model` through the real binary: fresh weights
//! return the source exactly (16-bit PNG and f32 EXR, odd size; and a photo larger than
//! `--max-side`, relit at the working size and applied at full size, with its planned memory
//! bounded), an output that is an input is refused, an impossible size is refused with its
//! figure, `model info` totals.
mod common;
use common::{pixl_q, relight_args, s, tiny_weights, write_image};
use pixl_core::Image;
use pixl_intrinsics::ct::{write_ct, Ct};
use std::path::{Path, PathBuf};

/// Runs `pixl args --quiet`, expecting success; returns stdout.
fn ok(args: &[&str]) -> String {
    pixl_q(args).ok().stdout
}

/// `relight_args` then `extra`.
fn relight_with<'a>(src: &'a Path, ct: &'a Path, w: &'a Path, out: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = relight_args(src, ct, w, out);
    v.extend_from_slice(extra);
    v
}

#[test]
fn fresh_weights_return_png_and_exr_sources_exactly() {
    let dir = common::tempdir();
    let (w, h) = (37, 21); // odd size: padding and cropping are exercised
    let w_path = fresh_weights(dir.path());
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
        let src = write_image(&dir.path().join(name), img);
        let out = dir.path().join(format!("out-{name}"));
        ok(&relight_args(&src, &ct_path, &w_path, &out));
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
    let o = pixl_q(&["bench", "model", "--config", "tiny", "--size", "512by512"]);
    assert!(!o.success());
    assert!(o.stderr.contains("WIDTHxHEIGHT"));
}

fn fresh_weights(dir: &Path) -> PathBuf {
    tiny_weights(&dir.join("w.safetensors"), 3)
}

fn smooth_ct(w: usize, h: usize) -> Ct {
    Ct::new(
        Image::from_fn(w, h, 3, |x, _, c| 0.2 + 0.1 * c as f32 + 0.3 * x as f32 / w as f32),
        Image::from_fn(w, h, 3, |_, y, _| 0.5 + 0.4 * y as f32 / h as f32),
        Image::from_fn(w, h, 3, |x, y, _| 0.01 * ((x + y) % 3) as f32),
    )
    .unwrap()
}

/// A 1500 x 1000 photo with `--max-side 128`: the network runs at 128 x 85, the output has the
/// photo's size and (fresh weights, g = b = 0) equals it exactly, and the planned memory is
/// under 30 MB for the network (200 MB with the full-size images), a twentieth of what the
/// network would plan at full size.
#[test]
fn a_photo_larger_than_max_side_relights_at_full_size_with_bounded_memory() {
    let dir = common::tempdir();
    let weights = fresh_weights(dir.path());
    let (w, h) = (1500, 1000);
    let photo = Image::from_fn(w, h, 3, |x, y, c| ((x * 31 + y * 17 + c * 7) % 65536) as f32 / 65535.0);
    let src = write_image(&dir.path().join("big.png"), &photo);
    // C_T at the photo's size: area-averaged to the working size.
    let ct_path = dir.path().join("ct.exr");
    write_ct(&ct_path, &smooth_ct(w, h)).unwrap();
    let out = dir.path().join("relit.png");
    let at_128 = relight_with(&src, &ct_path, &weights, &out, &["--max-side", "128"]);
    let json = ok(&[&at_128[..], &["--json"]].concat());
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!((v["width"].as_u64(), v["height"].as_u64()), (Some(1500), Some(1000)));
    assert_eq!(
        (v["working_width"].as_u64(), v["working_height"].as_u64()),
        (Some(128), Some(85))
    );
    // The network at the working size; the full-size photo, output and C_T (92 bytes a pixel).
    let network = v["planned_network_bytes"].as_u64().unwrap();
    let planned = network + v["planned_full_size_bytes"].as_u64().unwrap();
    assert!(
        network < 30_000_000 && planned < 200_000_000,
        "planned {network} + full size = {planned} bytes"
    );
    let at_full = pixl_model::fullres::plan_memory(&pixl_model::Config::tiny(), candle_core::DType::F32, w, h);
    assert!(
        at_full.peak_bytes() > 20 * network,
        "full size would plan {}",
        at_full.peak_bytes()
    );
    let back = pixl_core::io::read_rgb(&out).unwrap();
    assert_eq!((back.width, back.height), (w, h));
    let stored = pixl_core::io::read_rgb(&src).unwrap();
    assert!(back
        .data
        .iter()
        .zip(&stored.data)
        .all(|(a, b)| a.to_bits() == b.to_bits()));

    // A C_T at the working size is used as it is; any other size is refused, naming both.
    write_ct(&ct_path, &smooth_ct(128, 85)).unwrap();
    ok(&at_128);
    write_ct(&ct_path, &smooth_ct(100, 85)).unwrap();
    let o = pixl_q(&at_128);
    assert_eq!(o.code(), Some(1));
    let err = &o.stderr;
    assert!(err.contains("1500x1000") && err.contains("128x85"), "{err}");
}

/// `--out` naming the source (directly, or through another spelling of the path) is refused
/// before any work, and the source is left as it was.
#[test]
fn output_equal_to_the_source_is_refused_and_nothing_is_overwritten() {
    let dir = common::tempdir();
    let weights = fresh_weights(dir.path());
    let src = write_image(
        &dir.path().join("a.png"),
        &Image::from_fn(20, 12, 3, |x, _, _| x as f32 / 20.0),
    );
    let ct_path = dir.path().join("ct.exr");
    write_ct(&ct_path, &smooth_ct(20, 12)).unwrap();
    let before = std::fs::read(&src).unwrap();
    let sub = dir.path().join("sub");
    std::fs::create_dir(&sub).unwrap();
    let roundabout = sub.join("..").join("a.png");
    for out in [src.clone(), roundabout] {
        for form in [
            relight_args(&src, &ct_path, &weights, &out),
            vec![
                "relight",
                s(&src),
                "--preset",
                "warm-overhead-flash",
                "--depth",
                s(&ct_path),
                "-o",
                s(&out),
            ],
        ] {
            let o = pixl_q(&form);
            assert_eq!(o.code(), Some(1), "{form:?}");
            assert!(o.stderr.contains("input"), "{form:?}: {}", o.stderr);
            assert_eq!(std::fs::read(&src).unwrap(), before, "the source was changed");
        }
    }
    // The C_T, the weights: inputs too.
    let o = pixl_q(&relight_args(&src, &ct_path, &weights, &weights));
    assert_eq!(o.code(), Some(1));
    // An output format the extension does not name, and a missing folder, are refused first.
    for bad in ["relit.txt", "no/such/dir/relit.png"] {
        let out = dir.path().join(bad);
        let o = pixl_q(&relight_args(&src, &ct_path, &weights, &out));
        assert_eq!(o.code(), Some(1), "{bad}");
        assert!(!out.exists());
    }
}

/// A working size whose planned memory exceeds `--max-memory` is refused before any work, with
/// the figure and the flag to change.
#[test]
fn an_impossible_request_is_refused_with_its_figure_and_the_flag_to_change() {
    let dir = common::tempdir();
    let weights = fresh_weights(dir.path());
    let src = write_image(&dir.path().join("a.png"), &Image::from_fn(640, 480, 3, |_, _, _| 0.5));
    let ct_path = dir.path().join("ct.exr");
    write_ct(&ct_path, &smooth_ct(640, 480)).unwrap();
    let out = dir.path().join("relit.png");
    let small = relight_with(&src, &ct_path, &weights, &out, &["--max-memory", "0.05"]);
    let o = pixl_q(&small);
    assert_eq!(o.code(), Some(1));
    let err = &o.stderr;
    assert!(
        err.contains("GB") && err.contains("--max-side") && err.contains("640x480"),
        "{err}"
    );
    assert!(!out.exists());
    // The --max-side it suggests does fit.
    let side = err
        .split("--max-side ")
        .filter_map(|t| t.split(|c: char| !c.is_ascii_digit()).next()?.parse::<u32>().ok())
        .find(|s| *s < 1024)
        .expect("a suggested --max-side");
    ok(&[&small[..], &["--max-side", &side.to_string()]].concat());
}

/// `--int8` with the bundled weights: the relit photo stays within a small difference of the
/// f32 one (bitwise the same on a CPU without AVX-512 VNNI, where it warns and runs f32), and
/// it is refused with bf16.
#[test]
fn int8_relights_close_to_f32_and_refuses_bf16() {
    let dir = common::tempdir();
    let (w, h) = (96, 64);
    let ct_path = dir.path().join("ct.exr");
    write_ct(&ct_path, &smooth_ct(w, h)).unwrap();
    let photo = Image::from_fn(w, h, 3, |x, y, c| {
        0.15 + 0.6 * ((x as f32 * 0.11 + c as f32).sin() * 0.5 + 0.5) * (y as f32 / h as f32)
    });
    let src = write_image(&dir.path().join("src.png"), &photo);
    // `pixl relight` of the photo under the C_T with `extra` flags, into `name`.
    let relight = |name: &str, extra: &[&str]| {
        let out = dir.path().join(name);
        let mut args = vec![
            "relight",
            "--source",
            s(&src),
            "--intrinsics",
            s(&ct_path),
            "--out",
            s(&out),
        ];
        args.extend_from_slice(extra);
        (pixl_q(&args), out)
    };
    let read = |(result, out): (common::Run, PathBuf)| {
        result.ok();
        pixl_core::io::read_rgb(&out).unwrap()
    };
    let f32_run = relight("f32.exr", &["--json"]);
    let int8_run = relight("int8.exr", &["--int8", "--json"]);
    // The plan counts the 8-bit copies beside the f32 weights: about a quarter of the quantized
    // layers' f32 bytes, so more than nothing and less than a third of all the weights' bytes.
    let planned = |run: &(common::Run, PathBuf)| {
        run.0.json()["planned_network_bytes"]
            .as_u64()
            .expect("planned_network_bytes")
    };
    let extra = planned(&int8_run) as i64 - planned(&f32_run) as i64;
    // The bundled file is f32: its length is the weights' bytes (plus a small header).
    let weight_bytes = pixl_pipeline::relight::BUNDLED_WEIGHTS.len() as i64;
    if pixl_nn::int8::available() {
        assert!(
            extra > 0 && extra < weight_bytes / 3,
            "8-bit copies planned at {extra} bytes"
        );
    } else {
        assert_eq!(extra, 0);
    }
    let f32_out = read(f32_run);
    let int8_out = read(int8_run);
    let mse = f32_out
        .data
        .iter()
        .zip(&int8_out.data)
        .map(|(a, b)| ((a - b) as f64).powi(2))
        .sum::<f64>()
        / f32_out.data.len() as f64;
    if pixl_nn::int8::available() {
        let psnr = 10.0 * (1.0 / mse).log10();
        assert!(mse > 0.0 && psnr > 40.0, "int8 against f32: {psnr:.1} dB");
    } else {
        assert_eq!(mse, 0.0);
    }
    let (refused, _) = relight("x.exr", &["--int8", "--dtype", "bf16"]);
    assert!(!refused.success());
    assert!(refused.stderr.contains("--int8"));
}

/// `--weights`: the released checkpoint (here the tiny fixture in its presumed layout, placed as
/// `--models DIR/pixlrelight/`) is the default when it is on disk, and every run that uses it
/// prints its licence (even under --quiet); `--weights bundled` and a models folder without it
/// use the bundled weights (with a hint); `--weights pixlrelight` offline without it fails;
/// the release's model.safetensors can also be given as a path. The results equal the same
/// network loaded from our own format.
#[test]
fn released_checkpoint_is_the_default_when_on_disk_and_its_licence_is_shown() {
    let dir = common::tempdir();
    let fx = common::repo_path("fixtures/pixlrelight-official");
    let models = dir.path().join("models");
    let rel = models.join("pixlrelight");
    std::fs::create_dir_all(&rel).unwrap();
    for f in ["config.yaml", "model.safetensors"] {
        std::fs::copy(fx.join(f), rel.join(f)).unwrap();
    }
    let (w, h) = (40, 24);
    let ct_path = dir.path().join("ct.exr");
    write_ct(&ct_path, &smooth_ct(w, h)).unwrap();
    let img = Image::from_fn(w, h, 3, |x, y, c| 0.2 + 0.5 * ((x * 3 + y * 5 + c) % 17) as f32 / 17.0);
    let src = write_image(&dir.path().join("src.exr"), &img);
    let run = |out: &str, extra: &[&str]| {
        let out = dir.path().join(out);
        let mut args = vec!["relight", "--source", s(&src), "--intrinsics", s(&ct_path), "--out"];
        let out_s = out.to_str().unwrap().to_string();
        args.push(&out_s);
        args.extend_from_slice(extra);
        let r = common::run(common::cmd().env("PIXL_OFFLINE", "1").arg("--quiet").args(&args));
        (r, out)
    };
    let m = s(&models);
    let (r, default_out) = run("default.exr", &["--models", m]);
    let r = r.ok();
    assert!(
        r.stderr.contains("CC BY-NC 4.0 — non-commercial use only"),
        "{}",
        r.stderr
    );
    assert!(r.stderr.contains("PIXLRelight release"), "{}", r.stderr);
    let (r, native_out) = run("native.exr", &["--weights", s(&fx.join("native.safetensors"))]);
    assert!(!r.ok().stderr.contains("non-commercial"));
    let (a, b) = (
        pixl_core::io::read_image(&default_out).unwrap(),
        pixl_core::io::read_image(&native_out).unwrap(),
    );
    let d = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(d <= 1e-5, "release vs native differ by {d}");
    assert!(
        a.data.iter().zip(&img.data).any(|(x, y)| (x - y).abs() > 1e-3),
        "the network changed nothing"
    );
    let (r, path_out) = run("path.exr", &["--weights", s(&rel.join("model.safetensors"))]);
    assert!(r.ok().stderr.contains("non-commercial"));
    assert_eq!(pixl_core::io::read_image(&path_out).unwrap().data, a.data);
    let (r, _) = run("bundled.exr", &["--models", m, "--weights", "bundled"]);
    assert!(!r.ok().stderr.contains("non-commercial"));
    let empty = dir.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let (r, _) = run("fallback.exr", &["--models", s(&empty), "--weights", "pixlrelight"]);
    r.fails(&["pixlrelight"]);
}
