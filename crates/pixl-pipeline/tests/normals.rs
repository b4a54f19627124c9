//! Estimated normals reach the renderer: the reconstruction of a flat wall with a normal map
//! shades each region as `max(0, n · l)` of that region's normal under a sun, not of the wall's
//! own +Z, and its `Normal` pass is the map (a known answer worked out here, from the map and the
//! sun alone); and Marigold Normals' prediction (the fixture checkpoint) becomes the mesh's
//! vertex normals, pixel for pixel.
use pixl_core::Image;
use pixl_estimate::marigold::normals::{MarigoldNormals, NormalsOptions};
use pixl_pipeline::estimators::MarigoldNormalsEstimator;
use pixl_pipeline::exif::{Focal, FocalSource};
use pixl_pipeline::normals::{estimate_normals, NormalsEstimator};
use pixl_pipeline::observe::{Observer, Stage};
use pixl_pipeline::reconstruct::{reconstruct, Geometry, Maps, MeshSettings};
use pixl_pipeline::render::{render_film, RenderSettings};
use pixl_pipeline::{Photo, Silent};
use pixl_render::depth::DepthMap;
use pixl_render::{Color, Light};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

const W: usize = 24;
const H: usize = 16;

fn photo(w: usize, h: usize) -> Photo {
    let img = Image::from_fn(w, h, 3, |x, y, c| 0.3 + 0.4 * ((x * 5 + y * 3 + c) % 7) as f32 / 7.0);
    Photo::from_image(
        img,
        Focal {
            px: 0.5 * h as f64 / 20f64.to_radians().tan(),
            source: FocalSource::Default(40.0),
        },
    )
}

fn unit(v: [f32; 3]) -> [f32; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|c| c / l)
}

/// The normal of each quadrant of the frame (camera space), not unit length on purpose.
fn quadrant(x: usize, y: usize) -> [f32; 3] {
    match (x < W / 2, y < H / 2) {
        (true, true) => [0.0, 0.0, 2.0],
        (false, true) => [0.5, 0.0, 1.0],
        (true, false) => [0.0, -0.6, 1.0],
        (false, false) => [-0.4, 0.3, 1.0],
    }
}

/// Whether pixel (x, y) is inside its quadrant, away from the borders (a pixel's samples
/// spread over the triangles around its centre vertex) and from the frame's edge (where
/// pixel-centre vertices leave background).
fn interior(x: usize, y: usize) -> bool {
    let away = |v: usize, n: usize| v >= 1 && v + 2 <= n && v + 1 != n / 2 && v != n / 2;
    away(x, W) && away(y, H)
}

/// An estimator that returns the quadrant map, and says how far it got.
struct Quadrants;

impl NormalsEstimator for Quadrants {
    fn name(&self) -> String {
        "quadrants".into()
    }
    fn estimate(&self, photo: &Image, observer: &dyn Observer) -> pixl_pipeline::Result<Image> {
        observer.progress(Stage::Normals, 1, 1);
        Ok(Image::from_fn(photo.width, photo.height, 3, |x, y, c| {
            quadrant(x, y)[c]
        }))
    }
}

/// Records the stages it hears of.
#[derive(Default)]
struct Log(Mutex<Vec<String>>);

impl Observer for Log {
    fn begin(&self, stage: Stage, _: u64) {
        self.0.lock().unwrap().push(format!("begin {}", stage.name()));
    }
    fn progress(&self, stage: Stage, done: u64, total: u64) {
        self.0.lock().unwrap().push(format!("{} {done}/{total}", stage.name()));
    }
    fn end(&self, stage: Stage) {
        self.0.lock().unwrap().push(format!("end {}", stage.name()));
    }
}

/// A wall facing the camera 3 m away, every pixel a vertex.
fn wall(photo: &Photo, maps: &Maps) -> Geometry {
    let depth = DepthMap::new(W, H, vec![3.0; W * H]).unwrap();
    let settings = MeshSettings {
        stride: Some(1),
        pixel_centres: true,
        ..Default::default()
    };
    reconstruct(photo, &depth, "the wall", maps, &settings, &Silent).unwrap()
}

/// The wall under a sun of strength π from `l` (towards the light), Lambertian (no specular
/// coat), no world light: a pixel's direct diffuse light is `max(0, n · l)`.
fn render_under_sun(g: &Geometry, l: [f32; 3]) -> pixl_render::Film {
    let mut scene = g.scene.clone();
    scene.world = None;
    scene.objects[0].material.specular_ior_level = 0.0;
    scene.lights = vec![Light::Sun {
        name: "sun".into(),
        direction: Some(l.map(|c| -c)),
        strength: std::f32::consts::PI,
        angle_deg: 0.0,
        color: Color::default(),
    }];
    let rs = RenderSettings {
        spp: 4,
        bounces: 1,
        seed: 1,
    };
    render_film(&scene, (W, H), &rs, &Silent).unwrap()
}

