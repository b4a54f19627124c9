//! Layer norm over the last dimension as one differentiable op.
//!
//! [`layer_norm`] computes `y = (x − μ)/√(σ² + eps)·w + b` for every row of the last dimension
//! (PyTorch `nn.LayerNorm` semantics: biased variance, `eps` inside the square root), the same
//! values as [`crate::norm::layer_norm`], with `w`, `b` of shape `(D)` and `xs` of any rank ≥ 1.
//!
//! On the CPU in f32 it is a single candle custom op ([`LayerNormOp`]) with its own backward,
//! instead of the ~9 composed ops (each a pass over memory, an allocation and an autograd node)
//! of the composed path:
//! - forward: rows in parallel (rayon); per row a two-pass mean and variance accumulated in f32
//!   over 16 lanes (so the variance never suffers the `E[x²] − E[x]²` cancellation), then one
//!   pass writing `y`. When a gradient will be needed the per-row mean and `rstd = 1/√(σ² + eps)`
//!   stay in the op (8 bytes per row; recomputed from `x` if absent);
//! - backward, with `g = dy·w` and `x̂ = (x − μ)·rstd`:
//!   `dx = rstd·(g − mean(g) − x̂·mean(g·x̂))`, `dw = Σ_rows dy·x̂`, `db = Σ_rows dy`, in one
//!   parallel pass over blocks of rows (two reads of each row, cache-hot), with per-block partial
//!   sums for `dw` and `db` added up at the end. Only the inputs that track gradients get one.
//!   The returned gradients are constants (no second-order gradients).
//!
//! The row loops are compiled for AVX-512, AVX2+FMA and the baseline, picked at run time. The
//! backward pass records a "layer norm backward" [`crate::profile`] span; the forward pass
//! records none, as [`crate::norm::layer_norm`] (which sends training on the CPU in f32 here)
//! already spans it.
//! Elsewhere (other devices, dtypes, mixed dtypes) it is [`crate::norm::layer_norm`], whose
//! composed path is differentiable.
use std::sync::Mutex;

