//! Marigold-IID at the binary level on the tiny random checkpoints of `fixtures/marigold`:
//! `pixl estimate materials|lighting`, `pixl reconstruct --materials marigold`,
//! `pixl prepare-targets` (writes, resumes, feeds the training loader), and the bad inputs —
//! a folder that is not a Marigold checkpoint, the other IID variant, an unsupported scheduler —
//! each one clear error with nothing written. No test touches the network.
mod common;
use common::{cmd_in, copy_dir, run, write_image, write_png8, Run};
use pixl_core::Image;
use std::path::{Path, PathBuf};

fn fixture(name: &str) -> PathBuf {
    common::repo_path("fixtures/marigold").join(name)
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
    write_png8(path, &img);
}

/// `pixl estimate WHAT PHOTO -o OUT FLAGS --models MODELS` with HOME at `home`.
fn estimate(home: &Path, what: &str, photo: &Path, out: &Path, flags: &[&str], models: &Path) -> Run {
    run(cmd_in(home)
        .args(["estimate", what])
        .arg(photo)
        .arg("-o")
        .arg(out)
        .args(flags)
        .arg("--models")
        .arg(models))
}

#[test]
fn materials_writes_linear_and_srgb_albedo_and_scalar_maps() {
    let t = common::tempdir();
    let m = models(t.path(), "appearance", "marigold-appearance");
    let p = t.path().join("p.png");
    photo(&p, 37, 27, 0);
    let out = t.path().join("mat");
    let materials = |flags: &[&str]| estimate(t.path(), "materials", &p, &out, flags, &m);
    let v = materials(&["--res", "32", "--steps", "2", "--json"]).ok().json();
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
    let o = materials(&["--res", "32", "--steps", "2"]);
    assert!(!o.success() && o.stderr.contains("--force"), "{}", o.stderr);
}

#[test]
fn lighting_writes_a_ct_file_with_the_compose_rescale() {
    let t = common::tempdir();
    let m = models(t.path(), "lighting", "marigold-lighting");
    let p = t.path().join("p.png");
    photo(&p, 30, 20, 1);
    let out = t.path().join("p.intrinsics.exr");
    estimate(t.path(), "lighting", &p, &out, &["--res", "32"], &m).ok();
    let ct = pixl_intrinsics::ct::read_ct(&out).unwrap();
    assert_eq!((ct.width(), ct.height()), (30, 20));
    let [a, s, r] = ct.groups();
    assert!(a.data.iter().all(|v| (0.0..=1.0).contains(v)));
    // Joint p98 rescale: S and R in [0, 1], and about 2 % of their values at the cap.
    let sr: Vec<f32> = s.data.iter().chain(&r.data).copied().collect();
    assert!(sr.iter().all(|v| (0.0..=1.0).contains(v)));
    let max_sr = sr.iter().copied().fold(0f32, f32::max);
    assert!((max_sr - 1.0).abs() < 1e-6, "max of S, R after the rescale: {max_sr}");
    run(cmd_in(t.path())
        .args(["intrinsics", "preview"])
        .arg(&out)
        .arg("-o")
        .arg(t.path().join("preview.png")))
    .ok();
}

#[test]
fn bad_checkpoints_are_refused_and_nothing_is_written() {
    let t = common::tempdir();
    let p = t.path().join("p.png");
    photo(&p, 20, 20, 2);
    let out_dir = t.path().join("mat");
    let ct = t.path().join("ct.exr");
    // `pixl estimate WHAT` with `models` fails cleanly with `needles`, writing nothing.
    let refused = |what: &str, res: &str, models: &Path, needles: &[&str]| {
        let out = if what == "materials" { &out_dir } else { &ct };
        estimate(t.path(), what, &p, out, &["--res", res], models).fails(needles);
        assert!(!out.exists());
    };

    // The Lighting checkpoint where the Appearance one is expected.
    let m = models(&t.path().join("a"), "lighting", "marigold-appearance");
    refused("materials", "32", &m, &["Lighting", "Appearance"]);

    // And the other way round.
    let m = models(&t.path().join("b"), "appearance", "marigold-lighting");
    refused("lighting", "32", &m, &["Appearance", "Lighting"]);

    // A folder with the right file names that is another pipeline.
    let m = models(&t.path().join("c"), "lighting", "marigold-lighting");
    let idx = m.join("marigold-lighting/model_index.json");
    let text = std::fs::read_to_string(&idx).unwrap();
    std::fs::write(
        &idx,
        text.replace("MarigoldIntrinsicsPipeline", "MarigoldDepthPipeline"),
    )
    .unwrap();
    refused("lighting", "32", &m, &["not a Marigold intrinsics"]);

    // A scheduler predicting something this port does not implement.
    let m = models(&t.path().join("d"), "lighting", "marigold-lighting");
    let sc = m.join("marigold-lighting/scheduler/scheduler_config.json");
    let text = std::fs::read_to_string(&sc).unwrap();
    assert!(text.contains("v_prediction"));
    std::fs::write(&sc, text.replace("v_prediction", "flow_prediction")).unwrap();
    refused("lighting", "32", &m, &["prediction_type", "flow_prediction"]);

    // A processing resolution the VAE cannot take.
    let m = models(&t.path().join("e"), "lighting", "marigold-lighting");
    refused("lighting", "30", &m, &["multiple of 8"]);
}

