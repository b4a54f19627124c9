//! `pixl synth` and `pixl train` end to end on the real binary: a tiny synthetic set, a few
//! training steps (L1 only), resume, and the refusal to start without VGG weights.
mod common;
use common::{pixl, s, synth_args, write_file, Run};
use std::path::{Path, PathBuf};

fn config(dir: &Path, steps: u64, perceptual: f64) -> PathBuf {
    let text = format!(
        "[model]\npreset = \"tiny\"\n[data]\ndataset = \"synth:{data}\"\nsplit = \"train\"\n[data.sampler]\nlong_side = 32\n\
         [optim]\nbatch_size = 1\n[optim.schedule]\npeak_lr = 1e-3\nwarmup_steps = 1\ntotal_steps = 10\n\
         [loss]\nperceptual_weight = {perceptual}\n[run]\nout_dir = \"{out}\"\nsteps = {steps}\ncheckpoint_every = 2\nsample_every = 2\nlog_every = 1\n",
        data = dir.join("synth").display(),
        out = dir.join("run").display()
    );
    write_file(&dir.join(format!("train-{steps}-{perceptual}.toml")), text)
}

/// `pixl -q train --config CONFIG` then `extra`.
fn train(config: &Path, extra: &[&str]) -> Run {
    pixl(&[&["-q", "train", "--config", s(config)][..], extra].concat())
}

/// `pixl -q eval --dataset synth:ROOT --runs 0 --out OUT` then `extra`.
fn eval_synth(root: &Path, out: &Path, extra: &[&str]) -> Run {
    let data = format!("synth:{}", root.display());
    pixl(
        &[
            &["-q", "eval", "--dataset", &data, "--runs", "0", "--out", s(out)][..],
            extra,
        ]
        .concat(),
    )
}

#[test]
fn synth_then_train_then_resume() {
    let dir = common::tempdir();
    let synth = dir.path().join("synth");
    pixl(&synth_args(s(&synth), "32", "2", &["-q"])).ok();
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(synth.join("scenes.json")).unwrap()).unwrap();
    assert_eq!(manifest["scenes"].as_array().unwrap().len(), 2);
    assert_eq!(manifest["scenes"][1]["split"], "test");
    for f in [
        "scene0000/light_0.png",
        "scene0000/light_1.intrinsics.exr",
        "scene0001/light_1.png",
    ] {
        assert!(synth.join(f).is_file(), "{f}");
    }
    // the exact C_T is a valid C_T file of the image's size
    let ct = pixl_intrinsics::ct::read_ct(&synth.join("scene0000/light_0.intrinsics.exr")).unwrap();
    assert_eq!((ct.width(), ct.height()), (32, 32));

    train(&config(dir.path(), 2, 0.0), &[]).ok();
    let run = dir.path().join("run");
    assert!(run.join("model.safetensors").is_file() && run.join("train-state.safetensors").is_file());
    assert!(run.join("samples/step_0000002.png").is_file());
    // a second fresh start into the same directory is refused; --resume continues
    let again = train(&config(dir.path(), 4, 0.0), &[]);
    assert!(!again.success());
    assert!(again.stderr.contains("--resume"));
    train(&config(dir.path(), 4, 0.0), &["--resume"]).ok();
    let log = std::fs::read_to_string(run.join("log.jsonl")).unwrap();
    let steps: Vec<u64> = log
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()?["step"].as_u64())
        .collect();
    assert_eq!(steps, [0, 1, 2, 2, 3, 4], "start events then one line per step:\n{log}");
    // Resuming with a changed optimiser setting works but warns that it is no longer bit-exact.
    let changed = std::fs::read_to_string(config(dir.path(), 5, 0.0))
        .unwrap()
        .replace("peak_lr = 1e-3", "peak_lr = 5e-4");
    let changed_path = write_file(&dir.path().join("changed.toml"), changed);
    let err = pixl(&["train", "--resume", "--config", s(&changed_path)]).ok().stderr;
    assert!(
        err.contains("no longer bit-exact") && err.contains("optim.schedule.peak_lr: 0.001 → 0.0005"),
        "{err}"
    );
    let (_, _model) = pixl_model::load(
        &run.join("model.safetensors"),
        &candle_core::Device::Cpu,
        candle_core::DType::F32,
    )
    .unwrap();
}

#[test]
fn perceptual_loss_without_vgg_refuses_to_start() {
    let dir = common::tempdir();
    let out = train(&config(dir.path(), 2, 0.2), &[]);
    assert!(!out.success());
    let err = &out.stderr;
    assert!(err.contains("--perceptual-weight 0") && err.contains("vgg"), "{err}");
}

