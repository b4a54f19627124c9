//! `pixl estimate depth` (and `pixl reconstruct` without `--depth`) on the tiny randomly
//! initialised Depth Anything 3 checkpoint in `fixtures/da3/tiny` (or `$PIXL_DA3_TINY`), and
//! their bad inputs at the binary level: each a clear error, exit 1, nothing written. No test
//! touches the network (`--offline`, a private HOME, a closed endpoint).
mod common;
use common::{assert_only, cmd_in, png_header_only, run, write_file, write_image};
use pixl_core::Image;
use std::path::{Path, PathBuf};
use std::process::Command;

/// The tiny checkpoint folder (config.json + model.safetensors).
fn tiny() -> PathBuf {
    let p = std::env::var_os("PIXL_DA3_TINY")
        .map(PathBuf::from)
        .unwrap_or_else(|| common::repo_path("fixtures/da3/tiny"));
    assert!(
        p.join("config.json").is_file() && p.join("model.safetensors").is_file(),
        "the tiny DA3 checkpoint is missing at {} (set PIXL_DA3_TINY)",
        p.display()
    );
    p
}

/// A models folder holding the tiny checkpoint as `name` (config.json edited by `edit`).
fn models_dir(root: &Path, name: &str, edit: impl Fn(&str) -> String) -> PathBuf {
    let dir = root.join("models");
    let own = dir.join(name);
    std::fs::create_dir_all(&own).unwrap();
    let cfg = std::fs::read_to_string(tiny().join("config.json")).unwrap();
    std::fs::write(own.join("config.json"), edit(&cfg)).unwrap();
    std::fs::copy(tiny().join("model.safetensors"), own.join("model.safetensors")).unwrap();
    dir
}

/// The tiny checkpoint as a metric model (the fixture is `da3mono-tiny`).
fn as_metric(cfg: &str) -> String {
    cfg.replace("da3mono", "da3metric")
}

fn photo(path: &Path, w: usize, h: usize) {
    let img = Image::from_fn(w, h, 3, |x, y, c| ((x * 7 + y * 13 + c * 29) % 64) as f32 / 63.0);
    write_image(path, &img);
}

/// `pixl estimate depth PHOTO -o OUT` with HOME at `home`.
fn depth_cmd(home: &Path, photo: &Path, out: &Path) -> Command {
    let mut c = cmd_in(home);
    c.args(["estimate", "depth"]).arg(photo).arg("-o").arg(out);
    c
}

/// `pixl reconstruct --image PHOTO -o OUT` with HOME at `home`.
fn reconstruct_cmd(home: &Path, photo: &Path, out: &Path) -> Command {
    let mut c = cmd_in(home);
    c.args(["reconstruct", "--image"]).arg(photo).arg("-o").arg(out);
    c
}

/// A fresh HOME with an empty `work` folder in it.
fn home_and_work() -> (tempfile::TempDir, PathBuf) {
    let t = common::tempdir();
    let work = t.path().join("work");
    std::fs::create_dir(&work).unwrap();
    (t, work)
}

/// Runs and expects exit 1 with every needle in stderr (whatever the case), no panic, and
/// nothing in `dir` but `keep` (no output, no temporary file).
fn expect_failure(c: &mut Command, needles: &[&str], dir: &Path, keep: &[&str]) {
    let r = run(c);
    r.fails_ignoring_case(needles);
    assert_only(dir, keep, &r.stderr);
}

/// The library's estimate of the tiny checkpoint, sky as 0: what the CLI must write.
fn library_depth(dir: &Path, photo: &Path, process_res: usize, focal: f64) -> (Vec<f32>, Vec<bool>) {
    use pixl_estimate::da3::{Da3, Da3Options};
    let net = Da3::load(dir, &candle_core::Device::Cpu).unwrap();
    let img = pixl_core::io::read_rgb(photo).unwrap();
    let est = net
        .estimate(
            &img,
            &Da3Options {
                process_res,
                focal_px_at_photo: Some(focal),
            },
        )
        .unwrap();
    let d: Vec<f32> = (0..img.width * img.height)
        .map(|i| {
            if est.sky_mask[i] {
                0.0
            } else {
                est.depth.data[i * est.depth.channels]
            }
        })
        .collect();
    (d, est.sky_mask)
}

