//! Times one training step of attention on fused qkv rows with 2D RoPE — forward, then
//! `(out ⊙ G).sum().backward()` — by `pixl_nn::attention_grad::qkv_attention` (one fused,
//! differentiable op) against the composed candle path (reshape/permute, RoPE by candle ops after
//! the registers, `pixl_nn::attention`'s candle ops on tracked inputs — `q·kᵀ`, softmax, `·v` —
//! merge, and candle's autograd over all of them).
//! Shapes of the training runs: B = 2, C = 384, 6 heads, 4 registers, 16×16 and 32×32 patches
//! (f32, CPU). 1 warm-up and 9 timed runs each; prints median / minimum (and the forward's median)
//! as a Markdown table, and the largest difference between the two gradients relative to the
//! largest gradient.
//!
//! `cargo run --release -p pixl-nn --example bench_attention_grad` (threads: `RAYON_NUM_THREADS`);
//! `… -- peak ours` or `… -- peak composed`: one step at N = 1028 and the process's peak memory.
use std::time::Instant;

use candle_core::{DType, Device, Result, Tensor, Var};
use pixl_nn::{attention_grad, Rope2d};

/// Median and minimum of `RUNS` timed runs after one warm-up, in ms.
fn time_ms(mut f: impl FnMut() -> Result<()>) -> Result<(f64, f64)> {
    f()?;
    let mut times = Vec::new();
    for _ in 0..RUNS {
        let t = Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    Ok((times[RUNS / 2], times[0]))
}

const RUNS: usize = 9;

/// Forward and backward; the gradient with respect to `qkv`.
fn step(attn: &dyn Fn(&Tensor) -> Result<Tensor>, qkv: &Var, g: &Tensor, forward_ms: &mut f64) -> Result<Tensor> {
    let t = Instant::now();
    let out = attn(qkv.as_tensor())?;
    *forward_ms = t.elapsed().as_secs_f64() * 1e3;
    let grads = (out * g)?.sum_all()?.backward()?;
    match grads.get(qkv.as_tensor()) {
        Some(d) => Ok(d.clone()),
        None => candle_core::bail!("no gradient for qkv"),
    }
}

/// Peak resident memory of this process so far, MiB (Linux; 0 elsewhere).
fn peak_rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(0.0, |kb| kb / 1024.0)
}

/// The composed candle path, differentiated op by op.
fn composed(qkv: &Tensor, heads: usize, rope: &Rope2d, prefix: usize) -> Result<Tensor> {
    let (b, n, c3) = qkv.dims3()?;
    let d = c3 / (3 * heads);
    let t = qkv.reshape((b, n, 3, heads, d))?.permute((2, 0, 3, 1, 4))?;
    let rotate = |x: &Tensor| -> Result<Tensor> {
        let patches = rope.apply(&x.narrow(2, prefix, n - prefix)?)?;
        Tensor::cat(&[&x.narrow(2, 0, prefix)?, &patches], 2)?.contiguous()
    };
    let q = rotate(&t.get(0)?.contiguous()?)?;
    let k = rotate(&t.get(1)?.contiguous()?)?;
    let out = pixl_nn::attention(&q, &k, &t.get(2)?.contiguous()?)?;
    out.transpose(1, 2)?.reshape((b, n, heads * d))
}

fn main() -> Result<()> {
    let dev = Device::Cpu;
    let (b, c, heads, prefix) = (2, 384, 6, 4);
    // `-- peak ours|composed`: one step at N = 1028 alone, then the process's peak memory.
    let args: Vec<String> = std::env::args().collect();
    if args.get(1).map(String::as_str) == Some("peak") {
        let (side, which) = (32, args.get(2).map_or("ours", String::as_str));
        let n = side * side + prefix;
        let rope = Rope2d::new(c / heads, side, side, 100.0, &dev)?;
        let qkv = Var::from_tensor(&Tensor::randn(0f32, 1.0, (b, n, 3 * c), &dev)?)?;
        let g = Tensor::randn(0f32, 1.0, (b, n, c), &dev)?;
        let before = peak_rss_mib();
        let mut fwd = 0.0;
        match which {
            "composed" => step(&|t| composed(t, heads, &rope, prefix), &qkv, &g, &mut fwd)?,
            _ => step(
                &|t| attention_grad::qkv_attention(t, heads, Some((&rope, prefix))),
                &qkv,
                &g,
                &mut fwd,
            )?,
        };
        println!(
            "{which}: peak RSS {:.1} MiB (inputs ready: {before:.1} MiB)",
            peak_rss_mib()
        );
        return Ok(());
    }
    println!("| (B, N, 3C), heads | composed fwd+bwd ms median / min (fwd) | fused fwd+bwd ms median / min (fwd) | speed-up | grad rel diff |");
    println!("|---|---:|---:|---:|---:|");
    for side in [16, 32] {
        let n = side * side + prefix;
        let rope = Rope2d::new(c / heads, side, side, 100.0, &dev)?;
        let qkv = Var::from_tensor(&Tensor::randn(0f32, 1.0, (b, n, 3 * c), &dev)?)?;
        let g = Tensor::randn(0f32, 1.0, (b, n, c), &dev)?;
        let composed = |t: &Tensor| composed(t, heads, &rope, prefix);
        let ours = |t: &Tensor| attention_grad::qkv_attention(t, heads, Some((&rope, prefix)));
        let (mut f_slow, mut f_fast) = (Vec::new(), Vec::new());
        let mut fwd = 0.0;
        let slow = time_ms(|| {
            step(&composed, &qkv, &g, &mut fwd)?;
            f_slow.push(fwd);
            Ok(())
        })?;
        let fast = time_ms(|| {
            step(&ours, &qkv, &g, &mut fwd)?;
            f_fast.push(fwd);
            Ok(())
        })?;
        let median = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let want = step(&composed, &qkv, &g, &mut fwd)?;
        let got = step(&ours, &qkv, &g, &mut fwd)?;
        let diff = (&got - &want)?
            .abs()?
            .flatten_all()?
            .max(0)?
            .to_dtype(DType::F64)?
            .to_scalar::<f64>()?;
        let scale = want
            .abs()?
            .flatten_all()?
            .max(0)?
            .to_dtype(DType::F64)?
            .to_scalar::<f64>()?;
        println!(
            "| ({b}, {n}, {}), {heads} | {:.1} / {:.1} ({:.1}) | {:.1} / {:.1} ({:.1}) | {:.2}× | {:.1e} |",
            3 * c,
            slow.0,
            slow.1,
            median(f_slow),
            fast.0,
            fast.1,
            median(f_fast),
            slow.0 / fast.0,
            diff / scale
        );
    }
    Ok(())
}
