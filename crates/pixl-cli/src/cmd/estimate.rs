//! `pixl estimate depth`: a photo → a depth map with Depth Anything 3 (paper §3.4), written as a
//! single-channel OpenEXR (channel `Z`) that `pixl reconstruct --depth` reads.
//! `pixl estimate materials`: a photo → albedo, roughness and metallic maps with
//! Marigold-IID Appearance (§3.4 materials), the textures `pixl reconstruct` takes.
//! `pixl estimate lighting`: a photo → its own C_T (albedo, diffuse shading, non-diffuse
//! residual) with Marigold-IID Lighting (§3.3 training targets), rescaled like `pixl compose`.
//! `pixl estimate normals`: a photo → its camera-space surface normals with Marigold Normals
//! (X right, Y up, Z towards the camera; EXR values in [-1, 1], or a 16-bit PNG of n/2 + 1/2),
//! the map `pixl reconstruct --normals` takes.
//!
//! - **Model**: `da3-metric` (default; depth in metres, scaled by the focal length) or `da3-mono`
//!   (relative depth, up to scale: reconstruct it with `--depth-kind relative`). Weights: see
//!   `pixl models` (models folder, Hugging Face cache, download on first use; `--offline`).
//! - **Focal length** (for the metric scale and the camera): `--focal`, `--fov`, EXIF, default
//!   50° vertical; see `pixl_pipeline::exif`.
//! - **Sky** (the estimator's sky score ≥ its threshold) is written as depth **0** = missing:
//!   `pixl reconstruct` builds no mesh there and the scene's world stands in for it.
//! - **Outputs** are checked before any work (extension, folder exists, none is the photo, none
//!   repeats), each written atomically.
use crate::estimators::{estimate_depth, read_photo, DepthModel};
use crate::iid::{self, IidArgs};
use crate::weights::WeightsArgs;
use crate::Ctx;
use anyhow::Context;
use pixl_core::output::check_output;
use pixl_core::Image;
use pixl_estimate::hub::Resolved;
use pixl_estimate::marigold::IidVariant;
use pixl_pipeline::estimators::{check_process_res, depth_without_sky};
use pixl_pipeline::estimators::{ct_from_lighting, Materials};
use pixl_pipeline::Photo;
use std::path::{Path, PathBuf};

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Depth (and sky) from one photo with Depth Anything 3.
    #[command(
        after_help = "Examples:\n  pixl estimate depth photo.jpg -o depth.exr --preview depth.png\n  \
pixl estimate depth photo.jpg -o depth.exr --model da3-mono --fov 60 --sky sky.png --json\n\n\
Then: pixl reconstruct --image photo.jpg --depth depth.exr -o scene/ (metric), or add --depth-kind relative \
--depth-range NEAR,FAR for da3-mono.\nSky pixels are written as depth 0 (missing): they get no mesh."
    )]
    Depth(DepthArgs),
    /// Albedo, roughness and metallic maps of a photo with Marigold-IID Appearance.
    #[command(after_help = "Examples:\n  pixl estimate materials photo.jpg -o materials/\n  \
pixl estimate materials photo.jpg -o materials/ --res 512 --ensemble 3 --json\n\n\
Writes albedo.exr (linear), albedo.png (sRGB), roughness.exr and metallic.exr into the folder \
(created if missing; must be empty unless --force).\nThen: pixl reconstruct --image photo.jpg --albedo materials/albedo.png \
--roughness materials/roughness.exr --metallic materials/metallic.exr -o scene/ (or just --materials marigold).\n\
On a CPU one photo takes minutes at 768 px (the time is shown before it starts).")]
    Materials(MaterialsArgs),
    /// The photo's own C_T (albedo, diffuse shading, residual) with Marigold-IID Lighting.
    #[command(
        after_help = "Examples:\n  pixl estimate lighting photo.jpg -o photo.intrinsics.exr\n  \
pixl estimate lighting photo.jpg -o photo.intrinsics.exr --res 512 && pixl intrinsics preview photo.intrinsics.exr -o ct.png\n\n\
The file has the channels `pixl compose` writes (albedo/shading/residual .R .G .B); shading and residual share the \
p98 rescale of App. B. For a whole dataset use `pixl prepare-targets`."
    )]
    Lighting(LightingArgs),
    /// Camera-space surface normals of a photo with Marigold Normals.
    #[command(after_help = "Examples:\n  pixl estimate normals photo.jpg -o normals.exr\n  \
