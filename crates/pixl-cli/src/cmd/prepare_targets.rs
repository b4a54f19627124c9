//! `pixl prepare-targets`: the training targets of real multi-illumination photos (paper §3.3):
//! for every image of a dataset, its C_T from Marigold-IID Lighting (albedo, diffuse shading,
//! non-diffuse residual, App. B's rescale) written as the cache file the loaders read,
//! `<image stem>.intrinsics.exr` beside the image ([`pixl_data::ct_cache_path`]).
//!
//! - **Resumable**: an image whose cache file exists is skipped (`--overwrite` redoes it), each
//!   file is written atomically, so an interrupted run loses at most the image in progress and
//!   the next run goes on from there. Images with exact renderer targets (`synth:` sets) need
//!   nothing and are counted apart.
//! - One model load for the whole run; a progress bar over images with an ETA; `--limit N`
//!   prepares at most N images this run.
use crate::iid::{self, IidArgs};
use crate::weights::WeightsArgs;
use crate::Ctx;
use anyhow::Context;
use pixl_estimate::marigold::IidVariant;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(after_help = concat!(
    "Examples:\n  pixl prepare-targets --dataset miiw:~/data/multi_illumination --res 512\n  \
pixl prepare-targets --dataset folder:photos/ --limit 100 --json\n\n\
Then: pixl train --config train.toml (with `dataset = \"miiw:...\"`) reads the targets.\n\
Each image takes minutes on a CPU at 768 px; run it again to continue after an interruption.\n\n",
    crate::dataset_kinds_help!()
))]
pub struct Args {
    /// The dataset, KIND:ROOT (every image of every split).
    #[arg(long)]
    pub dataset: String,
    /// Prepare at most this many images in this run (the rest are left for the next run).
    #[arg(long, value_parser = crate::ctx::at_least_one_usize)]
    pub limit: Option<usize>,
    /// Recompute images that already have a cached C_T.
    #[arg(long)]
    pub overwrite: bool,
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

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    let started = std::time::Instant::now();
    let scenes = pixl_data::scenes_all(&args.dataset)?;
    let entries: Vec<_> = scenes.into_iter().flat_map(|s| s.images).collect();
    let total = entries.len();
    // Loaders point an entry at its cache file once it exists; any other file is an exact one.
    let is_exact = |e: &pixl_data::ImageEntry| {
        e.intrinsics
            .as_ref()
            .is_some_and(|p| *p != pixl_data::ct_cache_path(&e.image))
    };
    let exact = entries.iter().filter(|e| is_exact(e)).count();
    let mut todo: Vec<(PathBuf, PathBuf)> = Vec::new();
    let mut cached = 0;
    for e in entries.iter().filter(|e| !is_exact(e)) {
        let out = pixl_data::ct_cache_path(&e.image);
        if out.is_file() && !args.overwrite {
            cached += 1;
        } else {
            todo.push((e.image.clone(), out));
        }
    }
    let pending = todo.len();
    if let Some(n) = args.limit {
        todo.truncate(n);
    }
    let mut written = Vec::new();
    if !todo.is_empty() {
        let (m, resolved) = iid::load(IidVariant::Lighting, &args.device, &args.weights, ctx)?;
        tracing::info!(
            "{} image(s) to prepare with marigold-lighting ({} from {}); {cached} already done",
            todo.len(),
            resolved.spec.licence,
            resolved.source
        );
        let opts = args.iid.options();
        let pb = ctx.progress(todo.len() as u64, "targets");
        for (image, out) in &todo {
            let photo = pixl_data::load_image(image)?;
            let pred = m
                .predict(&photo, &opts, &mut |_| {})
                .with_context(|| format!("{}: estimating its intrinsics", image.display()))?;
            let (ct, _) = pixl_pipeline::estimators::ct_from_lighting(&pred)?;
            pixl_intrinsics::ct::write_ct(out, &ct)?;
            written.push(out.clone());
            pb.inc(1);
        }
        pb.finish_and_clear();
    }
    let left = pending - written.len();
    if args.json {
        return ctx.print_json(&serde_json::json!({
            "dataset": args.dataset,
            "images": total,
            "exact_targets": exact,
            "already_cached": cached,
            "written": written.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
            "left": left,
            "seconds": started.elapsed().as_secs_f64(),
        }));
    }
    ctx.say(format!(
        "{}: {total} images: {} C_T written, {cached} already cached, {exact} with exact targets, {left} left{}",
        args.dataset,
        written.len(),
        if left > 0 { " (run again to continue)" } else { "" }
    ));
    Ok(())
}
