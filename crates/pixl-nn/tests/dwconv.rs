//! Depthwise convolution: the CPU kernel against a naive f64 loop written here (forward, input
//! gradient, weight gradient), against candle's grouped conv, and against finite differences.
use candle_core::{DType, Device, Result, Tensor, Var};
use pixl_nn::dwconv::{depthwise_conv2d, grouped_conv2d};
use pixl_nn::testing::{assert_gradients, max_abs_diff, uniform};

/// `(b, c, h, w, k)` shapes: odd sizes, kernels 3 to 9, a kernel wider than the image, batch > 1.
/// Widths ≥ 16 (multiple of 16 or not) take the register-blocked kernel for k = 3, 5, 7; k = 9
/// and narrow rows the general one.
const SHAPES: [(usize, usize, usize, usize, usize); 10] = [
    (2, 3, 5, 7, 3),
    (2, 2, 9, 6, 7),
    (1, 4, 11, 13, 7),
    (3, 1, 4, 3, 7),
    (1, 2, 1, 1, 3),
    (2, 3, 9, 37, 7),
    (1, 2, 5, 16, 3),
    (2, 2, 4, 21, 5),
    (1, 2, 3, 33, 7),
    (1, 2, 6, 19, 9),
];

struct Naive {
    y: Vec<f64>,
    gx: Vec<f64>,
    gw: Vec<f64>,
    gb: Vec<f64>,
}

/// Direct loops over the definition: `y[b,c,i,j] = bias[c] + Σ w[c,u,v] x[b,c,i+u-p,j+v-p]`, and
/// for an upstream gradient `g`, `gx[.., i+u-p, j+v-p] += w[c,u,v] g[b,c,i,j]`,
/// `gw[c,u,v] += x[.., i+u-p, j+v-p] g[b,c,i,j]`, `gb[c] += g[b,c,i,j]`.
#[allow(clippy::needless_range_loop)] // index loops mirror the formula
fn naive(
    x: &[f64],
    w: &[f64],
    bias: &[f64],
    g: &[f64],
    (nb, nc, h, wd, k): (usize, usize, usize, usize, usize),
) -> Naive {
    let p = k as isize / 2;
    let mut out = Naive {
        y: vec![0.0; x.len()],
        gx: vec![0.0; x.len()],
        gw: vec![0.0; w.len()],
        gb: vec![0.0; nc],
    };
    for b in 0..nb {
        for c in 0..nc {
            let base = (b * nc + c) * h * wd;
            for i in 0..h {
                for j in 0..wd {
                    let o = base + i * wd + j;
                    out.y[o] = bias[c];
                    out.gb[c] += g[o];
                    for u in 0..k {
                        for v in 0..k {
                            let r = i as isize + u as isize - p;
                            let s = j as isize + v as isize - p;
                            if r < 0 || s < 0 || r >= h as isize || s >= wd as isize {
                                continue;
                            }
                            let xi = base + r as usize * wd + s as usize;
                            let wi = c * k * k + u * k + v;
                            out.y[o] += w[wi] * x[xi];
                            out.gx[xi] += w[wi] * g[o];
                            out.gw[wi] += x[xi] * g[o];
                        }
                    }
                }
            }
        }
    }
    out
}

fn vec(t: &Tensor) -> Result<Vec<f64>> {
    t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()
}

fn inputs(s: (usize, usize, usize, usize, usize), seed: u64) -> Result<[Tensor; 4]> {
    let (b, c, h, w, k) = s;
    let dev = Device::Cpu;
    Ok([
        uniform((b, c, h, w), -1.0, 1.0, seed, &dev)?,
        uniform((c, 1, k, k), -1.0, 1.0, seed + 1, &dev)?,
        uniform(c, -1.0, 1.0, seed + 2, &dev)?,
        uniform((b, c, h, w), -1.0, 1.0, seed + 3, &dev)?,
    ])
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, |m, d| if d.is_nan() || m.is_nan() { f64::NAN } else { m.max(d) })
}

#[test]
fn forward_and_gradients_match_naive_loops_f64() -> Result<()> {
    for (n, &s) in SHAPES.iter().enumerate() {
        let [x, w, b, g] = inputs(s, 10 * n as u64)?;
        let reference = naive(&vec(&x)?, &vec(&w)?, &vec(&b)?, &vec(&g)?, s);
        let (xv, wv, bv) = (Var::from_tensor(&x)?, Var::from_tensor(&w)?, Var::from_tensor(&b)?);
        let y = depthwise_conv2d(xv.as_tensor(), wv.as_tensor(), bv.as_tensor())?;
        assert_eq!(y.dims(), x.dims());
        let grads = (&y * &g)?.sum_all()?.backward()?;
        let get = |v: &Var| {
            grads
                .get(v.as_tensor())
                .cloned()
                .ok_or_else(|| candle_core::Error::Msg("no grad".into()))
        };
        let checks = [
            ("y", vec(&y)?, &reference.y),
            ("grad x", vec(&get(&xv)?)?, &reference.gx),
            ("grad w", vec(&get(&wv)?)?, &reference.gw),
            ("grad b", vec(&get(&bv)?)?, &reference.gb),
        ];
        for (what, got, want) in checks {
            let d = max_diff(&got, want);
            assert!(d < 1e-12, "{what} differs by {d} for shape {s:?}");
        }
    }
    Ok(())
}

