//! One relighting job through `pixl_pipeline::job::run`, against the same stages called one by
//! one: the photo is used as decoded (never re-read), the depth estimated once, nothing written
//! without `keep`, and `keep` holding exactly what it lists.
use candle_core::{DType, Device};
use pixl_core::Image;
use pixl_pipeline::depth::{DepthEstimator, DepthKind, EstimatedDepth};
use pixl_pipeline::exif::{Focal, FocalSource};
use pixl_pipeline::job::{self, DepthSource, Job, LightSet, Lighting, KEPT};
use pixl_pipeline::lights::{LightSpec, LightType};
use pixl_pipeline::reconstruct::{reconstruct, Maps, MeshSettings};
use pixl_pipeline::relight::{ct_at_working_size, relight, Network};
use pixl_pipeline::render::{render_intrinsics, RenderSettings};
use pixl_pipeline::{Photo, Silent};
use pixl_render::depth::DepthMap;
use std::sync::atomic::{AtomicUsize, Ordering};

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

/// A tilted wall 3 m away, counting its calls.
struct Wall(AtomicUsize);

impl DepthEstimator for Wall {
    fn name(&self) -> String {
        "wall".into()
    }
    fn estimate(&self, photo: &Image, _focal_px: f64) -> pixl_pipeline::Result<EstimatedDepth> {
        self.0.fetch_add(1, Ordering::SeqCst);
        let (w, h) = (photo.width, photo.height);
        Ok(EstimatedDepth {
            depth: DepthMap::new(w, h, (0..w * h).map(|i| 3.0 + (i % w) as f32 / w as f32).collect())?,
            kind: DepthKind::Metric,
            sky_fraction: 0.0,
        })
    }
}

const RENDER: RenderSettings = RenderSettings {
    spp: 2,
    bounces: 2,
    seed: 3,
};

fn lights() -> LightSet {
    let spec = LightSpec {
        light_type: Some(LightType::Point),
        at_pixel: Some([20.0, 10.0]),
        power: Some(40.0),
        ..Default::default()
    };
    LightSet {
        preset: Some("cool-side-flash".into()),
        placed: vec![("--type point --at-pixel 20,10 --power 40".into(), spec)],
        fixed: vec![],
    }
}

#[test]
fn a_job_with_lights_is_its_stages_in_order_and_writes_only_what_keep_asks() {
    let (w, h) = (40, 28);
    let net = Network::load(None, DType::F32, &Device::Cpu, false).unwrap();
    let wall = Wall(AtomicUsize::new(0));
    let lights = lights();
    let job = |keep| Job {
        photo: photo(w, h),
        lighting: Lighting::Lights {
            lights: &lights,
            depth: DepthSource::Estimate(&wall),
        },
        max_side: 20,
        render: RENDER,
        max_memory: None,
        keep,
    };
    let cwd_before: Vec<_> = std::fs::read_dir(".").unwrap().map(|e| e.unwrap().path()).collect();
    let relit = job::run(&net, job(None), &Device::Cpu, &Silent).unwrap();
    assert_eq!(wall.0.load(Ordering::SeqCst), 1, "the depth is estimated once");
    assert!(relit.kept.is_empty() && relit.like.is_none());
    let cwd_after: Vec<_> = std::fs::read_dir(".").unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(cwd_before, cwd_after, "nothing written without keep");
    assert_eq!((relit.image.width, relit.image.height), (w, h));
    let work = relit.budget.work;
    assert_eq!(work, (20, 14));

    // The same stages, one by one: mesh stride = ceil(long side / working long side) = 2, the
    // preset's lights first, then the placed one.
    let p = photo(w, h);
    let depth = wall.estimate(&p.image, p.focal.px).unwrap().depth;
    let settings = MeshSettings {
        stride: Some(2),
        ..Default::default()
    };
    let geometry = reconstruct(&p, &depth, "wall", &Maps::default(), &settings, &Silent).unwrap();
    let mut scene = geometry.scene.clone();
    scene.lights.clear();
    pixl_render::presets::apply_preset(&mut scene, "cool-side-flash", false).unwrap();
    let preset_lights = scene.lights.len();
    let (light, _) = lights.placed[0].1.build(&scene).unwrap();
    scene.lights.push(light);
    let (_, composed) = render_intrinsics(&scene, work, &RENDER, &Silent).unwrap();
    let ct_work = ct_at_working_size(&composed.ct, work).unwrap();
    let expected = relight(&net, p.image.clone(), &ct_work, work, &Device::Cpu, &Silent).unwrap();
    assert_eq!(relit.image.data, expected.data);

    // With keep: the listed files, the C_T as rendered, the scene with every light.
    let dir = tempfile::tempdir().unwrap();
    let kept_dir = dir.path().join("steps");
    let kept = job::run(&net, job(Some(kept_dir.clone())), &Device::Cpu, &Silent).unwrap();
    assert_eq!(kept.image.data, expected.data);
    let names: Vec<_> = kept
        .kept
        .iter()
        .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names, KEPT);
    for p in &kept.kept {
        assert!(p.exists(), "{} listed but missing", p.display());
    }
    let ct = pixl_intrinsics::ct::read_ct(&kept_dir.join("CT.exr")).unwrap();
    assert_eq!(ct.to_chw(), composed.ct.to_chw());
    let scene_file = std::fs::read_dir(kept_dir.join("scene"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "toml"))
        .expect("a scene file");
    let on_disk = pixl_render::Scene::load(&scene_file).unwrap();
    assert_eq!(on_disk.lights.len(), preset_lights + 1);
}

#[test]
fn intrinsics_of_another_size_are_refused_and_a_tiny_budget_before_any_work() {
    let net = Network::load(None, DType::F32, &Device::Cpu, false).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let ct_path = dir.path().join("ct.exr");
    let grey = |c| Image::from_fn(10, 10, 3, move |_, _, _| c);
    let ct = pixl_intrinsics::ct::Ct::new(grey(0.5), grey(0.4), grey(0.0)).unwrap();
    pixl_intrinsics::ct::write_ct(&ct_path, &ct).unwrap();
    let job = |max_memory| Job {
        photo: photo(40, 28),
        lighting: Lighting::Intrinsics(&ct_path),
        max_side: 20,
        render: RENDER,
        max_memory,
        keep: None,
    };
    let err = job::run(&net, job(None), &Device::Cpu, &Silent)
        .err()
        .unwrap()
        .to_string();
    assert!(err.contains("10x10") && err.contains("20x14"), "{err}");
    let wall = Wall(AtomicUsize::new(0));
    let lights = lights();
    let tiny = Job {
        lighting: Lighting::Lights {
            lights: &lights,
            depth: DepthSource::Estimate(&wall),
        },
        ..job(Some(1000))
    };
    let err = job::run(&net, tiny, &Device::Cpu, &Silent).err().unwrap().to_string();
    assert!(err.contains("--max-memory"), "{err}");
    assert_eq!(wall.0.load(Ordering::SeqCst), 0, "refused before the depth");
}
