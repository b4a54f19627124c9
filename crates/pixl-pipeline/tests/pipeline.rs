//! The pipeline through its library API, on a photo in memory: depth → geometry → lights →
//! render → C_T → network, each stage checked against an independent computation.
use candle_core::{DType, Device};
use pixl_core::Image;
use pixl_pipeline::depth::{resize_depth, to_metric, DepthKind};
use pixl_pipeline::exif::{Focal, FocalSource};
use pixl_pipeline::reconstruct::{grid_triangles, reconstruct, Maps, MeshFormat, MeshSettings};
use pixl_pipeline::relight::{ct_at_working_size, relight, Network};
use pixl_pipeline::render::{render_intrinsics, RenderSettings};
use pixl_pipeline::{Photo, Silent};
use pixl_render::depth::DepthMap;
use pixl_render::Scene;

fn photo(w: usize, h: usize) -> Photo {
    let img = Image::from_fn(w, h, 3, |x, y, c| {
        0.2 + 0.6 * ((x * 7 + y * 3 + c * 5) % 11) as f32 / 11.0
    });
    Photo::from_image(
        img,
        Focal {
            px: 0.5 * h as f64 / 25f64.to_radians().tan(),
            source: FocalSource::Default(50.0),
        },
    )
}

/// A wall 3 m away, tilted: depth 3 + x/w.
fn wall(w: usize, h: usize) -> DepthMap {
    DepthMap::new(w, h, (0..w * h).map(|i| 3.0 + (i % w) as f32 / w as f32).collect()).unwrap()
}

#[test]
fn a_photo_becomes_a_scene_a_ct_and_a_relit_photo() {
    let (w, h) = (48, 32);
    let photo = photo(w, h);
    let depth = wall(w, h);
    let settings = MeshSettings {
        stride: Some(2),
        ..Default::default()
    };
    let geometry = reconstruct(&photo, &depth, "the wall", &Maps::default(), &settings, &Silent).unwrap();
    // A smooth wall: nothing is cut, the grid is whole.
    assert_eq!(geometry.mesh.num_triangles(), grid_triangles(w, h, 2));
    assert_eq!(geometry.triangles_cut(), 0);
    assert_eq!(
        (geometry.scene.camera.width, geometry.scene.camera.height),
        (w as u32, h as u32)
    );
    // The photo is the texture, unchanged (8-bit PNG written from it later).
    assert_eq!(geometry.textures[0].0, "photo.png");
    assert_eq!(geometry.textures[0].1.data, photo.image.data);

    // In memory: the scene renders without any file.
    let dir = tempfile::tempdir().unwrap();
    let mut scene = geometry.scene.clone();
    scene.base_dir = dir.path().join("nowhere");
    pixl_render::presets::apply_preset(&mut scene, "warm-overhead-flash", false).unwrap();
    let rs = RenderSettings {
        spp: 2,
        bounces: 2,
        seed: 0,
    };
    let work = (24, 16);
    let (film, composed) = render_intrinsics(&scene, work, &rs, &Silent).unwrap();
    assert_eq!((film.width, film.height), work);
    let ct = composed.ct;
    assert_eq!((ct.width(), ct.height()), work);
    assert!(ct.shading.data.iter().any(|v| *v > 0.0), "the lit wall has shading");
    assert!(!dir.path().join("nowhere").exists());
    // Written, the same scene renders the same passes (the texture written as 8-bit PNG and read
    // back: C_T within 8-bit rounding).
    let scene_path = geometry.write(dir.path(), MeshFormat::Ply, &scene.lights).unwrap();
    let from_disk = Scene::load(&scene_path).unwrap();
    assert!(from_disk.assets.is_empty());
    let (_, composed_disk) = render_intrinsics(&from_disk, work, &rs, &Silent).unwrap();
    let worst = composed_disk
        .ct
        .albedo
        .data
        .iter()
        .zip(&ct.albedo.data)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 0.01, "albedo differs by {worst} between memory and disk");

    // A freshly initialised network (zero-initialised modulation) returns the photo exactly, at
    // its own size.
    let wpath = dir.path().join("fresh.safetensors");
    let cfg = pixl_model::Config::tiny();
    let (varmap, _) = pixl_model::build_trainable(&cfg, 0, &Device::Cpu).unwrap();
    pixl_model::save(&wpath, &varmap, &cfg).unwrap();
    let net = Network::load(Some(&wpath), DType::F32, &Device::Cpu, false).unwrap();
    let ct_work = ct_at_working_size(&ct, (16, 16)).unwrap();
    assert_eq!(ct_work.len(), 9 * 16 * 16);
    let relit = relight(&net, photo.image.clone(), &ct_work, (16, 16), &Device::Cpu, &Silent).unwrap();
    assert_eq!((relit.width, relit.height), (w, h));
    assert_eq!(relit.data, photo.image.data);
}

#[test]
fn depth_of_another_kind_and_size_becomes_metric_at_the_photo() {
    // Disparity 1..2 over a 4x2 map → 1 m (largest) to 10 m (smallest), then up to 8x4.
    let mut d = DepthMap::new(4, 2, vec![1.0, 1.5, 2.0, 1.0, 1.0, 1.5, 2.0, 1.0]).unwrap();
    to_metric(&mut d, DepthKind::Disparity, (1.0, 10.0));
    assert!((d.get(2, 0) - 1.0).abs() < 1e-6 && (d.get(0, 0) - 10.0).abs() < 1e-5);
    // 1.5 is halfway in disparity: 1 / (0.1 + 0.5 · 0.9)
    assert!((d.get(1, 0) - 1.0 / 0.55).abs() < 1e-5);
    let up = resize_depth(&d, 8, 4).unwrap();
    assert_eq!((up.width, up.height), (8, 4));
    assert!(up.data.iter().all(|v| *v >= 1.0 - 1e-6 && *v <= 10.0 + 1e-5));
}

#[test]
fn bad_input_is_refused_with_a_reason() {
    let p = photo(8, 6);
    let wrong = wall(4, 3);
    let e = reconstruct(
        &p,
        &wrong,
        "wrong.exr",
        &Maps::default(),
        &MeshSettings::default(),
        &Silent,
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("wrong.exr is 4x3") && e.to_string().contains("8x6"),
        "{e}"
    );
    let empty = DepthMap::new(8, 6, vec![0.0; 48]).unwrap();
    let e = reconstruct(
        &p,
        &empty,
        "empty.exr",
        &Maps::default(),
        &MeshSettings::default(),
        &Silent,
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("empty.exr: no pixel has a positive depth"),
        "{e}"
    );
    let s0 = MeshSettings {
        stride: Some(0),
        ..Default::default()
    };
    assert!(reconstruct(&p, &wall(8, 6), "wall.exr", &Maps::default(), &s0, &Silent).is_err());
}
