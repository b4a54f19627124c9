//! `pixl render`: path-trace a scene file into Cycles-equivalent render passes (one multilayer
//! EXR named like Cycles': `ViewLayer.Diffuse Direct.R`, …), optionally with a lighting preset
//! and a tonemapped preview.
//!
//! Both outputs are checked before the scene is loaded (extension, folder, not an input: see
//! `pixl_core::output`) and written atomically. `--json` prints one document on stdout:
//! `{scene, output, preview, width, height, spp, seed, bounces, preset, seconds}`
//! (`preview` and `preset` null when not given); see `crates/pixl-cli/README.md`.
use crate::Ctx;
use anyhow::Context;
use pixl_core::output::check_output;
use pixl_render::presets::{apply_preset, PRESETS};
use pixl_render::{render, RenderOptions, Scene};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(after_help = concat!("Examples:\n  \
pixl render scene/scene.toml -o passes.exr\n  \
pixl render scene.toml --spp 64 --size 512x384 --preset warm-overhead-flash -o passes.exr --preview relit.png\n\n\
Presets: cool-side-flash, warm-overhead-flash, dim-overhead-spot, soft-frontal-sun, warm-interior-sun\n\n",
crate::scene_axes_help!()))]
pub struct Args {
    /// Scene file (.toml or .json).
    pub scene: PathBuf,
    /// Output EXR with all passes (.exr; replaced atomically if it exists).
    #[arg(short, long)]
    pub out: PathBuf,
    /// Samples per pixel (at least 1).
    #[arg(long, default_value_t = 16, value_parser = crate::ctx::at_least_one)]
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
    /// Also write a Reinhard-tonemapped 8-bit sRGB image of Combined (.png, .jpg or .jpeg).
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Print a JSON summary on stdout (even with --quiet) instead of the summary line.
    #[arg(long)]
    pub json: bool,
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
    let ctx = &ctx.for_json(args.json);
    check_output(&args.out, &["exr"], &[&args.scene])?;
    if let Some(p) = &args.preview {
        check_output(p, &["png", "jpg", "jpeg"], &[&args.scene, &args.out])?;
    }
    let mut scene = Scene::load(&args.scene)?;
    if let Some(p) = &args.preset {
        apply_preset(&mut scene, p, true).with_context(|| format!("{}: preset {p}", args.scene.display()))?;
    }
    // The scene's own files (meshes, textures, world image) are inputs too.
    let referenced = scene_files(&scene);
    let mut inputs: Vec<&std::path::Path> = vec![&args.scene];
    inputs.extend(referenced.iter().map(PathBuf::as_path));
    check_output(&args.out, &["exr"], &inputs)?;
    if let Some(p) = &args.preview {
        inputs.push(&args.out);
        check_output(p, &["png", "jpg", "jpeg"], &inputs)?;
    }
    let opts = RenderOptions {
        spp: args.spp,
        width: args.size.map(|s| s.0),
        height: args.size.map(|s| s.1),
        seed: args.seed,
        max_bounces: args.bounces,
    };
    let (w, h) = opts.resolution(&scene);
    let bar = ctx.progress(h as u64, "rendering");
    let t0 = std::time::Instant::now();
    let film = render(&scene, &opts, &|done, _total| bar.set_position(done as u64))
        .with_context(|| format!("rendering {}", args.scene.display()))?;
    bar.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    film.write_exr(&args.out)?;
    if let Some(p) = &args.preview {
        let img = film.combined_srgb();
        match pixl_core::io::extension(p).as_str() {
            "png" => pixl_core::io::write_png(p, &img, pixl_core::io::PngDepth::Eight)?,
            _ => pixl_core::io::write_image(p, &img)?,
        }
    }
    if args.json {
        ctx.print_json(&serde_json::json!({
            "scene": args.scene.display().to_string(),
            "output": args.out.display().to_string(),
            "preview": args.preview.as_ref().map(|p| p.display().to_string()),
            "width": w,
            "height": h,
            "spp": args.spp,
            "seed": args.seed,
            "bounces": args.bounces,
            "preset": args.preset,
            "seconds": secs,
        }))?;
    }
    ctx.say(format!(
        "rendered {w}x{h} at {} spp in {secs:.2} s -> {}",
        args.spp,
        args.out.display()
    ));
    Ok(())
}

/// The files a scene reads (meshes, textures, the world image), resolved against its folder.
fn scene_files(scene: &Scene) -> Vec<PathBuf> {
    let mut v = Vec::new();
    for o in &scene.objects {
        if let pixl_render::Shape::Mesh { path } = &o.shape {
            v.push(scene.resolve(path));
        }
        let m = &o.material;
        for t in [&m.base_color_texture, &m.roughness_texture, &m.metallic_texture]
            .into_iter()
            .flatten()
        {
            v.push(scene.resolve(t));
        }
    }
    if let Some(img) = scene.world.as_ref().and_then(|w| w.image.as_ref()) {
        v.push(scene.resolve(img));
    }
    v
}
