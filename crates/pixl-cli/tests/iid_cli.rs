//! Marigold-IID at the binary level on the tiny random checkpoints of `fixtures/marigold`:
//! `pixl estimate materials|lighting`, `pixl reconstruct --materials marigold`,
//! `pixl prepare-targets` (writes, resumes, feeds the training loader), and the bad inputs —
//! a folder that is not a Marigold checkpoint, the other IID variant, an unsupported scheduler —
//! each one clear error with nothing written. No test touches the network.
mod common;
use common::{copy_dir, pixl, run};
use pixl_core::Image;
use std::path::{Path, PathBuf};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures/marigold")
        .join(name)
}

/// A models folder with the fixture `src` (appearance | lighting) installed as `as_name`.
fn models(root: &Path, src: &str, as_name: &str) -> PathBuf {
    let dir = root.join("models");
    copy_dir(&fixture(src), &dir.join(as_name));
    dir
}

/// A small smooth test photo.
fn photo(path: &Path, w: usize, h: usize, seed: usize) {
    let img = Image::from_fn(w, h, 3, |x, y, c| {
        ((x * (c + 1) + y * 3 + seed * 7) % 23) as f32 / 22.0 * 0.8 + 0.1
    });
    pixl_core::io::write_png(path, &img, pixl_core::io::PngDepth::Eight).unwrap();
}

#[test]
fn materials_writes_linear_and_srgb_albedo_and_scalar_maps() {
    let t = tempfile::tempdir().unwrap();
    let m = models(t.path(), "appearance", "marigold-appearance");
    let p = t.path().join("p.png");
    photo(&p, 37, 27, 0);
    let out = t.path().join("mat");
    let (o, stdout, err) = run(pixl(t.path())
        .args(["estimate", "materials"])
        .arg(&p)
        .arg("-o")
        .arg(&out)
        .args(["--res", "32", "--steps", "2", "--json", "--models"])
        .arg(&m));
    assert!(o.status.success(), "{err}");
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(v["steps"], 2);
    let lin = pixl_core::io::read_image(&out.join("albedo.exr")).unwrap();
    let png = pixl_core::io::read_image(&out.join("albedo.png")).unwrap();
    assert_eq!((lin.width, lin.height, lin.channels), (37, 27, 3));
    // The EXR is the PNG's sRGB values decoded (up to the PNG's 8-bit rounding).
    let worst = lin
        .data
        .iter()
        .zip(&png.data)
        .map(|(&l, &s)| (pixl_core::image::linear_to_srgb(l) - s).abs())
        .fold(0f32, f32::max);
    assert!(worst <= 0.5 / 255.0 + 1e-4, "albedo.exr vs albedo.png: {worst}");
    for f in ["roughness.exr", "metallic.exr"] {
        let r = pixl_core::io::read_image(&out.join(f)).unwrap();
        assert_eq!((r.width, r.height, r.channels), (37, 27, 1), "{f}");
        assert!(r.data.iter().all(|v| (0.0..=1.0).contains(v)), "{f} in [0, 1]");
    }
    // Same seed, same maps; another folder needs no --force, the same one does.
    let (o, _, err) = run(pixl(t.path())
        .args(["estimate", "materials"])
        .arg(&p)
        .arg("-o")
        .arg(&out)
        .args(["--res", "32", "--steps", "2", "--models"])
        .arg(&m));
    assert!(!o.status.success() && err.contains("--force"), "{err}");
}

