//! `pixl compose`: C_T = [albedo; shading; residual] from Cycles render passes (paper App. B).
//!
//! Reads a Blender multilayer EXR (`<ViewLayer>.<Pass>.<R|G|B>`, short or long pass names) or a
//! folder of single-pass EXRs named by pass, composes with `pixl_intrinsics::compose` (formulas,
//! p98 definition and ε in that module's docs), and writes the C_T file (f32 EXR, channels
//! `albedo.R/G/B`, `shading.R/G/B`, `residual.R/G/B`).
use crate::Ctx;
use pixl_intrinsics::compose::{compose, ComposeOptions, PassSet};
use pixl_intrinsics::ct::write_ct;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  pixl compose render.exr -o ct.exr\n  pixl compose passes_dir/ -o ct.exr --layer ViewLayer --json"
)]
pub struct Args {
    /// Cycles multilayer EXR, or a folder of single-pass EXRs named by pass (DiffCol.exr, Diffuse Direct.exr, …).
    pub passes: PathBuf,
    /// Output C_T file (.exr).
    #[arg(short = 'o', long = "out", visible_alias = "output")]
    pub output: PathBuf,
    /// View layer to read (default: the only one in the file).
    #[arg(long)]
    pub layer: Option<String>,
    /// Replace NaN/Inf in the passes by 0 (and report how many) instead of failing.
    #[arg(long)]
    pub sanitize: bool,
    /// Keep S and R in HDR (skip the joint p98 rescale), for debugging and round trips.
    #[arg(long)]
    pub no_rescale: bool,
    /// Print a JSON summary on stdout (even with --quiet).
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    pixl_core::output::check_output(&args.output, &["exr"], &[&args.passes])?;
    let set = PassSet::read(&args.passes, args.layer.as_deref())?;
    let opts = ComposeOptions {
        rescale: !args.no_rescale,
        sanitize: args.sanitize,
    };
    let out = compose(&set, &opts)?;
    if out.sanitized > 0 {
        tracing::warn!(
            "{}: replaced {} non-finite value(s) by 0",
            args.passes.display(),
            out.sanitized
        );
    }
    write_ct(&args.output, &out.ct)?;
    if args.json {
        let summary = serde_json::json!({
            "input": args.passes.display().to_string(),
            "output": args.output.display().to_string(),
            "width": out.ct.width(),
            "height": out.ct.height(),
            "passes": set.names(),
            "missing_optional": out.missing,
            "rescaled": opts.rescale,
            "tau": out.tau,
            "sanitized": out.sanitized,
        });
        ctx.print_json(&summary)?;
    } else {
        let scale = match out.tau {
            Some(t) => format!("τ = {t:.6} (S, R rescaled to [0, 1])"),
            None => "HDR (no rescale)".into(),
        };
        ctx.say(format!(
            "wrote {} ({}x{}, {scale}{})",
            args.output.display(),
            out.ct.width(),
            out.ct.height(),
            if out.sanitized > 0 {
                format!(", {} NaN/Inf replaced by 0", out.sanitized)
            } else {
                String::new()
            }
        ));
    }
    Ok(())
}
