//! A training step's convolutions ([`pixl_nn::conv_grad`]): the forward pass and
//! `sum(out ⊙ G).backward()` per shape, every argument a `Var` (except inputs marked as having
//! no gradient, as the network's stems), for our kernels with the direct kernels for narrow
//! layers ("direct"), for our kernels with every pass on GEMMs ("gemm", the path before the
//! direct kernels: [`pixl_nn::conv_grad::set_direct_kernels`]), and for candle's composed path
//! (`conv2d` / `conv_transpose2d` + a broadcast bias add, with candle's backward). "loss" is the
//! backward of `sum(y ⊙ G)` alone on an output-shaped `Var`: the part of every backward time
//! that is candle's, not the convolution's. Two groups:
//!
//! - `wide`: 64–384 channels; the fastest of `RUNS` interleaved runs of direct, gemm and
//!   candle, and where the direct run's time goes (`pixl_nn::profile`; "conv 3x3" is the
//!   Winograd kernel, forward and input gradient together).
//! - `tiny`: the narrow layers of the small `tiny` model (batch 4, 3–64 channels, 3×3 to 96×96
//!   pixels), where per-call overhead matters: medians of `20·RUNS` interleaved runs of direct
//!   and gemm, the kernels' medians (forward, input, weight and bias gradient), and the sums.
//!
//! `cargo run --release -p pixl-nn --example bench_conv_grad [RUNS] [wide|tiny|all] [FILTER]`
//! (default 5, all; FILTER keeps the shapes whose name contains it; threads:
//! `RAYON_NUM_THREADS`).
use candle_core::{DType, Device, Result, Tensor, Var};
use pixl_nn::conv_grad::{conv2d, conv2d_candle, conv_transpose_k, conv_transpose_k_candle, set_direct_kernels};
use std::collections::BTreeMap;
use std::time::Instant;

/// A convolution (stride, padding) or a transposed one (stride = kernel).
#[derive(Clone, Copy)]
enum Kind {
    Conv { stride: usize, padding: usize },
    Transpose,
}

type Dims = (usize, usize, usize, usize);

/// One benchmarked layer: name, x, weight, kind, input gradient, bias.
type Layer = (&'static str, Dims, Dims, Kind, bool, bool);

/// Milliseconds by profiled kernel.
type Spans = Vec<(&'static str, f64)>;

/// Which implementation a run times.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Path {
    Direct,
    Gemm,
    Candle,
}

/// The profiled kernels of our passes, as the tiny table's columns.
const KERNELS: [&str; 4] = [
    "conv2d (training)",
    "conv2d input gradient",
    "conv2d weight gradient",
    "conv2d bias gradient",
];

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let runs: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(5);
    let group = args.next().unwrap_or_else(|| "all".into());
    let filter = args.next().unwrap_or_default();
    if group != "tiny" {
        wide(runs, &filter)?;
    }
    if group != "wide" {
        tiny(20 * runs, &filter)?;
    }
    set_direct_kernels(true);
    Ok(())
}

const fn conv(stride: usize, padding: usize) -> Kind {
    Kind::Conv { stride, padding }
}

/// A layer's variables and output-gradient weights.
struct Bench {
    kind: Kind,
    x: Tensor,
    w: Var,
    b: Option<Var>,
    g: Tensor,
}

impl Bench {
    fn new((_, xd, wd, kind, x_grad, bias): Layer, dev: &Device) -> Result<Self> {
        let cout = match kind {
            Kind::Conv { .. } => wd.0,
            Kind::Transpose => wd.1,
        };
        let x = Var::from_tensor(&Tensor::randn(0f32, 1.0, xd, dev)?)?;
        let x = if x_grad {
            x.as_tensor().clone()
        } else {
            x.as_tensor().detach()
        };
        let w = Var::from_tensor(&Tensor::randn(0f32, 0.05, wd, dev)?)?;
        let b = if bias {
            Some(Var::from_tensor(&Tensor::randn(0f32, 0.1, cout, dev)?)?)
        } else {
            None
        };
        let mut me = Self {
            kind,
            x,
            w,
            b,
            g: Tensor::zeros(1, DType::F32, dev)?,
        };
        me.g = Tensor::randn(0f32, 1.0, me.forward(Path::Gemm)?.dims(), dev)?;
        Ok(me)
    }

