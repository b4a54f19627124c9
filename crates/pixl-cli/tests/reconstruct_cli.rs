//! `pixl reconstruct` end to end on a tiny generated photo + depth, and its bad inputs.
mod common;
use common::{cmd, run, write_npy_f32 as npy_f32, Run};
use std::path::Path;
use std::process::Command;

/// `pixl reconstruct --image DIR/photo.png --depth DIR/DEPTH -o OUT`.
fn reconstruct(dir: &Path, depth: &str, out: &Path) -> Command {
    let mut c = cmd();
    c.args(["reconstruct", "--image"])
        .arg(dir.join("photo.png"))
        .arg("--depth")
        .arg(dir.join(depth))
        .arg("-o")
        .arg(out);
    c
}

fn photo(path: &Path, w: u32, h: u32) {
    image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 20) as u8, (y * 30) as u8, 128]))
        .save(path)
        .unwrap();
}

#[test]
fn reconstructs_a_step_into_a_loadable_scene() {
    let dir = common::tempdir();
    let (w, h) = (8usize, 6usize);
    photo(&dir.path().join("photo.png"), w as u32, h as u32);
    // Left half 2 m, right half 4 m: the column of quads across the step is cut.
    let depth: Vec<f32> = (0..w * h).map(|i| if i % w < 4 { 2.0 } else { 4.0 }).collect();
    npy_f32(&dir.path().join("d.npy"), h, w, &depth);
    for fmt in ["glb", "obj", "ply"] {
        let out = dir.path().join(format!("scene_{fmt}"));
        run(reconstruct(dir.path(), "d.npy", &out).args(["--fov", "60", "--format", fmt])).ok();
        let scene = pixl_render::Scene::load(&out.join("scene.toml")).unwrap();
        assert_eq!((scene.camera.width, scene.camera.height), (w as u32, h as u32));
        assert!((scene.camera.fov_y() - 60.0).abs() < 1e-3);
        let mesh_file = match &scene.objects[0].shape {
            pixl_render::Shape::Mesh { path } => out.join(path),
            s => panic!("expected a mesh, got {s:?}"),
        };
        let mesh = pixl_render::export::load_mesh(&mesh_file).unwrap();
        assert_eq!(mesh.num_triangles(), 2 * (w - 1) * (h - 1) - 2 * (h - 1), "{fmt}");
        // Every vertex projects back into its pixel through the scene camera's FOV:
        // y_pix = H/2 − f·Y/d, f = (H/2)/tan(30°).
        let f = 0.5 * h as f32 / 30f32.to_radians().tan();
        for (p, uv) in mesh.positions.iter().zip(&mesh.uvs) {
            let d = -p[2];
            let px = 0.5 * w as f32 + f * p[0] / d;
            let py = 0.5 * h as f32 - f * p[1] / d;
            assert!(
                (px / w as f32 - uv[0]).abs() < 1e-5 && (py / h as f32 - uv[1]).abs() < 1e-5,
                "{fmt}: {p:?} {uv:?}"
            );
        }
        assert!(out.join("photo.png").exists());
    }
}

#[test]
fn bad_inputs_are_refused_with_the_file_named() {
    let dir = common::tempdir();
    photo(&dir.path().join("photo.png"), 4, 4);
    let mut nan = vec![1.0f32; 16];
    nan[5] = f32::NAN;
    npy_f32(&dir.path().join("nan.npy"), 4, 4, &nan);
    let refused = |depth: &str| {
        let o = run(&mut reconstruct(dir.path(), depth, &dir.path().join("out")));
        assert!(!o.success(), "{depth} should fail");
        o.stderr
    };
    let e = refused("nan.npy");
    assert!(e.contains("nan.npy") && e.contains("x=1, y=1"), "{e}");
    let e = refused("missing.exr");
    assert!(e.contains("missing.exr") && e.contains("not found"), "{e}");
    assert!(!dir.path().join("out").join("scene.toml").exists());
}