pixl estimate normals photo.jpg -o normals.png --res 512 --ensemble 5 --uncertainty spread.exr --json\n\n\
The normals are unit vectors in the camera's frame: X right, Y up, Z towards the camera (a wall facing \
the camera is 0,0,1). An .exr holds them as they are (R, G, B = X, Y, Z in [-1, 1]); a .png holds \
n/2 + 1/2 in 16 bits (the usual blue-ish normal-map picture).\n\
Then: pixl reconstruct --image photo.jpg --normals normals.exr -o scene/ (or just --normals marigold).\n\
Weights: marigold-normals (prs-eth/marigold-normals-v1-1, Apache-2.0), looked up in --models DIR, then \
the Hugging Face cache, then downloaded once (about 2.6 GB; --offline never downloads).\n\
On a CPU one photo takes minutes at 768 px (the time is shown before it starts).")]
    Normals(NormalsArgs),
}

#[derive(clap::Args, Debug)]
pub struct NormalsArgs {
    /// The photo (PNG/JPEG/EXR).
    pub photo: PathBuf,
    /// Output normal map: .exr (values in [-1, 1]) or .png (16-bit, n/2 + 1/2).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Also write the ensemble's uncertainty (.exr or .png, one channel in [0, 1]: the members'
    /// mean angle to their mean normal, over pi); needs --ensemble 2 or more.
    #[arg(long, value_name = "FILE")]
    pub uncertainty: Option<PathBuf>,
    #[command(flatten)]
    pub normals: crate::normals::MarigoldNormalsArgs,
    /// Device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub weights: WeightsArgs,
}

#[derive(clap::Args, Debug)]
pub struct DepthArgs {
    /// The photo (PNG/JPEG/EXR).
    pub photo: PathBuf,
    /// Output depth map (.exr, one channel `Z`; metres for da3-metric; sky and missing = 0).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// The estimator.
    #[arg(long, value_enum, default_value_t = DepthModel::Da3Metric)]
    pub model: DepthModel,
    /// Also write a preview (.png/.jpg: inverse depth in grey, near = bright, sky = black).
    #[arg(long)]
    pub preview: Option<PathBuf>,
    /// Also write the sky mask (.png: 255 = sky).
    #[arg(long)]
    pub sky: Option<PathBuf>,
    /// Longest side the photo is resized to for the network (a multiple of 14 after rounding).
    #[arg(long, default_value_t = 504)]
    pub process_res: usize,
    /// Vertical field of view in degrees (else --focal, else EXIF, else 50).
    #[arg(long, conflicts_with = "focal")]
    pub fov: Option<f64>,
    /// Focal length in pixels at the photo's resolution.
    #[arg(long)]
    pub focal: Option<f64>,
    /// Device: cpu, or cuda[:N] (needs a CUDA build: scripts/cuda-setup.sh; `pixl doctor` lists devices).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Print a JSON summary on stdout (statistics, focal length, where the weights came from).
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub weights: WeightsArgs,
}

#[derive(clap::Args, Debug)]
pub struct MaterialsArgs {
    /// The photo (PNG/JPEG/EXR).
    pub photo: PathBuf,
    /// Output folder (created if missing).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    /// Allow a non-empty output folder (the four maps in it are replaced).
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub iid: IidArgs,
    /// Device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub weights: WeightsArgs,
}

#[derive(clap::Args, Debug)]
pub struct LightingArgs {
    /// The photo (PNG/JPEG/EXR).
    pub photo: PathBuf,
    /// Output C_T file (.exr).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
    #[command(flatten)]
    pub iid: IidArgs,
    /// Device: cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Print a JSON summary.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub weights: WeightsArgs,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::Depth(a) => depth(a, ctx),
        Command::Materials(a) => materials(a, ctx),
        Command::Lighting(a) => lighting(a, ctx),
        Command::Normals(a) => normals(a, ctx),
    }
}