#[test]
fn f32_forward_and_gradients_match_naive_loops() -> Result<()> {
    let s = (2, 3, 10, 41, 7);
    let [x, w, b, g] = inputs(s, 77)?;
    let reference = naive(&vec(&x)?, &vec(&w)?, &vec(&b)?, &vec(&g)?, s);
    let f = |t: &Tensor| t.to_dtype(DType::F32);
    let (xv, wv, bv) = (
        Var::from_tensor(&f(&x)?)?,
        Var::from_tensor(&f(&w)?)?,
        Var::from_tensor(&f(&b)?)?,
    );
    let y = depthwise_conv2d(xv.as_tensor(), wv.as_tensor(), bv.as_tensor())?;
    assert_eq!(y.dtype(), DType::F32);
    let grads = (&y * &f(&g)?)?.sum_all()?.backward()?;
    assert!(max_diff(&vec(&y)?, &reference.y) < 1e-5);
    let gx = grads.get(xv.as_tensor()).expect("grad x");
    let gw = grads.get(wv.as_tensor()).expect("grad w");
    assert!(max_diff(&vec(gx)?, &reference.gx) < 1e-5);
    assert!(max_diff(&vec(gw)?, &reference.gw) < 1e-4);
    Ok(())
}

#[test]
fn matches_candle_grouped_conv_and_handles_half_precision() -> Result<()> {
    let s = (2, 5, 12, 24, 7);
    let [x, w, b, _] = inputs(s, 5)?;
    let ours = depthwise_conv2d(&x, &w, &b)?;
    let theirs = grouped_conv2d(&x, &w, &b)?;
    assert!(max_abs_diff(&ours, &theirs)? < 1e-12);
    for dt in [DType::F16, DType::BF16] {
        let y = depthwise_conv2d(&x.to_dtype(dt)?, &w.to_dtype(dt)?, &b.to_dtype(dt)?)?;
        assert_eq!(y.dtype(), dt);
        // Inputs rounded to 8 (bf16) or 11 (f16) bits, output values up to ~10: 0.2 covers bf16.
        let d = max_abs_diff(&y, &theirs)?;
        assert!(d < 0.2, "{dt:?} differs by {d}");
    }
    Ok(())
}

#[test]
fn non_contiguous_input_is_handled() -> Result<()> {
    let s = (2, 3, 6, 5, 3);
    let [x, w, b, _] = inputs(s, 9)?;
    let xt = x.transpose(2, 3)?.contiguous()?.transpose(2, 3)?; // same values, strided
    assert!(!xt.is_contiguous());
    assert!(max_abs_diff(&depthwise_conv2d(&xt, &w, &b)?, &depthwise_conv2d(&x, &w, &b)?)? < 1e-15);
    Ok(())
}

#[test]
fn even_kernel_falls_back_to_candle() -> Result<()> {
    let dev = Device::Cpu;
    let x = uniform((1, 2, 5, 5), -1.0, 1.0, 1, &dev)?;
    let w = uniform((2, 1, 4, 4), -1.0, 1.0, 2, &dev)?;
    let b = uniform(2, -1.0, 1.0, 3, &dev)?;
    let y = depthwise_conv2d(&x, &w, &b)?;
    assert_eq!(y.dims(), &[1, 2, 6, 6]); // PyTorch: H + 2·(k/2) − k + 1
    Ok(())
}

#[test]
fn rejects_mismatched_weight() -> Result<()> {
    let dev = Device::Cpu;
    let x = uniform((1, 2, 5, 5), -1.0, 1.0, 1, &dev)?;
    let w = uniform((3, 1, 3, 3), -1.0, 1.0, 2, &dev)?;
    let b = uniform(3, -1.0, 1.0, 3, &dev)?;
    assert!(depthwise_conv2d(&x, &w, &b).is_err());
    Ok(())
}

#[test]
fn finite_difference_gradients() -> Result<()> {
    for (s, seed) in [((2, 2, 5, 4, 3), 1), ((1, 2, 4, 5, 7), 2)] {
        let [x, w, b, _] = inputs(s, seed)?;
        assert_gradients(
            "depthwise conv",
            |t| depthwise_conv2d(&t[0], &t[1], &t[2]),
            &[x, w, b],
            1e-4,
        )?;
    }
    Ok(())
}
