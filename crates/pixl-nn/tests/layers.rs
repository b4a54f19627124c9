//! Layer norm, softmax, resize, RoPE, attention and MLP: hand-derived values, naive f64 loops
//! written here, fast-path vs differentiable-path equality (a plain tensor takes the fast path, a
//! `Var` the differentiable one), and finite-difference gradient checks.
use candle_core::{DType, Device, Module, Result, Tensor, Var, D};
use candle_nn::Linear;
use pixl_nn::norm::layer_norm;
use pixl_nn::ops::{gelu, interp_matrix, resize_bilinear, softmax_last_dim};
use pixl_nn::testing::{assert_gradients, max_abs_diff, uniform};
use pixl_nn::{attention, LayerNorm, LayerNorm2d, Mlp, Rope2d};

const TOL: f64 = 1e-4;

fn cpu() -> Device {
    Device::Cpu
}

/// The same values, tracked: forces the differentiable path.
fn tracked(t: &Tensor) -> Result<Tensor> {
    Ok(Var::from_tensor(t)?.as_tensor().clone())
}

fn rows(t: &Tensor) -> Result<Vec<Vec<f64>>> {
    let d = t.dim(D::Minus1)?;
    let v = t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    Ok(v.chunks(d).map(|c| c.to_vec()).collect())
}

fn naive_layer_norm(x: &[f64], w: &[f64], b: &[f64], eps: f64) -> Vec<f64> {
    let n = x.len() as f64;
    let mean = x.iter().sum::<f64>() / n;
    let var = x.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n;
    x.iter()
        .zip(w.iter().zip(b))
        .map(|(v, (w, b))| (v - mean) / (var + eps).sqrt() * w + b)
        .collect()
}

fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, |m, d| if d.is_nan() || m.is_nan() { f64::NAN } else { m.max(d) })
}

#[test]
fn layer_norm_hand_value() -> Result<()> {
    // [1, 2, 3, 4]: mean 2.5, biased variance 1.25.
    let x = Tensor::new(&[[1f64, 2., 3., 4.]], &cpu())?;
    let w = Tensor::new(&[1f64, 2., 1., 1.], &cpu())?;
    let b = Tensor::new(&[0f64, 0., 0., 1.], &cpu())?;
    let y = layer_norm(&x, &w, &b, 0.0)?.flatten_all()?.to_vec1::<f64>()?;
    let s = 1.25f64.sqrt();
    let want = [-1.5 / s, 2.0 * -0.5 / s, 0.5 / s, 1.5 / s + 1.0];
    assert!(max_diff(&y, &want) < 1e-12, "{y:?}");
    Ok(())
}

#[test]
fn layer_norm_paths_match_naive_including_eps() -> Result<()> {
    let d = 37;
    // An offset of 3 and a large eps make mean handling and eps placement visible.
    let x = (uniform((2, 5, d), -2.0, 2.0, 1, &cpu())? + 3.0)?;
    let w = uniform(d, 0.5, 1.5, 2, &cpu())?;
    let b = uniform(d, -0.5, 0.5, 3, &cpu())?;
    for eps in [1e-6, 0.5] {
        let want: Vec<Vec<f64>> = rows(&x)?
            .iter()
            .map(|r| naive_layer_norm(r, &w.to_vec1().unwrap(), &b.to_vec1().unwrap(), eps))
            .collect();
        let f = |t: &Tensor| t.to_dtype(DType::F32);
        let fast = layer_norm(&f(&x)?, &f(&w)?, &f(&b)?, eps)?;
        let slow = layer_norm(&tracked(&f(&x)?)?, &f(&w)?, &f(&b)?, eps)?;
        let f64_path = layer_norm(&x, &w, &b, eps)?;
        for (name, got, tol) in [
            ("fast f32", fast, 2e-5),
            ("slow f32", slow, 2e-5),
            ("f64", f64_path, 1e-12),
        ] {
            let got = rows(&got)?;
            let err = got.iter().zip(&want).map(|(g, w)| max_diff(g, w)).fold(0.0, f64::max);
            assert!(err < tol, "{name} eps {eps}: error {err}");
        }
    }
    Ok(())
}