fn normals(args: NormalsArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    check_output(&args.out, &["exr", "png"], &[&args.photo])?;
    if let Some(u) = &args.uncertainty {
        check_output(u, &["exr", "png"], &[&args.photo, &args.out])?;
        if args.normals.ensemble < 2 {
            anyhow::bail!(
                "--uncertainty is the spread of an ensemble: give --ensemble 2 or more (3 or more to be useful)"
            );
        }
    }
    let photo = read_photo(&args.photo)?;
    let started = std::time::Instant::now();
    let (m, resolved) = crate::normals::load(&args.device, &args.weights, ctx)?;
    let load_seconds = started.elapsed().as_secs_f64();
    let opts = args.normals.options(args.uncertainty.is_some());
    crate::normals::announce(&m, photo.width, photo.height, &opts)?;
    let started = std::time::Instant::now();
    let pb = ctx.progress(1, "normals");
    let pred = m.predict(&photo, &opts, &mut |p| {
        pb.set_length(p.total as u64);
        pb.set_position(p.done as u64);
    })?;
    pb.finish_and_clear();
    let estimate_seconds = started.elapsed().as_secs_f64();
    pixl_render::normals::write_normal_map(&args.out, &pred.normals)?;
    if let (Some(path), Some(u)) = (&args.uncertainty, &pred.uncertainty) {
        pixl_core::io::write_image(path, u)?;
    }
    // How much the normals turn away from the camera: the mean angle to +Z, in degrees.
    let n = &pred.normals;
    let tilt = n
        .data
        .chunks_exact(3)
        .map(|p| (p[2].clamp(-1.0, 1.0) as f64).acos().to_degrees())
        .sum::<f64>()
        / (n.width * n.height).max(1) as f64;
    if args.json {
        return ctx.print_json(&serde_json::json!({
            "photo": args.photo.display().to_string(),
            "out": args.out.display().to_string(),
            "uncertainty": args.uncertainty.as_ref().map(|p| p.display().to_string()),
            "width": photo.width,
            "height": photo.height,
            "processed_size": [pred.processed_size.0, pred.processed_size.1],
            "steps": pred.steps,
            "ensemble": pred.ensemble,
            "seed": args.normals.seed,
            "mean_tilt_deg": tilt,
            "load_seconds": load_seconds,
            "estimate_seconds": estimate_seconds,
            "weights": weights_json(&resolved),
        }));
    }
    ctx.say(format!(
        "{}: {}x{} at {}x{}, {} steps x {}: mean tilt from the view axis {tilt:.1} deg -> {}",
        crate::normals::MODEL,
        photo.width,
        photo.height,
        pred.processed_size.0,
        pred.processed_size.1,
        pred.steps,
        pred.ensemble,
        args.out.display()
    ));
    say_weights(ctx, &resolved);
    Ok(())
}

/// The files `pixl estimate materials` writes.
pub const MATERIAL_FILES: [&str; 4] = ["albedo.exr", "albedo.png", "roughness.exr", "metallic.exr"];

fn mean(img: &Image) -> f64 {
    img.data.iter().map(|&v| v as f64).sum::<f64>() / img.data.len().max(1) as f64
}

fn materials(args: MaterialsArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    pixl_core::output::check_output_dir(&args.out, args.force, &MATERIAL_FILES, &[&args.photo])?;
    let photo = read_photo(&args.photo)?;
    let (m, resolved) = iid::load(IidVariant::Appearance, &args.device, &args.weights, ctx)?;
    let pred = iid::run(&m, &photo, &args.iid, "materials", ctx)?;
    let mats = Materials::from_prediction(&pred)?;
    let mut created = pixl_core::output::Provisional::new();
    created.create_dir_all(&args.out)?;
    let out = |n: &str| args.out.join(n);
    pixl_core::io::write_image(&out("albedo.exr"), &mats.albedo_linear)?;
    let srgb = pred.get("albedo").context("the prediction has no albedo")?;
    pixl_core::io::write_png(&out("albedo.png"), srgb, pixl_core::io::PngDepth::Eight)?;
    pixl_core::io::write_image(&out("roughness.exr"), &mats.roughness)?;
    pixl_core::io::write_image(&out("metallic.exr"), &mats.metallic)?;
    iid::write_uncertainty(&pred, &format!("{}/", args.out.display()))?;
    created.keep();
    let (w, h) = (photo.width, photo.height);
    if args.json {
        return ctx.print_json(&serde_json::json!({
            "photo": args.photo.display().to_string(),
            "out": args.out.display().to_string(),
            "files": MATERIAL_FILES,
            "width": w,
            "height": h,
            "processed_size": [pred.processed_size.0, pred.processed_size.1],
            "steps": pred.steps,
            "ensemble": pred.ensemble,
            "seed": args.iid.seed,
            "mean_albedo_linear": mean(&mats.albedo_linear),
            "mean_roughness": mean(&mats.roughness),
            "mean_metallic": mean(&mats.metallic),
            "weights": weights_json(&resolved),
        }));
    }
    ctx.say(format!(
        "marigold-appearance: {w}x{h} at {}x{}, {} steps x {}: mean albedo {:.3} (linear), roughness {:.3}, metallic {:.3} -> {}",
        pred.processed_size.0,
        pred.processed_size.1,
        pred.steps,
        pred.ensemble,
        mean(&mats.albedo_linear),
        mean(&mats.roughness),
        mean(&mats.metallic),
        args.out.display()
    ));
    say_weights(ctx, &resolved);
    Ok(())
}

