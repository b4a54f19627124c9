//! `pixl eval` end to end on a tiny fake `folder:` dataset built here: two scenes of three 32×32
//! PNGs, each with its exact `<stem>.intrinsics.exr` beside it (the training loader's rule).
mod common;
use common::{run, tiny_weights, write_png8, Run};
use pixl_core::image::linear_to_srgb;
use pixl_core::Image;
use pixl_intrinsics::ct::{write_ct, Ct};
use std::path::{Path, PathBuf};
use std::process::Command;

const SIDE: usize = 32;

/// Scene `s`, light `l`: the PNG is exactly sRGB(A ⊙ S_l), 8-bit, with a C_T of R = 0, so the
/// compose baseline reproduces it up to 8-bit quantisation.
fn make_dataset(root: &Path) {
    for s in 0..2 {
        let dir = root.join(format!("scene{s}"));
        std::fs::create_dir_all(&dir).unwrap();
        let albedo = Image::from_fn(SIDE, SIDE, 3, |x, y, c| {
            0.2 + 0.6 * (((x * 7 + y * 3 + c * 5 + s) % 11) as f32 / 10.0)
        });
        for l in 0..3 {
            let shading = Image::from_fn(SIDE, SIDE, 3, |x, y, _| {
                let (cx, cy) = ([4.0, 28.0, 16.0][l], [4.0, 10.0, 28.0][l]);
                let d2 = (x as f32 - cx).powi(2) + (y as f32 - cy).powi(2);
                0.1 + 0.9 * (-d2 / 300.0).exp()
            });
            let residual = Image::new(SIDE, SIDE, 3);
            let ct = Ct::new(albedo.clone(), shading, residual).unwrap();
            let photo = ct.recompose().map(|v| linear_to_srgb(v.clamp(0.0, 1.0)));
            write_png8(&dir.join(format!("light{l}.png")), &photo);
            write_ct(&dir.join(format!("light{l}.intrinsics.exr")), &ct).unwrap();
        }
    }
}

/// A temporary folder with the data set in `data/`.
fn dataset() -> (tempfile::TempDir, PathBuf) {
    let tmp = common::tempdir();
    let root = tmp.path().join("data");
    make_dataset(&root);
    (tmp, root)
}

/// `pixl eval --split all --dataset folder:ROOT --out OUT`.
fn eval(root: &Path, out: &Path) -> Command {
    let mut c = common::cmd();
    c.args(["eval", "--split", "all", "--dataset"])
        .arg(format!("folder:{}", root.display()))
        .arg("--out")
        .arg(out);
    c
}

fn csv_rows(path: &Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next().unwrap(), "scene,source,target,method,psnr,ssim,lpips");
    lines.map(|l| l.split(',').map(String::from).collect()).collect()
}

#[test]
fn eval_writes_three_outputs_and_identity_is_exact_on_equal_pairs() {
    let (tmp, root) = dataset();
    let pairs = tmp.path().join("pairs.csv");
    std::fs::write(
        &pairs,
        "scene,source,target\nscene0,light1.png,light1.png\nscene1,light2.png,light2.png\nscene0,light0.png,light2.png\n",
    )
    .unwrap();
    let out = tmp.path().join("out");
    let stdout = run(eval(&root, &out)
        .args([
            "--baselines",
            "identity,compose",
            "--runs",
            "2",
            "--warmups",
            "1",
            "--pairs",
        ])
        .arg(&pairs))
    .ok()
    .stdout;
    assert!(
        stdout.contains("| Method | Lighting cue | PSNR ↑ | SSIM ↑ | LPIPS ↓ | Time (s) ↓ |"),
        "{stdout}"
    );
    for f in ["results.md", "results.json", "per_pair.csv"] {
        assert!(out.join(f).is_file(), "missing {f}");
    }
    let rows = csv_rows(&out.join("per_pair.csv"));
    assert_eq!(rows.len(), 3 * 2, "3 pairs x 2 methods");
    for r in &rows {
        let (src, tgt, method) = (&r[1], &r[2], &r[3]);
        let psnr: f64 = r[4].parse().unwrap();
        let ssim: f64 = r[5].parse().unwrap();
        assert_eq!(r[6], "", "LPIPS absent without weights");
        if method.starts_with("Identity") && src == tgt {
            assert_eq!(r[4], "inf", "{r:?}");
            assert_eq!(ssim, 1.0, "{r:?}");
        } else if method.starts_with("Compose") {
            // The target is sRGB(A⊙S) in 8 bits: only quantisation (≤ 1/510) separates them.
            assert!(psnr > 45.0 && ssim > 0.99, "{r:?}");
        } else {
            assert!(psnr.is_finite() && psnr < 40.0, "different lights must differ: {r:?}");
        }
    }
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap();
    assert_eq!(json["pairs"], 3);
    assert_eq!(json["scale_correction"], true);
    let methods = json["methods"].as_array().unwrap();
    assert_eq!(methods.len(), 2);
    assert!(methods[0]["lpips"].is_null());
    assert_eq!(methods[0]["timing"]["runs_ms"].as_array().unwrap().len(), 2);
    // The identity's mean includes one finite pair, so it is finite; per-pair entries carry "inf".
    assert!(json["per_pair"].as_array().unwrap().iter().any(|p| p["psnr"] == "inf"));
}

