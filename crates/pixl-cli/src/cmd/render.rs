//! `pixl render`: path-trace a scene file into Cycles-equivalent render passes (one multilayer
//! EXR named like Cycles': `ViewLayer.Diffuse Direct.R`, …), optionally with a lighting preset
//! and a tonemapped preview.
use crate::Ctx;
use anyhow::Context;
use pixl_render::presets::{apply_preset, PRESETS};
use pixl_render::{render, RenderOptions, Scene};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(after_help = "Examples:\n  \
pixl render scene/scene.toml -o passes.exr\n  \
pixl render scene.toml --spp 64 --size 512x384 --preset warm-overhead-flash -o passes.exr --preview relit.png\n\n\
Presets: cool-side-flash, warm-overhead-flash, dim-overhead-spot, soft-frontal-sun, warm-interior-sun")]
pub struct Args {
    /// Scene file (.toml or .json).
    pub scene: PathBuf,
    /// Output EXR with all passes.
    #[arg(short, long)]
    pub out: PathBuf,
    /// Samples per pixel.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    /// Output size WxH (default: the camera's).
    #[arg(long, value_parser = parse_size)]
    pub size: Option<(u32, u32)>,
    /// Random seed (same seed, same image).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Maximum bounces (Cycles' max_bounces; 0 = direct light only).
    #[arg(long, default_value_t = 8)]
    pub bounces: u32,
    /// Replace the scene's lights by a preset of the paper (§4.2).
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(PRESETS))]
    pub preset: Option<String>,
    /// Also write a Reinhard-tonemapped sRGB PNG of Combined.
    #[arg(long)]
    pub preview: Option<PathBuf>,
}

/// Parses `WxH`.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("size {s:?} is not WxH (e.g. 512x384)"))?;
    let w: u32 = w.trim().parse().map_err(|_| format!("size {s:?}: bad width"))?;
    let h: u32 = h.trim().parse().map_err(|_| format!("size {s:?}: bad height"))?;
    if w == 0 || h == 0 {
        return Err(format!("size {s:?} must be positive"));
    }
    Ok((w, h))
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let mut scene = Scene::load(&args.scene)?;
    if let Some(p) = &args.preset {
        apply_preset(&mut scene, p, true)?;
    }
    let opts = RenderOptions {
        spp: args.spp,
        width: args.size.map(|s| s.0),
        height: args.size.map(|s| s.1),
        seed: args.seed,
        max_bounces: args.bounces,
    };
    for note in scene.approximations() {
        tracing::warn!("{note}");
    }
    let (w, h) = opts.resolution(&scene);
    let bar = ctx.progress(h as u64, "rendering");
    let t0 = std::time::Instant::now();
    let film = render(&scene, &opts, &|done, _total| bar.set_position(done as u64))
        .with_context(|| format!("rendering {}", args.scene.display()))?;
    bar.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    film.write_exr(&args.out)?;
    if let Some(p) = &args.preview {
        pixl_core::io::write_png(p, &film.combined_srgb(), pixl_core::io::PngDepth::Eight)?;
    }
    ctx.say(format!(
        "rendered {w}x{h} at {} spp in {secs:.2} s -> {}",
        args.spp,
        args.out.display()
    ));
    Ok(())
}
