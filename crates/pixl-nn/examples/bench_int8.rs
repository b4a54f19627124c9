//! The 8-bit linear layer ([`pixl_nn::int8`]) against the f32 one ([`pixl_nn::fused::linear`])
//! on the relighting network's shapes: median wall time per call (alternating the two, 2
//! warm-ups then 7 runs each), the f32-equivalent GFLOP/s, and the 8-bit result's RMS error
//! relative to the f32 result's RMS (Gaussian inputs, weights ~ N(0, 0.02²)).
//!
//! `cargo run --release -p pixl-nn --example bench_int8` (threads: `RAYON_NUM_THREADS`).
use candle_core::{Device, Result, Tensor};
use pixl_nn::fused::{self, Act};
use pixl_nn::int8::{self, Int8Linear};
use std::time::Instant;

fn main() -> Result<()> {
    if !int8::available() {
        println!("this CPU has no AVX-512 VNNI: nothing to time");
        return Ok(());
    }
    let dev = Device::Cpu;
    // (name, tokens, in, out)
    let shapes = [
        ("paper qkv", 1032, 1024, 3072),
        ("paper proj", 1032, 1024, 1024),
        ("paper mlp fc1", 1032, 1024, 4096),
        ("paper mlp fc2", 1032, 4096, 1024),
        ("small qkv", 1028, 384, 1152),
        ("small mlp fc1", 1028, 384, 1536),
        ("small mlp fc2", 1028, 1536, 384),
        ("small convnext s1 fc1", 16384, 48, 192),
    ];
    for (name, m, k, n) in shapes {
        let x = Tensor::randn(0f32, 1.0, (1, m, k), &dev)?;
        let w = Tensor::randn(0f32, 0.02, (n, k), &dev)?;
        let b = Tensor::randn(0f32, 0.02, n, &dev)?;
        let layer = candle_nn::Linear::new(w, Some(b));
        let Some(q) = Int8Linear::new(&layer)? else {
            return Ok(());
        };
        let (mut tf, mut tq) = (Vec::new(), Vec::new());
        for i in 0..9 {
            let s = Instant::now();
            let yf = fused::linear(&x, &layer, Act::None)?;
            let f = s.elapsed().as_secs_f64();
            let s = Instant::now();
            let yq = q.forward(&x, Act::None)?;
            let g = s.elapsed().as_secs_f64();
            if i >= 2 {
                tf.push(f);
                tq.push(g);
            }
            if i == 8 {
                let err = (&yq - &yf)?.sqr()?.mean_all()?.sqrt()?.to_scalar::<f32>()?;
                let rms = yf.sqr()?.mean_all()?.sqrt()?.to_scalar::<f32>()?;
                let med = |v: &mut Vec<f64>| {
                    v.sort_by(f64::total_cmp);
                    v[v.len() / 2]
                };
                let (mf, mq) = (med(&mut tf), med(&mut tq));
                let gflop = 2.0 * (m * k * n) as f64 / 1e9;
                println!(
                    "{name:<22} {m:>5}x{k:<4}x{n:<4}  f32 {:>7.2} ms ({:>5.0} GFLOP/s)  int8 {:>7.2} ms ({:>5.0})  {:.2}x  rel. RMS error {:.4}",
                    mf * 1e3,
                    gflop / mf,
                    mq * 1e3,
                    gflop / mq,
                    mf / mq,
                    err / rms
                );
            }
        }
    }
    Ok(())
}