fn read_z(path: &Path) -> (usize, usize, Vec<f32>) {
    let ch = pixl_core::exrio::read_exr_channels(path).unwrap();
    assert_eq!(ch.names().collect::<Vec<_>>(), vec!["Z"], "{}", path.display());
    (ch.width, ch.height, ch.get("Z").unwrap().to_vec())
}

fn close(a: &[f32], b: &[f32]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + y.abs()))
}

#[test]
fn depth_of_the_fixture_photo_with_preview_sky_and_json() {
    let t = common::tempdir();
    let models = models_dir(t.path(), "da3-mono", str::to_string);
    let input = tiny().join("input_a.png");
    let (out, prev, sky) = (t.path().join("d.exr"), t.path().join("p.png"), t.path().join("s.png"));
    let v = run(depth_cmd(t.path(), &input, &out)
        .args(["--model", "da3-mono", "--process-res", "112", "--fov", "60", "--json"])
        .arg("--preview")
        .arg(&prev)
        .arg("--sky")
        .arg(&sky)
        .arg("--models")
        .arg(&models))
    .ok()
    .json();
    let (w, h) = (130usize, 90usize);
    assert_eq!(
        (v["width"].as_u64(), v["height"].as_u64()),
        (Some(w as u64), Some(h as u64))
    );
    assert_eq!(v["model"], "da3-mono");
    assert_eq!(v["metric"], false);
    // --fov 60 vertical: f = (H/2)/tan(30°).
    let f = 45.0 / 30f64.to_radians().tan();
    assert!((v["focal_px"].as_f64().unwrap() - f).abs() < 1e-9, "{v}");
    assert_eq!(v["weights"]["dir"], models.join("da3-mono").display().to_string());

    let (zw, zh, z) = read_z(&out);
    assert_eq!((zw, zh), (w, h));
    let (want, mask) = library_depth(&models.join("da3-mono"), &input, 112, f);
    assert!(close(&z, &want), "the written depth differs from the library's");
    let sky_px = mask.iter().filter(|s| **s).count();
    assert!((v["sky_fraction"].as_f64().unwrap() - sky_px as f64 / (w * h) as f64).abs() < 1e-12);
    let s = pixl_core::io::read_image(&sky).unwrap();
    assert_eq!((s.width, s.height, s.channels), (w, h, 1));
    for (i, m) in mask.iter().enumerate() {
        assert_eq!(s.data[i] > 0.5, *m, "sky mask at {i}");
        if *m {
            assert_eq!(z[i], 0.0);
        }
    }
    let p = pixl_core::io::read_image(&prev).unwrap();
    assert_eq!((p.width, p.height), (w, h));
    // The nearest valid pixel is the brightest in the preview.
    let near = (0..w * h)
        .filter(|&i| z[i] > 0.0)
        .min_by(|&a, &b| z[a].total_cmp(&z[b]))
        .unwrap();
    assert!(p.data.iter().all(|&x| x <= p.data[near] + 1e-6));
}

/// Metric depth scales with the focal length (depth × f / 300 in the reference), and an EXIF
/// 35 mm-equivalent focal length is the one used when no flag is given.
#[test]
fn metric_depth_follows_the_focal_length_from_flags_or_exif() {
    let t = common::tempdir();
    let models = models_dir(t.path(), "da3-metric", as_metric);
    // A 3:2 JPEG whose EXIF says 36 mm equivalent: f = W (diagonal rule = long-side rule).
    let (w, h) = (60usize, 40usize);
    let plain = t.path().join("plain.jpg");
    photo(&plain, w, h);
    let jpg = write_file(
        &t.path().join("exif.jpg"),
        with_exif(&std::fs::read(&plain).unwrap(), 36),
    );
    let depth = |src: &Path, name: &str, extra: &[&str]| -> (Vec<f32>, serde_json::Value) {
        let out = t.path().join(name);
        let r = run(depth_cmd(t.path(), src, &out)
            .args(["--process-res", "56", "--json", "--models"])
            .arg(&models)
            .args(extra))
        .ok();
        (read_z(&out).2, r.json())
    };
    let (a, va) = depth(&jpg, "a.exr", &[]);
    assert!(va["focal_source"].as_str().unwrap().contains("EXIF"), "{va}");
    assert!((va["focal_px"].as_f64().unwrap() - w as f64).abs() < 1e-9, "{va}");
    assert_eq!(va["metric"], true);
    let (b, _) = depth(&plain, "b.exr", &["--focal", "60"]);
    assert!(
        close(&a, &b),
        "EXIF focal 36 mm on a 60 px wide 3:2 photo must equal --focal 60"
    );
    let (c, _) = depth(&plain, "c.exr", &["--focal", "120"]);
    let valid: Vec<usize> = (0..w * h).filter(|&i| b[i] > 0.0).collect();
    assert!(!valid.is_empty());
    for &i in &valid {
        assert!((c[i] / b[i] - 2.0).abs() < 1e-4, "pixel {i}: {} vs {}", c[i], b[i]);
    }
}