#[test]
fn lighting_writes_a_ct_file_with_the_compose_rescale() {
    let t = tempfile::tempdir().unwrap();
    let m = models(t.path(), "lighting", "marigold-lighting");
    let p = t.path().join("p.png");
    photo(&p, 30, 20, 1);
    let out = t.path().join("p.intrinsics.exr");
    let (o, _, err) = run(pixl(t.path())
        .args(["estimate", "lighting"])
        .arg(&p)
        .arg("-o")
        .arg(&out)
        .args(["--res", "32", "--models"])
        .arg(&m));
    assert!(o.status.success(), "{err}");
    let ct = pixl_intrinsics::ct::read_ct(&out).unwrap();
    assert_eq!((ct.width(), ct.height()), (30, 20));
    let [a, s, r] = ct.groups();
    assert!(a.data.iter().all(|v| (0.0..=1.0).contains(v)));
    // Joint p98 rescale: S and R in [0, 1], and about 2 % of their values at the cap.
    let sr: Vec<f32> = s.data.iter().chain(&r.data).copied().collect();
    assert!(sr.iter().all(|v| (0.0..=1.0).contains(v)));
    let max_sr = sr.iter().copied().fold(0f32, f32::max);
    assert!((max_sr - 1.0).abs() < 1e-6, "max of S, R after the rescale: {max_sr}");
    let (o, _, err) = run(pixl(t.path())
        .args(["intrinsics", "preview"])
        .arg(&out)
        .arg("-o")
        .arg(t.path().join("preview.png")));
    assert!(o.status.success(), "{err}");
}

/// Runs `args` expecting failure; returns stderr.
fn fails(t: &Path, args: &[&str], models: &Path) -> String {
    let (o, _, err) = run(pixl(t).args(args).arg("--models").arg(models));
    assert!(!o.status.success(), "expected a failure: {args:?}");
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    err
}

#[test]
fn bad_checkpoints_are_refused_and_nothing_is_written() {
    let t = tempfile::tempdir().unwrap();
    let p = t.path().join("p.png");
    photo(&p, 20, 20, 2);
    let ps = p.to_str().unwrap();
    let out_dir = t.path().join("mat");
    let od = out_dir.to_str().unwrap();
    let ct = t.path().join("ct.exr");
    let cs = ct.to_str().unwrap();

    // The Lighting checkpoint where the Appearance one is expected.
    let m = models(&t.path().join("a"), "lighting", "marigold-appearance");
    let err = fails(t.path(), &["estimate", "materials", ps, "-o", od, "--res", "32"], &m);
    assert!(err.contains("Lighting") && err.contains("Appearance"), "{err}");
    assert!(!out_dir.exists());

    // And the other way round.
    let m = models(&t.path().join("b"), "appearance", "marigold-lighting");
    let err = fails(t.path(), &["estimate", "lighting", ps, "-o", cs, "--res", "32"], &m);
    assert!(err.contains("Appearance") && err.contains("Lighting"), "{err}");
    assert!(!ct.exists());

    // A folder with the right file names that is another pipeline.
    let m = models(&t.path().join("c"), "lighting", "marigold-lighting");
    let idx = m.join("marigold-lighting/model_index.json");
    let text = std::fs::read_to_string(&idx).unwrap();
    std::fs::write(
        &idx,
        text.replace("MarigoldIntrinsicsPipeline", "MarigoldDepthPipeline"),
    )
    .unwrap();
    let err = fails(t.path(), &["estimate", "lighting", ps, "-o", cs, "--res", "32"], &m);
    assert!(err.contains("not a Marigold intrinsics"), "{err}");
    assert!(!ct.exists());

    // A scheduler predicting something this port does not implement.
    let m = models(&t.path().join("d"), "lighting", "marigold-lighting");
    let sc = m.join("marigold-lighting/scheduler/scheduler_config.json");
    let text = std::fs::read_to_string(&sc).unwrap();
    assert!(text.contains("v_prediction"));
    std::fs::write(&sc, text.replace("v_prediction", "flow_prediction")).unwrap();
    let err = fails(t.path(), &["estimate", "lighting", ps, "-o", cs, "--res", "32"], &m);
    assert!(
        err.contains("prediction_type") && err.contains("flow_prediction"),
        "{err}"
    );
    assert!(!ct.exists());

    // A processing resolution the VAE cannot take.
    let m = models(&t.path().join("e"), "lighting", "marigold-lighting");
    let err = fails(t.path(), &["estimate", "lighting", ps, "-o", cs, "--res", "30"], &m);
    assert!(err.contains("multiple of 8"), "{err}");
    assert!(!ct.exists());
}

