//! `pixl train --config train.toml [--resume]`: train PIXLRelight (`pixl_train::Trainer`).
//! Flags override the config file. Progress bar with loss, lr and images/s; JSONL log,
//! sample grids and atomic checkpoints under `[run] out_dir`.
//!
//! The output folder is checked before any work (`pixl_core::output::check_output_dir`: creatable,
//! writable, the weights it writes are not the run's inputs). `--json` prints one document on
//! stdout: `{config, out_dir, resumed, start_step, step, final_loss, weights, ema_weights, state,
//! seconds}` (`ema_weights` null without `[optim] ema_decay`);
//! see `crates/pixl-cli/README.md`.
use crate::Ctx;
use anyhow::Context;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
#[command(
    after_help = concat!("Examples:\n  pixl train --config assets/demo-weights/train.toml\n  pixl train --config train.toml --resume\n  \
pixl train --config train.toml --init-weights assets/demo-weights/pixl-tiny-synth.safetensors\n\n\
train.toml (every key optional; defaults are the paper's settings):\n  \
[model]           preset = \"tiny\" | \"small\" | \"paper\" | a model config file; init_seed; init_weights (fine-tune)\n  \
[data]            dataset = \"KIND:ROOT\" (kinds below); split = \"train\"; cache = true; refresh_every = 0 (N: add new scenes every N steps)\n  \
[data.sampler]    long_side = 512; multiple; min_scale; aspect_min; aspect_max; flip; coarse_ct; coarse_pair_share\n  \
[optim]           batch_size = 4; accumulate = 1; clip_norm = 1.0; precision = \"f32\" | \"bf16\"; checkpoint = false;\n                  ema_decay = 0 (e.g. 0.999: also write the weights' moving average, model-ema.safetensors)\n  \
[optim.schedule]  peak_lr = 5e-5; final_lr; warmup_steps; total_steps\n  \
[optim.adamw]     beta1; beta2; eps; weight_decay\n  \
[loss]            perceptual_weight = 0.2 (0: L1 only, no VGG weights needed); vgg = \"vgg16.safetensors\";\n                  ssim_weight = 0 (μ of an extra μ·(1 − SSIM) term, not in the paper);\n                  scale_corrected = 0 (share of the L1 taken after `pixl eval`'s per-channel scale correction)\n  \
[augment]         enabled = true (corrupt C_T on the fly with the paper's App. C pipeline; see `pixl augment`);\n                  coarse = true (also the samples on a coarse-reconstruction C_T; false: only those on exact C_T)\n  \
[run]             out_dir; steps; seed; log_every; sample_every; checkpoint_every; max_minutes; checkpoint_minutes\n\
Config files: assets/demo-weights/train.toml (a small run on a `pixl synth` set in /tmp/demo/synth);\n\
assets/demo-weights/train-dim128.toml (the run of the bundled demo weights; its data: assets/demo-weights/README.md).\n\n",
crate::dataset_kinds_help!())
)]
pub struct Args {
    /// The run's `train.toml` (keys listed below).
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
    /// Stop after this many minutes of training (`[run] max_minutes`; the learning rate's cosine
    /// then runs over the time).
    #[arg(long, value_parser = positive_minutes)]
    pub minutes: Option<f64>,
    /// Also checkpoint whenever this many minutes have passed (`[run] checkpoint_minutes`).
    #[arg(long, value_parser = positive_minutes)]
    pub checkpoint_minutes: Option<f64>,
    /// Fine-tune: start from these weights (`[model] init_weights`; the checkpoint's model
    /// config must match `[model] preset`). Ignored with `--resume`.
    #[arg(long)]
    pub init_weights: Option<PathBuf>,
    /// Device: cpu, or cuda[:N] (a CUDA build: scripts/cuda-setup.sh; `pixl doctor` lists
    /// devices). Resume is bit-exact on the CPU; on CUDA some reductions are not deterministic.
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Print a JSON summary on stdout (even with --quiet) instead of the summary lines.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
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
    if let Some(m) = args.minutes {
        cfg.run.max_minutes = Some(m);
    }
    if let Some(m) = args.checkpoint_minutes {
        cfg.run.checkpoint_minutes = Some(m);
    }
    check_out_dir(&cfg, &args.config)?;
    let device = crate::device::parse_device(&args.device)?;
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
    let saved = cfg.run.out_dir.join("train.toml");
    let text = cfg.to_toml()?;
    if args.resume {
        if let Ok(before) = std::fs::read_to_string(&saved) {
            let changed = changed_settings(&before, &text);
            if !changed.is_empty() {
                tracing::warn!(
                    "settings differ from the run's {} (the continued run is no longer bit-exact with an \
                     uninterrupted one): {}",
                    saved.display(),
                    changed.join("; ")
                );
            }
        }
    }
    pixl_core::io::atomic_write_bytes(&saved, text.as_bytes())?;
    let pb = ctx.progress(cfg.run.steps, "train");
    pb.set_position(trainer.step);
    let start_step = trainer.step;
    let mut last_loss = None;
    let t0 = std::time::Instant::now();
    trainer.run(|r| {
        pb.set_position(r.step);
        pb.set_message(format!(
            "loss {:.4} lr {:.2e} {:.1} img/s",
            r.loss, r.lr, r.images_per_s
        ));
        last_loss = Some(r.loss);
    })?;
    pb.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    if args.json {
        ctx.print_json(&serde_json::json!({
            "config": args.config.display().to_string(),
            "out_dir": cfg.run.out_dir.display().to_string(),
            "resumed": args.resume,
            "start_step": start_step,
            "step": trainer.step,
            "stopped_by": if trainer.step >= cfg.run.steps { "steps" } else { "time" },
            "scenes": trainer.scenes().len(),
            "final_loss": last_loss,
            "weights": trainer.model_path().display().to_string(),
            "ema_weights": trainer.ema_model_path().map(|p| p.display().to_string()),
            "state": trainer.state_path().display().to_string(),
            "seconds": secs,
        }))?;
    }
    ctx.say(format!(
        "trained to step {} in {secs:.1} s; weights {}{}",
        trainer.step,
        trainer.model_path().display(),
        trainer
            .ema_model_path()
            .map(|p| format!(", their moving average {}", p.display()))
            .unwrap_or_default()
    ));
    Ok(())
}