#[test]
fn layer_norm_module_and_2d_match_naive() -> Result<()> {
    let c = 6;
    let x = uniform((2, c, 3, 5), -1.0, 1.0, 4, &cpu())?;
    let w = uniform(c, 0.5, 1.5, 5, &cpu())?;
    let b = uniform(c, -0.5, 0.5, 6, &cpu())?;
    let ln = LayerNorm {
        weight: w.clone(),
        bias: b.clone(),
        eps: 1e-6,
    };
    let ln2d = LayerNorm2d { inner: ln.clone() };
    let y = ln2d.forward(&x)?;
    assert_eq!(y.dims(), x.dims());
    let (wv, bv) = (w.to_vec1::<f64>()?, b.to_vec1::<f64>()?);
    let x4 = x.flatten_all()?.to_vec1::<f64>()?;
    let y4 = y.contiguous()?.flatten_all()?.to_vec1::<f64>()?;
    let plane = 15;
    for bi in 0..2 {
        for p in 0..plane {
            let idx: Vec<usize> = (0..c).map(|ch| (bi * c + ch) * plane + p).collect();
            let xs: Vec<f64> = idx.iter().map(|&i| x4[i]).collect();
            let want = naive_layer_norm(&xs, &wv, &bv, 1e-6);
            let got: Vec<f64> = idx.iter().map(|&i| y4[i]).collect();
            assert!(max_diff(&got, &want) < 1e-12);
        }
    }
    // The f32 fast path (plain tensors) agrees with the f32 differentiable path.
    let f = |t: &Tensor| t.to_dtype(DType::F32);
    let ln32 = LayerNorm2d {
        inner: LayerNorm {
            weight: f(&w)?,
            bias: f(&b)?,
            eps: 1e-6,
        },
    };
    let fast = ln32.forward(&f(&x)?)?;
    let slow = ln32.forward(&tracked(&f(&x)?)?)?;
    assert!(max_abs_diff(&fast, &slow)? < 1e-5);
    assert!(max_abs_diff(&fast, &y)? < 1e-5);
    Ok(())
}

#[test]
fn layer_norm_gradients() -> Result<()> {
    let d = 7;
    let x = uniform((3, d), -1.0, 1.0, 7, &cpu())?;
    let w = uniform(d, 0.5, 1.5, 8, &cpu())?;
    let b = uniform(d, -0.5, 0.5, 9, &cpu())?;
    assert_gradients(
        "layer_norm",
        |t| layer_norm(&t[0], &t[1], &t[2], 1e-5),
        &[x, w.clone(), b.clone()],
        TOL,
    )?;
    let x = uniform((2, d, 2, 3), -1.0, 1.0, 10, &cpu())?;
    let f = |t: &[Tensor]| {
        LayerNorm2d {
            inner: LayerNorm {
                weight: t[1].clone(),
                bias: t[2].clone(),
                eps: 1e-5,
            },
        }
        .forward(&t[0])
    };
    assert_gradients("LayerNorm2d", f, &[x, w, b], TOL)
}

#[test]
fn softmax_matches_naive_on_both_paths() -> Result<()> {
    // Large logits: a naive exp would overflow, the max shift must not.
    let x = (uniform((4, 9), -3.0, 3.0, 11, &cpu())? * 300.0)?;
    let want: Vec<Vec<f64>> = rows(&x)?
        .iter()
        .map(|r| {
            let m = r.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let s: f64 = r.iter().map(|v| (v - m).exp()).sum();
            r.iter().map(|v| (v - m).exp() / s).collect()
        })
        .collect();
    for (name, got, tol) in [
        ("fast f64", softmax_last_dim(&x)?, 1e-14),
        ("slow f64", softmax_last_dim(&tracked(&x)?)?, 1e-14),
        ("fast f32", softmax_last_dim(&x.to_dtype(DType::F32)?)?, 1e-6),
        ("slow f32", softmax_last_dim(&tracked(&x.to_dtype(DType::F32)?)?)?, 1e-6),
        ("fast strided", softmax_last_dim(&x.t()?.contiguous()?.t()?)?, 1e-14),
    ] {
        let err = rows(&got)?
            .iter()
            .zip(&want)
            .map(|(g, w)| max_diff(g, w))
            .fold(0.0, f64::max);
        assert!(err < tol, "{name}: {err}");
    }
    let x = uniform((3, 5), -2.0, 2.0, 12, &cpu())?;
    assert_gradients("softmax", |t| softmax_last_dim(&t[0]), &[x], TOL)
}

