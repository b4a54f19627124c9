//! Times one forward of the Marigold UNet (`marigold::unet`, f32, CPU) at Stable Diffusion 2's
//! size (`UnetConfig::sd2(8, 4)`: block_out_channels 320, 640, 1280, 1280, 8 input channels,
//! cross-attention on 77 tokens of 1024) against candle-transformers' `UNet2DConditionModel` on
//! the same random weights, in the same process.
//!
//! ```text
//! RAYON_NUM_THREADS=2 cargo run --release -p pixl-estimate --example bench_unet -- \
//!     [--size 64] [--size 96] [--iters 3] [--warmup 1] [--tiny] [--ours-only] [--profile] \
//!     [--reference-max 64]
//! ```
//! Like `pixl`, the process first calls `pixl_nn::prefer_rayon_pool` (candle's own elementwise
//! pool off, `CANDLE_NUM_THREADS=1`, unless the environment sets it) and
//! `pixl_nn::recycle_freed_buffers`. Both networks' matrix products run on rayon's pool
//! (`RAYON_NUM_THREADS`). Prints, per latent size, the median / min / max wall time of `--iters`
//! forwards after `--warmup` untimed ones for each network, the max abs difference of their
//! outputs (they differ only by candle-transformers' tanh GELU), then the peak resident memory.
//! The weights are candle-nn's default initialisations (GroupNorm scales 1, shifts 0). `--tiny`
//! uses a small network instead (a smoke test of the harness); `--profile` prints where our
//! forwards spent their time (`pixl_nn::profile` kinds, per forward).
//!
//! candle-transformers' UNet forms the full attention score matrices (its sliced attention fails
//! on these shapes): at a 96×96 latent one is 1.7 GB, and its forward needs more than 20 GB
//! (on a 23 GB machine it was refused memory), so it runs only at latent sides up to
//! `--reference-max` (64). Ours peaks at about 4 GB there, 3.5 GB of it the weights.
#[path = "../tests/marigold_common/reference_unet.rs"]
mod reference_unet;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use candle_transformers::models::stable_diffusion::unet_2d as reference;
use pixl_estimate::marigold::unet::UNet2DConditionModel;
use pixl_estimate::marigold::UnetConfig;
use reference_unet::reference_config;
use std::collections::HashMap;
use std::time::Instant;

struct Args {
    sizes: Vec<usize>,
    iters: usize,
    warmup: usize,
    tiny: bool,
    ours_only: bool,
    profile: bool,
    reference_max: usize,
}

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        sizes: Vec::new(),
        iters: 3,
        warmup: 1,
        tiny: false,
        ours_only: false,
        profile: false,
        reference_max: 64,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--size" => {
                let v = value()?;
                let s: usize = v.parse().map_err(|_| format!("--size {v}: expected a number"))?;
                if s == 0 {
                    return Err("--size must be positive".into());
                }
                a.sizes.push(s);
            }
            "--iters" => a.iters = value()?.parse().map_err(|_| "--iters: expected a number")?,
            "--warmup" => a.warmup = value()?.parse().map_err(|_| "--warmup: expected a number")?,
            "--tiny" => a.tiny = true,
            "--ours-only" => a.ours_only = true,
            "--profile" => a.profile = true,
            "--reference-max" => {
                a.reference_max = value()?.parse().map_err(|_| "--reference-max: expected a number")?
            }
            other => return Err(format!("unknown argument {other}")),
        }
    }
    if a.sizes.is_empty() {
        a.sizes = vec![64, 96];
    }
    if a.iters == 0 {
        return Err("--iters must be at least 1".into());
    }
    Ok(a)
}

fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// `(median, min, max)` of a list of times in ms.
fn summary(mut times: Vec<f64>) -> (f64, f64, f64) {
    times.sort_by(f64::total_cmp);
    (times[times.len() / 2], times[0], times[times.len() - 1])
}