/// By default the mesh covers the whole frame: on a constant-depth map the outermost vertices
/// project onto the image's edges (pixel coordinates 0 and W/H, by the pinhole model computed
/// here); `--pixel-centres` keeps them at the border pixels' centres, half a pixel inside.
#[test]
fn mesh_reaches_the_frame_edges_unless_pixel_centres() {
    let dir = common::tempdir();
    let (w, h, d) = (6usize, 4usize, 3.0f32);
    photo(&dir.path().join("photo.png"), w as u32, h as u32);
    npy_f32(&dir.path().join("d.npy"), h, w, &vec![d; w * h]);
    let f = 5.0f32;
    let projected_extent = |extra: &[&str]| {
        let out = dir.path().join(format!("scene{}", extra.len()));
        let flags = [&["--focal", "5"][..], extra].concat();
        let (mesh, _, _) = reconstruct_ply(dir.path(), "d.npy", &flags, &out);
        assert_eq!(mesh.num_triangles(), 2 * (w - 1) * (h - 1));
        let px: Vec<f32> = mesh
            .positions
            .iter()
            .map(|p| 0.5 * w as f32 + f * p[0] / -p[2])
            .collect();
        let py: Vec<f32> = mesh
            .positions
            .iter()
            .map(|p| 0.5 * h as f32 - f * p[1] / -p[2])
            .collect();
        let lo_hi = |v: &[f32]| {
            (
                v.iter().copied().fold(f32::INFINITY, f32::min),
                v.iter().copied().fold(f32::NEG_INFINITY, f32::max),
            )
        };
        (lo_hi(&px), lo_hi(&py))
    };
    let close = |a: (f32, f32), b: (f32, f32)| (a.0 - b.0).abs() < 1e-4 && (a.1 - b.1).abs() < 1e-4;
    let (x, y) = projected_extent(&[]);
    assert!(close(x, (0.0, w as f32)) && close(y, (0.0, h as f32)), "{x:?} {y:?}");
    let (x, y) = projected_extent(&["--pixel-centres"]);
    assert!(
        close(x, (0.5, w as f32 - 0.5)) && close(y, (0.5, h as f32 - 0.5)),
        "{x:?} {y:?}"
    );
}

/// Runs [`reconstruct`] with `flags` into `out` (PLY) and returns the mesh, stdout and stderr.
fn reconstruct_ply(dir: &Path, depth: &str, flags: &[&str], out: &Path) -> (pixl_render::mesh::Mesh, String, String) {
    let o = run(reconstruct(dir, depth, out).args(flags).args(["--format", "ply"])).ok();
    let mesh = pixl_render::export::load_mesh(&out.join("mesh.ply")).unwrap();
    (mesh, o.stdout, o.stderr)
}

/// Distinct vertex depths (−z), sorted, rounded to 1e-4.
fn depths(mesh: &pixl_render::mesh::Mesh) -> Vec<f32> {
    let mut d: Vec<f32> = mesh.positions.iter().map(|p| (-p[2] * 1e4).round() / 1e4).collect();
    d.sort_by(f32::total_cmp);
    d.dedup();
    d
}

/// A depth map of another size is resampled to the photo (with a warning), not refused.
#[test]
fn depth_of_another_size_is_resampled() {
    let dir = common::tempdir();
    let (w, h) = (8usize, 6usize);
    photo(&dir.path().join("photo.png"), w as u32, h as u32);
    npy_f32(&dir.path().join("small.npy"), 3, 4, &[2.0; 12]);
    let (mesh, _, err) = reconstruct_ply(dir.path(), "small.npy", &[], &dir.path().join("out"));
    assert!(
        err.contains("small.npy") && err.contains("4x3") && err.contains("resampling"),
        "{err}"
    );
    assert_eq!(mesh.num_triangles(), 2 * (w - 1) * (h - 1));
    assert_eq!(depths(&mesh), vec![2.0]);
}