#[test]
fn the_wall_is_shaded_with_the_given_normals() {
    let p = photo(W, H);
    let log = Log::default();
    let normals = estimate_normals(&Quadrants, &p, &log).unwrap();
    assert_eq!(
        *log.0.lock().unwrap(),
        vec!["begin normals", "normals 1/1", "end normals"]
    );
    let with = wall(
        &p,
        &Maps {
            normals: Some(normals),
            ..Default::default()
        },
    );
    let without = wall(&p, &Maps::default());
    // The mesh the scene holds carries the map's normals, one vertex per pixel in row order.
    let mesh = &with.scene.assets.meshes[Path::new("mesh.glb")];
    assert_eq!(mesh.normals.len(), W * H);
    for y in 0..H {
        for x in 0..W {
            let (got, want) = (mesh.normals[y * W + x], unit(quadrant(x, y)));
            assert!(
                (0..3).all(|c| (got[c] - want[c]).abs() < 1e-6),
                "({x},{y}): {got:?} vs {want:?}"
            );
        }
    }

    let l = unit([0.2, 0.3, 1.0]);
    let film = render_under_sun(&with, l);
    let plain = render_under_sun(&without, l);
    let (dir, normal) = (film.pass("DiffDir").unwrap(), film.pass("Normal").unwrap());
    let dir0 = plain.pass("DiffDir").unwrap();
    let mut checked = 0;
    for y in 0..H {
        for x in (0..W).filter(|&x| interior(x, y)) {
            let n = unit(quadrant(x, y));
            let want = (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]).max(0.0);
            for (c, nc) in n.iter().enumerate() {
                let got = dir.get(x, y, c);
                assert!((got - want).abs() < 1e-3, "({x},{y}) DiffDir {got} vs n·l {want}");
                assert!((normal.get(x, y, c) - nc).abs() < 1e-4, "({x},{y}) Normal pass");
                // Without the map, the flat wall's own +Z.
                assert!((dir0.get(x, y, c) - l[2]).abs() < 1e-3, "({x},{y}) plain wall");
            }
            checked += 1;
        }
    }
    assert!(checked >= 100, "{checked} pixels checked");
}

fn fixture_copy(to: &Path) -> PathBuf {
    fn copy_dir(src: &Path, dst: &Path) {
        std::fs::create_dir_all(dst).unwrap();
        for e in std::fs::read_dir(src).unwrap() {
            let e = e.unwrap();
            if e.path().is_dir() {
                copy_dir(&e.path(), &dst.join(e.file_name()));
            } else {
                std::fs::copy(e.path(), dst.join(e.file_name())).unwrap();
            }
        }
    }
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/marigold/normals");
    copy_dir(&src, to);
    to.to_owned()
}

#[test]
fn marigold_normals_become_the_meshs_vertex_normals() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = fixture_copy(&tmp.path().join("marigold-normals"));
    let options = NormalsOptions {
        resolution: Some(32),
        steps: Some(2),
        seed: 3,
        ..Default::default()
    };
    let dev = candle_core::Device::Cpu;
    let est = MarigoldNormalsEstimator::load(&dir, options.clone(), "marigold-normals", &dev).unwrap();
    let p = photo(W, H);
    let log = Log::default();
    let normals = estimate_normals(&est, &p, &log).unwrap();
    // Encoding, 2 steps and a decode, then the end.
    let log = log.0.into_inner().unwrap();
    assert_eq!(log.first().map(String::as_str), Some("begin normals"));
    assert_eq!(log.last().map(String::as_str), Some("end normals"));
    assert_eq!(log.len(), 2 + 4, "{log:?}");
    // The reference: the estimator crate's own prediction, in Marigold's frame.
    let reference = MarigoldNormals::load(&dir, &dev)
        .unwrap()
        .predict(&p.srgb(), &options, &mut |_| {})
        .unwrap()
        .normals;
    let g = wall(
        &p,
        &Maps {
            normals: Some(normals),
            ..Default::default()
        },
    );
    let mesh = &g.scene.assets.meshes[Path::new("mesh.glb")];
    for y in 0..H {
        for x in 0..W {
            let want = unit([0, 1, 2].map(|c| reference.get(x, y, c)));
            let got = mesh.normals[y * W + x];
            assert!(
                (0..3).all(|c| (got[c] - want[c]).abs() < 1e-5),
                "({x},{y}): {got:?} vs {want:?}"
            );
        }
    }
    // A tiny random model's normals vary over the photo: the mesh does not keep the wall's +Z.
    assert!(mesh.normals.iter().any(|n| n[2] < 0.99));
}

#[test]
fn a_normal_map_of_another_size_is_refused() {
    struct Small;
    impl NormalsEstimator for Small {
        fn name(&self) -> String {
            "small".into()
        }
        fn estimate(&self, _: &Image, _: &dyn Observer) -> pixl_pipeline::Result<Image> {
            Ok(Image::from_fn(4, 4, 3, |_, _, c| [0.0, 0.0, 1.0][c]))
        }
    }
    let e = estimate_normals(&Small, &photo(W, H), &Silent).unwrap_err().to_string();
    assert!(e.contains("small") && e.contains("4x4") && e.contains("24x16"), "{e}");
}
