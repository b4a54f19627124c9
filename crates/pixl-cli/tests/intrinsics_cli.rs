//! `pixl compose`, `pixl intrinsics preview`, `pixl augment`: the real binary on small inputs.
use pixl_core::exrio::{write_exr_channels, ExrChannels};
use pixl_core::io::read_image;
use pixl_intrinsics::compose::{compose, ComposeOptions, PassSet};
use pixl_intrinsics::ct::{read_ct, write_ct, Ct};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn pixl(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_pixl"))
        .args(args)
        .output()
        .expect("run pixl")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
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
    let dir = tempfile::tempdir().unwrap();
    let input = passes_file(dir.path(), "render.exr", &["ViewLayer"], ALL_LONG, None);
    let out = dir.path().join("ct.exr");
    let o = pixl(&[
        "compose",
        input.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let want = compose(&PassSet::read(&input, None).unwrap(), &ComposeOptions::default()).unwrap();
    assert_eq!(read_ct(&out).unwrap(), want.ct);
    assert!((json["tau"].as_f64().unwrap() - want.tau.unwrap() as f64).abs() < 1e-6);
    assert_eq!(json["missing_optional"].as_array().unwrap().len(), 5);
    assert!(
        String::from_utf8_lossy(&o.stderr).contains("TransCol"),
        "one warning lists the missing passes"
    );

    let raw = dir.path().join("raw.exr");
    let o = pixl(&[
        "compose",
        input.to_str().unwrap(),
        "-o",
        raw.to_str().unwrap(),
        "--no-rescale",
        "-q",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    // The rescaled file is the HDR file, clipped at τ and divided by it (App. B).
    let (hdr, scaled, tau) = (read_ct(&raw).unwrap(), read_ct(&out).unwrap(), want.tau.unwrap());
    for (h, s) in hdr.to_chw().iter().zip(scaled.to_chw()).skip(9 * 6 * 4 / 3) {
        assert!((h.clamp(0.0, tau) / tau - s).abs() < 1e-6, "{h} -> {s}, tau {tau}");
    }
}

#[test]
fn compose_refuses_bad_inputs_with_clear_messages() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ct.exr");
    let o_str = out.to_str().unwrap();

    let missing = passes_file(
        dir.path(),
        "missing.exr",
        &["ViewLayer"],
        &["Diffuse Color", "Diffuse Direct"],
        None,
    );
    let o = pixl(&["compose", missing.to_str().unwrap(), "-o", o_str]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o).contains("DiffInd") && text(&o).contains("missing.exr"),
        "{}",
        text(&o)
    );
    assert!(!out.exists());

    let nan = passes_file(dir.path(), "nan.exr", &["ViewLayer"], ALL_LONG, Some(9));
    let o = pixl(&["compose", nan.to_str().unwrap(), "-o", o_str]);
    assert_eq!(o.status.code(), Some(1));
    // Channel index 9 of a 6-wide image: x=3, y=1; pass index 1 = DiffDir, channel R.
    assert!(
        text(&o).contains("1 non-finite") && text(&o).contains("DiffDir at x=3, y=1, channel R"),
        "{}",
        text(&o)
    );
    let o = pixl(&["compose", nan.to_str().unwrap(), "-o", o_str, "--sanitize", "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let json: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(json["sanitized"], 1);

    let two = passes_file(dir.path(), "two.exr", &["Front", "Back"], ALL_LONG, None);
    let o = pixl(&["compose", two.to_str().unwrap(), "-o", o_str]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o).contains("Back, Front") && text(&o).contains("--layer"),
        "{}",
        text(&o)
    );
    let o = pixl(&["compose", two.to_str().unwrap(), "-o", o_str, "--layer", "Back"]);
    assert!(o.status.success(), "{}", text(&o));

    let o = pixl(&[
        "compose",
        two.to_str().unwrap(),
        "-o",
        dir.path().join("ct.png").to_str().unwrap(),
    ]);
    assert!(text(&o).contains(".exr"), "{}", text(&o));
    let o = pixl(&["compose", dir.path().join("none.exr").to_str().unwrap(), "-o", o_str]);
    assert!(text(&o).contains("not found"), "{}", text(&o));
}

#[test]
fn compose_reads_the_real_cycles_render() {
    let f = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/cycles/scene256_multipart.exr");
    if !f.exists() {
        println!("skipping: {} not found", f.display());
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ct.exr");
    let o = pixl(&["compose", f.to_str().unwrap(), "-o", out.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", text(&o));
    let ct = read_ct(&out).unwrap();
    assert_eq!((ct.width(), ct.height()), (256, 256));
    assert!(ct.to_chw().iter().all(|v| (0.0..=1.0).contains(v)));
}

fn small_ct(dir: &Path) -> PathBuf {
    let (w, h) = (10, 6);
    let img = |k: f32| pixl_core::Image::from_fn(w, h, 3, |x, y, c| ((x + y + c) as f32 * 0.05 * k).min(1.0));
    let ct = Ct::new(img(1.0), img(0.7), img(0.3)).unwrap();
    let p = dir.join("ct.exr");
    write_ct(&p, &ct).unwrap();
    p
}

#[test]
fn preview_draws_four_panels() {
    let dir = tempfile::tempdir().unwrap();
    let ct = small_ct(dir.path());
    let png = dir.path().join("sheet.png");
    let o = pixl(&[
        "intrinsics",
        "preview",
        ct.to_str().unwrap(),
        "-o",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let img = read_image(&png).unwrap();
    assert_eq!((img.width, img.height), (4 * 10 + 3 * 4, 6));

    // A file without C_T channels: the error lists what is missing.
    let not_ct = dir.path().join("rgb.exr");
    pixl_core::io::write_image(&not_ct, &pixl_core::Image::new(4, 4, 3)).unwrap();
    let o = pixl(&[
        "intrinsics",
        "preview",
        not_ct.to_str().unwrap(),
        "-o",
        png.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o).contains("albedo.R") && text(&o).contains("rgb.exr"),
        "{}",
        text(&o)
    );
}

#[test]
fn augment_sheet_is_deterministic_per_seed() {
    let dir = tempfile::tempdir().unwrap();
    let ct = small_ct(dir.path());
    let sheet = |seed: &str, name: &str| {
        let png = dir.path().join(name);
        let o = pixl(&[
            "augment",
            ct.to_str().unwrap(),
            "--seed",
            seed,
            "--n",
            "3",
            "-o",
            png.to_str().unwrap(),
            "--always",
        ]);
        assert!(o.status.success(), "{}", text(&o));
        std::fs::read(png).unwrap()
    };
    let a = sheet("5", "a.png");
    assert_eq!(a, sheet("5", "b.png"));
    assert_ne!(a, sheet("6", "c.png"));
    let img = read_image(&dir.path().join("a.png")).unwrap();
    assert_eq!((img.width, img.height), (4 * 10 + 3 * 4, 4 * 6 + 3 * 4));

    let cfg = dir.path().join("aug.toml");
    std::fs::write(&cfg, "p_apply = 2.0\n").unwrap();
    let o = pixl(&[
        "augment",
        ct.to_str().unwrap(),
        "--config",
        cfg.to_str().unwrap(),
        "-o",
        "x.png",
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        text(&o).contains("p_apply") && text(&o).contains("aug.toml"),
        "{}",
        text(&o)
    );
}
