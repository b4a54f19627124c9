//! `pixl bench`: timings with the paper's protocol (2 untimed warm-ups, then 5 timed runs; mean
//! and median), on the CPU or a CUDA device, and device-against-CPU parity.
//!
//! - `model`: forward passes of one network at one image size.
//! - `train-step`: whole optimiser steps (forward, backward, global-norm clip, AdamW) on random
//!   data; bf16 compute keeps f32 master weights and moments (`pixl_train::precision`).
//! - `parity`: the network, and with `--fixtures` the estimators, on a device and on the CPU with
//!   the same weights and inputs; fails when an error is over its tolerance.
//!
//! Every timed run ends with a device synchronisation, so CUDA's asynchronous launches are
//! inside the time.
use crate::args::DtypeArg;
use crate::Ctx;
use candle_core::{DType, Device, Tensor};
use pixl_core::Rng;
use pixl_model::Config;
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Time forward passes of the network (random weights and inputs; init time not counted).
    #[command(after_help = "Example:\n  pixl bench model --config small --size 512x512 --dtype f32 --json")]
    Model(ModelArgs),
    /// Time training steps (forward, backward, clip, AdamW) on random data.
    #[command(
        name = "train-step",
        after_help = "Example:\n  pixl bench train-step --config paper --size 512x512 --batch 8 --dtype bf16 --device cuda"
    )]
    TrainStep(TrainStepArgs),
    /// Compare a device against the CPU: the network (f32 and bf16) and, with --fixtures, the
    /// estimators; fails if an error is over its tolerance.
    #[command(after_help = "Examples:\n  pixl bench parity --device cuda --fixtures fixtures\n  \
pixl bench parity --device cpu --config tiny   # a dry run: both sides on the CPU")]
    Parity(ParityArgs),
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
    /// 8-bit matrix products in the linear layers (CPU f32 with AVX-512 VNNI).
    #[arg(long)]
    pub int8: bool,
    #[command(flatten)]
    pub run: RunArgs,
}

#[derive(clap::Args, Debug)]
pub struct TrainStepArgs {
    /// Preset (tiny, small, paper) or a .toml/.json config file.
    #[arg(long, default_value = "tiny")]
    pub config: String,
    /// Crop size WIDTHxHEIGHT.
    #[arg(long, default_value = "256x256", value_parser = parse_size)]
    pub size: (usize, usize),
    /// Images per step.
    #[arg(long, default_value_t = 2, value_parser = crate::ctx::at_least_one_usize)]
    pub batch: usize,
    /// Compute dtype (master weights and AdamW moments stay f32).
    #[arg(long, value_enum, default_value_t = DtypeArg::F32)]
    pub dtype: DtypeArg,
    /// Recompute each block's activations in the backward pass (gradient checkpointing).
    #[arg(long)]
    pub checkpoint: bool,
    #[command(flatten)]
    pub run: RunArgs,
}

/// The timing protocol, device and output shared by `model` and `train-step`.
#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// Untimed warm-up runs.
    #[arg(long, default_value_t = pixl_eval::timing::DEFAULT_WARMUPS)]
    pub warmups: usize,
    /// Timed runs.
    #[arg(long, default_value_t = pixl_eval::timing::DEFAULT_RUNS)]
    pub runs: usize,
    /// Device: cpu, or cuda[:N] (a CUDA build: scripts/cuda-setup.sh).
    #[arg(long, default_value = "cpu")]
    pub device: String,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

#[derive(clap::Args, Debug)]
pub struct ParityArgs {
    /// The device compared with the CPU: cuda[:N], or cpu for a dry run.
    #[arg(long, default_value = "cuda")]
    pub device: String,
    /// Network preset (or config file) for the comparison.
    #[arg(long, default_value = "small")]
    pub config: String,
    /// Image size WIDTHxHEIGHT of the network comparison.
    #[arg(long, default_value = "256x256", value_parser = parse_size)]
    pub size: (usize, usize),
    /// The repository's fixtures folder: also compare Depth Anything 3 (da3/tiny) and
    /// Marigold-IID Appearance (marigold/appearance) on their fixture models (copied to a
    /// temporary folder first; nothing under it is written).
    #[arg(long, value_name = "DIR")]
    pub fixtures: Option<PathBuf>,
    /// Largest relative L2 error accepted for f32 (‖device − cpu‖ / ‖cpu‖ of the change the
    /// network makes to the source, (1 + g)·I_S + b − I_S).
    #[arg(long, default_value_t = 1e-4)]
    pub tol_f32: f64,
    /// Largest relative L2 error accepted for bf16 against bf16 on the CPU.
    #[arg(long, default_value_t = 2e-2)]
    pub tol_bf16: f64,
    /// Largest relative L2 error accepted for bf16 on the device against f32 on the CPU.
    #[arg(long, default_value_t = 1e-1)]
    pub tol_bf16_vs_f32: f64,
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
        Command::TrainStep(a) => bench_train_step(a, ctx),
        Command::Parity(a) => parity(a, ctx),
    }
}