/// Runs `f` and returns its output and wall time in ms.
fn timed(f: impl FnOnce() -> candle_core::Result<Tensor>) -> candle_core::Result<(Tensor, f64)> {
    let t = Instant::now();
    let y = f()?;
    Ok((y, t.elapsed().as_secs_f64() * 1e3))
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    pixl_nn::prefer_rayon_pool();
    pixl_nn::recycle_freed_buffers();
    let args = parse_args().map_err(|e| format!("bench_unet: {e}"))?;
    let dev = Device::Cpu;
    let cfg = if args.tiny {
        UnetConfig {
            block_out_channels: vec![32, 64, 64, 64],
            attention_head_dim: vec![2, 4, 4, 4],
            cross_attention_dim: 64,
            ..UnetConfig::sd2(8, 4)
        }
    } else {
        UnetConfig::sd2(8, 4)
    };
    let t0 = Instant::now();
    // candle-transformers' UNet asks for every tensor; the VarMap draws them.
    let varmap = VarMap::new();
    let theirs = reference::UNet2DConditionModel::new(
        VarBuilder::from_varmap(&varmap, DType::F32, &dev),
        cfg.in_channels,
        cfg.out_channels,
        false,
        reference_config(&cfg),
    )?;
    let weights: HashMap<String, Tensor> = varmap
        .data()
        .lock()
        .map_err(|_| "varmap lock poisoned")?
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().detach()))
        .collect();
    let params: usize = weights.values().map(Tensor::elem_count).sum();
    let ours = UNet2DConditionModel::new(&cfg, VarBuilder::from_tensors(weights, DType::F32, &dev))?;
    let threads = rayon::current_num_threads();
    let candle_threads = std::env::var("CANDLE_NUM_THREADS").unwrap_or_default();
    eprintln!(
        "{:.0} M parameters, built in {:.1} s; {threads} rayon threads, CANDLE_NUM_THREADS={candle_threads}",
        params as f64 / 1e6,
        t0.elapsed().as_secs_f64()
    );
    let ctx = Tensor::randn(0f32, 1.0, (1, 77, cfg.cross_attention_dim), &dev)?;
    for s in args.sizes {
        let x = Tensor::randn(0f32, 1.0, (1, cfg.in_channels, s, s), &dev)?;
        let t = 499.0;
        let run_ours = || -> candle_core::Result<(Tensor, f64)> {
            pixl_nn::profile::enable(args.profile);
            let r = timed(|| ours.forward(&x, t, &ctx));
            pixl_nn::profile::enable(false);
            r
        };
        let run_theirs = || timed(|| theirs.forward(&x, t, &ctx));
        let reference = !args.ours_only && s <= args.reference_max;
        if !args.ours_only && !reference {
            println!(
                "candle-transformers   skipped at {s}x{s} (above --reference-max {})",
                args.reference_max
            );
        }
        // Warm-up, then the timed runs interleaved (ours, theirs, ours, …) so that both see the
        // same load on a shared machine.
        for _ in 0..args.warmup {
            run_ours()?;
            if reference {
                run_theirs()?;
            }
        }
        let (mut t_ours, mut t_theirs) = (Vec::new(), Vec::new());
        let (mut y_ours, mut y_theirs) = (None, None);
        for _ in 0..args.iters {
            let (y, ms) = run_ours()?;
            t_ours.push(ms);
            y_ours = Some(y);
            if reference {
                let (y, ms) = run_theirs()?;
                t_theirs.push(ms);
                y_theirs = Some(y);
            }
        }
        if args.profile {
            // The warm-up runs are in the totals too: report per forward.
            let runs = (args.warmup + args.iters) as f64;
            let mut kinds = pixl_nn::profile::take();
            kinds.sort_by(|a, b| b.1.total_cmp(&a.1));
            for (kind, secs, calls) in kinds {
                println!(
                    "  {kind:<22} {:>8.0} ms per forward ({} calls)",
                    secs * 1e3 / runs,
                    calls as f64 / runs
                );
            }
        }
        let (med, lo, hi) = summary(t_ours);
        println!(
            "ours                  UNet forward {s}x{s} latent: median {med:.0} ms (min {lo:.0}, max {hi:.0}, {} runs, {threads} threads)",
            args.iters
        );
        let (Some(y_ours), Some(y_theirs)) = (y_ours, y_theirs) else {
            continue;
        };
        let (med, lo, hi) = summary(t_theirs);
        println!(
            "candle-transformers   UNet forward {s}x{s} latent: median {med:.0} ms (min {lo:.0}, max {hi:.0}, {} runs, {threads} threads)",
            args.iters
        );
        let diff = (&y_ours - &y_theirs)?.abs()?.max_all()?.to_scalar::<f32>()?;
        let scale = y_theirs.abs()?.max_all()?.to_scalar::<f32>()?;
        println!("  outputs: max abs difference {diff:.2e} (output max {scale:.2})");
    }
    if let Some(p) = peak_rss_mib() {
        println!("peak RSS {p:.0} MiB");
    }
    Ok(())
}