    fn forward(&self, path: Path) -> Result<Tensor> {
        let (x, w, b) = (&self.x, self.w.as_tensor(), self.b.as_ref().map(Var::as_tensor));
        set_direct_kernels(path == Path::Direct);
        match (self.kind, path == Path::Candle) {
            (Kind::Conv { stride, padding }, false) => conv2d(x, w, b, stride, padding),
            (Kind::Conv { stride, padding }, true) => conv2d_candle(x, w, b, stride, padding),
            (Kind::Transpose, false) => conv_transpose_k(x, w, b),
            (Kind::Transpose, true) => conv_transpose_k_candle(x, w, b),
        }
    }

    /// `(forward ms, backward ms, our kernels' ms by kind)` of one run.
    fn run(&self, path: Path) -> Result<(f64, f64, Spans)> {
        pixl_nn::profile::enable(path != Path::Candle);
        let t0 = Instant::now();
        let y = self.forward(path)?;
        let tf = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = Instant::now();
        drop((&y * &self.g)?.sum_all()?.backward()?);
        let tb = t1.elapsed().as_secs_f64() * 1e3;
        pixl_nn::profile::enable(false);
        let spans = pixl_nn::profile::take();
        Ok((tf, tb, spans.into_iter().map(|(k, s, _)| (k, s * 1e3)).collect()))
    }

    /// The backward of the loss alone, on an output-shaped `Var` (ms).
    fn loss_only(&self, yv: &Var) -> Result<f64> {
        let y = yv.as_tensor().affine(1.0, 0.0)?;
        let t = Instant::now();
        drop((&y * &self.g)?.sum_all()?.backward()?);
        Ok(t.elapsed().as_secs_f64() * 1e3)
    }
}

fn wide(runs: usize, filter: &str) -> Result<()> {
    let dev = Device::Cpu;
    #[rustfmt::skip]
    let shapes: [Layer; 11] = [
        ("3x3 128->128 @64", (2, 128, 64, 64), (128, 128, 3, 3), conv(1, 1), true, true),
        ("3x3 64->32 @256", (2, 64, 256, 256), (32, 64, 3, 3), conv(1, 1), true, true),
        ("4x4/s4 9->48 @256", (2, 9, 256, 256), (48, 9, 4, 4), conv(4, 0), true, true),
        ("  stem, no x grad", (2, 9, 256, 256), (48, 9, 4, 4), conv(4, 0), false, true),
        ("3x3 128->64 @128", (2, 128, 128, 128), (64, 128, 3, 3), conv(1, 1), true, true),
        ("3x3 32->6 @256", (2, 32, 256, 256), (6, 32, 3, 3), conv(1, 1), true, true),
        ("3x3 256->256 @16", (2, 256, 16, 16), (256, 256, 3, 3), conv(1, 1), true, true),
        ("3x3/s2 256->256 @16", (2, 256, 16, 16), (256, 256, 3, 3), conv(2, 1), true, true),
        ("1x1 384->256 @16", (2, 384, 16, 16), (256, 384, 1, 1), conv(1, 0), true, true),
        ("2x2/s2 96->192 @64", (2, 96, 64, 64), (192, 96, 2, 2), conv(2, 0), true, true),
        ("convT k4 256->128 @16", (2, 256, 16, 16), (256, 128, 4, 4), Kind::Transpose, true, true),
    ];
    println!("wide layers (batch 2), fastest of {runs} runs");
    println!(
        "{:<22} {:>7} {:>7} {:>7} | {:>7} {:>7} {:>7} | {:>7} {:>7} {:>7} | {:>6} | {:>7} {:>7}",
        "ms", "direct", "bwd", "total", "gemm", "bwd", "total", "candle", "bwd", "total", "loss", "vs gemm", "vs cand"
    );
    for layer in shapes.into_iter().filter(|l| l.0.contains(filter)) {
        let bench = Bench::new(layer, &dev)?;
        let yv = Var::from_tensor(&bench.g.zeros_like()?)?;
        // best[2·p], best[2·p + 1]: forward and backward of path p; best[6]: the loss alone.
        let mut best = [f64::MAX; 7];
        let mut kernels: BTreeMap<&'static str, f64> = BTreeMap::new();
        for run in 0..=runs {
            for (p, path) in [Path::Direct, Path::Gemm, Path::Candle].into_iter().enumerate() {
                let (tf, tb, spans) = bench.run(path)?;
                if run > 0 {
                    best[2 * p] = best[2 * p].min(tf);
                    best[2 * p + 1] = best[2 * p + 1].min(tb);
                    if path == Path::Direct {
                        for (k, ms) in spans {
                            let e = kernels.entry(k).or_insert(f64::MAX);
                            *e = e.min(ms);
                        }
                    }
                }
            }
            let tl = bench.loss_only(&yv)?;
            if run > 0 {
                best[6] = best[6].min(tl);
            }
        }
        let [df, db, gf, gb, cf, cb, lb] = best;
        println!(
            "{:<22} {df:>7.1} {db:>7.1} {:>7.1} | {gf:>7.1} {gb:>7.1} {:>7.1} | {cf:>7.1} {cb:>7.1} {:>7.1} | {lb:>6.1} | {:>6.2}x {:>6.1}x",
            layer.0,
            df + db,
            gf + gb,
            cf + cb,
            (gf + gb) / (df + db),
            (cf + cb) / (df + db),
        );
        let parts: Vec<String> = kernels.iter().map(|(k, ms)| format!("{k} {ms:.1}")).collect();
        println!("    direct by kernel (ms): {}", parts.join(", "));
    }
    Ok(())
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    match v.len() {
        0 => f64::NAN,
        n => v[n / 2],
    }
}

