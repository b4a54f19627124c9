//! A moving-camera clip through `pixl_pipeline::video::relight_video` (needs the system's
//! FFmpeg): detected as moving, depth estimated once per frame, every frame written, the output
//! sequence complete; and a static one estimates depth once.
use candle_core::{DType, Device};
use pixl_core::Image;
use pixl_pipeline::depth::{DepthEstimator, DepthKind, EstimatedDepth};
use pixl_pipeline::job::{DepthSource, LightSet};
use pixl_pipeline::relight::Network;
use pixl_pipeline::render::RenderSettings;
use pixl_pipeline::video::{relight_video, CameraMotion, Ffmpeg, VideoJob};
use pixl_pipeline::Silent;
use pixl_render::depth::DepthMap;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A wall whose estimated scale drifts from call to call (as a monocular estimator's does).
struct Drifting(AtomicUsize);

impl DepthEstimator for Drifting {
    fn name(&self) -> String {
        "drifting wall".into()
    }
    fn estimate(&self, photo: &Image, _focal_px: f64) -> pixl_pipeline::Result<EstimatedDepth> {
        let n = self.0.fetch_add(1, Ordering::SeqCst);
        let (w, h) = (photo.width, photo.height);
        let scale = 1.0 + 0.3 * (n % 3) as f32;
        Ok(EstimatedDepth {
            depth: DepthMap::new(
                w,
                h,
                (0..w * h).map(|i| scale * (3.0 + (i % w) as f32 / w as f32)).collect(),
            )?,
            kind: DepthKind::Metric,
            sky_fraction: 0.0,
        })
    }
}

fn clip(dir: &std::path::Path, shift: impl Fn(usize) -> usize) -> std::path::PathBuf {
    for t in 0..6 {
        let s = shift(t);
        let img = Image::from_fn(40, 24, 3, |x, y, c| {
            0.2 + 0.5 * (((x + s) / 4 + y / 4) % 2) as f32 + 0.05 * c as f32
        });
        pixl_core::io::write_image(&dir.join(format!("in{:02}.png", t + 1)), &img).unwrap();
    }
    dir.join("in%02d.png")
}

#[test]
fn a_moving_camera_gets_depth_and_ct_per_frame_a_static_one_once() {
    let ff = Ffmpeg::find().expect("this test needs ffmpeg and ffprobe");
    let net = Network::load(None, DType::F32, &Device::Cpu, false).unwrap();
    let lights = LightSet {
        preset: Some("cool-side-flash".into()),
        ..Default::default()
    };
    for (moving, calls) in [(true, 6), (false, 1)] {
        let dir = tempfile::tempdir().unwrap();
        let input = clip(dir.path(), |t| if moving { t * 5 } else { 0 });
        let est = Drifting(AtomicUsize::new(0));
        let job = VideoJob {
            input,
            output: dir.path().join("out%02d.png"),
            lights: &lights,
            depth: DepthSource::Estimate(&est),
            camera: CameraMotion::Auto,
            max_side: 32,
            render: RenderSettings {
                spp: 2,
                bounces: 1,
                seed: 0,
            },
            max_memory: None,
            focal_px: None,
            fov_deg: None,
        };
        let v = relight_video(&ff, &net, job, &Device::Cpu, &Silent).unwrap();
        assert_eq!((v.frames, v.static_camera), (6, !moving));
        assert_eq!(est.0.load(Ordering::SeqCst), calls);
        for t in 1..=6 {
            let f = pixl_core::io::read_image(&dir.path().join(format!("out{t:02}.png"))).unwrap();
            assert_eq!((f.width, f.height), (40, 24));
        }
        assert!(!dir.path().join("out07.png").exists());
    }
}
