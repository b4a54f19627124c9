//! Marigold Normals at the binary level on the tiny random checkpoint of
//! `fixtures/marigold/normals`: `pixl estimate normals` (EXR and PNG maps, the ensemble's
//! uncertainty), `pixl reconstruct --normals marigold|FILE` (the same normals either way), and
//! the bad inputs — each one clear error with nothing written. No test touches the network.
mod common;
use common::{cmd_in, copy_dir, run, write_png8, Run};
use pixl_core::Image;
use std::path::{Path, PathBuf};

/// A models folder with the fixture `src` (normals | appearance | …) installed as `as_name`.
fn models(root: &Path, src: &str, as_name: &str) -> PathBuf {
    let dir = root.join("models");
    copy_dir(&common::repo_path("fixtures/marigold").join(src), &dir.join(as_name));
    dir
}

fn photo(path: &Path, w: usize, h: usize) -> PathBuf {
    let img = Image::from_fn(w, h, 3, |x, y, c| {
        ((x * (c + 2) + y * 5) % 19) as f32 / 18.0 * 0.8 + 0.1
    });
    write_png8(path, &img)
}

/// `pixl estimate normals PHOTO -o OUT FLAGS --models MODELS` with HOME at `home`.
fn estimate(home: &Path, photo: &Path, out: &Path, flags: &[&str], models: &Path) -> Run {
    run(cmd_in(home)
        .args(["estimate", "normals"])
        .arg(photo)
        .arg("-o")
        .arg(out)
        .args(flags)
        .arg("--models")
        .arg(models))
}

fn off_unit(n: &Image) -> f32 {
    n.data
        .chunks_exact(3)
        .map(|p| ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 1.0).abs())
        .fold(0f32, f32::max)
}

#[test]
fn estimate_normals_writes_unit_normals_as_exr_or_png() {
    let t = common::tempdir();
    let m = models(t.path(), "normals", "marigold-normals");
    let p = photo(&t.path().join("p.png"), 37, 27);
    let exr = t.path().join("n.exr");
    let v = estimate(t.path(), &p, &exr, &["--res", "32", "--steps", "2", "--json"], &m)
        .ok()
        .json();
    assert_eq!((v["steps"].as_u64(), v["ensemble"].as_u64()), (Some(2), Some(1)));
    assert_eq!(v["weights"]["licence"], "Apache-2.0");
    assert!(v["uncertainty"].is_null());
    let n = pixl_core::io::read_image(&exr).unwrap();
    assert_eq!((n.width, n.height, n.channels), (37, 27, 3));
    assert!(off_unit(&n) < 1e-5, "{}", off_unit(&n));
    // The same run as a PNG: n/2 + 1/2 in 16 bits, the same normals within the quantisation;
    // an ensemble with its uncertainty beside it.
    let png = t.path().join("n.png");
    let u = t.path().join("u.exr");
    estimate(t.path(), &p, &png, &["--res", "32", "--steps", "2"], &m).ok();
    let back = pixl_render::normals::read_normal_map(&png).unwrap();
    let worst = back
        .data
        .iter()
        .zip(&n.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst <= 2.0 / 65535.0, "PNG vs EXR: {worst}");
    let png2 = t.path().join("n2.png");
    let ens = ["--res", "32", "--steps", "2", "--ensemble", "3", "--uncertainty"];
    run(cmd_in(t.path())
        .args(["estimate", "normals"])
        .arg(&p)
        .arg("-o")
        .arg(&png2)
        .args(ens)
        .arg(&u)
        .args(["--reduction", "mean", "--models"])
        .arg(&m))
    .ok();
    let spread = pixl_core::io::read_image(&u).unwrap();
    assert_eq!((spread.width, spread.height, spread.channels), (37, 27, 1));
    assert!(spread.data.iter().all(|v| (0.0..=1.0).contains(v)));
    assert!(
        spread.data.iter().any(|v| *v > 0.0),
        "three members that all agree exactly?"
    );
}

