//! `pixl model`: create network weights (`init`) and report parameter counts (`info`).
use crate::Ctx;
use anyhow::Context;
use candle_core::Device;
use pixl_model::Config;
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Write freshly initialised weights (deterministic in the seed). Fresh weights return the
    /// source unchanged (zero-initialised modulation conv).
    #[command(after_help = "Example:\n  pixl model init --config tiny --seed 0 -o tiny.safetensors")]
    Init(InitArgs),
    /// Parameters per module and in total, from a preset/config file or a weights file.
    #[command(
        after_help = "Examples:\n  pixl model info --config paper\n  pixl model info --weights tiny.safetensors --json"
    )]
    Info(InfoArgs),
}

#[derive(clap::Args, Debug)]
pub struct InitArgs {
    /// Preset (tiny, small, paper) or a .toml/.json config file.
    #[arg(long, default_value = "tiny")]
    pub config: String,
    /// Seed of the initialisation.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output .safetensors file (replaced atomically if it exists).
    #[arg(short = 'o', long = "out")]
    pub out: PathBuf,
}

#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    /// Preset (tiny, small, paper) or a .toml/.json config file.
    #[arg(long, conflicts_with = "weights", required_unless_present = "weights")]
    pub config: Option<String>,
    /// A weights file (its config is read from the metadata).
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::Init(a) => init(a, ctx),
        Command::Info(a) => info(a, ctx),
    }
}

fn init(args: InitArgs, ctx: &Ctx) -> anyhow::Result<()> {
    // A config given as a file is an input (a preset name is no file and is skipped).
    pixl_core::output::check_output(&args.out, &["safetensors"], &[std::path::Path::new(&args.config)])?;
    let cfg = Config::from_name_or_file(&args.config)?;
    let (varmap, _model) = pixl_model::build_trainable(&cfg, args.seed, &Device::Cpu)
        .with_context(|| format!("building the `{}` network", args.config))?;
    pixl_model::save(&args.out, &varmap, &cfg)?;
    ctx.say(format!(
        "wrote {} ({} parameters, seed {})",
        args.out.display(),
        cfg.param_count(),
        args.seed
    ));
    Ok(())
}

fn info(args: InfoArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let (source, cfg) = match (&args.config, &args.weights) {
        (Some(c), _) => (c.clone(), Config::from_name_or_file(c)?),
        (None, Some(w)) => (w.display().to_string(), pixl_model::read_config(w)?),
        (None, None) => anyhow::bail!("give --config or --weights"),
    };
    let modules = cfg.param_breakdown();
    let total = cfg.param_count();
    if args.json {
        let map: serde_json::Map<String, serde_json::Value> = modules
            .iter()
            .map(|(m, n)| (m.to_string(), serde_json::Value::from(*n)))
            .collect();
        let out = serde_json::json!({ "source": source, "modules": map, "total": total, "config": cfg });
        return ctx.print_json(&out);
    }
    ctx.say(format!(
        "{source}: d={}, ViT {} blocks, trunk {} blocks",
        cfg.dim, cfg.src_encoder.depth, cfg.trunk.depth
    ));
    for (m, n) in &modules {
        ctx.say(format!(
            "  {m:<14} {n:>13}  ({:>5.1}%)",
            100.0 * *n as f64 / total as f64
        ));
    }
    ctx.say(format!("  {:<14} {total:>13}  ({:.1} M)", "total", total as f64 / 1e6));
    Ok(())
}