/// Relative depth maps linearly to --depth-range; disparity without a range maps to the
/// default 1–10 m, linear in 1/depth, with a warning.
#[test]
fn relative_and_disparity_depth_map_to_metres() {
    let dir = common::tempdir();
    let (w, h) = (8usize, 2usize);
    photo(&dir.path().join("photo.png"), w as u32, h as u32);
    // Column x holds x + 1 (1..8).
    let ramp: Vec<f32> = (0..w * h).map(|i| (i % w) as f32 + 1.0).collect();
    npy_f32(&dir.path().join("ramp.npy"), h, w, &ramp);
    let ramp_as = |kind: &str, extra: &[&str], out: &str| {
        let flags = [&["--depth-kind", kind, "--max-jump", "100"][..], extra].concat();
        reconstruct_ply(dir.path(), "ramp.npy", &flags, &dir.path().join(out))
    };
    let (mesh, _, _) = ramp_as("relative", &["--depth-range", "0.5,4"], "rel");
    let want: Vec<f32> = (0..w)
        .map(|x| ((0.5 + 3.5 * x as f64 / 7.0) * 1e4).round() as f32 / 1e4)
        .collect();
    assert_eq!(depths(&mesh), want);

    let (mesh, _, err) = ramp_as("disparity", &[], "disp");
    assert!(err.contains("--depth-range") && err.contains("1-10 m"), "{err}");
    // Disparity x+1: largest (8) → 1 m, smallest (1) → 10 m, 1/d linear in between.
    let mut want: Vec<f32> = (0..w)
        .map(|x| {
            let t = x as f64 / 7.0;
            ((1.0 / (0.1 + t * (1.0 - 0.1))) * 1e4).round() as f32 / 1e4
        })
        .collect();
    want.sort_by(f32::total_cmp);
    assert_eq!(depths(&mesh), want);
}

/// Without --stride, the stride is raised until the grid fits --max-triangles (and said so).
#[test]
fn max_triangles_picks_the_stride() {
    let dir = common::tempdir();
    let (w, h) = (41usize, 31usize);
    photo(&dir.path().join("photo.png"), w as u32, h as u32);
    npy_f32(&dir.path().join("d.npy"), h, w, &vec![3.0; w * h]);
    let budget = 300usize;
    // Naive: the grid keeps 0, s, 2s, … and the last pixel on each axis.
    let tris = |s: usize| {
        let n = |len: usize| {
            let mut kept: Vec<usize> = (0..len).step_by(s).collect();
            if kept.last() != Some(&(len - 1)) {
                kept.push(len - 1);
            }
            kept.len()
        };
        2 * (n(w) - 1) * (n(h) - 1)
    };
    let s = (1..).find(|&s| tris(s) <= budget).unwrap();
    assert!(s > 1);
    let (mesh, out, _) = reconstruct_ply(
        dir.path(),
        "d.npy",
        &["--max-triangles", "300"],
        &dir.path().join("auto"),
    );
    assert_eq!(mesh.num_triangles(), tris(s));
    assert!(out.contains(&format!("stride {s}")), "{out}");
    // An explicit stride is kept.
    let (mesh, _, _) = reconstruct_ply(
        dir.path(),
        "d.npy",
        &["--max-triangles", "300", "--stride", "1"],
        &dir.path().join("explicit"),
    );
    assert_eq!(mesh.num_triangles(), tris(1));
}

/// The output folder may hold old results (they are replaced) but never an input that a result
/// would overwrite: the photo there is refused before any work and stays as it was.
#[test]
fn an_output_folder_holding_the_photo_is_refused() {
    let dir = common::tempdir();
    let scene = dir.path().join("scene");
    std::fs::create_dir(&scene).unwrap();
    photo(&scene.join("photo.png"), 4, 4);
    let before = std::fs::read(scene.join("photo.png")).unwrap();
    npy_f32(&dir.path().join("d.npy"), 4, 4, &[1.0; 16]);
    run(cmd()
        .args(["reconstruct", "--image"])
        .arg(scene.join("photo.png"))
        .arg("--depth")
        .arg(dir.path().join("d.npy"))
        .arg("-o")
        .arg(&scene))
    .fails(&["photo.png"]);
    assert_eq!(std::fs::read(scene.join("photo.png")).unwrap(), before);
    assert!(!scene.join("scene.toml").exists());
}

/// [`reconstruct`] with a 60° field of view and `extra`.
fn run_reconstruct(dir: &Path, depth: &str, extra: &[&str], out: &Path) -> Run {
    run(reconstruct(dir, depth, out).args(["--fov", "60"]).args(extra))
}