#[test]
fn bad_input_is_one_clear_error_and_nothing_is_written() {
    let t = common::tempdir();
    let m = models(t.path(), "normals", "marigold-normals");
    let p = photo(&t.path().join("p.png"), 20, 16);
    let out = t.path().join("n.exr");
    let refused = |photo: &Path, out: &Path, flags: &[&str], models: &Path, needles: &[&str]| {
        estimate(t.path(), photo, out, flags, models).fails(needles);
        assert!(!out.exists(), "{} was written", out.display());
    };
    refused(
        &t.path().join("missing.png"),
        &out,
        &["--res", "32"],
        &m,
        &["missing.png"],
    );
    refused(&p, &t.path().join("n.jpg"), &["--res", "32"], &m, &["n.jpg", "exr"]);
    refused(&p, &out, &["--res", "30"], &m, &["multiple of 8"]);
    refused(
        &p,
        &out,
        &["--res", "32", "--uncertainty", "u.exr"],
        &m,
        &["--uncertainty", "--ensemble 2"],
    );
    // An IID checkpoint where the normals one is expected.
    let iid = models(&t.path().join("iid"), "appearance", "marigold-normals");
    refused(
        &p,
        &out,
        &["--res", "32"],
        &iid,
        &[
            "marigold-normals",
            "MarigoldIntrinsicsPipeline",
            "not a Marigold normals checkpoint",
        ],
    );
    // No weights and no network.
    let empty = t.path().join("empty");
    std::fs::create_dir_all(&empty).unwrap();
    let o = run(cmd_in(t.path())
        .args(["estimate", "normals"])
        .arg(&p)
        .arg("-o")
        .arg(&out)
        .args(["--offline", "--models"])
        .arg(&empty));
    o.fails(&["marigold-normals", "pixl models fetch marigold-normals"]);
    assert!(!out.exists());
}

#[test]
fn reconstruct_takes_marigold_normals_estimated_or_from_a_file() {
    let t = common::tempdir();
    let m = models(t.path(), "normals", "marigold-normals");
    let (w, h) = (24, 16);
    let p = photo(&t.path().join("p.png"), w, h);
    let d = common::write_depth(&t.path().join("d.exr"), w, h, |x, _| 2.0 + x as f32 * 0.01);
    let reconstruct = |out: &Path, flags: &[&str]| {
        run(cmd_in(t.path())
            .arg("reconstruct")
            .arg("--image")
            .arg(&p)
            .arg("--depth")
            .arg(&d)
            .args(["--format", "ply", "--stride", "1", "--json"])
            .args(flags)
            .arg("--models")
            .arg(&m)
            .arg("-o")
            .arg(out))
    };
    let a = t.path().join("a");
    let v = reconstruct(&a, &["--normals", "marigold", "--normals-res", "32"])
        .ok()
        .json();
    assert_eq!(v["normals"], "marigold-normals");
    // The same estimate written by `pixl estimate normals` (EXR: exact) gives the same mesh.
    let n = t.path().join("n.exr");
    estimate(t.path(), &p, &n, &["--res", "32"], &m).ok();
    let b = t.path().join("b");
    let v = reconstruct(&b, &["--normals", n.to_str().unwrap()]).ok().json();
    assert_eq!(v["normals"], "file");
    let (ma, mb) = (
        std::fs::read(a.join("mesh.ply")).unwrap(),
        std::fs::read(b.join("mesh.ply")).unwrap(),
    );
    assert_eq!(ma, mb, "meshes from --normals marigold and from its file differ");
    // Without normals the mesh differs (its normals come from its faces).
    let c = t.path().join("c");
    reconstruct(&c, &[]).ok();
    assert_ne!(std::fs::read(c.join("mesh.ply")).unwrap(), ma);

    // Bad --normals: a one-channel map, a missing file, --normals-res without marigold.
    let grey = t.path().join("grey.png");
    write_png8(&grey, &Image::new(w, h, 1));
    let e = t.path().join("e");
    reconstruct(&e, &["--normals", grey.to_str().unwrap()]).fails(&["grey.png", "3 channels"]);
    reconstruct(&e, &["--normals", "nowhere.exr"]).fails(&["nowhere.exr"]);
    reconstruct(&e, &["--normals", n.to_str().unwrap(), "--normals-res", "32"])
        .fails(&["--normals-res", "--normals marigold"]);
    let small = t.path().join("small.exr");
    pixl_render::normals::write_normal_map(&small, &Image::from_fn(4, 4, 3, |_, _, c| [0.0, 0.0, 1.0][c])).unwrap();
    reconstruct(&e, &["--normals", small.to_str().unwrap()]).fails(&["small.exr", "4x4", "24x16"]);
    assert!(!e.exists());
}
