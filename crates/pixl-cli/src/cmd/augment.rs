//! `pixl augment`: a contact sheet of corrupted draws of a C_T (paper App. C), for a person to
//! look at. Row 0 is the clean input, row k (1..=n) the draw with seed `S + k − 1`; every row
//! shows `A | S | R | A⊙S+R` with the clean input's white point (see `pixl intrinsics preview`).
use crate::Ctx;
use anyhow::Context;
use pixl_core::io::{write_png, PngDepth};
use pixl_intrinsics::augment::{corrupt_ct, AugmentConfig, Plan};
use pixl_intrinsics::ct::read_ct;
use pixl_intrinsics::preview::contact_sheet;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(after_help = "Example:\n  pixl augment ct.exr --seed 7 --n 8 -o sheet.png")]
pub struct Args {
    /// C_T file.
    pub ct: PathBuf,
    /// Seed of the first draw (draw k uses seed + k).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Number of draws.
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u64).range(1..=64))]
    pub n: u64,
    /// Output PNG.
    #[arg(short = 'o', long = "out", visible_alias = "output")]
    pub output: PathBuf,
    /// Augmentation config (TOML or JSON, fields of AugmentConfig; missing fields take Table 4's values).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Force the global gate open (every draw corrupted; the other probabilities unchanged).
    #[arg(long)]
    pub always: bool,
}

fn load_config(path: &std::path::Path) -> anyhow::Result<AugmentConfig> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))?;
    let cfg: AugmentConfig = if pixl_core::io::extension(path) == "json" {
        serde_json::from_str(&text).with_context(|| format!("{}: not a valid augment config", path.display()))?
    } else {
        toml::from_str(&text).with_context(|| format!("{}: not a valid augment config", path.display()))?
    };
    cfg.validate().with_context(|| path.display().to_string())?;
    Ok(cfg)
}

/// Names of what fires in a plan, for the log.
fn describe(plan: &Plan) -> String {
    if !plan.applied {
        return "clean (gate closed)".into();
    }
    let mut parts = Vec::new();
    let groups = ["albedo", "shading", "residual"];
    for (g, name) in groups.iter().enumerate() {
        if plan.cast[g].is_some() {
            parts.push(format!("cast({name})"));
        }
        if plan.gamma[g].is_some() {
            parts.push(format!("gamma({name})"));
        }
    }
    if let Some(h) = plan.holes {
        parts.push(format!(
            "holes({:.3}{})",
            h.fraction,
            if h.edge_weight.is_some() { ", edge" } else { "" }
        ));
    }
    if let Some(c) = plan.cracks {
        parts.push(format!("cracks(q {:.3}, s {:.2})", c.quantile, c.strength));
    }
    if let Some(f) = plan.salt_pepper {
        parts.push(format!("salt-pepper({f:.4})"));
    }
    if let Some(s) = plan.noise {
        parts.push(format!("noise(σ {s:.3})"));
    }
    if let Some(s) = plan.blur {
        parts.push(format!("blur(σ {s:.2})"));
    }
    if let Some(l) = plan.posterize {
        parts.push(format!("posterize({l})"));
    }
    if parts.is_empty() {
        "gate open, nothing fired".into()
    } else {
        parts.join(" ")
    }
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let mut inputs = vec![args.ct.as_path()];
    inputs.extend(args.config.as_deref());
    pixl_core::output::check_output(&args.output, &["png"], &inputs)?;
    let mut cfg = match &args.config {
        Some(p) => load_config(p)?,
        None => AugmentConfig::default(),
    };
    if args.always {
        cfg.p_apply = 1.0;
    }
    let ct = read_ct(&args.ct)?;
    let mut rows = vec![ct.clone()];
    let pb = ctx.progress(args.n, "augment");
    for k in 0..args.n {
        let seed = args.seed.wrapping_add(k);
        ctx.say(format!("draw {k} (seed {seed}): {}", describe(&Plan::draw(seed, &cfg))));
        rows.push(corrupt_ct(&ct, seed, &cfg)?);
        pb.inc(1);
    }
    pb.finish_and_clear();
    let sheet = contact_sheet(&rows)?;
    write_png(&args.output, &sheet, PngDepth::Eight)?;
    ctx.say(format!(
        "wrote {} (row 0 clean, rows 1..={} corrupted; A | S | R | A⊙S+R)",
        args.output.display(),
        args.n
    ));
    Ok(())
}