#[test]
fn gelu_is_exact_erf_form() -> Result<()> {
    // x·Φ(x); Φ(1) = 0.841344746068543, Φ(−1) = 1 − Φ(1), Φ(0) = 1/2.
    let y = gelu(&Tensor::new(&[1f64, -1.0, 0.0, 2.0], &cpu())?)?.to_vec1::<f64>()?;
    let phi1 = 0.841_344_746_068_542_9;
    let want = [phi1, -(1.0 - phi1), 0.0, 2.0 * 0.977_249_868_051_820_8];
    assert!(max_diff(&y, &want) < 1e-6, "{y:?}");
    Ok(())
}

#[test]
fn resize_hand_values_pytorch_align_corners_false() -> Result<()> {
    // 1D cases by hand, source coordinate (o + 0.5)·n_in/n_out − 0.5, clamped at 0:
    // [0,1,2,3] → 8: src = 0.5o − 0.25 → 0, .25, .75, …, 3.25 (upper neighbour clamped to 3).
    // [0,1,2,3] → 2: src = 2o + 0.5 → 0.5, 2.5.
    // [0,1,4,9,16] → 3: src = 1/3, 2, 11/3 → 1/3, 4, 9 + (2/3)·7.
    let cases: [(&[f64], usize, &[f64]); 3] = [
        (&[0., 1., 2., 3.], 8, &[0., 0.25, 0.75, 1.25, 1.75, 2.25, 2.75, 3.]),
        (&[0., 1., 2., 3.], 2, &[0.5, 2.5]),
        (&[0., 1., 4., 9., 16.], 3, &[1. / 3., 4., 9. + 14. / 3.]),
    ];
    for (a, n_out, want_a) in cases {
        // Separable additive image x[i, j] = a[i] + 10·a[j]: bilinear weights sum to one, so the
        // resized image is want[i] + 10·want[j].
        let n = a.len();
        let img: Vec<f64> = (0..n * n).map(|k| a[k / n] + 10.0 * a[k % n]).collect();
        let x = Tensor::from_vec(img, (1, 1, n, n), &cpu())?;
        let want: Vec<f64> = (0..n_out * n_out)
            .map(|k| want_a[k / n_out] + 10.0 * want_a[k % n_out])
            .collect();
        for (name, y) in [
            ("fast", resize_bilinear(&x, n_out, n_out)?),
            ("slow", resize_bilinear(&tracked(&x)?, n_out, n_out)?),
        ] {
            assert_eq!(y.dims(), &[1, 1, n_out, n_out]);
            let got = y.flatten_all()?.to_vec1::<f64>()?;
            assert!(max_diff(&got, &want) < 1e-12, "{name} {n}→{n_out}: {got:?}");
        }
    }
    let m = interp_matrix(4, 2, &cpu())?.to_vec2::<f32>()?;
    assert_eq!(m, vec![vec![0.5, 0.5, 0.0, 0.0], vec![0.0, 0.0, 0.5, 0.5]]);
    assert!(resize_bilinear(&Tensor::zeros((1, 1, 2, 2), DType::F32, &cpu())?, 0, 3).is_err());
    Ok(())
}

#[test]
fn resize_fast_and_slow_paths_agree_and_gradients() -> Result<()> {
    let x = uniform((2, 3, 7, 5), -1.0, 1.0, 13, &cpu())?;
    for (h, w) in [(13, 9), (3, 4), (7, 11), (1, 1)] {
        let fast = resize_bilinear(&x, h, w)?;
        let slow = resize_bilinear(&tracked(&x)?, h, w)?;
        let d = max_abs_diff(&fast, &slow)?;
        assert!(d < 1e-12, "{h}x{w}: {d}");
    }
    let x = uniform((1, 2, 4, 3), -1.0, 1.0, 14, &cpu())?;
    assert_gradients(
        "resize up",
        |t| resize_bilinear(&t[0], 7, 5),
        std::slice::from_ref(&x),
        TOL,
    )?;
    assert_gradients("resize down", |t| resize_bilinear(&t[0], 3, 2), &[x], TOL)
}

