//! `pixl synth`: generate a synthetic multi-illumination data set with exact intrinsics
//! (`pixl_train::synth`): per scene `light_<k>.png` + `light_<k>.intrinsics.exr`, plus `scenes.json`.
use crate::Ctx;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(after_help = "Example:\n  pixl synth --scenes 48 --lights 4 --size 128 --spp 16 --seed 1 -o synth/")]
pub struct Args {
    /// Number of procedural scenes.
    #[arg(long, default_value_t = 100)]
    pub scenes: usize,
    /// Lightings per scene (at least 2).
    #[arg(long, default_value_t = 6)]
    pub lights: usize,
    /// Image side in pixels (square images).
    #[arg(long, default_value_t = 256)]
    pub size: u32,
    /// Path-tracing samples per pixel.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
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
    /// rendered under lighting i+1 (`light_<j>.from_light_<i>.intrinsics.exr`; read by
    /// `pixl eval --ct coarse` and by training with `[data.sampler] coarse_ct`). Doubles the time.
    #[arg(long)]
    pub coarse: bool,
    /// With --coarse: the reconstruction's albedo texture — `diffcol` (the source render's
    /// diffuse colour pass: a perfect albedo estimator) or `photo` (the source image itself, as
    /// `pixl reconstruct` does without --albedo: no estimator, source shading stays in it).
    #[arg(long, value_enum, default_value_t = CoarseAlbedoArg::Diffcol, requires = "coarse")]
    pub coarse_albedo: CoarseAlbedoArg,
    /// Output directory.
    #[arg(short, long)]
    pub out: PathBuf,
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let opts = pixl_train::synth::SynthOptions {
        scenes: args.scenes,
        lights: args.lights,
        size: args.size,
        spp: args.spp,
        max_bounces: args.max_bounces,
        seed: args.seed,
        test_every: args.test_every,
        coarse: args.coarse,
        coarse_albedo: match args.coarse_albedo {
            CoarseAlbedoArg::Diffcol => pixl_train::synth::CoarseAlbedo::Diffcol,
            CoarseAlbedoArg::Photo => pixl_train::synth::CoarseAlbedo::Photo,
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
        .filter(|s| s.split == pixl_train::data::Split::Test)
        .count();
    ctx.say(format!(
        "wrote {} scenes x {} lightings ({} test scenes) to {} in {:.1} s",
        manifest.scenes.len(),
        args.lights,
        test,
        args.out.display(),
        t0.elapsed().as_secs_f64()
    ));
    Ok(())
}

/// `--coarse-albedo` values (see [`pixl_train::synth::CoarseAlbedo`]).
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum CoarseAlbedoArg {
    Diffcol,
    Photo,
}
