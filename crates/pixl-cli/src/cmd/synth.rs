//! `pixl synth`: generate a synthetic multi-illumination data set with exact intrinsics
//! (`pixl_train::synth`): per scene `light_<k>.png` + `light_<k>.intrinsics.exr`, plus `scenes.json`.
//!
//! The output folder is checked first: a non-empty one is refused without `--force`. A run that
//! fails or is interrupted removes the folders and files it created (`pixl_core::output::Provisional`).
//! `--json` prints one document on stdout: `{output, scenes, test_scenes, lights, size, spp,
//! image_spp, style, seed, coarse, manifest, seconds}`; see `crates/pixl-cli/README.md`.
use crate::Ctx;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Example:\n  pixl synth --scenes 48 --lights 4 --size 128 --spp 16 --seed 1 -o synth/\n\n\
Styles: photo (default) — furnished rooms and table-tops, textured wood/stone/fabric/paint/prints/\n\
tiles/metal, glossy, dark and glass objects, 1-3 lights of every kind, images shown with a camera's\n\
tone curve; boxes — the first generator (random boxes and spheres, Reinhard), for making older\n\
sets again.\n\n\
Layout: OUT/scenes.json, OUT/scene<NNNN>/light_<k>.png (+ light_<k>.intrinsics.exr), OUT/textures/.\n\
Read it back with --dataset synth:OUT (pixl train, pixl eval)."
)]
pub struct Args {
    /// Scene generator: `photo` (rooms and table-tops that look like photographs) or `boxes`
    /// (the first generator; its sets and the bundled demo weights' runs are made with it).
    #[arg(long, value_enum, default_value_t = StyleArg::Photo)]
    pub style: StyleArg,
    /// Number of procedural scenes (at least 1).
    #[arg(long, default_value_t = 100, value_parser = crate::ctx::at_least_one_usize)]
    pub scenes: usize,
    /// Lightings per scene (at least 2).
    #[arg(long, default_value_t = 6, value_parser = at_least_two)]
    pub lights: usize,
    /// Image side in pixels (square images, at least 8).
    #[arg(long, default_value_t = 256, value_parser = at_least_eight)]
    pub size: u32,
    /// Path-tracing samples per pixel of the passes C_T is composed from (at least 1): C_T keeps
    /// the noise of a quick render, as at run time.
    #[arg(long, default_value_t = 16, value_parser = crate::ctx::at_least_one)]
    pub spp: u32,
    /// Samples per pixel of the images (the training targets), from a separate render
    /// [default: 4 × --spp for photo; --spp for boxes, one render for both].
    #[arg(long, value_parser = crate::ctx::at_least_one)]
    pub image_spp: Option<u32>,
    /// Maximum bounces of the path tracer.
    #[arg(long, default_value_t = 2)]
    pub max_bounces: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Every N-th scene is held out as the test split.
    #[arg(long, default_value_t = 10)]
    pub test_every: usize,
    /// Also write, for every pair i → i+1 of every scene, the C_T of the paper's inference
    /// setting: the coarse reconstruction of image i (depth → mesh, diffuse colour → albedo)
    /// rendered under lighting i+1 (`light_<j>.from_light_<i>.intrinsics.exr`, with its
    /// path-traced picture; read by `pixl eval --ct coarse` and by training with
    /// `[data.sampler] coarse_ct`), and the same under lighting i itself (for `pixl eval`'s
    /// light-response score). Two more renders per image, at --spp.
    #[arg(long)]
    pub coarse: bool,
    /// With --coarse: the reconstruction's albedo texture — `diffcol` (the source render's
    /// diffuse colour pass: a perfect albedo estimator), `photo` (the source image itself, as
    /// `pixl reconstruct` does without --albedo: no estimator, source shading stays in it) or
    /// `estimated` (the diffuse colour with an estimator's errors drawn per source: 10-40 % of
    /// the source's shading left in, a blur of up to 5 px, a tint of up to 12 % per channel).
    #[arg(long, value_enum, default_value_t = CoarseAlbedoArg::Diffcol, requires = "coarse")]
    pub coarse_albedo: CoarseAlbedoArg,
    /// Output folder (created if missing; a non-empty one only with --force).
    #[arg(short, long)]
    pub out: PathBuf,
    /// Write into a non-empty output folder, replacing the files of the same names.
    #[arg(long)]
    pub force: bool,
    /// Print a JSON summary on stdout (even with --quiet) instead of the summary line.
    #[arg(long)]
    pub json: bool,
}

fn at_least_two(s: &str) -> Result<usize, String> {
    crate::ctx::parse_count(s, 2, u32::MAX as u64)
        .map(|v| v as usize)
        .map_err(|e| {
            if e.contains("at least") {
                format!("{e} (a pair of lightings)")
            } else {
                e
            }
        })
}

fn at_least_eight(s: &str) -> Result<u32, String> {
    crate::ctx::parse_count(s, 8, u32::MAX as u64).map(|v| v as u32)
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    pixl_core::output::check_output_dir(&args.out, args.force, &[], &[])?;
    let opts = pixl_train::synth::SynthOptions {
        style: match args.style {
            StyleArg::Photo => pixl_train::synth::SynthStyle::Photo,
            StyleArg::Boxes => pixl_train::synth::SynthStyle::Boxes,
        },
        image_spp: args.image_spp,
        scenes: args.scenes,
        lights: args.lights,
        size: args.size,
        spp: args.spp,
        max_bounces: args.max_bounces,
        seed: args.seed,
        test_every: args.test_every,
        coarse: args.coarse,
        coarse_albedo: match args.coarse_albedo {
            CoarseAlbedoArg::Diffcol => pixl_data::CoarseAlbedo::Diffcol,
            CoarseAlbedoArg::Photo => pixl_data::CoarseAlbedo::Photo,
            CoarseAlbedoArg::Estimated => pixl_data::CoarseAlbedo::Estimated,
        },
    };
    let pb = ctx.progress((args.scenes * args.lights) as u64, "synth");
    let t0 = std::time::Instant::now();
    let manifest = pixl_train::synth::generate(&opts, &args.out, &|done, total| {
        pb.set_length(total as u64);
        pb.set_position(done as u64)
    })?;
    pb.finish_and_clear();
    let test = manifest
        .scenes
        .iter()
        .filter(|s| s.split == pixl_data::Split::Test)
        .count();
    let secs = t0.elapsed().as_secs_f64();
    if args.json {
        ctx.print_json(&serde_json::json!({
            "output": args.out.display().to_string(),
            "scenes": manifest.scenes.len(),
            "test_scenes": test,
            "lights": args.lights,
            "size": args.size,
            "spp": args.spp,
            "image_spp": opts.image_spp(),
            "style": opts.style.name(),
            "seed": args.seed,
            "coarse": args.coarse,
            "manifest": args.out.join(pixl_data::folder::MANIFEST).display().to_string(),
            "seconds": secs,
        }))?;
    }
    ctx.say(format!(
        "wrote {} scenes x {} lightings ({} test scenes) to {} in {secs:.1} s",
        manifest.scenes.len(),
        args.lights,
        test,
        args.out.display(),
    ));
    Ok(())
}

/// `--style` values (see [`pixl_train::synth::SynthStyle`]).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum StyleArg {
    Photo,
    Boxes,
}

/// `--coarse-albedo` values (see [`pixl_data::CoarseAlbedo`]).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum CoarseAlbedoArg {
    Diffcol,
    Photo,
    Estimated,
}