/// Splices an APP1 Exif segment with FocalLengthIn35mmFilm = `f35` right after the SOI.
fn with_exif(jpeg: &[u8], f35: u16) -> Vec<u8> {
    // Little-endian TIFF: IFD0 (1 entry: ExifIFD pointer → 26), Exif IFD (1 entry: 0xA405).
    let mut t = b"II".to_vec();
    t.extend_from_slice(&42u16.to_le_bytes());
    t.extend_from_slice(&8u32.to_le_bytes());
    t.extend_from_slice(&1u16.to_le_bytes());
    t.extend_from_slice(&0x8769u16.to_le_bytes());
    t.extend_from_slice(&4u16.to_le_bytes());
    t.extend_from_slice(&1u32.to_le_bytes());
    t.extend_from_slice(&26u32.to_le_bytes());
    t.extend_from_slice(&0u32.to_le_bytes());
    t.extend_from_slice(&1u16.to_le_bytes());
    t.extend_from_slice(&0xA405u16.to_le_bytes());
    t.extend_from_slice(&3u16.to_le_bytes());
    t.extend_from_slice(&1u32.to_le_bytes());
    t.extend_from_slice(&f35.to_le_bytes());
    t.extend_from_slice(&[0, 0]);
    t.extend_from_slice(&0u32.to_le_bytes());
    let mut seg = vec![0xFF, 0xE1];
    seg.extend_from_slice(&((2 + 6 + t.len()) as u16).to_be_bytes());
    seg.extend_from_slice(b"Exif\0\0");
    seg.extend_from_slice(&t);
    let mut out = jpeg[..2].to_vec();
    out.extend_from_slice(&seg);
    out.extend_from_slice(&jpeg[2..]);
    out
}

/// `pixl reconstruct --image photo -o scene/` estimates the depth with da3-metric: the mesh's
/// vertex depths are the estimated depths, sky has no mesh, and the camera has the focal length.
#[test]
fn reconstruct_from_a_photo_alone() {
    let t = common::tempdir();
    let models = models_dir(t.path(), "da3-metric", as_metric);
    let (w, h) = (42usize, 28usize);
    let p = t.path().join("photo.png");
    photo(&p, w, h);
    let scene = t.path().join("scene");
    let stdout = run(reconstruct_cmd(t.path(), &p, &scene)
        .args([
            "--fov",
            "55",
            "--process-res",
            "56",
            "--max-jump",
            "1000",
            "--format",
            "ply",
        ])
        .arg("--models")
        .arg(&models))
    .ok()
    .stdout;
    assert!(
        stdout.contains("da3-metric") && stdout.contains(&models.join("da3-metric").display().to_string()),
        "{stdout}"
    );
    let s = pixl_render::Scene::load(&scene.join("scene.toml")).unwrap();
    assert!((s.camera.fov_y() - 55.0).abs() < 1e-3);
    let f = 0.5 * h as f64 / 27.5f64.to_radians().tan();
    let (want, mask) = library_depth(&models.join("da3-metric"), &p, 56, f);
    let mesh = pixl_render::export::load_mesh(&scene.join("mesh.ply")).unwrap();
    assert!(mesh.num_triangles() > 0);
    // Each vertex's depth is the estimated depth of the pixel under its UV (full-frame mesh:
    // border vertices sit on the frame's edge with the border pixel's depth).
    for (pos, uv) in mesh.positions.iter().zip(&mesh.uvs) {
        let x = ((uv[0] * w as f32 - 0.5).round().clamp(0.0, (w - 1) as f32)) as usize;
        let y = ((uv[1] * h as f32 - 0.5).round().clamp(0.0, (h - 1) as f32)) as usize;
        let i = y * w + x;
        assert!(!mask[i], "a vertex on a sky pixel");
        assert!(
            (-pos[2] - want[i]).abs() <= 1e-4 * want[i].max(1.0),
            "({x},{y}): {} vs {}",
            -pos[2],
            want[i]
        );
    }
}

