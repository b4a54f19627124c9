//! The packed f32 linear kernel ([`pixl_nn::packed`]) against `fused::linear` (the `gemm`
//! crate) on the ViT-L shapes of DA3 at 504×378 (973 tokens), GFLOP/s, best of `--iters`.
//!
//! `RAYON_NUM_THREADS=2 cargo run --release -p pixl-nn --example bench_packed -- [--iters 5]`
use candle_core::{Device, Tensor};
use pixl_nn::fused::{self, Act};
use pixl_nn::packed::{self, Epilogue, PackedLinear};
use std::time::Instant;

fn best(iters: usize, mut f: impl FnMut()) -> f64 {
    (0..iters)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut iters = 5;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--iters" => iters = args.next().ok_or("--iters needs a value")?.parse()?,
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    if !packed::available() {
        return Err("no AVX-512F on this CPU".into());
    }
    let dev = Device::Cpu;
    let m = 973;
    for (name, k, n) in [
        ("qkv", 1024, 3072),
        ("proj", 1024, 1024),
        ("fc1", 1024, 4096),
        ("fc2", 4096, 1024),
    ] {
        let x = Tensor::randn(0f32, 1.0, (m, k), &dev)?;
        let w = Tensor::randn(0f32, 0.02, (n, k), &dev)?;
        let b = Tensor::randn(0f32, 0.02, n, &dev)?;
        let layer = candle_nn::Linear::new(w.clone(), Some(b.clone()));
        let flops = 2.0 * (m * k * n) as f64 / 1e9;
        let t_gemm = best(iters, || {
            fused::linear(&x, &layer, Act::None).map(|_| ()).unwrap_or(());
        });
        let wv = w.flatten_all()?.to_vec1::<f32>()?;
        let bv = b.to_vec1::<f32>()?;
        let p = PackedLinear::from_weights(&wv, n, k, Some(&bv))?;
        let xv = x.flatten_all()?.to_vec1::<f32>()?;
        let mut out = vec![0f32; m * n];
        let t_packed = best(iters, || p.forward_slice(&xv, m, &mut out, &Epilogue::act(Act::None)));
        let t_gelu = best(iters, || p.forward_slice(&xv, m, &mut out, &Epilogue::act(Act::Gelu)));
        println!(
            "{name:<5} {m}x{k}x{n}: gemm {:>6.1} GFLOP/s, packed {:>6.1} GFLOP/s, packed+GELU {:>6.1}",
            flops / t_gemm,
            flops / t_packed,
            flops / t_gelu
        );
    }
    Ok(())
}