use candle_core::{CpuStorage, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use crate::fused::{cpu_f32, slice, storage_slice};

/// Elements per parallel task.
const CHUNK: usize = 1 << 14;
/// Accumulator lanes in the row loops: one AVX-512 register.
const LANES: usize = 16;

/// Differentiable layer norm over the last dim, PyTorch semantics (biased variance, eps inside
/// the sqrt): same values as [`crate::norm::layer_norm`]. See the module docs for the paths.
pub fn layer_norm(xs: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    let Some(&d) = xs.dims().last() else {
        candle_core::bail!("layer norm: a scalar input");
    };
    if w.dims() != [d] || b.dims() != [d] {
        candle_core::bail!(
            "layer norm: weight {:?} / bias {:?} do not fit an input of shape {:?}",
            w.dims(),
            b.dims(),
            xs.dims()
        );
    }
    if !(cpu_f32(xs) && cpu_f32(w) && cpu_f32(b)) {
        // Not all CPU f32, so `crate::norm::layer_norm` takes its composed path (it sends only
        // CPU f32 inputs here).
        return crate::norm::layer_norm(xs, w, b, eps);
    }
    let op = LayerNormOp {
        eps,
        keep: crate::needs_grad(&[xs, w, b]),
        stats: Mutex::new(None),
    };
    xs.contiguous()?.apply_op3(&w.contiguous()?, &b.contiguous()?, op)
}

/// The CPU f32 kernel, `(x, w, b) → y`, differentiable in all three.
#[derive(Debug)]
pub struct LayerNormOp {
    eps: f64,
    /// Whether the forward pass keeps the row statistics for the backward pass.
    keep: bool,
    /// Per row `[mean, rstd]`, interleaved, from the forward pass.
    stats: Mutex<Option<Vec<f32>>>,
}

impl CustomOp3 for LayerNormOp {
    fn name(&self) -> &'static str {
        "pixl-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let x = slice(s1, l1, "layer norm input")?;
        let w = slice(s2, l2, "layer norm weight")?;
        let b = slice(s3, l3, "layer norm bias")?;
        let d = l1.shape().dims().last().copied().unwrap_or(0);
        if w.len() != d || b.len() != d {
            candle_core::bail!(
                "layer norm: weight {:?} / bias {:?} do not fit {:?}",
                l2.shape(),
                l3.shape(),
                l1.shape()
            );
        }
        let mut y = vec![0f32; x.len()];
        if d == 0 || x.is_empty() {
            return Ok((CpuStorage::F32(y), l1.shape().clone()));
        }
        let rows = x.len() / d;
        let mut stats = vec![0f32; 2 * rows];
        let per = (CHUNK / d).max(1);
        y.par_chunks_mut(per * d)
            .zip(x.par_chunks(per * d))
            .zip(stats.par_chunks_mut(2 * per))
            .for_each(|((y, x), st)| forward_rows(x, w, b, self.eps, y, st));
        if self.keep {
            *self.lock_stats()? = Some(stats);
        }
        Ok((CpuStorage::F32(y), l1.shape().clone()))
    }

    fn bwd(
        &self,
        xs: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let (need_x, need_w, need_b) = (xs.track_op(), w.track_op(), b.track_op());
        if !(need_x || need_w || need_b) {
            return Ok((None, None, None));
        }
        let _t = crate::profile::span("layer norm backward");
        let grad = grad.contiguous()?;
        let (gs, gl) = grad.storage_and_layout();
        let dy = storage_slice(&gs, gl, "layer norm output gradient")?;
        let (xs_s, xs_l) = xs.storage_and_layout();
        let x = storage_slice(&xs_s, xs_l, "layer norm input")?;
        let (ws, wl) = w.storage_and_layout();
        let wv = storage_slice(&ws, wl, "layer norm weight")?;
        let d = wv.len();
        if dy.len() != x.len() || x.len() % d.max(1) != 0 {
            candle_core::bail!(
                "layer norm backward: gradient {:?} for input {:?}",
                grad.dims(),
                xs.dims()
            );
        }
        let rows = x.len().checked_div(d).unwrap_or(0);
        let mut dx = vec![0f32; if need_x { x.len() } else { 0 }];
        let mut dw = vec![0f32; d];
        let mut db = vec![0f32; d];
        if rows > 0 {
            let saved = self.lock_stats()?;
            let recomputed;
            let stats: &[f32] = match saved.as_deref() {
                Some(s) if s.len() == 2 * rows => s,
                _ => {
                    recomputed = row_stats(x, d, self.eps);
                    &recomputed
                }
            };
            let per = (CHUNK / d).max(1);
            let block = |t: usize, dx: Option<&mut [f32]>| {
                let (r0, r1) = (t * per, ((t + 1) * per).min(rows));
                let mut pw = vec![0f32; d];
                let mut pb = vec![0f32; d];
                backward_rows(
                    &x[r0 * d..r1 * d],
                    &dy[r0 * d..r1 * d],
                    wv,
                    &stats[2 * r0..2 * r1],
                    dx,
                    &mut pw,
                    &mut pb,
                );
                (pw, pb)
            };
            let partials: Vec<(Vec<f32>, Vec<f32>)> = if need_x {
                dx.par_chunks_mut(per * d)
                    .enumerate()
                    .map(|(t, dx)| block(t, Some(dx)))
                    .collect()
            } else {
                (0..rows.div_ceil(per))
                    .into_par_iter()
                    .map(|t| block(t, None))
                    .collect()
            };
            for (pw, pb) in &partials {
                dw.iter_mut().zip(pw).for_each(|(a, v)| *a += v);
                db.iter_mut().zip(pb).for_each(|(a, v)| *a += v);
            }
        }
        let dev = xs.device();
        let gx = need_x.then(|| Tensor::from_vec(dx, xs.shape(), dev)).transpose()?;
        let gw = need_w.then(|| Tensor::from_vec(dw, d, dev)).transpose()?;
        let gb = need_b.then(|| Tensor::from_vec(db, d, dev)).transpose()?;
        Ok((gx, gw, gb))
    }
}

impl LayerNormOp {
    fn lock_stats(&self) -> Result<std::sync::MutexGuard<'_, Option<Vec<f32>>>> {
        match self.stats.lock() {
            Ok(g) => Ok(g),
            Err(_) => candle_core::bail!("layer norm: the saved statistics are poisoned"),
        }
    }
}