#[test]
fn resize_f32_training_path_matches_the_f64_matrix_path() -> Result<()> {
    // The f32 CPU op with a gradient (direct kernel + adjoint) against the f64 matrix path,
    // values and the input gradient of Σ y ⊙ G, up and down, odd sizes.
    for (shape, (h, w)) in [
        ((2, 3, 7, 5), (13, 9)),
        ((1, 2, 9, 8), (4, 3)),
        ((1, 1, 5, 6), (5, 6 * 2 + 1)),
    ] {
        let x64 = uniform(shape, -1.0, 1.0, 21, &cpu())?;
        let g64 = uniform((shape.0, shape.1, h, w), -1.0, 1.0, 22, &cpu())?;
        let run = |x: &Tensor, g: &Tensor| -> Result<(Tensor, Tensor)> {
            let v = candle_core::Var::from_tensor(x)?;
            let y = resize_bilinear(v.as_tensor(), h, w)?;
            let grads = (&y * g)?.sum_all()?.backward()?;
            let dx = grads.get(v.as_tensor()).expect("input gradient").clone();
            Ok((y.to_dtype(DType::F64)?, dx.to_dtype(DType::F64)?))
        };
        let (y32, dx32) = run(&x64.to_dtype(DType::F32)?, &g64.to_dtype(DType::F32)?)?;
        let (y64, dx64) = run(&x64, &g64)?;
        let (dy, ddx) = (max_abs_diff(&y32, &y64)?, max_abs_diff(&dx32, &dx64)?);
        assert!(
            dy < 1e-5 && ddx < 1e-5,
            "{shape:?} -> {h}x{w}: values {dy}, gradient {ddx}"
        );
    }
    Ok(())
}

#[test]
fn relu_training_op_equals_candles_relu() -> Result<()> {
    // Values and the gradient of Σ relu(x) ⊙ G against candle's relu, exact zeros included
    // (both pass the gradient at 0).
    let x = uniform((2, 3, 5, 7), -1.0, 1.0, 31, &cpu())?.to_dtype(DType::F32)?;
    let vals: Vec<f32> = x.flatten_all()?.to_vec1::<f32>()?;
    let vals: Vec<f32> = vals.into_iter().map(|v| if v < -0.5 { 0.0 } else { v }).collect();
    assert!(vals.contains(&0.0));
    let x = Tensor::from_vec(vals, (2, 3, 5, 7), &cpu())?;
    let g = uniform((2, 3, 5, 7), -1.0, 1.0, 32, &cpu())?.to_dtype(DType::F32)?;
    let v = candle_core::Var::from_tensor(&x)?;
    let run = |y: Tensor| -> Result<(Tensor, Tensor)> {
        let store = (&y * &g)?.sum_all()?.backward()?;
        Ok((y, store.get(v.as_tensor()).expect("gradient").clone()))
    };
    let (y1, d1) = run(pixl_nn::ops::relu(v.as_tensor())?)?;
    let (y2, d2) = run(v.as_tensor().relu()?)?;
    assert_eq!(max_abs_diff(&y1, &y2)?, 0.0);
    assert_eq!(max_abs_diff(&d1, &d2)?, 0.0);
    Ok(())
}

#[test]
fn rope_hand_value_and_identity_at_origin() -> Result<()> {
    // head_dim 4: one frequency (base⁰ = 1); dims (0,1) rotate by y, (2,3) by x.
    let rope = Rope2d::new(4, 2, 3, 100.0, &cpu())?;
    let v = Tensor::new(&[1f64, 0., 0., 1.], &cpu())?
        .reshape((1, 1, 1, 4))?
        .repeat((1, 1, 6, 1))?;
    let y = rope.apply(&v)?.flatten_all()?.to_vec1::<f64>()?;
    // Token 0 is (y=0, x=0): unchanged. Token 5 is (y=1, x=2).
    assert!(max_diff(&y[0..4], &[1., 0., 0., 1.]) < 1e-7);
    let want5 = [1f64.cos(), 1f64.sin(), -(2f64.sin()), 2f64.cos()];
    assert!(max_diff(&y[20..24], &want5) < 1e-6, "{:?}", &y[20..24]);
    assert!(Rope2d::new(6, 2, 2, 100.0, &cpu()).is_err());
    assert!(rope.apply(&Tensor::zeros((1, 1, 5, 4), DType::F32, &cpu())?).is_err());
    Ok(())
}

