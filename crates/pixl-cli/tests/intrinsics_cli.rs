//! `pixl compose`, `pixl intrinsics preview`, `pixl augment`: the real binary on small inputs.
mod common;
use common::{pixl, s, write_ct, Run};
use pixl_core::exrio::{write_exr_channels, ExrChannels};
use pixl_core::io::read_image;
use pixl_intrinsics::compose::{compose, ComposeOptions, PassSet};
use pixl_intrinsics::ct::read_ct;
use std::path::{Path, PathBuf};

/// Asserts the run failed with exit 1 and that its output (stdout and stderr) holds every needle.
#[track_caller]
fn refused(o: &Run, needles: &[&str]) {
    assert_eq!(o.code(), Some(1), "{}", o.text());
    says(o, needles);
}

/// Asserts that the output (stdout and stderr) holds every needle.
#[track_caller]
fn says(o: &Run, needles: &[&str]) {
    let text = o.text();
    assert!(needles.iter().all(|n| text.contains(n)), "{text}");
}

/// A Blender-style multilayer file: `<layer>.<Long Pass Name>.<R|G|B>` for each layer.
fn passes_file(dir: &Path, name: &str, layers: &[&str], passes: &[&str], nan_at: Option<usize>) -> PathBuf {
    let (w, h) = (6, 4);
    let mut ch = ExrChannels::new(w, h);
    for l in layers {
        for (k, p) in passes.iter().enumerate() {
            for (c, comp) in ["R", "G", "B"].iter().enumerate() {
                let mut data: Vec<f32> = (0..w * h)
                    .map(|i| 0.1 + 0.05 * ((i + k + c) % 7) as f32 * (k + 1) as f32)
                    .collect();
                if let (Some(i), 1, 0) = (nan_at, k, c) {
                    data[i] = f32::NAN;
                }
                ch.push(format!("{l}.{p}.{comp}"), data).unwrap();
            }
        }
    }
    let path = dir.join(name);
    write_exr_channels(&path, &ch).unwrap();
    path
}

const ALL_LONG: &[&str] = &[
    "Diffuse Color",
    "Diffuse Direct",
    "Diffuse Indirect",
    "Glossy Color",
    "Glossy Direct",
    "Glossy Indirect",
    "Emission",
];

#[test]
fn compose_writes_what_the_library_computes() {
    let dir = common::tempdir();
    let input = passes_file(dir.path(), "render.exr", &["ViewLayer"], ALL_LONG, None);
    let out = dir.path().join("ct.exr");
    let o = pixl(&["compose", s(&input), "-o", s(&out), "--json"]).ok();
    let json = o.json();
    let want = compose(&PassSet::read(&input, None).unwrap(), &ComposeOptions::default()).unwrap();
    assert_eq!(read_ct(&out).unwrap(), want.ct);
    assert!((json["tau"].as_f64().unwrap() - want.tau.unwrap() as f64).abs() < 1e-6);
    assert_eq!(json["missing_optional"].as_array().unwrap().len(), 5);
    assert!(o.stderr.contains("TransCol"), "one warning lists the missing passes");

    let raw = dir.path().join("raw.exr");
    pixl(&["compose", s(&input), "-o", s(&raw), "--no-rescale", "-q"]).ok();
    // The rescaled file is the HDR file, clipped at τ and divided by it (App. B).
    let (hdr, scaled, tau) = (read_ct(&raw).unwrap(), read_ct(&out).unwrap(), want.tau.unwrap());
    for (h, s) in hdr.to_chw().iter().zip(scaled.to_chw()).skip(9 * 6 * 4 / 3) {
        assert!((h.clamp(0.0, tau) / tau - s).abs() < 1e-6, "{h} -> {s}, tau {tau}");
    }
}