fn bench_model(args: ModelArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let cfg = Config::from_name_or_file(&args.config)?;
    let device = crate::device::parse_device(&args.run.device)?;
    let dtype: DType = args.dtype.into();
    let mut model = pixl_model::build_inference(&cfg, 0, dtype, &device)?;
    let int8_layers = if args.int8 {
        crate::device::check_int8(&device, dtype)?;
        match model.quantize_int8()? {
            0 => anyhow::bail!("--int8: this CPU has no AVX-512 VNNI"),
            n => n,
        }
    } else {
        0
    };
    let (w, h) = args.size;
    let mut rng = Rng::new(1);
    let (src, ct) = (
        random(&mut rng, (1, 3, h, w), &device)?,
        random(&mut rng, (1, 9, h, w), &device)?,
    );
    let timing = pixl_eval::timing::time_runs(args.run.warmups, args.run.runs, || -> anyhow::Result<()> {
        let out = model.forward(&src, &ct)?;
        device.synchronize()?;
        drop(out);
        Ok(())
    })?;
    if args.run.json {
        let out = serde_json::json!({
            "config": args.config, "params": cfg.param_count(), "width": w, "height": h,
            "dtype": format!("{:?}", args.dtype).to_lowercase(), "device": args.run.device,
            "int8_layers": int8_layers,
            "threads": candle_core::utils::get_num_threads(),
            "timing": timing,
        });
        ctx.print_json(&out)?;
    } else {
        ctx.say(format!(
            "{} ({:.1} M params), {w}x{h}, {:?}{}, {}: {}",
            args.config,
            cfg.param_count() as f64 / 1e6,
            args.dtype,
            if args.int8 {
                format!(", {int8_layers} int8 layers")
            } else {
                String::new()
            },
            args.run.device,
            timing.describe()
        ));
    }
    Ok(())
}

/// Uniform [0, 1) values of `shape` from `rng`, made on the CPU (the same numbers on any device).
fn random(rng: &mut Rng, shape: (usize, usize, usize, usize), device: &Device) -> candle_core::Result<Tensor> {
    let n = shape.0 * shape.1 * shape.2 * shape.3;
    let v: Vec<f32> = (0..n).map(|_| rng.f32()).collect();
    Tensor::from_vec(v, shape, &Device::Cpu)?.to_device(device)
}

fn bench_train_step(args: TrainStepArgs, ctx: &Ctx) -> anyhow::Result<()> {
    use pixl_train::optim::{clip_global_norm, AdamW, AdamWConfig};
    use pixl_train::recompute;
    let cfg = Config::from_name_or_file(&args.config)?;
    let device = crate::device::parse_device(&args.run.device)?;
    let dtype: DType = args.dtype.into();
    let (varmap, model) = pixl_model::build_trainable(&cfg, 0, &device)?;
    let vars: std::collections::BTreeMap<String, candle_core::Var> = varmap
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("VarMap lock poisoned"))?
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    let mut opt = AdamW::new(vars, AdamWConfig::default())?;
    let params: Vec<candle_core::Var> = opt.params.iter().map(|p| p.var.clone()).collect();
    let (w, h, b) = (args.size.0, args.size.1, args.batch);
    let mut rng = Rng::new(1);
    let src = random(&mut rng, (b, 3, h, w), &device)?;
    let ct = random(&mut rng, (b, 9, h, w), &device)?;
    let tgt = random(&mut rng, (b, 3, h, w), &device)?;
    let step_fn = if args.checkpoint {
        recompute::checkpointed
    } else {
        recompute::plain
    };
    let mut last_loss = f32::NAN;
    let timing = pixl_eval::timing::time_runs(args.run.warmups, args.run.runs, || -> anyhow::Result<()> {
        let mut grads: Vec<Option<Tensor>> = vec![None; params.len()];
        let compute;
        let m = if dtype == DType::F32 {
            &model
        } else {
            compute = pixl_train::precision::compute_model(&cfg, &opt.params, dtype, &device)?;
            &compute
        };
        let objective = pixl_train::loss::Objective::l1_only();
        let r = step_fn(m, &src, &ct, &tgt, &objective, 1.0, &params, &mut grads)?;
        clip_global_norm(&mut grads, 1.0)?;
        opt.step(&grads, 1e-4)?;
        device.synchronize()?;
        last_loss = r.loss;
        Ok(())
    })?;
    let dtype_name = format!("{:?}", args.dtype).to_lowercase();
    if args.run.json {
        return ctx.print_json(&serde_json::json!({
            "config": args.config, "params": cfg.param_count(), "width": w, "height": h, "batch": b,
            "dtype": dtype_name, "checkpoint": args.checkpoint, "device": args.run.device,
            "last_loss": last_loss, "timing": timing,
        }));
    }
    ctx.say(format!(
        "{} ({:.1} M params), batch {b} at {w}x{h}, {dtype_name} compute{}, {}: {} per step (last loss {last_loss:.4})",
        args.config,
        cfg.param_count() as f64 / 1e6,
        if args.checkpoint { ", checkpointed" } else { "" },
        args.run.device,
        timing.describe()
    ));
    Ok(())
}

