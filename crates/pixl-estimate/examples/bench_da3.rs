//! Times the DA3 network (`Da3::forward`, f32, CPU) on random weights of the released
//! architecture (`Da3Config::large()`: same shapes, same FLOPs as da3mono/metric-large).
//!
//! ```text
//! RAYON_NUM_THREADS=8 cargo run --release -p pixl-estimate --example bench_da3 -- \
//!     [--size 504x378] [--size 504x504] [--iters 5] [--warmup 1] [--tiny] [--int8] [--profile]
//! ```
//! Like `pixl`, the process first calls `pixl_nn::prefer_rayon_pool` and
//! `pixl_nn::recycle_freed_buffers`.
//! `--profile` prints where the timed forwards spent their time (`pixl_nn::profile` kinds, per
//! forward; the rest of the forward is whatever ran outside the instrumented ops).
//! `--int8` times the backbone's linear layers as 8-bit products (`Da3::quantize_int8`) and prints
//! how far the depth moves from the f32 forward on the same input (max and RMS relative
//! difference).
//! Prints, per size, the median / min / max wall time of `--iters` forwards after `--warmup`
//! untimed ones, then the process's peak resident memory (`VmHWM`). `--tiny` uses the test
//! fixtures' tiny architecture instead (a smoke test of the harness).
use candle_core::{DType, Device, Tensor};
use pixl_estimate::da3::weights::expected_tensors;
use pixl_estimate::da3::{Da3, Da3Config};
use std::collections::HashMap;
use std::time::Instant;

struct Args {
    sizes: Vec<(usize, usize)>,
    iters: usize,
    warmup: usize,
    tiny: bool,
    int8: bool,
    profile: bool,
}

fn parse_args() -> Result<Args, String> {
    let mut a = Args {
        sizes: Vec::new(),
        iters: 5,
        warmup: 1,
        tiny: false,
        int8: false,
        profile: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or(format!("{flag} needs a value"));
        match flag.as_str() {
            "--size" => {
                let v = value()?;
                let (w, h) = v.split_once('x').ok_or(format!("--size {v}: expected WxH"))?;
                let w: usize = w.parse().map_err(|_| format!("--size {v}: bad width"))?;
                let h: usize = h.parse().map_err(|_| format!("--size {v}: bad height"))?;
                if w == 0 || h == 0 || !w.is_multiple_of(14) || !h.is_multiple_of(14) {
                    return Err(format!("--size {v}: sides must be positive multiples of 14"));
                }
                a.sizes.push((w, h));
            }
            "--iters" => a.iters = value()?.parse().map_err(|_| "--iters: expected a number")?,
            "--warmup" => a.warmup = value()?.parse().map_err(|_| "--warmup: expected a number")?,
            "--tiny" => a.tiny = true,
            "--int8" => a.int8 = true,
            "--profile" => a.profile = true,
            other => return Err(format!("unknown argument {other}")),
        }
    }
    if a.sizes.is_empty() {
        a.sizes = vec![(504, 378), (504, 504)];
    }
    if a.iters == 0 {
        return Err("--iters must be at least 1".into());
    }
    Ok(a)
}

/// Every tensor of the checkpoint, random, drawn when the model reads it (so that a layer that
/// repacks its weights does not leave a second copy alive): N(0, 0.02²) weights, unit norm
/// scales. Names and shapes are those of the checkpoint (`expected_tensors`).
struct RandomWeights {
    shapes: HashMap<String, Vec<usize>>,
}

impl candle_nn::var_builder::SimpleBackend for RandomWeights {
    fn get(
        &self,
        shape: candle_core::Shape,
        name: &str,
        _: candle_nn::Init,
        dtype: DType,
        dev: &Device,
    ) -> candle_core::Result<Tensor> {
        let t = self.get_unchecked(name, dtype, dev)?;
        if t.dims() != shape.dims() {
            candle_core::bail!("{name}: asked for {shape:?}, the checkpoint has {:?}", t.dims());
        }
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let Some(shape) = self.shapes.get(name) else {
            candle_core::bail!("{name}: not a tensor of the checkpoint");
        };
        let norm = name.ends_with("norm1.weight") || name.ends_with("norm2.weight") || name.ends_with("norm.weight");
        let t = if norm {
            Tensor::ones(shape.as_slice(), DType::F32, dev)?
        } else {
            Tensor::randn(0f32, 0.02, shape.as_slice(), dev)?
        };
        t.to_dtype(dtype)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        self.shapes.contains_key(name)
    }
}

fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // As `pixl` does: candle's own elementwise pool off, freed buffers recycled.
    pixl_nn::prefer_rayon_pool();
    pixl_nn::recycle_freed_buffers();
    let args = parse_args().map_err(|e| format!("bench_da3: {e}"))?;
    let dev = Device::Cpu;
    let cfg = if args.tiny {
        Da3Config::tiny()
    } else {
        Da3Config::large()
    };
    let t0 = Instant::now();
    let shapes = expected_tensors(&cfg).into_iter().collect();
    let vb = candle_nn::VarBuilder::from_backend(Box::new(RandomWeights { shapes }), DType::F32, dev.clone());
    let mut model = Da3::from_var_builder(cfg, vb, &dev)?;
    // The f32 depth of each size's input, for the 8-bit comparison.
    let mut f32_depth = Vec::new();
    if args.int8 {
        for &(w, h) in &args.sizes {
            let xs = Tensor::randn(0f32, 1.0, (1, 3, h, w), &dev)?;
            f32_depth.push((xs.clone(), model.forward(&xs)?));
        }
        let n = model.quantize_int8()?;
        eprintln!("{n} linear layers in 8 bits");
    }
    let threads = candle_core::utils::get_num_threads();
    eprintln!("built in {:.1} s; {threads} threads", t0.elapsed().as_secs_f64());
    for (i, (w, h)) in args.sizes.into_iter().enumerate() {
        let xs = match f32_depth.get(i) {
            Some((xs, want)) => {
                let got = model.forward(xs)?;
                let (g, r) = (
                    got.0.flatten_all()?.to_vec1::<f32>()?,
                    want.0.flatten_all()?.to_vec1::<f32>()?,
                );
                let rel: Vec<f64> = g
                    .iter()
                    .zip(&r)
                    .map(|(a, b)| ((a - b) / b.abs().max(1e-6)).abs() as f64)
                    .collect();
                let rms = (rel.iter().map(|v| v * v).sum::<f64>() / rel.len() as f64).sqrt();
                let max = rel.iter().cloned().fold(0.0, f64::max);
                println!("int8 depth vs f32 {w}x{h}: relative difference max {max:.4}, RMS {rms:.5}");
                xs.clone()
            }
            None => Tensor::randn(0f32, 1.0, (1, 3, h, w), &dev)?,
        };
        for _ in 0..args.warmup {
            model.forward(&xs)?;
        }
        pixl_nn::profile::take();
        pixl_nn::profile::enable(args.profile);
        let times: Result<Vec<f64>, _> = (0..args.iters)
            .map(|_| {
                let t = Instant::now();
                model.forward(&xs).map(|_| t.elapsed().as_secs_f64() * 1e3)
            })
            .collect();
        pixl_nn::profile::enable(false);
        let mut times = times?;
        times.sort_by(|a, b| a.total_cmp(b));
        println!(
            "candle da3 forward {w}x{h}: median {:.0} ms (min {:.0}, max {:.0}, {} runs, {threads} threads)",
            times[times.len() / 2],
            times[0],
            times[times.len() - 1],
            times.len()
        );
        if args.profile {
            let mut kinds = pixl_nn::profile::take();
            kinds.sort_by(|a, b| b.1.total_cmp(&a.1));
            let total: f64 = times.iter().sum::<f64>() / times.len() as f64;
            let mut inside = 0.0;
            for (kind, secs, calls) in kinds {
                let ms = secs * 1e3 / args.iters as f64;
                inside += ms;
                println!("  {kind:<30} {ms:>7.0} ms per forward ({} calls)", calls / args.iters);
            }
            println!("  {:<30} {:>7.0} ms per forward", "(outside the kinds)", total - inside);
        }
    }
    if let Some(p) = peak_rss_mib() {
        println!("candle peak RSS {p:.0} MiB");
    }
    Ok(())
}