#[test]
fn reconstruct_textures_the_scene_with_estimated_materials() {
    let t = common::tempdir();
    let m = models(t.path(), "appearance", "marigold-appearance");
    let p = t.path().join("p.png");
    photo(&p, 24, 16, 3);
    let d = common::write_depth(&t.path().join("d.exr"), 24, 16, |x, _| 2.0 + x as f32 * 0.01);
    let out = t.path().join("scene");
    let v = run(cmd_in(t.path())
        .arg("reconstruct")
        .arg("--image")
        .arg(&p)
        .arg("--depth")
        .arg(&d)
        .args(["--materials", "marigold", "--materials-res", "32", "--json", "--models"])
        .arg(&m)
        .arg("-o")
        .arg(&out))
    .ok()
    .json();
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
            let img = Image::from_fn(20, 14, 3, |x, y, c| ((x + y + c + 3 * l + k) % 9) as f32 / 10.0 + 0.05);
            v.push(write_image(&d.join(format!("dir_{l}_mip2.jpg")), &img));
        }
    }
    v
}

#[test]
fn prepare_targets_writes_resumes_and_feeds_the_loader() {
    let t = common::tempdir();
    let m = models(t.path(), "lighting", "marigold-lighting");
    let root = t.path().join("miiw");
    let images = miiw(&root);
    let spec = format!("miiw:{}", root.display());
    let prep = |extra: &[&str]| {
        run(cmd_in(t.path())
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
            .arg(&m))
        .ok()
        .json()
    };
    // When each target was last written.
    let written = || -> Vec<_> {
        images
            .iter()
            .map(|p| {
                std::fs::metadata(pixl_data::ct_cache_path(p))
                    .unwrap()
                    .modified()
                    .unwrap()
            })
            .collect()
    };
    // A limited first run, then the rest, then nothing to do.
    let v = prep(&["--limit", "3"]);
    assert_eq!(v["written"].as_array().unwrap().len(), 3);
    assert_eq!(v["left"], 1);
    let v = prep(&[]);
    assert_eq!(v["written"].as_array().unwrap().len(), 1);
    assert_eq!(v["already_cached"], 3);
    let before = written();
    let v = prep(&[]);
    assert_eq!(v["written"].as_array().unwrap().len(), 0);
    assert_eq!(v["already_cached"], 4);
    assert_eq!(before, written(), "a second run rewrote finished targets");
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

/// `--uncertainty` with an ensemble of 3 writes one map per target beside the C_T, at the photo's
/// size, non-negative and not all zero (the members differ by their noise); without an ensemble it
/// is refused before any output.
#[test]
fn uncertainty_of_an_ensemble_is_written_beside_the_output() {
    let t = common::tempdir();
    let m = models(t.path(), "lighting", "marigold-lighting");
    let p = t.path().join("p.png");
    photo(&p, 30, 20, 1);
    let out = t.path().join("p.intrinsics.exr");
    let flags = ["--res", "32", "--steps", "1", "--ensemble", "3", "--uncertainty"];
    estimate(t.path(), "lighting", &p, &out, &flags, &m).ok();
    for target in ["albedo", "shading", "residual"] {
        let f = t.path().join(format!("p.intrinsics.uncertainty-{target}.exr"));
        let u = pixl_core::io::read_image(&f).unwrap();
        assert_eq!((u.width, u.height), (30, 20), "{target}");
        assert!(
            u.data.iter().all(|v| *v >= 0.0) && u.data.iter().any(|v| *v > 0.0),
            "{target}"
        );
    }
    let out2 = t.path().join("q.exr");
    estimate(t.path(), "lighting", &p, &out2, &["--res", "32", "--uncertainty"], &m).fails(&["ensemble"]);
    assert!(!out2.exists());
}