/// One comparison of [`parity`].
#[derive(serde::Serialize)]
struct ParityRow {
    what: String,
    dtype: &'static str,
    rel_l2: f64,
    max_abs: f64,
    tolerance: f64,
    pass: bool,
}

/// The comparisons of [`parity`], in order.
#[derive(Default)]
struct Rows(Vec<ParityRow>);

impl Rows {
    fn push(
        &mut self,
        what: String,
        dtype: &'static str,
        got: &[f32],
        want: &[f32],
        tolerance: f64,
    ) -> anyhow::Result<()> {
        let (rel_l2, max_abs) = errors(got, want)?;
        let pass = rel_l2 <= tolerance;
        self.0.push(ParityRow {
            what,
            dtype,
            rel_l2,
            max_abs,
            tolerance,
            pass,
        });
        Ok(())
    }
}

/// (‖a − b‖₂ / ‖b‖₂, max |a − b|) in f64.
fn errors(a: &[f32], b: &[f32]) -> anyhow::Result<(f64, f64)> {
    anyhow::ensure!(a.len() == b.len(), "outputs of {} and {} values", a.len(), b.len());
    let (mut num, mut den, mut max) = (0f64, 0f64, 0f64);
    for (&x, &y) in a.iter().zip(b) {
        let d = x as f64 - y as f64;
        num += d * d;
        den += (y as f64) * (y as f64);
        max = max.max(d.abs());
    }
    let rel = if den > 0.0 { (num / den).sqrt() } else { num.sqrt() };
    // A NaN anywhere must fail, not compare as small.
    if a.iter().any(|v| !v.is_finite()) {
        return Ok((f64::INFINITY, f64::INFINITY));
    }
    Ok((rel, max))
}

fn flat(t: &Tensor) -> candle_core::Result<Vec<f32>> {
    t.to_device(&Device::Cpu)?
        .to_dtype(DType::F32)?
        .flatten_all()?
        .to_vec1::<f32>()
}