#[test]
fn compose_refuses_bad_inputs_with_clear_messages() {
    let dir = common::tempdir();
    let out = dir.path().join("ct.exr");
    let compose = |input: &Path, extra: &[&str]| {
        let mut args = vec!["compose", s(input), "-o", s(&out)];
        args.extend_from_slice(extra);
        pixl(&args)
    };

    let missing = passes_file(
        dir.path(),
        "missing.exr",
        &["ViewLayer"],
        &["Diffuse Color", "Diffuse Direct"],
        None,
    );
    refused(&compose(&missing, &[]), &["DiffInd", "missing.exr"]);
    assert!(!out.exists());

    let nan = passes_file(dir.path(), "nan.exr", &["ViewLayer"], ALL_LONG, Some(9));
    // Channel index 9 of a 6-wide image: x=3, y=1; pass index 1 = DiffDir, channel R.
    refused(&compose(&nan, &[]), &["1 non-finite", "DiffDir at x=3, y=1, channel R"]);
    let json = compose(&nan, &["--sanitize", "--json"]).ok().json();
    assert_eq!(json["sanitized"], 1);

    let two = passes_file(dir.path(), "two.exr", &["Front", "Back"], ALL_LONG, None);
    refused(&compose(&two, &[]), &["Back, Front", "--layer"]);
    compose(&two, &["--layer", "Back"]).ok();

    let o = pixl(&["compose", s(&two), "-o", s(&dir.path().join("ct.png"))]);
    says(&o, &[".exr"]);
    says(&compose(&dir.path().join("none.exr"), &[]), &["not found"]);
}

#[test]
fn compose_reads_the_real_cycles_render() {
    let f = common::repo_path("fixtures/cycles/scene256_multipart.exr");
    if !f.exists() {
        println!("skipping: {} not found", f.display());
        return;
    }
    let dir = common::tempdir();
    let out = dir.path().join("ct.exr");
    pixl(&["compose", s(&f), "-o", s(&out), "--json"]).ok();
    let ct = read_ct(&out).unwrap();
    assert_eq!((ct.width(), ct.height()), (256, 256));
    assert!(ct.to_chw().iter().all(|v| (0.0..=1.0).contains(v)));
}

fn small_ct(dir: &Path) -> PathBuf {
    let (w, h) = (10, 6);
    let img = |k: f32| pixl_core::Image::from_fn(w, h, 3, |x, y, c| ((x + y + c) as f32 * 0.05 * k).min(1.0));
    write_ct(&dir.join("ct.exr"), img(1.0), img(0.7), img(0.3))
}

#[test]
fn preview_draws_four_panels() {
    let dir = common::tempdir();
    let ct = small_ct(dir.path());
    let png = dir.path().join("sheet.png");
    pixl(&["intrinsics", "preview", s(&ct), "-o", s(&png)]).ok();
    let img = read_image(&png).unwrap();
    assert_eq!((img.width, img.height), (4 * 10 + 3 * 4, 6));

    // A file without C_T channels: the error lists what is missing.
    let not_ct = common::write_image(&dir.path().join("rgb.exr"), &pixl_core::Image::new(4, 4, 3));
    refused(
        &pixl(&["intrinsics", "preview", s(&not_ct), "-o", s(&png)]),
        &["albedo.R", "rgb.exr"],
    );
}

#[test]
fn augment_sheet_is_deterministic_per_seed() {
    let dir = common::tempdir();
    let ct = small_ct(dir.path());
    let sheet = |seed: &str, name: &str| {
        let png = dir.path().join(name);
        pixl(&["augment", s(&ct), "--seed", seed, "--n", "3", "-o", s(&png), "--always"]).ok();
        std::fs::read(png).unwrap()
    };
    let a = sheet("5", "a.png");
    assert_eq!(a, sheet("5", "b.png"));
    assert_ne!(a, sheet("6", "c.png"));
    let img = read_image(&dir.path().join("a.png")).unwrap();
    assert_eq!((img.width, img.height), (4 * 10 + 3 * 4, 4 * 6 + 3 * 4));

    let cfg = common::write_file(&dir.path().join("aug.toml"), "p_apply = 2.0\n");
    refused(
        &pixl(&["augment", s(&ct), "--config", s(&cfg), "-o", "x.png"]),
        &["p_apply", "aug.toml"],
    );
}
