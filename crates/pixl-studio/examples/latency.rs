//! Latency of the studio at its default settings (512 px working size, 128 px preview, stages
//! 4 spp at 256 px then 16 spp at 512 px, bundled weights): from a light move to (a) the preview
//! (the move request returns with it), (b) the first relit image, (c) the final relit image.
//! The settle delay (250 ms) is included in (b) and (c), as a user sees it.
//!
//! `cargo run --release -p pixl-studio --example latency [-- RUNS]`
//! The photo is the bundled demo scene rendered at 512×410 (16 spp); geometry is the fallback.
use pixl_studio::{LightPatch, Studio, StudioConfig, WaitFor};
use std::time::{Duration, Instant};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let runs: usize = std::env::args().nth(1).and_then(|a| a.parse().ok()).unwrap_or(5);
    let demo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo/scene.toml");
    let scene = pixl_render::Scene::load(&demo)?;
    let opts = pixl_render::RenderOptions {
        spp: 16,
        width: Some(512),
        ..Default::default()
    };
    let photo = pixl_render::render(&scene, &opts, &|_, _| {})?.combined_srgb();
    let png = pixl_studio::pipeline::png_bytes(&photo)?;
    let out = tempfile::tempdir()?;
    let studio = Studio::new(StudioConfig {
        out_dir: out.path().to_owned(),
        ..StudioConfig::default()
    })?;
    let t = Instant::now();
    studio.load_photo_bytes(&png, "demo.png")?;
    println!(
        "photo {}x{}: load + fallback geometry {:.0} ms",
        photo.width,
        photo.height,
        t.elapsed().as_secs_f64() * 1e3
    );
    let add: LightPatch = serde_json::from_str(r#"{"kind": "point", "anchor": [0.3, 0.4]}"#)?;
    let light = studio.add_light(&add)?;
    studio.wait(WaitFor::Final, None, Duration::from_secs(300));
    let (mut pv, mut first, mut fin) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..runs {
        let u = 0.3 + 0.4 * (i % 2) as f32;
        let mv: LightPatch = serde_json::from_value(serde_json::json!({"anchor": [u, 0.4 + 0.01 * i as f32]}))?;
        let t = Instant::now();
        studio.update_light(light.id, &mv)?;
        pv.push(t.elapsed().as_secs_f64() * 1e3);
        studio.wait(WaitFor::Render, None, Duration::from_secs(300));
        first.push(t.elapsed().as_secs_f64() * 1e3);
        studio.wait(WaitFor::Final, None, Duration::from_secs(300));
        fin.push(t.elapsed().as_secs_f64() * 1e3);
        println!(
            "run {i}: preview {:.1} ms, first relit {:.0} ms, final relit {:.0} ms",
            pv[i], first[i], fin[i]
        );
    }
    // A move while the final stage renders: the preview must not wait for the render.
    let mut busy = Vec::new();
    for i in 0..runs {
        let mv: LightPatch = serde_json::from_value(serde_json::json!({"anchor": [0.5, 0.3 + 0.02 * i as f32]}))?;
        studio.update_light(light.id, &mv)?;
        studio.wait(WaitFor::Render, None, Duration::from_secs(300));
        std::thread::sleep(Duration::from_millis(300));
        let mv: LightPatch = serde_json::from_value(serde_json::json!({"anchor": [0.6, 0.3 + 0.02 * i as f32]}))?;
        let t = Instant::now();
        studio.update_light(light.id, &mv)?;
        busy.push(t.elapsed().as_secs_f64() * 1e3);
    }
    studio.wait(WaitFor::Final, None, Duration::from_secs(300));
    println!("preview while the final stage renders: median {:.1} ms", median(busy));
    println!(
        "median of {runs}: preview {:.1} ms, first relit (256 px, 4 spp) {:.0} ms, final relit (512 px, 16 spp) {:.0} ms",
        median(pv),
        median(first),
        median(fin)
    );
    Ok(())
}