fn parity(args: ParityArgs, ctx: &Ctx) -> anyhow::Result<()> {
    let device = crate::device::parse_device(&args.device)?;
    let cpu = Device::Cpu;
    let mut rows = Rows::default();

    // The network: seeded weights and inputs made on the CPU, then moved.
    let cfg = Config::from_name_or_file(&args.config)?;
    let (varmap, _) = pixl_model::build_trainable(&cfg, 0, &cpu)?;
    // The released initialisation zeroes the modulation (the network returns its source), which
    // would hide every difference: add small seeded noise to every weight.
    {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| anyhow::anyhow!("VarMap lock poisoned"))?;
        let mut names: Vec<&String> = data.keys().collect();
        names.sort();
        let mut rng = Rng::new(11);
        for name in names {
            let var = &data[name];
            let noise: Vec<f32> = (0..var.elem_count()).map(|_| 0.02 * rng.normal()).collect();
            let noise = Tensor::from_vec(noise, var.dims(), &cpu)?;
            var.set(&(var.as_tensor() + noise)?)?;
        }
    }
    let (w, h) = args.size;
    let mut rng = Rng::new(7);
    let src = random(&mut rng, (1, 3, h, w), &cpu)?;
    let ct = random(&mut rng, (1, 9, h, w), &cpu)?;
    // Compared: the change the network makes, (1 + g)·I_S + b − I_S (the source itself would
    // dominate a relative error of the output).
    let change =
        |out: &Tensor| -> candle_core::Result<Vec<f32>> { flat(&(out.to_device(&cpu)?.to_dtype(DType::F32)? - &src)?) };
    let run = |dtype: DType, device: &Device| -> anyhow::Result<Vec<f32>> {
        let model = pixl_model::freeze(&cfg, &varmap, dtype, device)?;
        Ok(change(
            &model.forward_unclipped(&src.to_device(device)?, &ct.to_device(device)?)?,
        )?)
    };
    let net = format!("network {} {w}x{h}", args.config);
    let want_f32 = run(DType::F32, &cpu)?;
    rows.push(net.clone(), "f32", &run(DType::F32, &device)?, &want_f32, args.tol_f32)?;
    // bf16 on the device against bf16 on the CPU (the same computation in the same dtype), and
    // how far bf16 is from f32 at all (for information: bf16 keeps 8 bits of mantissa).
    let got_bf16 = run(DType::BF16, &device)?;
    rows.push(net.clone(), "bf16", &got_bf16, &run(DType::BF16, &cpu)?, args.tol_bf16)?;
    rows.push(
        format!("{net} vs f32"),
        "bf16",
        &got_bf16,
        &want_f32,
        args.tol_bf16_vs_f32,
    )?;

    if let Some(fixtures) = &args.fixtures {
        let tmp = std::env::temp_dir().join(format!("pixl-parity-{}", std::process::id()));
        let result = estimator_parity(fixtures, &tmp, &device, args.tol_f32, &mut rows);
        let _ = std::fs::remove_dir_all(&tmp);
        result?;
    }

    let rows = rows.0;
    let failed = rows.iter().filter(|r| !r.pass).count();
    if args.json {
        ctx.print_json(&serde_json::json!({ "device": args.device, "rows": rows, "failed": failed }))?;
    } else {
        ctx.say(format!("{} against the CPU:", args.device));
        for r in &rows {
            ctx.say(format!(
                "  {:<34} {:<5} rel L2 {:.2e}  max abs {:.2e}  (tolerance {:.0e}) {}",
                r.what,
                r.dtype,
                r.rel_l2,
                r.max_abs,
                r.tolerance,
                if r.pass { "ok" } else { "FAILED" }
            ));
        }
    }
    anyhow::ensure!(failed == 0, "{failed} of {} parity checks over tolerance", rows.len());
    Ok(())
}

/// Depth Anything 3 and Marigold-IID Appearance on their fixture models, device against CPU.
fn estimator_parity(
    fixtures: &std::path::Path,
    tmp: &std::path::Path,
    device: &Device,
    tol: f64,
    rows: &mut Rows,
) -> anyhow::Result<()> {
    use anyhow::Context as _;
    use pixl_estimate::da3::{Da3, Da3Options};
    use pixl_estimate::marigold::{Marigold, MarigoldOptions};
    let da3_dir = fixtures.join("da3/tiny");
    let photo = pixl_core::io::read_rgb(&da3_dir.join("input_a.png"))
        .with_context(|| format!("{} is not the repository's fixtures folder", fixtures.display()))?;
    let opts = Da3Options::default();
    let want = Da3::load(&da3_dir, &Device::Cpu)?.estimate(&photo, &opts)?;
    let got = Da3::load(&da3_dir, device)?.estimate(&photo, &opts)?;
    rows.push(
        "depth anything 3 (tiny) depth".into(),
        "f32",
        &got.depth.data,
        &want.depth.data,
        tol,
    )?;
    rows.push(
        "depth anything 3 (tiny) sky".into(),
        "f32",
        &got.sky.data,
        &want.sky.data,
        tol,
    )?;

    // Marigold writes its empty-prompt embedding cache into the model folder: work on a copy.
    let src = fixtures.join("marigold/appearance");
    let dir = tmp.join("appearance");
    copy_tree(&src, &dir).with_context(|| format!("copying {}", src.display()))?;
    let opts = MarigoldOptions {
        steps: Some(4),
        ensemble: 1,
        resolution: Some(32),
        ..Default::default()
    };
    let want = Marigold::load(&dir, &Device::Cpu)?.predict(&photo, &opts, &mut |_| {})?;
    let got = Marigold::load(&dir, device)?.predict(&photo, &opts, &mut |_| {})?;
    for ((target, g), (_, w)) in got.maps.iter().zip(&want.maps) {
        rows.push(
            format!("marigold appearance {}", target.name),
            "f32",
            &g.data,
            &w.data,
            tol,
        )?;
    }
    Ok(())
}

fn copy_tree(src: &std::path::Path, dst: &std::path::Path) -> std::io::Result<()> {
    std::fs::create_dir_all(dst)?;
    for entry in std::fs::read_dir(src)? {
        let entry = entry?;
        let to = dst.join(entry.file_name());
        if entry.file_type()?.is_dir() {
            copy_tree(&entry.path(), &to)?;
        } else {
            std::fs::copy(entry.path(), &to)?;
        }
    }
    Ok(())
}