fn lighting(args: LightingArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    check_output(&args.out, &["exr"], &[&args.photo])?;
    let photo = read_photo(&args.photo)?;
    let (m, resolved) = iid::load(IidVariant::Lighting, &args.device, &args.weights, ctx)?;
    let pred = iid::run(&m, &photo, &args.iid, "lighting", ctx)?;
    let (ct, tau) = ct_from_lighting(&pred)?;
    pixl_intrinsics::ct::write_ct(&args.out, &ct)?;
    iid::write_uncertainty(&pred, &format!("{}.", args.out.with_extension("").display()))?;
    let [a, s, r] = ct.groups();
    if args.json {
        return ctx.print_json(&serde_json::json!({
            "photo": args.photo.display().to_string(),
            "out": args.out.display().to_string(),
            "width": photo.width,
            "height": photo.height,
            "processed_size": [pred.processed_size.0, pred.processed_size.1],
            "steps": pred.steps,
            "ensemble": pred.ensemble,
            "seed": args.iid.seed,
            "tau": tau,
            "mean_albedo": mean(a),
            "mean_shading": mean(s),
            "mean_residual": mean(r),
            "weights": weights_json(&resolved),
        }));
    }
    ctx.say(format!(
        "marigold-lighting: {}x{}, mean albedo {:.3}, shading {:.3}, residual {:.3} (tau {tau:.4}) -> {}",
        photo.width,
        photo.height,
        mean(a),
        mean(s),
        mean(r),
        args.out.display()
    ));
    say_weights(ctx, &resolved);
    Ok(())
}

/// The line every estimate ends with: which weights, under which licence, from where.
fn say_weights(ctx: &Ctx, r: &Resolved) {
    ctx.say(format!(
        "weights: {} ({}), from {}",
        r.spec.repo, r.spec.licence, r.source
    ));
}

fn weights_json(r: &Resolved) -> serde_json::Value {
    serde_json::json!({
        "dir": r.dir.display().to_string(),
        "source": r.source.to_string(),
        "licence": r.spec.licence,
    })
}

/// Min, median and max of the positive values (None if there are none).
fn stats(v: &[f32]) -> Option<(f32, f32, f32)> {
    let mut s: Vec<f32> = v.iter().copied().filter(|x| *x > 0.0).collect();
    if s.is_empty() {
        return None;
    }
    s.sort_by(f32::total_cmp);
    Some((s[0], s[s.len() / 2], s[s.len() - 1]))
}

/// Inverse depth in grey, normalised between its 2nd and 98th percentiles; missing = black.
fn preview(w: usize, h: usize, depth: &[f32]) -> Image {
    let mut inv: Vec<f32> = depth.iter().filter(|d| **d > 0.0).map(|d| 1.0 / d).collect();
    inv.sort_by(f32::total_cmp);
    let q = |p: f64| {
        inv.get(((inv.len().saturating_sub(1)) as f64 * p).round() as usize)
            .copied()
    };
    let (lo, hi) = (q(0.02).unwrap_or(0.0), q(0.98).unwrap_or(1.0));
    let span = if hi > lo { hi - lo } else { 1.0 };
    Image::from_fn(w, h, 1, |x, y, _| {
        let d = depth[y * w + x];
        if d > 0.0 {
            (0.05 + 0.95 * ((1.0 / d - lo) / span).clamp(0.0, 1.0)).min(1.0)
        } else {
            0.0
        }
    })
}