#[test]
fn reconstruct_textures_the_scene_with_estimated_materials() {
    let t = tempfile::tempdir().unwrap();
    let m = models(t.path(), "appearance", "marigold-appearance");
    let p = t.path().join("p.png");
    photo(&p, 24, 16, 3);
    let depth = Image::from_fn(24, 16, 1, |x, _, _| 2.0 + x as f32 * 0.01);
    let d = t.path().join("d.exr");
    pixl_core::io::write_image(&d, &depth).unwrap();
    let out = t.path().join("scene");
    let (o, stdout, err) = run(pixl(t.path())
        .arg("reconstruct")
        .arg("--image")
        .arg(&p)
        .arg("--depth")
        .arg(&d)
        .args(["--materials", "marigold", "--materials-res", "32", "--json", "--models"])
        .arg(&m)
        .arg("-o")
        .arg(&out));
    assert!(o.status.success(), "{err}");
    let v: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(v["materials"], "marigold-appearance");
    for f in ["albedo.png", "roughness.png", "metallic.png"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    let scene = std::fs::read_to_string(out.join("scene.toml")).unwrap();
    assert!(
        scene.contains("albedo.png") && scene.contains("roughness.png"),
        "{scene}"
    );
}

/// A MIIW-like tree: two scenes (one in the test split) with two lights each.
fn miiw(root: &Path) -> Vec<PathBuf> {
    let mut v = Vec::new();
    for (k, scene) in ["kitchen", "everett_hall"].iter().enumerate() {
        let d = root.join(scene);
        std::fs::create_dir_all(&d).unwrap();
        for l in 0..2 {
            let p = d.join(format!("dir_{l}_mip2.jpg"));
            let img = Image::from_fn(20, 14, 3, |x, y, c| ((x + y + c + 3 * l + k) % 9) as f32 / 10.0 + 0.05);
            pixl_core::io::write_image(&p, &img).unwrap();
            v.push(p);
        }
    }
    v
}

#[test]
fn prepare_targets_writes_resumes_and_feeds_the_loader() {
    let t = tempfile::tempdir().unwrap();
    let m = models(t.path(), "lighting", "marigold-lighting");
    let root = t.path().join("miiw");
    let images = miiw(&root);
    let spec = format!("miiw:{}", root.display());
    let prep = |extra: &[&str]| {
        let (o, stdout, err) = run(pixl(t.path())
            .args([
                "prepare-targets",
                "--dataset",
                &spec,
                "--res",
                "32",
                "--steps",
                "1",
                "--json",
            ])
            .args(extra)
            .arg("--models")
            .arg(&m));
        assert!(o.status.success(), "{err}");
        serde_json::from_str::<serde_json::Value>(&stdout).unwrap()
    };
    // A limited first run, then the rest, then nothing to do.
    let v = prep(&["--limit", "3"]);
    assert_eq!(v["written"].as_array().unwrap().len(), 3);
    assert_eq!(v["left"], 1);
    let v = prep(&[]);
    assert_eq!(v["written"].as_array().unwrap().len(), 1);
    assert_eq!(v["already_cached"], 3);
    let before: Vec<_> = images
        .iter()
        .map(|p| {
            std::fs::metadata(pixl_data::ct_cache_path(p))
                .unwrap()
                .modified()
                .unwrap()
        })
        .collect();
    let v = prep(&[]);
    assert_eq!(v["written"].as_array().unwrap().len(), 0);
    assert_eq!(v["already_cached"], 4);
    let after: Vec<_> = images
        .iter()
        .map(|p| {
            std::fs::metadata(pixl_data::ct_cache_path(p))
                .unwrap()
                .modified()
                .unwrap()
        })
        .collect();
    assert_eq!(before, after, "a second run rewrote finished targets");
    // The training loader reads them, for both splits.
    for split in [pixl_data::Split::Train, pixl_data::Split::Test] {
        let ds = pixl_data::open(&spec, split).unwrap();
        for scene in ds.scenes() {
            for e in &scene.images {
                let ct = pixl_data::load_intrinsics(e).unwrap();
                assert_eq!((ct.width(), ct.height()), (20, 14));
            }
        }
    }
}
