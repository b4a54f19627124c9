//! `pixl relight PHOTO --like TARGET -o OUT` through the real binary, with the tiny random
//! Marigold-IID-Lighting checkpoint of `fixtures/marigold/lighting` installed in a models folder
//! and the bundled network: the relit image has the photo's size; `--keep` writes the C_T maps,
//! and that C_T is the target's own (`pixl estimate lighting` of the target, bit for bit) and
//! gives the same relit image again through `--intrinsics`; a target of another shape is
//! stretched with a warning; `--like` conflicts with the other ways of giving the lighting; bad
//! inputs are each one clear error with nothing written.
mod common;
use common::{cmd_in, copy_dir, run, s, write_file, write_png8, Run};
use pixl_core::Image;
use std::path::{Path, PathBuf};

/// A models folder under `root` holding the fixture `src` (lighting | appearance) as
/// `marigold-lighting`.
fn models(root: &Path, src: &str) -> PathBuf {
    let dir = root.join("models");
    copy_dir(
        &common::repo_path("fixtures/marigold").join(src),
        &dir.join("marigold-lighting"),
    );
    dir
}

/// A small 8-bit photo; `seed` changes its colours.
fn photo(path: &Path, w: usize, h: usize, seed: usize) -> PathBuf {
    let img = Image::from_fn(w, h, 3, |x, y, c| {
        ((x * (c + 1) + y * 3 + seed * 7) % 23) as f32 / 22.0 * 0.8 + 0.1
    });
    write_png8(path, &img)
}

/// `pixl ARGS --quiet` with HOME at `home` (offline, no model folders but the ones given).
fn pixl(home: &Path, args: &[&str]) -> Run {
    run(cmd_in(home).args(args).arg("--quiet"))
}

/// Asserts exit 1 with exactly one line on stderr, holding every needle.
#[track_caller]
fn one_error(o: &Run, needles: &[&str]) {
    o.fails(needles);
    let lines: Vec<&str> = o.stderr.trim().lines().collect();
    assert_eq!(lines.len(), 1, "one error line expected: {}", o.stderr);
    assert!(lines[0].starts_with("error: "), "{}", o.stderr);
}

#[test]
fn like_relights_at_the_photos_size_and_keeps_the_targets_own_ct() {
    let t = common::tempdir();
    let home = t.path();
    let m = models(home, "lighting");
    let src = photo(&home.join("src.png"), 40, 30, 0);
    let tgt = photo(&home.join("tgt.png"), 40, 30, 3);
    let out = home.join("relit.png");
    let keep = home.join("steps");
    let o = pixl(
        home,
        &[
            "relight",
            s(&src),
            "--like",
            s(&tgt),
            "-o",
            s(&out),
            "--models",
            s(&m),
            "--like-res",
            "32",
            "--keep",
            s(&keep),
            "--json",
        ],
    )
    .ok();
    let v = o.json();
    assert_eq!((v["width"].as_u64(), v["height"].as_u64()), (Some(40), Some(30)));
    assert_eq!(v["like"]["target_width"], 40);
    assert_eq!(v["like"]["steps"], 1);
    assert_eq!(v["like"]["weights"]["licence"], "OpenRAIL++-M");
    assert_eq!(v["kept"].as_array().map(Vec::len), Some(3));
    let relit = pixl_core::io::read_rgb(&out).unwrap();
    assert_eq!((relit.width, relit.height), (40, 30));
    let sheet = pixl_core::io::read_image(&keep.join("CT_sheet.png")).unwrap();
    assert!(sheet.width > 40);
    assert!(keep.join("before_after.png").is_file());

    // The kept C_T is the target's own, as the training targets are made: `pixl estimate
    // lighting` of the target with the same resolution, steps and seed writes the same file.
    let ct = pixl_intrinsics::ct::read_ct(&keep.join("CT.exr")).unwrap();
    assert_eq!((ct.width(), ct.height()), (40, 30));
    let own = home.join("tgt.intrinsics.exr");
    pixl(
        home,
        &[
            "estimate",
            "lighting",
            s(&tgt),
            "-o",
            s(&own),
            "--models",
            s(&m),
            "--res",
            "32",
            "--steps",
            "1",
        ],
    )
    .ok();
    let own = pixl_intrinsics::ct::read_ct(&own).unwrap();
    assert_eq!(ct.to_chw(), own.to_chw(), "--like's C_T is not the target's own");
    // Joint p98 rescale: S and R in [0, 1] with the cap reached.
    let sr_max = ct
        .shading
        .data
        .iter()
        .chain(&ct.residual.data)
        .copied()
        .fold(0f32, f32::max);
    assert!((sr_max - 1.0).abs() < 1e-6, "{sr_max}");

    // The same C_T through --intrinsics gives the same relit image, bit for bit.
    let again = home.join("again.png");
    pixl(
        home,
        &[
            "relight",
            "--source",
            s(&src),
            "--intrinsics",
            s(&keep.join("CT.exr")),
            "-o",
            s(&again),
        ],
    )
    .ok();
    let again = pixl_core::io::read_rgb(&again).unwrap();
    assert!(again
        .data
        .iter()
        .zip(&relit.data)
        .all(|(a, b)| a.to_bits() == b.to_bits()));

    // Another target lights the photo differently.
    let other = photo(&home.join("other.png"), 40, 30, 11);
    let out2 = home.join("relit2.png");
    pixl(
        home,
        &[
            "relight",
            s(&src),
            "--like",
            s(&other),
            "-o",
            s(&out2),
            "--models",
            s(&m),
            "--like-res",
            "32",
        ],
    )
    .ok();
    let relit2 = pixl_core::io::read_rgb(&out2).unwrap();
    assert_ne!(relit.data, relit2.data, "two targets, one relit image");
}