fn depth(args: DepthArgs, ctx: &Ctx) -> anyhow::Result<()> {
    // Everything that can be checked without the photo or the model, first.
    let ctx = &ctx.for_json(args.json);
    check_output(&args.out, &["exr"], &[&args.photo])?;
    if let Some(p) = &args.preview {
        check_output(p, &["png", "jpg", "jpeg"], &[&args.photo, &args.out])?;
    }
    if let Some(s) = &args.sky {
        let mut inputs: Vec<&Path> = vec![&args.photo, &args.out];
        inputs.extend(args.preview.as_deref());
        check_output(s, &["png"], &inputs)?;
    }
    check_process_res(args.process_res)?;
    let photo = Photo::open(&args.photo, args.focal, args.fov)?;
    let (w, h) = photo.size();
    let est = estimate_depth(&photo, args.model, args.process_res, &args.device, &args.weights, ctx)?;
    let depth = depth_without_sky(&est.estimate);
    let mut chans = pixl_core::exrio::ExrChannels::new(w, h);
    chans.push("Z", depth.clone())?;
    pixl_core::exrio::write_exr_channels(&args.out, &chans)?;
    if let Some(p) = &args.preview {
        let img = preview(w, h, &depth);
        pixl_core::io::write_png(p, &img, pixl_core::io::PngDepth::Eight)?;
    }
    let sky_px = est.estimate.sky_mask.iter().filter(|s| **s).count();
    if let Some(s) = &args.sky {
        let mask = Image::from_fn(w, h, 1, |x, y, _| {
            if est.estimate.sky_mask.get(y * w + x).copied().unwrap_or(false) {
                1.0
            } else {
                0.0
            }
        });
        pixl_core::io::write_png(s, &mask, pixl_core::io::PngDepth::Eight)?;
    }
    let st = stats(&depth);
    let unit = if est.estimate.metric { "m" } else { "(relative)" };
    if args.json {
        let v = serde_json::json!({
            "photo": args.photo.display().to_string(),
            "out": args.out.display().to_string(),
            "preview": args.preview.as_ref().map(|p| p.display().to_string()),
            "sky": args.sky.as_ref().map(|p| p.display().to_string()),
            "model": est.model.name(),
            "metric": est.estimate.metric,
            "width": w,
            "height": h,
            "processed_size": [est.estimate.processed_size.0, est.estimate.processed_size.1],
            "focal_px": est.focal.px,
            "vfov_deg": est.focal.vfov_deg(h),
            "focal_source": est.focal.source.to_string(),
            "depth_min": st.map(|s| s.0),
            "depth_median": st.map(|s| s.1),
            "depth_max": st.map(|s| s.2),
            "sky_fraction": sky_px as f64 / (w * h) as f64,
            "weights": weights_json(&est.weights),
        });
        return ctx.print_json(&v);
    }
    let range = match st {
        Some((lo, med, hi)) => format!("depth {lo:.3}–{hi:.3} {unit}, median {med:.3}"),
        None => "no pixel has a depth (all sky?)".into(),
    };
    ctx.say(format!(
        "{}: {w}x{h}, {range}, sky {:.1} % (written as 0), focal {:.1} px ({}) -> {}",
        est.model.name(),
        100.0 * sky_px as f64 / (w * h) as f64,
        est.focal.px,
        est.focal.source,
        args.out.display()
    ));
    say_weights(ctx, &est.weights);
    if !est.estimate.metric {
        ctx.say("relative depth: reconstruct it with --depth-kind relative --depth-range NEAR,FAR");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn preview_is_brighter_nearer_and_black_where_missing() {
        let d = [1.0, 2.0, 4.0, 0.0];
        let p = preview(4, 1, &d);
        assert!(p.data[0] > p.data[1] && p.data[1] > p.data[2] && p.data[2] > 0.0);
        assert_eq!(p.data[3], 0.0);
        assert_eq!(stats(&d), Some((1.0, 2.0, 4.0)));
        assert_eq!(stats(&[0.0]), None);
    }
}