/// Re-running over a scene someone has lit keeps it unless --force; --force replaces it.
#[test]
fn an_existing_scene_is_replaced_only_with_force() {
    let dir = common::tempdir();
    photo(&dir.path().join("photo.png"), 8, 6);
    npy_f32(&dir.path().join("d.npy"), 6, 8, &[2.0; 48]);
    let out = dir.path().join("scene");
    run_reconstruct(dir.path(), "d.npy", &[], &out).ok();
    let scene_file = out.join("scene.toml");
    run(cmd()
        .args(["light", "add"])
        .arg(&scene_file)
        .args(["--preset", "warm-overhead-flash"]))
    .ok();
    let lit = std::fs::read_to_string(&scene_file).unwrap();
    assert_eq!(pixl_render::Scene::load(&scene_file).unwrap().lights.len(), 1);

    let o = run_reconstruct(dir.path(), "d.npy", &[], &out);
    assert!(!o.success());
    assert!(
        o.stderr.contains("--force") && o.stderr.contains("scene.toml"),
        "{}",
        o.stderr
    );
    assert_eq!(
        std::fs::read_to_string(&scene_file).unwrap(),
        lit,
        "the lit scene was touched"
    );

    run_reconstruct(dir.path(), "d.npy", &["--force"], &out).ok();
    assert!(pixl_render::Scene::load(&scene_file).unwrap().lights.is_empty());
}

/// When no triangle is kept, the message names the cause that cut them: a stride too coarse for
/// the photo, missing depth, or depth jumps (counted by hand on 8×6 maps); nothing is written.
#[test]
fn an_empty_mesh_blames_the_right_flag() {
    let dir = common::tempdir();
    photo(&dir.path().join("photo.png"), 8, 6);
    // Flat but for the top-left pixel: at stride 1 only its two triangles are cut; at stride
    // 1000 the grid is the four corners and both of its triangles use that pixel.
    let mut corner = [2.0f32; 48];
    corner[0] = 0.0;
    npy_f32(&dir.path().join("corner.npy"), 6, 8, &corner);
    // Every other column without depth: every triangle has a corner in one of them.
    let holes: Vec<f32> = (0..48).map(|i| if i % 2 == 0 { 0.0 } else { 2.0 }).collect();
    npy_f32(&dir.path().join("holes.npy"), 6, 8, &holes);
    // Every other column 2 m / 3 m: each quad spans a 50 % jump.
    let zebra: Vec<f32> = (0..48).map(|i| if i % 2 == 0 { 2.0 } else { 3.0 }).collect();
    npy_f32(&dir.path().join("zebra.npy"), 6, 8, &zebra);
    let cases: [(&str, &[&str], &[&str]); 3] = [
        (
            "corner.npy",
            &["--stride", "1000"],
            &["--stride 1000", "2x2 grid", "smaller --stride"],
        ),
        ("holes.npy", &[], &["holes.npy", "lack depth", "70 of 70"]),
        (
            "zebra.npy",
            &[],
            &["zebra.npy", "depth jump", "--max-jump 0.05", "70 of 70"],
        ),
    ];
    for (depth, flags, needles) in cases {
        let out = dir.path().join(format!("out-{depth}"));
        let o = run_reconstruct(dir.path(), depth, flags, &out);
        assert!(!o.success(), "{depth}");
        let err = &o.stderr;
        for n in needles {
            assert!(err.contains(n), "{depth}: {n:?} not in {err}");
        }
        assert!(!err.contains("max-jump") || depth == "zebra.npy", "{depth}: {err}");
        assert!(!out.exists(), "{depth}: {} was created", out.display());
    }
}

/// `--json`: one document on stdout with the mesh's counts (a step of 2 m / 4 m on 8×6: the
/// column of quads across it is cut, 2·7·5 − 2·5 = 60 triangles kept, 10 cut).
#[test]
fn json_summary_counts_the_mesh() {
    let dir = common::tempdir();
    photo(&dir.path().join("photo.png"), 8, 6);
    let depth: Vec<f32> = (0..48).map(|i| if i % 8 < 4 { 2.0 } else { 4.0 }).collect();
    npy_f32(&dir.path().join("d.npy"), 6, 8, &depth);
    let out = dir.path().join("scene");
    let v = run(reconstruct(dir.path(), "d.npy", &out).args(["--quiet", "--json", "--fov", "60"]))
        .ok()
        .json();
    assert_eq!(v["triangles"], 60);
    assert_eq!(v["triangles_cut"], 10);
    assert_eq!((v["width"].as_u64(), v["height"].as_u64()), (Some(8), Some(6)));
    assert!((v["fov_y_deg"].as_f64().unwrap() - 60.0).abs() < 1e-6);
    assert_eq!(v["stride"], 1);
    assert!(out.join("scene.toml").is_file());
}