#[test]
fn a_target_of_another_shape_is_stretched_to_the_photo_with_a_warning() {
    let t = common::tempdir();
    let home = t.path();
    let m = models(home, "lighting");
    let src = photo(&home.join("src.png"), 40, 30, 0);
    let wide = photo(&home.join("wide.png"), 64, 24, 5);
    let out = home.join("relit.png");
    let keep = home.join("k");
    // Without --quiet: the warning is on stderr.
    let o = run(cmd_in(home).args([
        "relight",
        s(&src),
        "--like",
        s(&wide),
        "-o",
        s(&out),
        "--models",
        s(&m),
        "--like-res",
        "32",
        "--keep",
        s(&keep),
    ]))
    .ok();
    assert!(
        o.stderr.contains("aspect ratios") && o.stderr.contains("same view"),
        "{}",
        o.stderr
    );
    let relit = pixl_core::io::read_rgb(&out).unwrap();
    assert_eq!((relit.width, relit.height), (40, 30));
    let ct = pixl_intrinsics::ct::read_ct(&keep.join("CT.exr")).unwrap();
    assert_eq!((ct.width(), ct.height()), (40, 30));
    // The same shape at another size: no warning.
    let big = photo(&home.join("big.png"), 80, 60, 5);
    let o = run(cmd_in(home).args([
        "relight",
        s(&src),
        "--like",
        s(&big),
        "-o",
        s(&home.join("r2.png")),
        "--models",
        s(&m),
        "--like-res",
        "32",
    ]))
    .ok();
    assert!(!o.stderr.contains("aspect ratios"), "{}", o.stderr);
}

#[test]
fn like_conflicts_with_the_other_ways_of_giving_the_lighting() {
    let t = common::tempdir();
    let home = t.path();
    let src = photo(&home.join("src.png"), 20, 20, 0);
    let tgt = photo(&home.join("tgt.png"), 20, 20, 1);
    let out = home.join("relit.png");
    let base = ["relight", s(&src), "--like", s(&tgt), "-o", s(&out)];
    for extra in [
        &["--preset", "warm-overhead-flash"][..],
        &["--light", "--type spot --from left"],
        &["--scene", "lights.toml"],
        &["--intrinsics", "ct.exr"],
        &["--depth", "depth.exr"],
        &["--spp", "4"],
    ] {
        let o = pixl(home, &[&base[..], extra].concat());
        assert_eq!(o.code(), Some(2), "{extra:?}: {}", o.stderr);
        assert!(
            o.stderr.contains("'--like <TARGET>' cannot be used with"),
            "{extra:?}: {}",
            o.stderr
        );
    }
    // The Marigold flags need --like.
    let o = pixl(
        home,
        &[
            "relight",
            s(&src),
            "--preset",
            "warm-overhead-flash",
            "-o",
            s(&out),
            "--like-res",
            "32",
        ],
    );
    assert_eq!(o.code(), Some(2), "{}", o.stderr);
    assert!(
        o.stderr.contains("cannot be used with '--like-res <PX>'"),
        "{}",
        o.stderr
    );
    let o = pixl(home, &["relight", s(&src), "-o", s(&out), "--like-steps", "2"]);
    assert_eq!(o.code(), Some(2), "{}", o.stderr);
    assert!(o.stderr.contains("--like <TARGET>"), "{}", o.stderr);
    assert!(!out.exists());
}

#[test]
fn bad_like_inputs_are_one_clear_error_each_and_nothing_is_written() {
    let t = common::tempdir();
    let home = t.path();
    let m = models(home, "lighting");
    let wrong = models(&home.join("wrong"), "appearance");
    let src = photo(&home.join("src.png"), 24, 20, 0);
    let tgt = photo(&home.join("tgt.png"), 24, 20, 1);
    let tiny = photo(&home.join("tiny.png"), 4, 4, 1);
    let junk = write_file(&home.join("junk.png"), b"not a png at all");
    let out = home.join("relit.png");
    let keep = home.join("keep");
    let like = |target: &Path, models: Option<&Path>, out: &Path| -> Run {
        let mut a = vec![
            "relight",
            s(&src),
            "--like",
            s(target),
            "-o",
            s(out),
            "--keep",
            s(&keep),
            "--like-res",
            "32",
        ];
        if let Some(m) = models {
            a.extend(["--models", s(m)]);
        }
        pixl(home, &a)
    };
    let nothing_written = |what: &str| {
        assert!(!out.exists(), "{what}: the output was written");
        assert!(!keep.exists(), "{what}: --keep's folder was made");
    };
    one_error(
        &like(&home.join("missing.png"), Some(&m), &out),
        &["--like", "missing.png", "not found"],
    );
    nothing_written("missing target");
    one_error(
        &like(&junk, Some(&m), &out),
        &["--like", "junk.png", "reading the target photo"],
    );
    nothing_written("unreadable target");
    one_error(&like(&tiny, Some(&m), &out), &["4x4", "at least 8x8"]);
    nothing_written("tiny target");
    // No weights on disk and downloads off (the tests' environment).
    one_error(
        &like(&tgt, None, &out),
        &["Marigold-IID-Lighting's weights", "marigold-lighting"],
    );
    nothing_written("no weights");
    // The Appearance checkpoint where the Lighting one is expected.
    one_error(&like(&tgt, Some(&wrong), &out), &["Appearance", "Lighting"]);
    nothing_written("wrong checkpoint");
    // The output may not be an input: neither the photo nor the target is overwritten.
    let before = std::fs::read(&tgt).unwrap();
    one_error(&like(&tgt, Some(&m), &tgt), &["tgt.png", "input"]);
    assert_eq!(std::fs::read(&tgt).unwrap(), before);
    nothing_written("output = target");
}