/// Per row `[mean, rstd]` of `x` (rows of `d`), in parallel: the forward pass's statistics.
fn row_stats(x: &[f32], d: usize, eps: f64) -> Vec<f32> {
    let mut stats = vec![0f32; 2 * (x.len() / d.max(1))];
    stats
        .par_chunks_mut(2)
        .zip(x.par_chunks(d.max(1)))
        .with_min_len(16)
        .for_each(|(st, row)| {
            let (mean, rstd) = stats_of(row, eps);
            st[0] = mean;
            st[1] = rstd;
        });
    stats
}

/// Sum of `x` over [`LANES`] accumulators.
#[inline(always)]
fn lane_sum(x: &[f32]) -> f32 {
    let mut acc = [0f32; LANES];
    let mut chunks = x.chunks_exact(LANES);
    for c in &mut chunks {
        acc.iter_mut().zip(c).for_each(|(a, &v)| *a += v);
    }
    chunks.remainder().iter().sum::<f32>() + acc.iter().sum::<f32>()
}

/// `Σ (x − m)²` over [`LANES`] accumulators.
#[inline(always)]
fn lane_sq_dev(x: &[f32], m: f32) -> f32 {
    let mut acc = [0f32; LANES];
    let mut chunks = x.chunks_exact(LANES);
    for c in &mut chunks {
        acc.iter_mut().zip(c).for_each(|(a, &v)| *a += (v - m) * (v - m));
    }
    let tail: f32 = chunks.remainder().iter().map(|&v| (v - m) * (v - m)).sum();
    tail + acc.iter().sum::<f32>()
}

/// Mean and `1/√(σ² + eps)` of one row (two passes, f32).
#[inline(always)]
fn stats_of(row: &[f32], eps: f64) -> (f32, f32) {
    let inv_d = 1.0 / row.len() as f32;
    let mean = lane_sum(row) * inv_d;
    let var = lane_sq_dev(row, mean) * inv_d;
    (mean, (1.0 / (var as f64 + eps).sqrt()) as f32)
}

#[inline(always)]
fn forward_rows_generic(x: &[f32], w: &[f32], b: &[f32], eps: f64, y: &mut [f32], stats: &mut [f32]) {
    let d = w.len();
    let rows = x
        .chunks_exact(d)
        .zip(y.chunks_exact_mut(d))
        .zip(stats.chunks_exact_mut(2));
    for ((xr, yr), st) in rows {
        let (mean, rstd) = stats_of(xr, eps);
        for (((o, &v), &wv), &bv) in yr.iter_mut().zip(xr).zip(w).zip(b) {
            *o = (v - mean) * rstd * wv + bv;
        }
        st[0] = mean;
        st[1] = rstd;
    }
}