#[test]
fn default_pairs_fresh_model_equals_identity_and_json_summary() {
    let (tmp, root) = dataset();
    // Fresh weights return the source exactly (zero-initialised modulation), so "Ours" must
    // score exactly like the identity on every pair.
    let weights = tiny_weights(&tmp.path().join("tiny.safetensors"), 0);
    let out = tmp.path().join("out");
    let summary = run(eval(&root, &out)
        .args(["--json", "--baselines", "identity", "--runs", "1", "--warmups", "0"])
        .arg("--weights")
        .arg(&weights))
    .ok()
    .json();
    // Default list: per scene i → (i+1) mod 3, two scenes.
    assert_eq!(summary["pairs"], 6);
    let m = summary["methods"].as_array().unwrap();
    assert_eq!(m[0]["method"], "Ours");
    assert_eq!(m[1]["method"], "Identity (source)");
    assert_eq!(m[0]["psnr"], m[1]["psnr"]);
    assert_eq!(m[0]["ssim"], m[1]["ssim"]);
    assert!(m[0]["device"].as_str().unwrap().starts_with("cpu"));
    let rows = csv_rows(&out.join("per_pair.csv"));
    let pairs: Vec<(String, String)> = rows
        .iter()
        .filter(|r| r[3] == "Ours")
        .map(|r| (r[1].clone(), r[2].clone()))
        .collect();
    let want: Vec<(String, String)> = [("light0", "light1"), ("light1", "light2"), ("light2", "light0")]
        .iter()
        .cycle()
        .take(6)
        .map(|(a, b)| (format!("{a}.png"), format!("{b}.png")))
        .collect();
    assert_eq!(pairs, want);
}

#[test]
fn bad_pair_list_names_file_and_line() {
    let (tmp, root) = dataset();
    let pairs = tmp.path().join("pairs.csv");
    std::fs::write(&pairs, "scene0,light0.png,light1.png\nscene0,light0.png,nope.png\n").unwrap();
    let o = run(eval(&root, &tmp.path().join("out")).arg("--pairs").arg(&pairs));
    assert_eq!(o.code(), Some(1));
    let err = &o.stderr;
    assert!(err.contains("pairs.csv, line 2") && err.contains("nope.png"), "{err}");
    assert!(!tmp.path().join("out").join("results.json").exists());
}

#[test]
fn missing_intrinsics_is_an_error_for_compose_not_identity() {
    let (tmp, root) = dataset();
    std::fs::remove_file(root.join("scene0/light1.intrinsics.exr")).unwrap();
    let with = |baselines: &str| {
        run(eval(&root, &tmp.path().join(format!("out-{baselines}"))).args([
            "-q",
            "--baselines",
            baselines,
            "--runs",
            "0",
        ]))
    };
    let o = with("compose");
    assert_eq!(o.code(), Some(1));
    assert!(o.stderr.contains("light1.intrinsics.exr"));
    with("identity").ok();
}

/// `--int8` evaluates the network with 8-bit linear layers: labelled as such, scoring within a
/// few hundredths of a dB of f32 with the bundled weights; refused without `--weights`, and
/// (with its reason) on a CPU without AVX-512 VNNI.
#[test]
fn int8_is_labelled_and_scores_as_f32() {
    let (tmp, root) = dataset();
    let weights = common::repo_path("assets/demo-weights/pixl-tiny-synth.safetensors");
    let with = |extra: &[&str], out: &str| {
        run(eval(&root, &tmp.path().join(out))
            .args(["-q", "--baselines", "", "--runs", "0", "--json"])
            .args(extra))
    };
    let w = common::s(&weights);
    let f32_run = with(&["--weights", w], "f32").ok();
    let int8_run = with(&["--weights", w, "--int8"], "int8");
    if !pixl_nn::int8::available() {
        assert_eq!(int8_run.code(), Some(1));
        assert!(int8_run.stderr.contains("VNNI"));
        return;
    }
    let int8_run = int8_run.ok();
    let row = |o: &Run| o.json()["methods"][0].clone();
    let (a, b) = (row(&f32_run), row(&int8_run));
    assert_eq!(
        (a["method"].as_str(), b["method"].as_str()),
        (Some("Ours"), Some("Ours (int8)"))
    );
    let (pa, pb) = (a["psnr"].as_f64().unwrap(), b["psnr"].as_f64().unwrap());
    assert!((pa - pb).abs() < 0.05, "PSNR f32 {pa} vs int8 {pb}");
    let refused = with(&["--int8"], "none");
    assert!(!refused.success());
}

