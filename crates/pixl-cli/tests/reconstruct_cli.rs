//! `pixl reconstruct` end to end on a tiny generated photo + depth, and its bad inputs.
use std::path::Path;
use std::process::Command;

fn pixl() -> Command {
    Command::new(env!("CARGO_BIN_EXE_pixl"))
}

fn npy_f32(path: &Path, h: usize, w: usize, vals: &[f32]) {
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({h}, {w}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(header.as_bytes());
    b.extend(vals.iter().flat_map(|v| v.to_le_bytes()));
    std::fs::write(path, b).unwrap();
}

fn photo(path: &Path, w: u32, h: u32) {
    image::RgbImage::from_fn(w, h, |x, y| image::Rgb([(x * 20) as u8, (y * 30) as u8, 128]))
        .save(path)
        .unwrap();
}

#[test]
fn reconstructs_a_step_into_a_loadable_scene() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h) = (8usize, 6usize);
    photo(&dir.path().join("photo.png"), w as u32, h as u32);
    // Left half 2 m, right half 4 m: the column of quads across the step is cut.
    let depth: Vec<f32> = (0..w * h).map(|i| if i % w < 4 { 2.0 } else { 4.0 }).collect();
    npy_f32(&dir.path().join("d.npy"), h, w, &depth);
    for fmt in ["glb", "obj", "ply"] {
        let out = dir.path().join(format!("scene_{fmt}"));
        let o = pixl()
            .args(["reconstruct", "--image"])
            .arg(dir.path().join("photo.png"))
            .arg("--depth")
            .arg(dir.path().join("d.npy"))
            .args(["--fov", "60", "--format", fmt, "-o"])
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{fmt}: {}", String::from_utf8_lossy(&o.stderr));
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
    let dir = tempfile::tempdir().unwrap();
    photo(&dir.path().join("photo.png"), 4, 4);
    npy_f32(&dir.path().join("small.npy"), 3, 4, &[1.0; 12]);
    let mut nan = vec![1.0f32; 16];
    nan[5] = f32::NAN;
    npy_f32(&dir.path().join("nan.npy"), 4, 4, &nan);
    let run = |depth: &str| {
        let o = pixl()
            .args(["reconstruct", "--image"])
            .arg(dir.path().join("photo.png"))
            .arg("--depth")
            .arg(dir.path().join(depth))
            .arg("-o")
            .arg(dir.path().join("out"))
            .output()
            .unwrap();
        assert!(!o.status.success(), "{depth} should fail");
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let e = run("small.npy");
    assert!(e.contains("small.npy") && e.contains("4x3"), "{e}");
    let e = run("nan.npy");
    assert!(e.contains("nan.npy") && e.contains("x=1, y=1"), "{e}");
    let e = run("missing.exr");
    assert!(e.contains("missing.exr") && e.contains("not found"), "{e}");
    assert!(!dir.path().join("out").join("scene.toml").exists());
}

/// By default the mesh covers the whole frame: on a constant-depth map the outermost vertices
/// project onto the image's edges (pixel coordinates 0 and W/H, by the pinhole model computed
/// here); `--pixel-centres` keeps them at the border pixels' centres, half a pixel inside.
#[test]
fn mesh_reaches_the_frame_edges_unless_pixel_centres() {
    let dir = tempfile::tempdir().unwrap();
    let (w, h, d) = (6usize, 4usize, 3.0f32);
    photo(&dir.path().join("photo.png"), w as u32, h as u32);
    npy_f32(&dir.path().join("d.npy"), h, w, &vec![d; w * h]);
    let f = 5.0f32;
    let projected_extent = |extra: &[&str]| {
        let out = dir.path().join(format!("scene{}", extra.len()));
        let o = pixl()
            .args(["reconstruct", "--image"])
            .arg(dir.path().join("photo.png"))
            .arg("--depth")
            .arg(dir.path().join("d.npy"))
            .args(["--focal", "5", "--format", "ply"])
            .args(extra)
            .arg("-o")
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let mesh = pixl_render::export::load_mesh(&out.join("mesh.ply")).unwrap();
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
