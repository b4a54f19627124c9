//! A training step's convolutions ([`pixl_nn::conv_grad`]) against candle's composed path
//! (`conv2d` / `conv_transpose2d` + a broadcast bias add, with candle's backward): the fastest of
//! `RUNS` interleaved runs of the forward pass and of `sum(out ⊙ G).backward()` per shape, every
//! argument a `Var` (the ConvNeXt stem also without an input gradient, as in the network), and
//! where our time goes (`pixl_nn::profile`; "conv 3x3" is the Winograd kernel, forward and
//! input gradient together). "loss" is the backward of `sum(y ⊙ G)` alone on an output-shaped
//! `Var`: the part of both backward times that is candle's, not the convolution's.
//!
//! `cargo run --release -p pixl-nn --example bench_conv_grad [RUNS]` (default 5; threads:
//! `RAYON_NUM_THREADS`).
use candle_core::{Device, Result, Tensor, Var};
use pixl_nn::conv_grad::{conv2d, conv2d_candle, conv_transpose_k, conv_transpose_k_candle};
use std::collections::BTreeMap;
use std::time::Instant;

/// A convolution (stride, padding) or a transposed one (stride = kernel).
#[derive(Clone, Copy)]
enum Kind {
    Conv { stride: usize, padding: usize },
    Transpose,
}

type Dims = (usize, usize, usize, usize);

fn main() -> Result<()> {
    let runs: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(5);
    let dev = Device::Cpu;
    let conv = |stride, padding| Kind::Conv { stride, padding };
    // (name, x, weight, kind, input gradient)
    let shapes: [(&str, Dims, Dims, Kind, bool); 11] = [
        ("3x3 128->128 @64", (2, 128, 64, 64), (128, 128, 3, 3), conv(1, 1), true),
        ("3x3 64->32 @256", (2, 64, 256, 256), (32, 64, 3, 3), conv(1, 1), true),
        ("4x4/s4 9->48 @256", (2, 9, 256, 256), (48, 9, 4, 4), conv(4, 0), true),
        ("  stem, no x grad", (2, 9, 256, 256), (48, 9, 4, 4), conv(4, 0), false),
        (
            "3x3 128->64 @128",
            (2, 128, 128, 128),
            (64, 128, 3, 3),
            conv(1, 1),
            true,
        ),
        ("3x3 32->6 @256", (2, 32, 256, 256), (6, 32, 3, 3), conv(1, 1), true),
        ("3x3 256->256 @16", (2, 256, 16, 16), (256, 256, 3, 3), conv(1, 1), true),
        (
            "3x3/s2 256->256 @16",
            (2, 256, 16, 16),
            (256, 256, 3, 3),
            conv(2, 1),
            true,
        ),
        ("1x1 384->256 @16", (2, 384, 16, 16), (256, 384, 1, 1), conv(1, 0), true),
        ("2x2/s2 96->192 @64", (2, 96, 64, 64), (192, 96, 2, 2), conv(2, 0), true),
        (
            "convT k4 256->128 @16",
            (2, 256, 16, 16),
            (256, 128, 4, 4),
            Kind::Transpose,
            true,
        ),
    ];
    println!(
        "{:<22} {:>8} {:>8} {:>8} | {:>8} {:>8} {:>8} | {:>6} | {:>7}",
        "ms", "ours fwd", "bwd", "total", "cand fwd", "bwd", "total", "loss", "speedup"
    );
    for (name, xd, wd, kind, x_grad) in shapes {
        let cout = match kind {
            Kind::Conv { .. } => wd.0,
            Kind::Transpose => wd.1,
        };
        let x = Var::from_tensor(&Tensor::randn(0f32, 1.0, xd, &dev)?)?;
        let w = Var::from_tensor(&Tensor::randn(0f32, 0.05, wd, &dev)?)?;
        let b = Var::from_tensor(&Tensor::randn(0f32, 0.1, cout, &dev)?)?;
        let xin = if x_grad {
            x.as_tensor().clone()
        } else {
            x.as_tensor().detach()
        };
        let forward = |ours: bool| -> Result<Tensor> {
            let (w, b) = (w.as_tensor(), Some(b.as_tensor()));
            match (kind, ours) {
                (Kind::Conv { stride, padding }, true) => conv2d(&xin, w, b, stride, padding),
                (Kind::Conv { stride, padding }, false) => conv2d_candle(&xin, w, b, stride, padding),
                (Kind::Transpose, true) => conv_transpose_k(&xin, w, b),
                (Kind::Transpose, false) => conv_transpose_k_candle(&xin, w, b),
            }
        };
        let g = Tensor::randn(0f32, 1.0, forward(true)?.dims(), &dev)?;
        let yv = Var::from_tensor(&g.zeros_like()?)?;
        // best[0..2]: ours fwd/bwd, [2..4]: candle fwd/bwd, [4]: the loss alone.
        let mut best = [f64::MAX; 5];
        let mut kernels: BTreeMap<&'static str, f64> = BTreeMap::new();
        for run in 0..=runs {
            for (i, ours) in [(0, true), (2, false)] {
                pixl_nn::profile::enable(ours);
                let t0 = Instant::now();
                let y = forward(ours)?;
                let tf = t0.elapsed().as_secs_f64() * 1e3;
                let t1 = Instant::now();
                drop((&y * &g)?.sum_all()?.backward()?);
                let tb = t1.elapsed().as_secs_f64() * 1e3;
                pixl_nn::profile::enable(false);
                let spans = pixl_nn::profile::take();
                if run > 0 {
                    best[i] = best[i].min(tf);
                    best[i + 1] = best[i + 1].min(tb);
                    for (k, secs, _) in spans {
                        let e = kernels.entry(k).or_insert(f64::MAX);
                        *e = e.min(secs * 1e3);
                    }
                }
            }
            let y = yv.as_tensor().affine(1.0, 0.0)?;
            let t = Instant::now();
            drop((&y * &g)?.sum_all()?.backward()?);
            if run > 0 {
                best[4] = best[4].min(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        let [of, ob, cf, cb, lb] = best;
        println!(
            "{name:<22} {of:>8.1} {ob:>8.1} {:>8.1} | {cf:>8.1} {cb:>8.1} {:>8.1} | {lb:>6.1} | {:>6.1}x",
            of + ob,
            cf + cb,
            (cf + cb) / (of + ob)
        );
        let parts: Vec<String> = kernels.iter().map(|(k, ms)| format!("{k} {ms:.1}")).collect();
        println!("    ours by kernel (ms): {}", parts.join(", "));
    }
    Ok(())
}
