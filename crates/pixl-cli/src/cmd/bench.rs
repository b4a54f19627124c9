//! `pixl bench model`: the paper's timing protocol (2 untimed warm-ups, then 5 timed forward
//! passes; mean and median) for one network on one image size, on the CPU.
use crate::Ctx;
use candle_core::{DType, Device, Tensor};
use pixl_core::Rng;
use pixl_model::Config;

/// Compute dtype of the network.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum DtypeArg {
    F32,
    Bf16,
}

impl From<DtypeArg> for DType {
    fn from(d: DtypeArg) -> DType {
        match d {
            DtypeArg::F32 => DType::F32,
            DtypeArg::Bf16 => DType::BF16,
        }
    }
}

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Time forward passes of the network (random weights and inputs; init time not counted).
    #[command(after_help = "Example:\n  pixl bench model --config small --size 512x512 --dtype f32 --json")]
    Model(ModelArgs),
}

#[derive(clap::Args, Debug)]
pub struct ModelArgs {
    /// Preset (tiny, small, paper) or a .toml/.json config file.
    #[arg(long, default_value = "tiny")]
    pub config: String,
    /// Image size WIDTHxHEIGHT.
    #[arg(long, default_value = "512x512", value_parser = parse_size)]
    pub size: (usize, usize),
    #[arg(long, value_enum, default_value_t = DtypeArg::F32)]
    pub dtype: DtypeArg,
    /// Untimed warm-up passes.
    #[arg(long, default_value_t = pixl_eval::timing::DEFAULT_WARMUPS)]
    pub warmups: usize,
    /// Timed passes.
    #[arg(long, default_value_t = pixl_eval::timing::DEFAULT_RUNS)]
    pub runs: usize,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

fn parse_size(s: &str) -> Result<(usize, usize), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("size {s:?} is not WIDTHxHEIGHT, e.g. 512x512"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|_| format!("size {s:?}: {v:?} is not a positive integer"))
    };
    let (w, h) = (parse(w)?, parse(h)?);
    if w == 0 || h == 0 || w * h > pixl_core::io::MAX_PIXELS {
        return Err(format!(
            "size {s:?} must be positive and at most {} pixels",
            pixl_core::io::MAX_PIXELS
        ));
    }
    Ok((w, h))
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::Model(a) => bench_model(a, ctx),
    }
}

fn bench_model(args: ModelArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let cfg = Config::from_name_or_file(&args.config)?;
    let device = Device::Cpu;
    let dtype: DType = args.dtype.into();
    let model = pixl_model::build_inference(&cfg, 0, dtype, &device)?;
    let (w, h) = args.size;
    let mut rng = Rng::new(1);
    let mut rand = |c: usize| -> candle_core::Result<Tensor> {
        let v: Vec<f32> = (0..c * h * w).map(|_| rng.f32()).collect();
        Tensor::from_vec(v, (1, c, h, w), &device)
    };
    let (src, ct) = (rand(3)?, rand(9)?);
    let timing = pixl_eval::timing::time_runs(args.warmups, args.runs, || -> anyhow::Result<()> {
        let out = model.forward(&src, &ct)?;
        out.sum_all()?.to_scalar::<f32>()?; // forces the result
        Ok(())
    })?;
    if args.json {
        let out = serde_json::json!({
            "config": args.config, "params": cfg.param_count(), "width": w, "height": h,
            "dtype": format!("{:?}", args.dtype).to_lowercase(), "device": "cpu",
            "threads": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
            "timing": timing,
        });
        ctx.print_json(&out)?;
    } else {
        ctx.say(format!(
            "{} ({:.1} M params), {w}x{h}, {:?}, CPU: {}",
            args.config,
            cfg.param_count() as f64 / 1e6,
            args.dtype,
            timing.describe()
        ));
    }
    Ok(())
}
