//! Times training steps of layer norm and linear layers on the CPU in f32: composed candle ops
//! (layer norm as mean, subtract, square, mean, add, sqrt, divide, multiply, add; candle's
//! `Linear` then `gelu_erf`), each with candle's own backward, against the fused differentiable
//! ops of `pixl_nn::norm_grad` and `pixl_nn::linear_grad`.
//! Forward alone (inputs tracking gradients) and forward + backward of `Σ y·G` (gradients for
//! the input, weight and bias). 2 warm-ups and 7 timed runs each; prints the median as a
//! Markdown table, with the cost of the loss itself (candle's ops, the same for both paths, part
//! of both fwd+bwd times), then the fused kernels' own times from `pixl_nn::profile`.
//!
//! `cargo run --release -p pixl-nn --example bench_norm_linear_grad`
use std::time::Instant;

use candle_core::{Device, Result, Tensor, Var, D};
use pixl_nn::fused::Act;

fn median_ms(mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    for _ in 0..2 {
        f()?;
    }
    let mut times = Vec::new();
    for _ in 0..7 {
        let t = Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    Ok(times[3])
}

type Layer = dyn Fn(&Tensor, &Tensor, &Tensor) -> Result<Tensor>;

/// (forward ms, forward + backward ms) of `f(x, w, b)` with all three tracking gradients.
fn time(f: &Layer, x: &Tensor, w: &Tensor, b: &Tensor) -> Result<(f64, f64)> {
    let (x, w, b) = (Var::from_tensor(x)?, Var::from_tensor(w)?, Var::from_tensor(b)?);
    let (xt, wt, bt) = (x.as_tensor(), w.as_tensor(), b.as_tensor());
    let g = f(xt, wt, bt)?.randn_like(0.0, 1.0)?;
    let fwd = median_ms(|| f(xt, wt, bt).map(|_| ()))?;
    let step = median_ms(|| {
        let grads = (f(xt, wt, bt)? * &g)?.sum_all()?.backward()?;
        for v in [xt, wt, bt] {
            if grads.get(v).is_none() {
                candle_core::bail!("missing gradient");
            }
        }
        Ok(())
    })?;
    Ok((fwd, step))
}

/// Forward + backward of the loss alone, `Σ y·G` on a `Var` `y` of the output's shape: the part
/// of every fwd+bwd time that is candle's, the same for both paths.
fn harness_ms(g: &Tensor) -> Result<f64> {
    let y = Var::from_tensor(&g.ones_like()?)?;
    median_ms(|| (y.as_tensor() * g)?.sum_all()?.backward().map(|_| ()))
}

/// Largest relative difference of the outputs and of the three gradients of the two paths.
fn agreement(a: &Layer, b: &Layer, x: &Tensor, w: &Tensor, bias: &Tensor) -> Result<f64> {
    let (x, w, bias) = (Var::from_tensor(x)?, Var::from_tensor(w)?, Var::from_tensor(bias)?);
    let vs = [x.as_tensor(), w.as_tensor(), bias.as_tensor()];
    let ya = a(vs[0], vs[1], vs[2])?;
    let yb = b(vs[0], vs[1], vs[2])?;
    let g = ya.randn_like(0.0, 1.0)?;
    let ga = (&ya * &g)?.sum_all()?.backward()?;
    let gb = (&yb * &g)?.sum_all()?.backward()?;
    let rel = |p: &Tensor, q: &Tensor| -> Result<f64> {
        let d = (p - q)?.abs()?.max_all()?.to_scalar::<f32>()? as f64;
        let s = q.abs()?.max_all()?.to_scalar::<f32>()? as f64;
        Ok(d / s.max(1e-12))
    };
    let mut worst = rel(&ya, &yb)?;
    for v in vs {
        match (ga.get(v), gb.get(v)) {
            (Some(p), Some(q)) => worst = worst.max(rel(p, q)?),
            _ => candle_core::bail!("missing gradient"),
        }
    }
    Ok(worst)
}

fn row(
    kernels: &mut Vec<String>,
    name: &str,
    composed: &Layer,
    ours: &Layer,
    x: &Tensor,
    w: &Tensor,
    b: &Tensor,
) -> Result<()> {
    let diff = agreement(ours, composed, x, w, b)?;
    if diff.is_nan() || diff > 1e-3 {
        candle_core::bail!("{name}: paths disagree by {diff:e}");
    }
    let (cf, cs) = time(composed, x, w, b)?;
    pixl_nn::profile::take();
    pixl_nn::profile::enable(true);
    let (of, os) = time(ours, x, w, b)?;
    pixl_nn::profile::enable(false);
    let h = harness_ms(&ours(x, w, b)?.randn_like(0.0, 1.0)?)?;
    println!(
        "| {name} | {cf:.2} | {of:.2} | {:.1}× | {cs:.2} | {os:.2} | {:.1}× | {h:.2} | {diff:.1e} |",
        cf / of,
        cs / os
    );
    for (kind, secs, calls) in pixl_nn::profile::take() {
        kernels.push(format!(
            "{name}: {kind} {:.2} ms/call",
            secs * 1e3 / calls.max(1) as f64
        ));
    }
    Ok(())
}

/// Layer norm from candle ops, as the differentiable path was before the fused op.
fn ln_composed(xs: &Tensor, w: &Tensor, b: &Tensor) -> Result<Tensor> {
    let mean = xs.mean_keepdim(D::Minus1)?;
    let xc = xs.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    let xn = xc.broadcast_div(&(var + EPS)?.sqrt()?)?;
    xn.broadcast_mul(w)?.broadcast_add(b)
}

const EPS: f64 = 1e-6;

fn main() -> Result<()> {
    let dev = Device::Cpu;
    println!("threads: {}", rayon::current_num_threads());
    let mut kernels = Vec::new();
    println!("| case | composed fwd ms | fused fwd ms | speed-up | composed fwd+bwd ms | fused fwd+bwd ms | speed-up | loss alone ms | max rel diff |");
    println!("|---|---|---|---|---|---|---|---|---|");

    let ln_ours = |x: &Tensor, w: &Tensor, b: &Tensor| {
        let _t = pixl_nn::profile::span("layer norm");
        pixl_nn::norm_grad::layer_norm(x, w, b, EPS)
    };
    for (name, shape) in [
        ("layer norm (2,260,384)", vec![2usize, 260, 384]),
        ("layer norm (2,64,64,96)", vec![2, 64, 64, 96]),
    ] {
        let d = shape[shape.len() - 1];
        let x = Tensor::randn(0.5f32, 1.0, shape, &dev)?;
        let w = Tensor::randn(1f32, 0.1, d, &dev)?;
        let b = Tensor::randn(0f32, 0.1, d, &dev)?;
        row(&mut kernels, name, &ln_composed, &ln_ours, &x, &w, &b)?;
    }
    for (name, k, n, act) in [
        ("linear 384→1536 GELU (2,260)", 384usize, 1536usize, Act::Gelu),
        ("linear 1536→384 (2,260)", 1536, 384, Act::None),
    ] {
        let composed = move |x: &Tensor, w: &Tensor, b: &Tensor| {
            let y = candle_core::Module::forward(&candle_nn::Linear::new(w.clone(), Some(b.clone())), x)?;
            match act {
                Act::Gelu => y.gelu_erf(),
                _ => Ok(y),
            }
        };
        let ours = move |x: &Tensor, w: &Tensor, b: &Tensor| pixl_nn::linear_grad::linear(x, w, Some(b), act);
        let x = Tensor::randn(0f32, 1.0, (2, 260, k), &dev)?;
        let w = Tensor::randn(0f32, 1.0 / (k as f32).sqrt(), (n, k), &dev)?;
        let b = Tensor::randn(0f32, 0.1, n, &dev)?;
        row(&mut kernels, name, &composed, &ours, &x, &w, &b)?;
    }
    println!();
    println!("fused ops' own time (profile spans, forward and backward kernels, all timed runs):");
    for k in kernels {
        println!("- {k}");
    }
    Ok(())
}