fn tiny(reps: usize, filter: &str) -> Result<()> {
    let dev = Device::Cpu;
    let (c3, c1) = (conv(1, 1), conv(1, 0));
    #[rustfmt::skip]
    let shapes: [Layer; 25] = [
        ("3x3 16->16 @96", (4, 16, 96, 96), (16, 16, 3, 3), c3, true, true),
        ("3x3 32->16 @48", (4, 32, 48, 48), (16, 32, 3, 3), c3, true, true),
        ("3x3 32->32 @24", (4, 32, 24, 24), (32, 32, 3, 3), c3, true, true),
        ("3x3 32->32 @12", (4, 32, 12, 12), (32, 32, 3, 3), c3, true, true),
        ("3x3 32->32 @6", (4, 32, 6, 6), (32, 32, 3, 3), c3, true, true),
        ("3x3 32->32 @3", (4, 32, 3, 3), (32, 32, 3, 3), c3, true, true),
        ("3x3 16->32 @24 nb", (4, 16, 24, 24), (32, 16, 3, 3), c3, true, false),
        ("3x3 32->32 @12 nb", (4, 32, 12, 12), (32, 32, 3, 3), c3, true, false),
        ("3x3 64->32 @6 nb", (4, 64, 6, 6), (32, 64, 3, 3), c3, true, false),
        ("3x3 64->32 @3 nb", (4, 64, 3, 3), (32, 64, 3, 3), c3, true, false),
        ("3x3/s2 64->64 @6", (4, 64, 6, 6), (64, 64, 3, 3), conv(2, 1), true, true),
        ("1x1 16->6 @96", (4, 16, 96, 96), (6, 16, 1, 1), c1, true, true),
        ("1x1 32->32 @48", (4, 32, 48, 48), (32, 32, 1, 1), c1, true, true),
        ("1x1 32->32 @24", (4, 32, 24, 24), (32, 32, 1, 1), c1, true, true),
        ("1x1 32->32 @12", (4, 32, 12, 12), (32, 32, 1, 1), c1, true, true),
        ("1x1 32->32 @6", (4, 32, 6, 6), (32, 32, 1, 1), c1, true, true),
        ("1x1 32->32 @3", (4, 32, 3, 3), (32, 32, 1, 1), c1, true, true),
        ("1x1 64->16 @6", (4, 64, 6, 6), (16, 64, 1, 1), c1, true, true),
        ("1x1 64->32 @6", (4, 64, 6, 6), (32, 64, 1, 1), c1, true, true),
        ("1x1 64->64 @6", (4, 64, 6, 6), (64, 64, 1, 1), c1, true, true),
        ("4x4/s4 9->16 @96 nx", (4, 9, 96, 96), (16, 9, 4, 4), conv(4, 0), false, true),
        ("2x2/s2 16->32 @24", (4, 16, 24, 24), (32, 16, 2, 2), conv(2, 0), true, true),
        ("2x2/s2 32->64 @12", (4, 32, 12, 12), (64, 32, 2, 2), conv(2, 0), true, true),
        ("2x2/s2 64->64 @6", (4, 64, 6, 6), (64, 64, 2, 2), conv(2, 0), true, true),
        ("16x16/s16 3->64 @96 nx", (4, 3, 96, 96), (64, 3, 16, 16), conv(16, 0), false, true),
    ];
    println!("tiny layers (batch 4; nb: no bias, nx: no input gradient), medians of {reps} runs");
    println!(
        "{:<23} {:>7} {:>7} | {:>7} {:>7} | {:>6} | {:>6} {:>6} {:>6} {:>6} | {:>6} {:>6} {:>6}",
        "ms", "direct", "bwd", "gemm", "bwd", "loss", "k fwd", "k dx", "k dw", "k db", "gemm", "dx", "dw"
    );
    let mut sums = [0f64; 12];
    for layer in shapes.into_iter().filter(|l| l.0.contains(filter)) {
        let bench = Bench::new(layer, &dev)?;
        let yv = Var::from_tensor(&bench.g.zeros_like()?)?;
        // [0..4]: direct fwd/bwd, gemm fwd/bwd; [4]: the loss alone; [5..9]: direct kernels;
        // [9..12]: gemm kernels (forward, input and weight gradient).
        let mut t: [Vec<f64>; 12] = Default::default();
        for run in 0..=reps {
            for (p, path) in [Path::Direct, Path::Gemm].into_iter().enumerate() {
                let (tf, tb, spans) = bench.run(path)?;
                if run == 0 {
                    continue;
                }
                t[2 * p].push(tf);
                t[2 * p + 1].push(tb);
                let first = if path == Path::Direct { 5 } else { 9 };
                for (k, kind) in KERNELS.iter().enumerate().take(if first == 5 { 4 } else { 3 }) {
                    t[first + k].push(spans.iter().filter(|s| s.0 == *kind).map(|s| s.1).sum::<f64>() + 0.0);
                }
            }
            let tl = bench.loss_only(&yv)?;
            if run > 0 {
                t[4].push(tl);
            }
        }
        let m: Vec<f64> = t.iter_mut().map(|v| median(v)).collect();
        for (s, v) in sums.iter_mut().zip(&m) {
            *s += v;
        }
        print_row(layer.0, &m);
    }
    print_row("sum", &sums);
    let s = sums;
    println!(
        "kernels, gemm / direct: forward {:.2}x, input gradient {:.2}x, weight gradient {:.2}x, all {:.2}x",
        s[9] / s[5],
        s[10] / s[6],
        s[11] / s[7],
        (s[9] + s[10] + s[11]) / (s[5] + s[6] + s[7])
    );
    Ok(())
}

fn print_row(name: &str, m: &[f64]) {
    println!(
        "{:<23} {:>7.3} {:>7.3} | {:>7.3} {:>7.3} | {:>6.3} | {:>6.3} {:>6.3} {:>6.3} {:>6.3} | {:>6.3} {:>6.3} {:>6.3}",
        name, m[0], m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9], m[10], m[11]
    );
}