/// One block of rows of the backward pass: `dx` (if asked) and the block's `dw`, `db` sums added
/// to `dw`, `db`.
#[inline(always)]
fn backward_rows_generic(
    x: &[f32],
    dy: &[f32],
    w: &[f32],
    stats: &[f32],
    dx: Option<&mut [f32]>,
    dw: &mut [f32],
    db: &mut [f32],
) {
    let d = w.len();
    let inv_d = 1.0 / d as f32;
    let rows = x.chunks_exact(d).zip(dy.chunks_exact(d)).zip(stats.chunks_exact(2));
    match dx {
        Some(dx) => {
            for (((xr, gr), st), dxr) in rows.zip(dx.chunks_exact_mut(d)) {
                let (mean, rstd) = (st[0], st[1]);
                // mean(g) and mean(g·x̂).
                let (mut sa, mut sc) = ([0f32; LANES], [0f32; LANES]);
                let mut xc = xr.chunks_exact(LANES);
                let mut gc = gr.chunks_exact(LANES);
                let mut wc = w.chunks_exact(LANES);
                for ((xl, gl), wl) in (&mut xc).zip(&mut gc).zip(&mut wc) {
                    let lanes = sa.iter_mut().zip(sc.iter_mut()).zip(xl.iter().zip(gl).zip(wl));
                    for ((a, c), ((&xv, &dyv), &wv)) in lanes {
                        let g = dyv * wv;
                        *a += g;
                        *c += g * ((xv - mean) * rstd);
                    }
                }
                let (mut ta, mut tc) = (0f32, 0f32);
                for ((&xv, &dyv), &wv) in xc.remainder().iter().zip(gc.remainder()).zip(wc.remainder()) {
                    let g = dyv * wv;
                    ta += g;
                    tc += g * ((xv - mean) * rstd);
                }
                let a = (ta + sa.iter().sum::<f32>()) * inv_d;
                let c = (tc + sc.iter().sum::<f32>()) * inv_d;
                let cols = dxr
                    .iter_mut()
                    .zip(xr.iter().zip(gr))
                    .zip(w.iter().zip(dw.iter_mut().zip(db.iter_mut())));
                for ((o, (&xv, &dyv)), (&wv, (pw, pb))) in cols {
                    let xh = (xv - mean) * rstd;
                    *o = rstd * (dyv * wv - a - xh * c);
                    *pw += dyv * xh;
                    *pb += dyv;
                }
            }
        }
        None => {
            for ((xr, gr), st) in rows {
                let (mean, rstd) = (st[0], st[1]);
                for ((&xv, &dyv), (pw, pb)) in xr.iter().zip(gr).zip(dw.iter_mut().zip(db.iter_mut())) {
                    *pw += dyv * ((xv - mean) * rstd);
                    *pb += dyv;
                }
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn forward_rows_avx512(x: &[f32], w: &[f32], b: &[f32], eps: f64, y: &mut [f32], stats: &mut [f32]) {
    forward_rows_generic(x, w, b, eps, y, stats)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn forward_rows_avx2(x: &[f32], w: &[f32], b: &[f32], eps: f64, y: &mut [f32], stats: &mut [f32]) {
    forward_rows_generic(x, w, b, eps, y, stats)
}

/// Normalises the rows of `x` (rows of `w.len()`) into `y` and writes `[mean, rstd]` per row.
fn forward_rows(x: &[f32], w: &[f32], b: &[f32], eps: f64, y: &mut [f32], stats: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { forward_rows_avx512(x, w, b, eps, y, stats) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { forward_rows_avx2(x, w, b, eps, y, stats) };
        }
    }
    forward_rows_generic(x, w, b, eps, y, stats)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn backward_rows_avx512(
    x: &[f32],
    dy: &[f32],
    w: &[f32],
    stats: &[f32],
    dx: Option<&mut [f32]>,
    dw: &mut [f32],
    db: &mut [f32],
) {
    backward_rows_generic(x, dy, w, stats, dx, dw, db)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn backward_rows_avx2(
    x: &[f32],
    dy: &[f32],
    w: &[f32],
    stats: &[f32],
    dx: Option<&mut [f32]>,
    dw: &mut [f32],
    db: &mut [f32],
) {
    backward_rows_generic(x, dy, w, stats, dx, dw, db)
}

/// See [`backward_rows_generic`].
fn backward_rows(
    x: &[f32],
    dy: &[f32],
    w: &[f32],
    stats: &[f32],
    dx: Option<&mut [f32]>,
    dw: &mut [f32],
    db: &mut [f32],
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { backward_rows_avx512(x, dy, w, stats, dx, dw, db) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { backward_rows_avx2(x, dy, w, stats, dx, dw, db) };
        }
    }
    backward_rows_generic(x, dy, w, stats, dx, dw, db)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Var};

    use crate::testing::uniform;

    const EPS: f64 = 1e-5;

    fn f32_uniform(shape: &[usize], lo: f64, hi: f64, seed: u64) -> Result<Tensor> {
        uniform(shape, lo, hi, seed, &Device::Cpu)?.to_dtype(DType::F32)
    }

    fn values(t: &Tensor) -> Result<Vec<f64>> {
        t.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()
    }

    /// `max |a − b| / max |b|`.
    fn rel_err(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len(), "lengths differ");
        let scale = b.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-12);
        let err = a.iter().zip(b).fold(0f64, |m, (x, y)| m.max((x - y).abs()));
        err / scale
    }

    /// Naive f64 layer norm over rows of `w.len()`.
    fn naive(x: &[f64], w: &[f64], b: &[f64]) -> Vec<f64> {
        let d = w.len();
        let mut y = Vec::with_capacity(x.len());
        for row in x.chunks(d) {
            let mean = row.iter().sum::<f64>() / d as f64;
            let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / d as f64;
            let rstd = 1.0 / (var + EPS).sqrt();
            y.extend(row.iter().zip(w).zip(b).map(|((v, w), b)| (v - mean) * rstd * w + b));
        }
        y
    }

    /// Central differences of `Σ naive(x, w, b)·r` with respect to input `which` (0 x, 1 w, 2 b).
    fn numeric_grad(args: &[Vec<f64>; 3], r: &[f64], which: usize) -> Vec<f64> {
        let h = 1e-6;
        let loss = |a: &[Vec<f64>; 3]| -> f64 { naive(&a[0], &a[1], &a[2]).iter().zip(r).map(|(y, r)| y * r).sum() };
        (0..args[which].len())
            .map(|e| {
                let mut p = args.clone();
                p[which][e] += h;
                let mut m = args.clone();
                m[which][e] -= h;
                (loss(&p) - loss(&m)) / (2.0 * h)
            })
            .collect()
    }

    /// Checks values against the naive f64 layer norm and the gradients of `Σ y·R` (for the inputs
    /// marked in `track`) against central differences of it; `x` may be any tensor (a view too).
    fn check(x: &Tensor, track: [bool; 3], seed: u64) -> Result<()> {
        let d = x.dims().last().copied().unwrap_or(0);
        let w = f32_uniform(&[d], 0.5, 1.5, seed + 1)?;
        let b = f32_uniform(&[d], -0.5, 0.5, seed + 2)?;
        let wrap = |t: &Tensor, on: bool| -> Result<(Tensor, Option<Var>)> {
            if on {
                let v = Var::from_tensor(t)?;
                Ok((v.as_tensor().clone(), Some(v)))
            } else {
                Ok((t.clone(), None))
            }
        };
        let (xt, xv) = wrap(x, track[0])?;
        let (wt, wv) = wrap(&w, track[1])?;
        let (bt, bv) = wrap(&b, track[2])?;
        let y = layer_norm(&xt, &wt, &bt, EPS)?;
        assert_eq!(y.dims(), x.dims());
        let args = [values(x)?, values(&w)?, values(&b)?];
        let want = naive(&args[0], &args[1], &args[2]);
        let got = values(&y)?;
        assert!(rel_err(&got, &want) < 1e-5, "values off: {:e}", rel_err(&got, &want));
        let r = f32_uniform(x.dims(), -1.0, 1.0, seed + 3)?;
        let grads = (&y * &r)?.sum_all()?.backward()?;
        let r = values(&r)?;
        for (i, var) in [xv, wv, bv].iter().enumerate() {
            match var {
                Some(v) => {
                    let g = grads.get(v.as_tensor()).expect("a gradient for a tracked input");
                    assert_eq!(g.dims(), args_dims(i, x, d).as_slice());
                    let want = numeric_grad(&args, &r, i);
                    let err = rel_err(&values(g)?, &want);
                    assert!(err < 1e-4, "gradient {i} of {:?}: relative error {err:e}", x.dims());
                }
                None => assert!(!track[i]),
            }
        }
        Ok(())
    }

    fn args_dims(i: usize, x: &Tensor, d: usize) -> Vec<usize> {
        if i == 0 {
            x.dims().to_vec()
        } else {
            vec![d]
        }
    }

    #[test]
    fn matches_inference_layer_norm() -> Result<()> {
        let shapes: [&[usize]; 5] = [&[13], &[14, 13], &[2, 7, 13], &[2, 3, 5, 96], &[3, 384]];
        for (i, shape) in shapes.iter().enumerate() {
            let x = f32_uniform(shape, -2.0, 3.0, 10 + i as u64)?;
            let d = shape[shape.len() - 1];
            let w = f32_uniform(&[d], 0.5, 1.5, 20 + i as u64)?;
            let b = f32_uniform(&[d], -0.5, 0.5, 30 + i as u64)?;
            let ours = values(&layer_norm(&x, &w, &b, EPS)?)?;
            let theirs = values(&crate::norm::layer_norm(&x, &w, &b, EPS)?)?;
            let err = rel_err(&ours, &theirs);
            assert!(err <= 1e-5, "{shape:?}: relative error {err:e}");
        }
        Ok(())
    }

    #[test]
    fn gradients_rank2() -> Result<()> {
        check(&f32_uniform(&[14, 13], -2.0, 2.0, 1)?, [true; 3], 100)
    }

    #[test]
    fn gradients_rank3() -> Result<()> {
        check(&f32_uniform(&[2, 7, 13], -2.0, 2.0, 2)?, [true; 3], 200)
    }

    #[test]
    fn gradients_rank4_and_rank1() -> Result<()> {
        check(&f32_uniform(&[2, 3, 2, 13], -2.0, 2.0, 3)?, [true; 3], 300)?;
        check(&f32_uniform(&[37], -2.0, 2.0, 4)?, [true; 3], 400)
    }

    #[test]
    fn gradients_wide_rows_with_offset() -> Result<()> {
        // 40 rows of 96 (several 16-lane chunks), values around 50: the two-pass statistics.
        check(&f32_uniform(&[40, 96], 49.0, 51.0, 5)?, [true; 3], 500)
    }

    #[test]
    fn gradients_non_contiguous_input() -> Result<()> {
        let x = f32_uniform(&[13, 2, 7], -2.0, 2.0, 6)?.permute((1, 2, 0))?;
        assert!(!x.is_contiguous());
        check(&x, [true; 3], 600)
    }

    #[test]
    fn gradients_without_input_gradient() -> Result<()> {
        check(&f32_uniform(&[2, 7, 13], -2.0, 2.0, 7)?, [false, true, true], 700)?;
        check(&f32_uniform(&[2, 7, 13], -2.0, 2.0, 8)?, [true, false, false], 800)?;
        check(&f32_uniform(&[2, 7, 13], -2.0, 2.0, 9)?, [false, false, true], 900)
    }

    #[test]
    fn no_gradient_for_untracked_input() -> Result<()> {
        let x = f32_uniform(&[14, 13], -2.0, 2.0, 11)?;
        let w = Var::from_tensor(&f32_uniform(&[13], 0.5, 1.5, 12)?)?;
        let b = f32_uniform(&[13], -0.5, 0.5, 13)?;
        let grads = layer_norm(&x, w.as_tensor(), &b, EPS)?.sum_all()?.backward()?;
        assert!(grads.get(&x).is_none());
        assert!(grads.get(&b).is_none());
        assert!(grads.get(w.as_tensor()).is_some());
        Ok(())
    }

    #[test]
    fn backward_twice_gives_the_same_gradients() -> Result<()> {
        let x = Var::from_tensor(&f32_uniform(&[5, 13], -2.0, 2.0, 14)?)?;
        let w = f32_uniform(&[13], 0.5, 1.5, 15)?;
        let b = f32_uniform(&[13], -0.5, 0.5, 16)?;
        let r = f32_uniform(&[5, 13], -1.0, 1.0, 17)?;
        let loss = (layer_norm(x.as_tensor(), &w, &b, EPS)? * &r)?.sum_all()?;
        let g1 = values(loss.backward()?.get(x.as_tensor()).expect("gradient"))?;
        let g2 = values(loss.backward()?.get(x.as_tensor()).expect("gradient"))?;
        assert_eq!(g1, g2);
        Ok(())
    }

    #[test]
    fn f64_falls_back_to_the_composed_path() -> Result<()> {
        let dev = Device::Cpu;
        let inputs = [
            uniform((3, 7), -2.0, 2.0, 18, &dev)?,
            uniform(7, 0.5, 1.5, 19, &dev)?,
            uniform(7, -0.5, 0.5, 20, &dev)?,
        ];
        crate::testing::assert_gradients(
            "layer norm f64",
            |a| layer_norm(&a[0], &a[1], &a[2], EPS),
            &inputs,
            1e-4,
        )
    }

    #[test]
    fn rejects_bad_shapes() -> Result<()> {
        let x = f32_uniform(&[4, 13], -1.0, 1.0, 21)?;
        let w = f32_uniform(&[12], 0.5, 1.5, 22)?;
        let b = f32_uniform(&[13], -0.5, 0.5, 23)?;
        assert!(layer_norm(&x, &w, &b, EPS).is_err());
        assert!(layer_norm(&x, &b, &w, EPS).is_err());
        let empty = Tensor::zeros((0, 13), DType::F32, &Device::Cpu)?;
        assert_eq!(layer_norm(&empty, &b, &b, EPS)?.dims(), &[0, 13]);
        Ok(())
    }
}
