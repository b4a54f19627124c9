//! Times `pixl_nn::attention`'s fused CPU kernel against the unfused candle path (scaled
//! `q·kᵀ`, candle's fused softmax, `·v`) on the network's attention shapes at 512² and 1024²
//! (B = 1, f32, CPU; N = (side/16)² patches + 8 registers). 1 warm-up and 5 timed runs each;
//! prints the median as a Markdown table, and the largest difference between the two.
//!
//! `cargo run --release -p pixl-nn --example bench_attention` (threads: `RAYON_NUM_THREADS`).
use std::time::Instant;

use candle_core::{DType, Device, Result, Tensor};

fn median_ms(mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    f()?;
    let mut times = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[2])
}

/// The candle path: what `pixl_nn::attention` did before the fused kernel.
fn unfused(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    let scale = 1.0 / (q.dim(3)? as f64).sqrt();
    let att = (q * scale)?.matmul(&k.t()?)?;
    candle_nn::ops::softmax_last_dim(&att)?.matmul(v)
}

fn main() -> Result<()> {
    let dev = Device::Cpu;
    println!("| model | side | (H, N, D) | unfused ms | fused ms | speed-up | max abs diff |");
    println!("|---|---|---|---:|---:|---:|---:|");
    for (model, heads, dim) in [("small", 6, 384), ("paper", 16, 1024)] {
        for side in [512, 1024] {
            let n = (side / 16) * (side / 16) + 8;
            let d = dim / heads;
            let shape = (1, heads, n, d);
            let q = Tensor::randn(0f32, 1.0, shape, &dev)?;
            let k = Tensor::randn(0f32, 1.0, shape, &dev)?;
            let v = Tensor::randn(0f32, 1.0, shape, &dev)?;
            let slow = median_ms(|| unfused(&q, &k, &v).map(|_| ()))?;
            let fast = median_ms(|| pixl_nn::attention(&q, &k, &v).map(|_| ()))?;
            let diff = (unfused(&q, &k, &v)? - pixl_nn::attention(&q, &k, &v)?)?
                .abs()?
                .flatten_all()?
                .max(0)?
                .to_dtype(DType::F64)?
                .to_scalar::<f64>()?;
            println!(
                "| {model} | {side} | ({heads}, {n}, {d}) | {slow:.1} | {fast:.1} | {:.2}× | {diff:.1e} |",
                slow / fast
            );
        }
    }
    Ok(())
}