#[test]
fn rope_is_a_rotation_with_relative_positions() -> Result<()> {
    let (gh, gw, d) = (3, 4, 16);
    let n = gh * gw;
    let rope = Rope2d::new(d, gh, gw, 100.0, &cpu())?;
    let x = uniform((2, 2, n, d), -1.0, 1.0, 15, &cpu())?;
    let norms = |t: &Tensor| -> Result<Vec<f64>> { t.sqr()?.sum(D::Minus1)?.flatten_all()?.to_vec1::<f64>() };
    let y = rope.apply(&x)?;
    assert!(max_diff(&norms(&y)?, &norms(&x)?) < 1e-5);
    // The same q and k at every token: q(p)·k(p') must depend on p − p' only.
    let q = uniform((1, 1, 1, d), -1.0, 1.0, 16, &cpu())?.repeat((1, 1, n, 1))?;
    let k = uniform((1, 1, 1, d), -1.0, 1.0, 17, &cpu())?.repeat((1, 1, n, 1))?;
    let dots = rope
        .apply(&q)?
        .matmul(&rope.apply(&k)?.t()?)?
        .flatten_all()?
        .to_vec1::<f64>()?;
    let at = |(y1, x1): (usize, usize), (y2, x2): (usize, usize)| dots[(y1 * gw + x1) * n + y2 * gw + x2];
    let mut compared = 0;
    for p in 0..n {
        for pp in 0..n {
            let (a, b) = ((p / gw, p % gw), (pp / gw, pp % gw));
            // Shift both by (+1, +1) where possible.
            if a.0 + 1 < gh && a.1 + 1 < gw && b.0 + 1 < gh && b.1 + 1 < gw {
                let shifted = at((a.0 + 1, a.1 + 1), (b.0 + 1, b.1 + 1));
                assert!((at(a, b) - shifted).abs() < 1e-5, "{a:?} {b:?}");
                compared += 1;
            }
        }
    }
    assert!(compared > 10);
    // And it is not trivially constant: different offsets give different dot products.
    assert!((at((0, 0), (0, 1)) - at((0, 0), (1, 0))).abs() > 1e-3);
    let x = uniform((1, 2, n, 8), -1.0, 1.0, 18, &cpu())?;
    let rope8 = Rope2d::new(8, gh, gw, 100.0, &cpu())?;
    assert_gradients("rope", |t| rope8.apply(&t[0]), &[x], TOL)
}

fn naive_attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Vec<f64>> {
    let (b, h, n, d) = q.dims4()?;
    let dv = v.dim(3)?;
    let (q, k, v) = (
        q.flatten_all()?.to_vec1::<f64>()?,
        k.flatten_all()?.to_vec1::<f64>()?,
        v.flatten_all()?.to_vec1::<f64>()?,
    );
    let m = k.len() / (b * h * d);
    let mut out = vec![0.0; b * h * n * dv];
    for bh in 0..b * h {
        for i in 0..n {
            let s: Vec<f64> = (0..m)
                .map(|j| {
                    (0..d)
                        .map(|e| q[(bh * n + i) * d + e] * k[(bh * m + j) * d + e])
                        .sum::<f64>()
                        / (d as f64).sqrt()
                })
                .collect();
            let mx = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let z: f64 = s.iter().map(|x| (x - mx).exp()).sum();
            for (j, sj) in s.iter().enumerate() {
                let p = (sj - mx).exp() / z;
                for e in 0..dv {
                    out[(bh * n + i) * dv + e] += p * v[(bh * m + j) * dv + e];
                }
            }
        }
    }
    Ok(out)
}

#[test]
fn attention_matches_naive_and_gradients() -> Result<()> {
    let q = uniform((2, 2, 5, 4), -1.0, 1.0, 19, &cpu())?;
    let k = uniform((2, 2, 6, 4), -1.0, 1.0, 20, &cpu())?;
    let v = uniform((2, 2, 6, 3), -1.0, 1.0, 21, &cpu())?;
    let want = naive_attention(&q, &k, &v)?;
    let got = attention(&q, &k, &v)?;
    assert_eq!(got.dims(), &[2, 2, 5, 3]);
    assert!(max_diff(&got.flatten_all()?.to_vec1::<f64>()?, &want) < 1e-12);
    let f = |t: &Tensor| t.to_dtype(DType::F32);
    let fast = attention(&f(&q)?, &f(&k)?, &f(&v)?)?;
    let slow = attention(&tracked(&f(&q)?)?, &f(&k)?, &f(&v)?)?;
    assert!(max_abs_diff(&fast, &slow)? < 1e-6);
    assert!(max_abs_diff(&fast, &got)? < 1e-5);
    assert_gradients("attention", |t| attention(&t[0], &t[1], &t[2]), &[q, k, v], TOL)
}