#[test]
fn a_non_image_photo_is_refused() {
    let (t, work) = home_and_work();
    let models = models_dir(t.path(), "da3-mono", str::to_string);
    let refused = |photo: &Path, keep: &[&str]| {
        expect_failure(
            depth_cmd(t.path(), photo, &work.join("d.exr"))
                .args(["--model", "da3-mono", "--models"])
                .arg(&models),
            &[photo.file_name().unwrap().to_str().unwrap()],
            &work,
            keep,
        );
    };
    let bad = write_file(&work.join("notes.png"), b"these are notes, not a picture");
    refused(&bad, &["notes.png"]);
    let txt = write_file(&work.join("notes.txt"), b"text");
    refused(&txt, &["notes.png", "notes.txt"]);
}

#[test]
fn a_one_pixel_photo_is_refused() {
    let (t, work) = home_and_work();
    let models = models_dir(t.path(), "da3-metric", as_metric);
    let p = work.join("dot.png");
    photo(&p, 1, 1);
    for mut c in [
        depth_cmd(t.path(), &p, &work.join("d.exr")),
        reconstruct_cmd(t.path(), &p, &work.join("scene")),
    ] {
        expect_failure(c.arg("--models").arg(&models), &["dot.png", "1x1"], &work, &["dot.png"]);
    }
}

/// A PNG whose header claims 100000 × 100000 pixels is refused before anything is allocated.
#[test]
fn a_huge_photo_header_is_refused() {
    let (t, work) = home_and_work();
    let p = write_file(&work.join("huge.png"), png_header_only(100_000, 100_000));
    for mut c in [
        depth_cmd(t.path(), &p, &work.join("d.exr")),
        reconstruct_cmd(t.path(), &p, &work.join("scene")),
    ] {
        expect_failure(&mut c, &["huge.png", "100000x100000"], &work, &["huge.png"]);
    }
}

/// A truncated weight file and a config.json of another model fail cleanly, naming the file.
#[test]
fn a_corrupt_checkpoint_is_refused() {
    let (t, work) = home_and_work();
    let models = models_dir(t.path(), "da3-mono", str::to_string);
    let p = work.join("photo.png");
    photo(&p, 30, 20);
    let weights = models.join("da3-mono/model.safetensors");
    let bytes = std::fs::read(&weights).unwrap();
    let refused = |needle: &str| {
        expect_failure(
            depth_cmd(t.path(), &p, &work.join("d.exr"))
                .args(["--model", "da3-mono", "--models"])
                .arg(&models),
            &[needle],
            &work,
            &["photo.png"],
        );
    };
    write_file(&weights, &bytes[..bytes.len() / 2]);
    refused("model.safetensors");

    // A config of another model (a BERT text encoder) beside intact weights.
    write_file(&weights, &bytes);
    write_file(
        &models.join("da3-mono/config.json"),
        br#"{"architectures": ["BertModel"], "model_type": "bert", "hidden_size": 768, "num_hidden_layers": 12}"#,
    );
    refused("config.json");
}

/// Offline with no weights anywhere: at once, naming `pixl models fetch`, for both commands.
#[test]
fn offline_without_weights_names_the_fetch_command() {
    let (t, work) = home_and_work();
    let p = work.join("photo.png");
    photo(&p, 30, 20);
    for (mut c, needles) in [
        (
            depth_cmd(t.path(), &p, &work.join("d.exr")),
            &["pixl models fetch da3-metric", "--models DIR"][..],
        ),
        (
            reconstruct_cmd(t.path(), &p, &work.join("scene")),
            &["pixl models fetch da3-metric"][..],
        ),
    ] {
        expect_failure(c.arg("--offline"), needles, &work, &["photo.png"]);
    }
}

/// Outputs are checked before any work: a wrong extension, a missing folder, the photo itself.
#[test]
fn bad_outputs_are_refused_before_any_work() {
    let (t, work) = home_and_work();
    let p = work.join("photo.exr");
    photo(&p, 30, 20);
    let before = std::fs::read(&p).unwrap();
    // No models anywhere and offline: reaching the model would fail with another message.
    for (out, needle) in [
        (work.join("d.png"), ".exr"),
        (work.join("nowhere/d.exr"), "does not exist"),
        (p.clone(), "photo.exr"),
    ] {
        expect_failure(&mut depth_cmd(t.path(), &p, &out), &[needle], &work, &["photo.exr"]);
    }
    assert_eq!(std::fs::read(&p).unwrap(), before, "the photo was touched");
}