/// `pixl synth --coarse` writes, for every scene, the inference-setting C_T of each pair
/// i → i+1 (whose albedo follows the exact one: the reconstruction's texture is the source's
/// DiffCol), and `pixl eval --ct coarse` scores with them — or says how to make them.
#[test]
fn synth_coarse_then_eval_with_coarse_intrinsics() {
    let dir = common::tempdir();
    let synth = dir.path().join("synth");
    let make = |out: &Path, extra: &[&str]| pixl(&synth_args(s(out), "32", "4", &[&["-q"][..], extra].concat()));
    make(&synth, &["--coarse"]).ok();
    // Pairs 0 → 1 and 1 → 0 of both scenes (scene0001 is the test scene) and each source under
    // its own lighting (for the light-response score), nothing else.
    for scene in ["scene0000", "scene0001"] {
        for f in [
            "light_1.from_light_0",
            "light_0.from_light_1",
            "light_0.from_light_0",
            "light_1.from_light_1",
        ] {
            assert!(synth.join(format!("{scene}/{f}.intrinsics.exr")).is_file(), "{f}");
            assert!(synth.join(format!("{scene}/{f}.path_traced.png")).is_file(), "{f}");
        }
        let n = std::fs::read_dir(synth.join(scene)).unwrap().count();
        assert_eq!(
            n,
            4 + 8 + 2,
            "{scene}: 2 images + 2 C_T, 4 coarse C_T + 4 renders, 2 reconstructions"
        );
    }
    let exact = pixl_intrinsics::ct::read_ct(&synth.join("scene0001/light_1.intrinsics.exr")).unwrap();
    let coarse = pixl_intrinsics::ct::read_ct(&synth.join("scene0001/light_1.from_light_0.intrinsics.exr")).unwrap();
    // Normalised cross-correlation of the albedos (scale-free: C_T is rescaled per file).
    let (a, b) = (&exact.albedo.data, &coarse.albedo.data);
    let dot = |x: &[f32], y: &[f32]| x.iter().zip(y).map(|(p, q)| *p as f64 * *q as f64).sum::<f64>();
    let ncc = dot(a, b) / (dot(a, a) * dot(b, b)).sqrt();
    assert!(ncc > 0.9, "coarse albedo does not follow the exact one: NCC {ncc}");
    assert!(a != b, "the coarse C_T is the exact one: nothing was reconstructed");

    let eval = |ct: &str, root: &Path| {
        eval_synth(
            root,
            &dir.path().join(format!("eval-{ct}")),
            &["--baselines", "compose,identity", "--json", "--ct", ct],
        )
    };
    let psnr = |o: &Run| -> f64 { o.json()["methods"][0]["psnr"].as_f64().unwrap() };
    let (e_exact, e_coarse) = (eval("exact", &synth).ok(), eval("coarse", &synth).ok());
    let (p_exact, p_coarse) = (psnr(&e_exact), psnr(&e_coarse));
    assert!(
        p_exact.is_finite() && p_coarse.is_finite() && p_exact != p_coarse,
        "{p_exact} {p_coarse}"
    );
    // The light-response score comes with both: the identity never responds.
    for o in [&e_exact, &e_coarse] {
        let v = o.json();
        let rows = v["response"].as_array().expect("response rows");
        assert_eq!(rows.len(), 2, "{v}");
        assert_eq!(rows[1]["method"], "Identity (source)");
        assert_eq!(rows[1]["gain"].as_f64(), Some(0.0));
        assert!(rows[0]["gain"].as_f64().is_some_and(f64::is_finite));
        assert_eq!(rows[0]["pairs"].as_u64(), Some(2), "one test scene, two pairs");
    }
    // A set made without --coarse: a clear error naming the missing file and the fix.
    let plain = dir.path().join("plain");
    assert!(make(&plain, &[]).success());
    let o = eval("coarse", &plain);
    assert!(!o.success());
    let err = &o.stderr;
    assert!(
        err.contains("from_light_") && err.contains("pixl synth --coarse"),
        "{err}"
    );
}

/// On a boxes-style set (images shown with Reinhard) the coarse scene's path-traced renders are
/// what compose-reinhard makes of their own C_T, so its light response over the coarse renders
/// is close to 1 — an independent check of the score's plumbing; `--no-response` turns it off.
#[test]
fn eval_light_response_of_compose_reinhard_follows_the_renders() {
    let dir = common::tempdir();
    let synth = dir.path().join("synth");
    pixl(&[
        "-q",
        "synth",
        "--style",
        "boxes",
        "--scenes",
        "1",
        "--lights",
        "3",
        "--size",
        "32",
        "--spp",
        "16",
        "--test-every",
        "1",
        "--coarse",
        "-o",
        s(&synth),
    ])
    .ok();
    let eval = |extra: &[&str]| {
        let flags = [
            &["--baselines", "compose-reinhard", "--json", "--ct", "coarse"][..],
            extra,
        ]
        .concat();
        eval_synth(&synth, &dir.path().join("eval"), &flags).ok().json()
    };
    let v = eval(&[]);
    let gain = v["response"][0]["gain"].as_f64().unwrap();
    let corr = v["response"][0]["correlation"].as_f64().unwrap();
    assert!(
        gain > 0.85 && gain < 1.15 && corr > 0.9,
        "gain {gain}, correlation {corr}"
    );
    assert_eq!(v["response"][0]["pairs"].as_u64(), Some(3));
    let off = eval(&["--no-response"]);
    assert!(off["response"].as_array().is_none_or(|r| r.is_empty()), "{off}");
}