/// The fused CPU kernel on shapes that span several query blocks with a partial last block
/// (1100 keys → 119 rows per block; 300 queries → 3 blocks), non-contiguous inputs, and scores
/// large enough that an unshifted softmax would overflow.
#[test]
fn fused_attention_blocks_match_naive() -> Result<()> {
    let q = (uniform((1, 2, 300, 16), -1.0, 1.0, 40, &cpu())? * 12.0)?;
    let k = uniform((1, 2, 16, 1100), -1.0, 1.0, 41, &cpu())?.transpose(2, 3)?;
    let v = uniform((1, 2, 1100, 8), -1.0, 1.0, 42, &cpu())?;
    assert!(!k.is_contiguous());
    let want = naive_attention(&q, &k.contiguous()?, &v)?;
    let f = |t: &Tensor| t.to_dtype(DType::F32);
    let got = attention(&f(&q)?, &f(&k)?, &f(&v)?)?;
    assert_eq!(got.dims(), &[1, 2, 300, 8]);
    let err = max_diff(&got.flatten_all()?.to_dtype(DType::F64)?.to_vec1::<f64>()?, &want);
    assert!(err < 2e-5, "fused attention error {err}");
    // The unfused f32 path agrees to the same order.
    let slow = attention(&tracked(&f(&q)?)?, &f(&k)?, &f(&v)?)?;
    assert!(max_abs_diff(&got, &slow)? < 2e-5);
    // Mismatched shapes are an error, not a panic.
    assert!(attention(&f(&q)?, &f(&k.narrow(2, 0, 1000)?)?, &f(&v)?).is_err());
    Ok(())
}

#[test]
fn mlp_gradients_and_value() -> Result<()> {
    let (i, hdim, o) = (3, 5, 2);
    let x = uniform((2, 4, i), -1.0, 1.0, 22, &cpu())?;
    let w1 = uniform((hdim, i), -1.0, 1.0, 23, &cpu())?;
    let b1 = uniform(hdim, -1.0, 1.0, 24, &cpu())?;
    let w2 = uniform((o, hdim), -1.0, 1.0, 25, &cpu())?;
    let b2 = uniform(o, -1.0, 1.0, 26, &cpu())?;
    let mlp = |t: &[Tensor]| Mlp {
        fc1: pixl_nn::Linear::new(Linear::new(t[1].clone(), Some(t[2].clone()))),
        fc2: pixl_nn::Linear::new(Linear::new(t[3].clone(), Some(t[4].clone()))),
    };
    let inputs = [x, w1, b1, w2, b2];
    // Value against a direct evaluation: fc2(gelu(fc1(x))).
    let y = mlp(&inputs).forward(&inputs[0])?;
    let h = inputs[0].broadcast_matmul(&inputs[1].t()?)?.broadcast_add(&inputs[2])?;
    let h = ((&h * ((&h / 2f64.sqrt())?.erf()? + 1.0)?)? * 0.5)?;
    let want = h.broadcast_matmul(&inputs[3].t()?)?.broadcast_add(&inputs[4])?;
    assert!(max_abs_diff(&y, &want)? < 1e-12);
    assert_gradients("mlp", |t| mlp(t).forward(&t[0]), &inputs, TOL)
}

/// The f32 CPU kernel (planes in parallel, a plane cut into bands of rows when there are fewer
/// planes than threads) against the f64 interpolation matrices `Wy · X · Wxᵀ` on the same f32
/// values: up, down, odd sizes, one plane and several, 1 and 3 threads.
#[test]
fn resize_f32_kernel_matches_the_interpolation_matrices() -> Result<()> {
    for (shape, (h, w)) in [
        ((1, 1, 7, 5), (13, 9)),
        ((1, 1, 5, 8), (16, 16)),
        ((2, 3, 9, 6), (4, 5)),
        ((1, 2, 3, 3), (10, 1)),
    ] {
        let x = uniform(shape, -1.0, 1.0, 21, &cpu())?.to_dtype(DType::F32)?;
        let (_, _, ih, iw) = shape;
        let wy = interp_matrix(ih, h, &cpu())?.to_dtype(DType::F64)?;
        let wx = interp_matrix(iw, w, &cpu())?.to_dtype(DType::F64)?;
        let want = wy.broadcast_matmul(&x.to_dtype(DType::F64)?.broadcast_matmul(&wx.t()?)?)?;
        for threads in [1, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            let got = pool.install(|| resize_bilinear(&x, h, w))?;
            assert_eq!(got.dtype(), DType::F32);
            let d = max_abs_diff(&got, &want)?;
            assert!(d < 1e-6, "{shape:?} -> {h}x{w}, {threads} threads: {d}");
        }
    }
    Ok(())
}
