//! Times candle's grouped convolution against `pixl_nn`'s depthwise kernel on ConvNeXt-B-like
//! shapes (B = 1, k = 7, f32, CPU): forward, and forward + backward (input, weight and bias
//! gradients). 2 warm-ups and 5 timed runs each; prints the median as a Markdown table.
//!
//! `cargo run --release -p pixl-nn --example bench_dwconv`
use std::time::Instant;

use candle_core::{Device, Result, Tensor, Var};
use pixl_nn::dwconv::{depthwise_conv2d, grouped_conv2d, DwConvOp, DwConvWeightGradOp};

type Conv = fn(&Tensor, &Tensor, &Tensor) -> Result<Tensor>;

fn median_ms(mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    for _ in 0..2 {
        f()?;
    }
    let mut times = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[2])
}

fn forward_ms(conv: Conv, x: &Tensor, w: &Tensor, b: &Tensor) -> Result<f64> {
    median_ms(|| conv(x, w, b).map(|_| ()))
}

fn backward_ms(conv: Conv, x: &Tensor, w: &Tensor, b: &Tensor) -> Result<f64> {
    let (x, w, b) = (Var::from_tensor(x)?, Var::from_tensor(w)?, Var::from_tensor(b)?);
    median_ms(|| {
        let y = conv(x.as_tensor(), w.as_tensor(), b.as_tensor())?;
        let grads = y.sum_all()?.backward()?;
        for v in [&x, &w, &b] {
            if grads.get(v.as_tensor()).is_none() {
                candle_core::bail!("missing gradient");
            }
        }
        Ok(())
    })
}

fn main() -> Result<()> {
    let dev = Device::Cpu;
    let k = 7;
    println!("threads: {}", rayon::current_num_threads());
    println!("| shape (B,C,H,W), k=7 | candle fwd ms | pixl-nn fwd ms | speed-up | candle fwd+bwd ms | pixl-nn fwd+bwd ms | speed-up |");
    println!("|---|---|---|---|---|---|---|");
    for (c, s) in [(128, 128), (256, 64), (512, 32)] {
        let x = Tensor::randn(0f32, 1.0, (1, c, s, s), &dev)?;
        let w = Tensor::randn(0f32, 0.1, (c, 1, k, k), &dev)?;
        let b = Tensor::randn(0f32, 0.1, c, &dev)?;
        let diff = (depthwise_conv2d(&x, &w, &b)? - grouped_conv2d(&x, &w, &b)?)?
            .abs()?
            .max_all()?
            .to_scalar::<f32>()?;
        if diff.is_nan() || diff > 1e-3 {
            candle_core::bail!("kernels disagree by {diff} on C={c}, {s}x{s}");
        }
        let (cf, of) = (
            forward_ms(grouped_conv2d, &x, &w, &b)?,
            forward_ms(depthwise_conv2d, &x, &w, &b)?,
        );
        let (cb, ob) = (
            backward_ms(grouped_conv2d, &x, &w, &b)?,
            backward_ms(depthwise_conv2d, &x, &w, &b)?,
        );
        println!(
            "| (1,{c},{s},{s}) | {cf:.2} | {of:.2} | {:.1}× | {cb:.2} | {ob:.2} | {:.1}× |",
            cf / of,
            cb / ob
        );
    }
    println!();
    println!("pixl-nn backward parts (ms): | shape | input grad | weight grad | bias grad |");
    for (c, s) in [(128, 128), (256, 64), (512, 32)] {
        let x = Tensor::randn(0f32, 1.0, (1, c, s, s), &dev)?;
        let g = Tensor::randn(0f32, 1.0, (1, c, s, s), &dev)?;
        let w = Tensor::randn(0f32, 0.1, (c, 1, k, k), &dev)?;
        let zero = Tensor::zeros(c, candle_core::DType::F32, &dev)?;
        let gx = median_ms(|| {
            g.apply_op3_no_bwd(&w, &zero, &DwConvOp { kernel: k, flip: true })
                .map(|_| ())
        })?;
        let gw = median_ms(|| x.apply_op2_no_bwd(&g, &DwConvWeightGradOp { kernel: k }).map(|_| ()))?;
        let gb = median_ms(|| g.reshape((1, c, s * s))?.sum(2)?.sum(0).map(|_| ()))?;
        println!("| (1,{c},{s},{s}) | {gx:.2} | {gw:.2} | {gb:.2} |");
    }
    Ok(())
}