/// Two `--weights` are two rows labelled by file stem, in the order given, and `--sheet` writes
/// the contact sheet: `--sheet-pairs` rows of 8 panels of 32×32 (source, three C_T maps, the two
/// networks, the identity, target), the source and target columns holding the data set's
/// images exactly; `--json` and results.json name it and its columns.
#[test]
fn two_weights_are_rows_by_stem_and_the_sheet_shows_the_first_pairs() {
    let (tmp, root) = dataset();
    let (wa, wb) = (
        tmp.path().join("run-a.safetensors"),
        tmp.path().join("run-b.safetensors"),
    );
    tiny_weights(&wa, 0);
    tiny_weights(&wb, 1);
    let out = tmp.path().join("out");
    let sheet = out.join("sheet.png");
    let summary = run(eval(&root, &out)
        .args(["--json", "--baselines", "identity", "--runs", "0"])
        .arg("--weights")
        .arg(&wa)
        .arg("--weights")
        .arg(&wb)
        .arg("--sheet")
        .arg(&sheet)
        .args(["--sheet-pairs", "2"]))
    .ok()
    .json();
    let results: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("results.json")).unwrap()).unwrap();
    let columns = [
        "source",
        "C_T albedo",
        "C_T shading",
        "C_T residual",
        "Ours (run-a)",
        "Ours (run-b)",
        "Identity (source)",
        "target",
    ];
    for v in [&summary, &results] {
        let labels: Vec<&str> = v["methods"]
            .as_array()
            .unwrap()
            .iter()
            .map(|m| m["method"].as_str().unwrap())
            .collect();
        assert_eq!(labels, ["Ours (run-a)", "Ours (run-b)", "Identity (source)"]);
        assert_eq!(v["sheet"], sheet.display().to_string());
        assert_eq!(v["sheet_columns"], serde_json::json!(columns));
    }
    assert_eq!(results["sheet_pairs"], 2);
    let md = std::fs::read_to_string(out.join("results.md")).unwrap();
    assert!(md.contains(&columns.join(" | ")), "{md}");
    let rows = csv_rows(&out.join("per_pair.csv"));
    assert_eq!(rows.iter().filter(|r| r[3] == "Ours (run-b)").count(), 6);

    let img = pixl_core::io::read_image(&sheet).unwrap();
    assert_eq!((img.width, img.height, img.channels), (8 * SIDE, 2 * SIDE, 3));
    // The default pairs start with scene0: light0 → light1, then light1 → light2.
    for (row, (src, tgt)) in [("light0", "light1"), ("light1", "light2")].iter().enumerate() {
        let src = pixl_core::io::read_image(&root.join(format!("scene0/{src}.png"))).unwrap();
        let tgt = pixl_core::io::read_image(&root.join(format!("scene0/{tgt}.png"))).unwrap();
        for y in 0..SIDE {
            for x in 0..SIDE {
                for c in 0..3 {
                    let at = |col: usize| img.get(col * SIDE + x, row * SIDE + y, c);
                    assert_eq!(at(0), src.get(x, y, c), "row {row} source ({x},{y},{c})");
                    assert_eq!(at(7), tgt.get(x, y, c), "row {row} target ({x},{y},{c})");
                    // Fresh weights return the source, scale-corrected like the identity.
                    assert_eq!(at(4), at(6), "row {row} ({x},{y},{c})");
                }
            }
        }
    }
}

/// Two weights files of one stem would share a label: refused before any work, naming both;
/// a sheet that is not a PNG is refused too.
#[test]
fn weights_of_one_stem_and_a_non_png_sheet_are_refused() {
    let (tmp, root) = dataset();
    let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    tiny_weights(&a.join("model.safetensors"), 0);
    std::fs::copy(a.join("model.safetensors"), b.join("model.safetensors")).unwrap();
    let with = |extra: &[&std::ffi::OsStr]| {
        run(eval(&root, &tmp.path().join("out"))
            .args(["-q", "--baselines", "identity", "--runs", "0"])
            .args(extra))
    };
    let (wa, wb) = (a.join("model.safetensors"), b.join("model.safetensors"));
    let o = with(&[
        "--weights".as_ref(),
        wa.as_os_str(),
        "--weights".as_ref(),
        wb.as_os_str(),
    ]);
    assert_eq!(o.code(), Some(1));
    let err = &o.stderr;
    assert!(
        err.contains("same file stem \"model\"")
            && err.contains(&*wa.to_string_lossy())
            && err.contains(&*wb.to_string_lossy()),
        "{err}"
    );
    assert!(!tmp.path().join("out").exists());
    let sheet = tmp.path().join("sheet.jpg");
    let o = with(&["--sheet".as_ref(), sheet.as_os_str()]);
    assert_eq!(o.code(), Some(1));
    assert!(o.stderr.contains(".png"));
    assert!(!tmp.path().join("out").exists() && !sheet.exists());
}
