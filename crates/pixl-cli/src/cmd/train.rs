//! `pixl train --config train.toml [--resume]`: train PIXLRelight (`pixl_train::Trainer`).
//! Flags override the config file. Progress bar with loss, lr and images/s; JSONL log,
//! sample grids and atomic checkpoints under `[run] out_dir`.
use crate::Ctx;
use anyhow::Context;
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  pixl train --config assets/demo-weights/train.toml\n  pixl train --config train.toml --resume\n  pixl train --config train.toml --init-weights assets/demo-weights/pixl-tiny-synth.safetensors"
)]
pub struct Args {
    /// The run's `train.toml` (see `pixl_train::config`).
    #[arg(long)]
    pub config: PathBuf,
    /// Continue from `<out_dir>/train-state.safetensors` (bit-exact on CPU).
    #[arg(long)]
    pub resume: bool,
    /// torchvision VGG16 weights (safetensors) for the perceptual loss.
    #[arg(long)]
    pub vgg: Option<PathBuf>,
    /// λ of the perceptual term (0: L1 only, no VGG needed).
    #[arg(long)]
    pub perceptual_weight: Option<f64>,
    /// Override `[run] steps`.
    #[arg(long)]
    pub steps: Option<u64>,
    /// Override `[run] out_dir`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Fine-tune: start from these weights (`[model] init_weights`; the checkpoint's model
    /// config must match `[model] preset`). Ignored with `--resume`.
    #[arg(long)]
    pub init_weights: Option<PathBuf>,
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let mut cfg = pixl_train::TrainConfig::from_file(&args.config)?;
    if let Some(v) = args.vgg {
        cfg.loss.vgg = Some(v);
    }
    if let Some(w) = args.perceptual_weight {
        cfg.loss.perceptual_weight = w;
    }
    if let Some(s) = args.steps {
        cfg.run.steps = s;
    }
    if let Some(w) = args.init_weights {
        cfg.model.init_weights = Some(w);
    }
    if let Some(o) = args.out {
        cfg.run.out_dir = o;
    }
    let device = candle_core::Device::Cpu;
    // A resumed run restores its own weights: the fine-tuning start is not read again (and
    // need not exist any more); train.toml keeps naming it.
    let mut build_cfg = cfg.clone();
    if args.resume {
        build_cfg.model.init_weights = None;
    }
    let mut trainer = pixl_train::Trainer::new(build_cfg, &device)?;
    if args.resume {
        trainer
            .restore()
            .with_context(|| format!("resuming from {}", trainer.state_path().display()))?;
        ctx.say(format!("resumed at step {}", trainer.step));
    } else if trainer.state_path().exists() {
        anyhow::bail!(
            "{} already exists: pass --resume to continue that run, or choose another out_dir",
            trainer.state_path().display()
        );
    }
    std::fs::create_dir_all(&cfg.run.out_dir).with_context(|| format!("creating {}", cfg.run.out_dir.display()))?;
    pixl_core::io::atomic_write_bytes(&cfg.run.out_dir.join("train.toml"), cfg.to_toml()?.as_bytes())?;
    if cfg.loss.perceptual_weight == 0.0 {
        ctx.say("perceptual weight 0: training with the L1 loss only");
    }
    let pb = ctx.progress(cfg.run.steps, "train");
    pb.set_position(trainer.step);
    let t0 = std::time::Instant::now();
    trainer.run(|r| {
        pb.set_position(r.step);
        pb.set_message(format!(
            "loss {:.4} lr {:.2e} {:.1} img/s",
            r.loss, r.lr, r.images_per_s
        ));
    })?;
    pb.finish_and_clear();
    ctx.say(format!(
        "trained to step {} in {:.1} s; weights {}",
        trainer.step,
        t0.elapsed().as_secs_f64(),
        trainer.model_path().display()
    ));
    Ok(())
}