/// `pixl -q synth` of one scene under two lights, 24 pixels at 2 samples, into `out`, then `extra`.
fn one_scene(out: &Path, extra: &[&str]) -> Run {
    let base = [
        "-q",
        "synth",
        "--scenes",
        "1",
        "--lights",
        "2",
        "--size",
        "24",
        "--spp",
        "2",
        "-o",
        s(out),
    ];
    pixl(&[&base[..], extra].concat())
}

/// `--coarse-albedo photo` textures each reconstruction with its source image itself (as `pixl
/// reconstruct` does without `--albedo`) and records that in the manifest; the option needs
/// `--coarse`.
#[test]
fn synth_coarse_albedo_photo_textures_with_the_source_image() {
    let dir = common::tempdir();
    let out = dir.path().join("synth");
    let refused = one_scene(dir.path(), &["--coarse-albedo", "photo"]);
    assert!(!refused.success(), "--coarse-albedo without --coarse was accepted");
    one_scene(&out, &["--coarse-albedo", "photo", "--coarse"]).ok();
    for k in 0..2 {
        let photo = pixl_core::io::read_rgb(&out.join(format!("scene0000/light_{k}.png"))).unwrap();
        let tex = pixl_core::io::read_rgb(&out.join(format!("scene0000/coarse_from_light_{k}/albedo.png"))).unwrap();
        assert_eq!((photo.width, photo.height), (tex.width, tex.height));
        // The image PNG is 8-bit, the texture 16-bit of the same values: within half an 8-bit step.
        let worst = photo
            .data
            .iter()
            .zip(&tex.data)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(
            worst <= 0.5 / 255.0 + 1e-4,
            "light_{k}: texture differs from the photo by {worst}"
        );
    }
    let manifest: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("scenes.json")).unwrap()).unwrap();
    assert_eq!(manifest["coarse_albedo"], "photo");
    // `pixl eval --ct coarse` says which reconstruction the C_T came from.
    let report = dir.path().join("eval");
    eval_synth(
        &out,
        &report,
        &["--split", "all", "--baselines", "compose", "--ct", "coarse"],
    )
    .ok();
    let md = std::fs::read_to_string(report.join("results.md")).unwrap();
    assert!(md.contains("textured with the source image"), "{md}");
}

/// `--coarse-albedo estimated` textures each reconstruction with the diffuse colour plus an
/// estimator's errors: not the `diffcol` texture of the same scenes, but close to it
/// (correlated), and recorded in the manifest.
#[test]
fn synth_coarse_albedo_estimated_is_diffcol_with_errors() {
    let dir = common::tempdir();
    let run = |albedo: &str| {
        let out = dir.path().join(albedo);
        one_scene(&out, &["--coarse", "--coarse-albedo", albedo]).ok();
        out
    };
    let (exact, estimated) = (run("diffcol"), run("estimated"));
    for k in 0..2 {
        let tex = |root: &std::path::Path| {
            pixl_core::io::read_rgb(&root.join(format!("scene0000/coarse_from_light_{k}/albedo.png"))).unwrap()
        };
        let (a, b) = (tex(&exact), tex(&estimated));
        let n = a.data.len() as f64;
        let mean = |v: &[f32]| v.iter().map(|&x| x as f64).sum::<f64>() / n;
        let (ma, mb) = (mean(&a.data), mean(&b.data));
        let cov: f64 = a
            .data
            .iter()
            .zip(&b.data)
            .map(|(&x, &y)| (x as f64 - ma) * (y as f64 - mb))
            .sum::<f64>()
            / n;
        let sd = |v: &[f32], m: f64| (v.iter().map(|&x| (x as f64 - m).powi(2)).sum::<f64>() / n).sqrt();
        let corr = cov / (sd(&a.data, ma) * sd(&b.data, mb));
        let diff = a
            .data
            .iter()
            .zip(&b.data)
            .map(|(x, y)| (x - y).abs() as f64)
            .sum::<f64>()
            / n;
        assert!(
            diff > 0.005,
            "light_{k}: the estimated texture equals DiffCol (mean |diff| {diff})"
        );
        assert!(
            corr > 0.5,
            "light_{k}: the estimated texture is unrelated to DiffCol (corr {corr})"
        );
    }
    let manifest: serde_json::Value =
        serde_json::from_slice(&std::fs::read(estimated.join("scenes.json")).unwrap()).unwrap();
    assert_eq!(manifest["coarse_albedo"], "estimated");
}