fn positive_minutes(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("{s:?} is not a positive number of minutes")),
    }
}

/// The run's folder, checked before any work: creatable and writable, and the weights and state
/// it will hold are none of the run's inputs (the config, the fine-tuning start, the VGG weights).
/// An existing folder is fine: a finished run is refused later unless `--resume`.
fn check_out_dir(cfg: &pixl_train::TrainConfig, config: &Path) -> anyhow::Result<()> {
    let mut inputs: Vec<&Path> = vec![config];
    inputs.extend(cfg.model.init_weights.as_deref());
    inputs.extend(cfg.loss.vgg.as_deref());
    pixl_core::output::check_output_dir(
        &cfg.run.out_dir,
        true,
        &[
            pixl_train::state::MODEL_FILE,
            pixl_train::state::MODEL_EMA_FILE,
            pixl_train::state::STATE_FILE,
            "log.jsonl",
        ],
        &inputs,
    )?;
    Ok(())
}

/// Settings of `before` and `after` (two `train.toml` texts) that differ, as
/// `key: old → new`, leaving out those a resumed run may change freely (its length, output
/// directory and logging / checkpoint intervals). Unparseable text compares as empty.
fn changed_settings(before: &str, after: &str) -> Vec<String> {
    const FREE: [&str; 7] = [
        "run.steps",
        "run.out_dir",
        "run.log_every",
        "run.sample_every",
        "run.checkpoint_every",
        "run.max_minutes",
        "run.checkpoint_minutes",
    ];
    fn flatten(prefix: &str, v: &toml::Value, out: &mut std::collections::BTreeMap<String, String>) {
        match v {
            toml::Value::Table(t) => {
                for (k, v) in t {
                    let key = if prefix.is_empty() {
                        k.clone()
                    } else {
                        format!("{prefix}.{k}")
                    };
                    flatten(&key, v, out);
                }
            }
            other => {
                out.insert(prefix.to_string(), other.to_string());
            }
        }
    }
    let parse = |text: &str| {
        let mut m = std::collections::BTreeMap::new();
        if let Ok(v) = text.parse::<toml::Value>() {
            flatten("", &v, &mut m);
        }
        m
    };
    let (a, b) = (parse(before), parse(after));
    let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
    keys.into_iter()
        .filter(|k| !FREE.contains(&k.as_str()))
        .filter_map(|k| {
            let (x, y) = (a.get(k), b.get(k));
            (x != y).then(|| {
                let show = |v: Option<&String>| v.cloned().unwrap_or_else(|| "(unset)".into());
                format!("{k}: {} → {}", show(x), show(y))
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::changed_settings;

    #[test]
    fn changed_settings_lists_only_relevant_differences() {
        let before = "[optim]\nbatch_size = 4\n[optim.schedule]\npeak_lr = 0.001\n[run]\nsteps = 10\nout_dir = \"a\"\n";
        let after = "[optim]\nbatch_size = 4\n[optim.schedule]\npeak_lr = 0.0005\nfinal_lr = 1e-5\n[run]\nsteps = 20\nout_dir = \"b\"\n";
        assert_eq!(
            changed_settings(before, after),
            vec![
                "optim.schedule.final_lr: (unset) → 0.00001".to_string(),
                "optim.schedule.peak_lr: 0.001 → 0.0005".to_string(),
            ]
        );
        assert!(changed_settings(before, before).is_empty());
    }
}
