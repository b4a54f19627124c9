//! A linear layer with its activation as one differentiable op.
//!
//! [`linear`] computes `y = act(x·Wᵀ + b)` over the last dim of `x` `(…, in)` (any leading
//! dims), with `W` `(out, in)` (PyTorch layout, read as stored) and an optional `b` `(out)`; `act`
//! is any [`Act`]: `None`, `Relu` (derivative 0 at 0, as PyTorch), `Gelu` (exact erf GELU with
//! the vectorised [`crate::fastmath::erf`], as [`crate::fused::linear`]) or `Silu`. Output
//! `(…, out)`, the same values as [`crate::fused::linear`].
//!
//! On the CPU in f32 it is a single candle custom op ([`LinearOp`]) with its own backward, instead
//! of matmul, broadcast bias add and activation as separate autograd nodes:
//! - forward: the output rows are filled with the bias, one parallel GEMM (the `gemm` crate) adds
//!   `x·Wᵀ` in place, the activation runs in place. For `Gelu` and `Silu`, when a gradient will
//!   be needed, the pre-activation `z` is kept in the op until the graph is dropped: one more f32
//!   buffer of the output's size (`rows·out·4` bytes). `None` and `Relu` keep nothing (the ReLU
//!   mask is read from the output);
//! - backward: `dz = dy ⊙ act'(z)` (`GELU'(z) = Φ(z) + z·φ(z)`, `SiLU'(z) = s·(1 + z·(1 − s))`
//!   with `s` the logistic sigmoid), in parallel, then `dx = dz·W` and `dW = dzᵀ·x` as GEMMs
//!   and `db` the column sums of `dz` (per-block partial sums, then added up). Only the inputs
//!   that track gradients get one (so a first layer's `dx` GEMM is skipped). The returned
//!   gradients are constants (no second-order gradients).
//!
//! Elsewhere (other devices, dtypes, mixed dtypes): candle's matmul with `Wᵀ`, broadcast bias
//! add and activation, differentiable.
use std::borrow::Cow;
use std::sync::Mutex;

use candle_core::{CpuStorage, CustomOp2, CustomOp3, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

use crate::fused::{cpu_f32, gemm_parallelism, slice, storage_slice, Act};

/// Elements per parallel task of the elementwise passes.
const CHUNK: usize = 1 << 14;

/// Differentiable `y = act(x·Wᵀ + b)`: `xs` `(…, in)`, `w` `(out, in)`, `b` `(out)`. See the module
/// docs for the paths.
pub fn linear(xs: &Tensor, w: &Tensor, b: Option<&Tensor>, act: Act) -> Result<Tensor> {
    let Some((&k, lead)) = xs.dims().split_last() else {
        candle_core::bail!("linear: a scalar input");
    };
    let (n, wk) = match w.dims() {
        &[n, wk] => (n, wk),
        d => candle_core::bail!("linear: weight of shape {d:?}, expected (out, in)"),
    };
    if wk != k {
        candle_core::bail!("linear: input {:?} does not fit weight {:?}", xs.dims(), w.dims());
    }
    if let Some(b) = b {
        if b.dims() != [n] {
            candle_core::bail!("linear: bias {:?} for {n} outputs", b.dims());
        }
    }
    let fast = cpu_f32(xs) && cpu_f32(w) && b.is_none_or(cpu_f32);
    if !fast {
        return composed(xs, w, b, act);
    }
    let _t = crate::profile::span("linear");
    let op = LinearOp {
        act,
        keep: crate::needs_grad(&[xs, w]) || b.is_some_and(Tensor::track_op),
        pre: Mutex::new(None),
    };
    let y = match b {
        Some(b) => xs.contiguous()?.apply_op3(&w.contiguous()?, &b.contiguous()?, op)?,
        None => xs.contiguous()?.apply_op2(&w.contiguous()?, op)?,
    };
    debug_assert_eq!(y.dims().split_last().map(|(_, l)| l), Some(lead));
    Ok(y)
}

/// The composed candle path: `act(x·Wᵀ + b)` with candle's matmul and activations.
pub fn composed(xs: &Tensor, w: &Tensor, b: Option<&Tensor>, act: Act) -> Result<Tensor> {
    let Some((&k, lead)) = xs.dims().split_last() else {
        candle_core::bail!("linear: a scalar input");
    };
    let rows: usize = lead.iter().product();
    let n = w.dim(0)?;
    let z = xs.reshape((rows, k))?.matmul(&w.t()?)?;
    let z = match b {
        Some(b) => z.broadcast_add(b)?,
        None => z,
    };
    let y = match act {
        Act::None => z,
        Act::Relu => z.relu()?,
        Act::Gelu => z.gelu_erf()?,
        Act::Silu => candle_nn::ops::silu(&z)?,
    };
    let mut dims = lead.to_vec();
    dims.push(n);
    y.reshape(dims)
}

/// The CPU f32 kernel: `(x, W, b) → y` as a [`CustomOp3`], `(x, W) → y` as a [`CustomOp2`];
/// differentiable in every operand.
#[derive(Debug)]
pub struct LinearOp {
    act: Act,
    /// Whether the forward pass keeps `z` (for `Gelu` and `Silu`) for the backward pass.
    keep: bool,
    /// The pre-activation `x·Wᵀ + b`, when kept.
    pre: Mutex<Option<Vec<f32>>>,
}

impl LinearOp {
    fn forward(
        &self,
        x: &[f32],
        xl: &Layout,
        w: &[f32],
        wl: &Layout,
        b: Option<&[f32]>,
    ) -> Result<(CpuStorage, Shape)> {
        let Some((&k, lead)) = xl.shape().dims().split_last() else {
            candle_core::bail!("linear: a scalar input");
        };
        let (n, wk) = wl.shape().dims2()?;
        let rows: usize = lead.iter().product();
        if wk != k || x.len() != rows * k || b.is_some_and(|b| b.len() != n) {
            candle_core::bail!(
                "linear: input {:?}, weight {:?}, bias of {:?}",
                xl.shape(),
                wl.shape(),
                b.map(<[f32]>::len)
            );
        }
        let mut z = vec![0f32; rows * n];
        if let Some(b) = b {
            z.par_chunks_mut(n.max(1))
                .with_min_len(16)
                .for_each(|row| row.copy_from_slice(b));
        }
        if rows > 0 && n > 0 && k > 0 {
            // SAFETY: dst (rows × n, row stride n) is `z`; lhs (rows × k, row stride k) is `x`;
            // rhs = Wᵀ (k × n): element (i, j) is W[j·k + i] (row stride 1, column stride k).
            unsafe {
                gemm::gemm(
                    rows,
                    n,
                    k,
                    z.as_mut_ptr(),
                    1,
                    n as isize,
                    b.is_some(),
                    x.as_ptr(),
                    1,
                    k as isize,
                    w.as_ptr(),
                    k as isize,
                    1,
                    1.0f32,
                    1.0f32,
                    false,
                    false,
                    false,
                    gemm_parallelism(),
                );
            }
        }
        let keep = self.keep && matches!(self.act, Act::Gelu | Act::Silu);
        let y = if keep {
            let mut y = vec![0f32; z.len()];
            y.par_chunks_mut(CHUNK).zip(z.par_chunks(CHUNK)).for_each(|(y, z)| {
                y.copy_from_slice(z);
                act_in_place(y, self.act);
            });
            *self.lock_pre()? = Some(z);
            y
        } else {
            if self.act != Act::None {
                z.par_chunks_mut(CHUNK).for_each(|c| act_in_place(c, self.act));
            }
            z
        };
        let mut dims = lead.to_vec();
        dims.push(n);
        Ok((CpuStorage::F32(y), Shape::from_dims(&dims)))
    }

    /// Gradients for `(x, W, b)`, each only if asked for.
    fn backward(
        &self,
        xs: &Tensor,
        w: &Tensor,
        res: &Tensor,
        grad: &Tensor,
        need: [bool; 3],
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let [need_x, need_w, need_b] = need;
        if !(need_x || need_w || need_b) {
            return Ok((None, None, None));
        }
        let _t = crate::profile::span("linear backward");
        let (n, k) = w.dims2()?;
        let grad = grad.contiguous()?;
        let (gs, gl) = grad.storage_and_layout();
        let dy = storage_slice(&gs, gl, "linear output gradient")?;
        let rows: usize = xs.dims().split_last().map_or(0, |(_, lead)| lead.iter().product());
        if xs.elem_count() != rows * k || dy.len() != rows * n {
            candle_core::bail!(
                "linear backward: gradient {:?} for input {:?} and weight {:?}",
                grad.dims(),
                xs.dims(),
                w.dims()
            );
        }
        let dz: Cow<[f32]> = match self.act {
            Act::None => Cow::Borrowed(dy),
            Act::Relu => {
                let (ys, yl) = res.storage_and_layout();
                let y = storage_slice(&ys, yl, "linear output")?;
                let mut dz = vec![0f32; dy.len()];
                dz.par_chunks_mut(CHUNK)
                    .zip(dy.par_chunks(CHUNK).zip(y.par_chunks(CHUNK)))
                    .for_each(|(o, (g, y))| {
                        for ((o, &g), &y) in o.iter_mut().zip(g).zip(y) {
                            *o = if y > 0.0 { g } else { 0.0 };
                        }
                    });
                Cow::Owned(dz)
            }
            Act::Gelu | Act::Silu => {
                let saved = self.lock_pre()?;
                let Some(z) = saved.as_deref().filter(|z| z.len() == dy.len()) else {
                    candle_core::bail!("linear backward: the pre-activation was not kept");
                };
                let mut dz = vec![0f32; dy.len()];
                let gelu = self.act == Act::Gelu;
                dz.par_chunks_mut(CHUNK)
                    .zip(dy.par_chunks(CHUNK).zip(z.par_chunks(CHUNK)))
                    .for_each(|(o, (g, z))| if gelu { gelu_grad(o, g, z) } else { silu_grad(o, g, z) });
                Cow::Owned(dz)
            }
        };
        let dz: &[f32] = &dz;
        let dev = xs.device();
        let gx = if need_x {
            let (ws, wl) = w.storage_and_layout();
            let wv = storage_slice(&ws, wl, "linear weight")?;
            let mut dx = vec![0f32; rows * k];
            if rows > 0 && n > 0 && k > 0 {
                // SAFETY: dst (rows × k, row stride k) is `dx`; lhs (rows × n, row stride n) is
                // `dz`; rhs (n × k, row stride k) is `W`.
                unsafe {
                    gemm::gemm(
                        rows,
                        k,
                        n,
                        dx.as_mut_ptr(),
                        1,
                        k as isize,
                        false,
                        dz.as_ptr(),
                        1,
                        n as isize,
                        wv.as_ptr(),
                        1,
                        k as isize,
                        0.0f32,
                        1.0f32,
                        false,
                        false,
                        false,
                        gemm_parallelism(),
                    );
                }
            }
            Some(Tensor::from_vec(dx, xs.shape(), dev)?)
        } else {
            None
        };
        let gw = if need_w {
            let (xs_s, xs_l) = xs.storage_and_layout();
            let x = storage_slice(&xs_s, xs_l, "linear input")?;
            let mut dw = vec![0f32; n * k];
            if rows > 0 && n > 0 && k > 0 {
                // SAFETY: dst (n × k, row stride k) is `dW`; lhs = dzᵀ (n × rows): element (i, r)
                // is dz[r·n + i] (row stride 1, column stride n); rhs (rows × k, row stride k)
                // is `x`.
                unsafe {
                    gemm::gemm(
                        n,
                        k,
                        rows,
                        dw.as_mut_ptr(),
                        1,
                        k as isize,
                        false,
                        dz.as_ptr(),
                        n as isize,
                        1,
                        x.as_ptr(),
                        1,
                        k as isize,
                        0.0f32,
                        1.0f32,
                        false,
                        false,
                        false,
                        gemm_parallelism(),
                    );
                }
            }
            Some(Tensor::from_vec(dw, (n, k), dev)?)
        } else {
            None
        };
        let gb = if need_b {
            Some(Tensor::from_vec(column_sums(dz, n), n, dev)?)
        } else {
            None
        };
        Ok((gx, gw, gb))
    }

    fn lock_pre(&self) -> Result<std::sync::MutexGuard<'_, Option<Vec<f32>>>> {
        match self.pre.lock() {
            Ok(g) => Ok(g),
            Err(_) => candle_core::bail!("linear: the saved pre-activation is poisoned"),
        }
    }
}

impl CustomOp3 for LinearOp {
    fn name(&self) -> &'static str {
        "pixl-linear"
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
        let x = slice(s1, l1, "linear input")?;
        let w = slice(s2, l2, "linear weight")?;
        let b = slice(s3, l3, "linear bias")?;
        self.forward(x, l1, w, l2, Some(b))
    }

    fn bwd(
        &self,
        xs: &Tensor,
        w: &Tensor,
        b: &Tensor,
        res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        self.backward(xs, w, res, grad, [xs.track_op(), w.track_op(), b.track_op()])
    }
}

impl CustomOp2 for LinearOp {
    fn name(&self) -> &'static str {
        "pixl-linear"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let x = slice(s1, l1, "linear input")?;
        let w = slice(s2, l2, "linear weight")?;
        self.forward(x, l1, w, l2, None)
    }

    fn bwd(&self, xs: &Tensor, w: &Tensor, res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (gx, gw, _) = self.backward(xs, w, res, grad, [xs.track_op(), w.track_op(), false])?;
        Ok((gx, gw))
    }
}

/// The activation in place, as [`crate::fused::linear`] applies it.
fn act_in_place(v: &mut [f32], act: Act) {
    match act {
        Act::None => {}
        Act::Gelu => crate::fastmath::gelu_in_place(v),
        _ => v.iter_mut().for_each(|e| *e = act.apply(*e)),
    }
}

/// Column sums of a row-major `(rows, n)` block: per-block partial sums in parallel, then added.
fn column_sums(dz: &[f32], n: usize) -> Vec<f32> {
    let mut sums = vec![0f32; n];
    if n == 0 || dz.is_empty() {
        return sums;
    }
    let per = (CHUNK / n).max(1) * n;
    let partials: Vec<Vec<f32>> = dz
        .par_chunks(per)
        .map(|block| {
            let mut acc = vec![0f32; n];
            for row in block.chunks_exact(n) {
                acc.iter_mut().zip(row).for_each(|(a, &v)| *a += v);
            }
            acc
        })
        .collect();
    for p in &partials {
        sums.iter_mut().zip(p).for_each(|(a, &v)| *a += v);
    }
    sums
}

/// `1/√(2π)`.
const INV_SQRT_2PI: f32 = 0.398_942_3;

#[inline(always)]
fn gelu_grad_generic(out: &mut [f32], dy: &[f32], z: &[f32]) {
    for ((o, &g), &z) in out.iter_mut().zip(dy).zip(z) {
        let cdf = 0.5 * (1.0 + crate::fastmath::erf(z * std::f32::consts::FRAC_1_SQRT_2));
        let pdf = crate::fastmath::exp(-0.5 * z * z) * INV_SQRT_2PI;
        *o = g * (cdf + z * pdf);
    }
}

#[inline(always)]
fn silu_grad_generic(out: &mut [f32], dy: &[f32], z: &[f32]) {
    for ((o, &g), &z) in out.iter_mut().zip(dy).zip(z) {
        let s = 1.0 / (1.0 + crate::fastmath::exp(-z));
        *o = g * (s * (1.0 + z * (1.0 - s)));
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn gelu_grad_avx512(out: &mut [f32], dy: &[f32], z: &[f32]) {
    gelu_grad_generic(out, dy, z)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn gelu_grad_avx2(out: &mut [f32], dy: &[f32], z: &[f32]) {
    gelu_grad_generic(out, dy, z)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn silu_grad_avx512(out: &mut [f32], dy: &[f32], z: &[f32]) {
    silu_grad_generic(out, dy, z)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn silu_grad_avx2(out: &mut [f32], dy: &[f32], z: &[f32]) {
    silu_grad_generic(out, dy, z)
}

/// `out = dy·GELU'(z)`, `GELU'(z) = Φ(z) + z·φ(z)`.
fn gelu_grad(out: &mut [f32], dy: &[f32], z: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { gelu_grad_avx512(out, dy, z) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { gelu_grad_avx2(out, dy, z) };
        }
    }
    gelu_grad_generic(out, dy, z)
}

/// `out = dy·SiLU'(z)`, `SiLU'(z) = s·(1 + z·(1 − s))`, `s = 1/(1 + e^(−z))`.
fn silu_grad(out: &mut [f32], dy: &[f32], z: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { silu_grad_avx512(out, dy, z) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { silu_grad_avx2(out, dy, z) };
        }
    }
    silu_grad_generic(out, dy, z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Var};

    use crate::testing::uniform;

    const ACTS: [Act; 4] = [Act::None, Act::Relu, Act::Gelu, Act::Silu];

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

    fn act64(act: Act, z: f64) -> f64 {
        match act {
            Act::None => z,
            Act::Relu => z.max(0.0),
            Act::Gelu => 0.5 * z * (1.0 + candle_core::cpu::erf::erf_f64(z / std::f64::consts::SQRT_2)),
            Act::Silu => z / (1.0 + (-z).exp()),
        }
    }

    /// Naive f64 `act(x·Wᵀ + b)` over rows of `k`; `b` empty for no bias.
    fn naive(x: &[f64], w: &[f64], b: &[f64], k: usize, act: Act) -> Vec<f64> {
        let n = w.len() / k;
        let mut y = Vec::with_capacity(x.len() / k * n);
        for row in x.chunks(k) {
            for j in 0..n {
                let dot: f64 = row.iter().zip(&w[j * k..(j + 1) * k]).map(|(a, b)| a * b).sum();
                y.push(act64(act, dot + b.get(j).copied().unwrap_or(0.0)));
            }
        }
        y
    }

    /// Checks values against the naive f64 linear layer and the gradients of `Σ y·R` for the
    /// tracked inputs (`track`: x, W, b) against central differences of it.
    fn check(x: &Tensor, n: usize, bias: bool, act: Act, track: [bool; 3], seed: u64) -> Result<()> {
        let k = x.dims().last().copied().unwrap_or(0);
        let w = f32_uniform(&[n, k], -0.5, 0.5, seed + 1)?;
        let b = f32_uniform(&[n], -0.5, 0.5, seed + 2)?;
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
        let (bt, bv) = wrap(&b, track[2] && bias)?;
        let y = linear(&xt, &wt, bias.then_some(&bt), act)?;
        let mut want_dims = x.dims().to_vec();
        *want_dims.last_mut().expect("rank ≥ 1") = n;
        assert_eq!(y.dims(), want_dims.as_slice());
        let args = [values(x)?, values(&w)?, if bias { values(&b)? } else { Vec::new() }];
        let want = naive(&args[0], &args[1], &args[2], k, act);
        let got = values(&y)?;
        let err = rel_err(&got, &want);
        assert!(err < 1e-5, "{act:?} values off: {err:e}");
        let r = f32_uniform(y.dims(), -1.0, 1.0, seed + 3)?;
        let grads = (&y * &r)?.sum_all()?.backward()?;
        let r = values(&r)?;
        let loss = |a: &[Vec<f64>; 3]| -> f64 {
            naive(&a[0], &a[1], &a[2], k, act)
                .iter()
                .zip(&r)
                .map(|(y, r)| y * r)
                .sum()
        };
        for (i, var) in [xv, wv, bv].iter().enumerate() {
            let Some(v) = var else {
                continue;
            };
            let g = grads.get(v.as_tensor()).expect("a gradient for a tracked input");
            assert_eq!(g.dims(), v.as_tensor().dims());
            let h = 1e-6;
            let numeric: Vec<f64> = (0..args[i].len())
                .map(|e| {
                    let mut p = args.clone();
                    p[i][e] += h;
                    let mut m = args.clone();
                    m[i][e] -= h;
                    (loss(&p) - loss(&m)) / (2.0 * h)
                })
                .collect();
            let err = rel_err(&values(g)?, &numeric);
            assert!(
                err < 1e-4,
                "{act:?}, bias {bias}: gradient {i} of {:?}: relative error {err:e}",
                x.dims()
            );
        }
        Ok(())
    }

    #[test]
    fn matches_fused_inference_linear() -> Result<()> {
        let shapes: [&[usize]; 4] = [&[13], &[14, 13], &[2, 7, 13], &[2, 3, 5, 40]];
        for (i, shape) in shapes.iter().enumerate() {
            let k = shape[shape.len() - 1];
            let x = f32_uniform(shape, -2.0, 2.0, 10 + i as u64)?;
            let w = f32_uniform(&[9, k], -0.5, 0.5, 20 + i as u64)?;
            let b = f32_uniform(&[9], -0.5, 0.5, 30 + i as u64)?;
            for act in ACTS {
                for bias in [true, false] {
                    let ours = linear(&x, &w, bias.then_some(&b), act)?;
                    let layer = candle_nn::Linear::new(w.clone(), bias.then(|| b.clone()));
                    let theirs = crate::fused::linear(&x, &layer, act)?;
                    assert_eq!(ours.dims(), theirs.dims());
                    let err = rel_err(&values(&ours)?, &values(&theirs)?);
                    assert!(err <= 1e-5, "{shape:?} {act:?} bias {bias}: relative error {err:e}");
                }
            }
        }
        Ok(())
    }

    #[test]
    fn gradients_rank2_every_act() -> Result<()> {
        let x = f32_uniform(&[14, 13], -2.0, 2.0, 1)?;
        for (i, act) in ACTS.into_iter().enumerate() {
            for bias in [true, false] {
                check(&x, 9, bias, act, [true; 3], 100 + 10 * i as u64)?;
            }
        }
        Ok(())
    }

    #[test]
    fn gradients_rank3_every_act() -> Result<()> {
        let x = f32_uniform(&[2, 7, 13], -2.0, 2.0, 2)?;
        for (i, act) in ACTS.into_iter().enumerate() {
            for bias in [true, false] {
                check(&x, 9, bias, act, [true; 3], 200 + 10 * i as u64)?;
            }
        }
        Ok(())
    }

    #[test]
    fn gradients_rank4_and_rank1() -> Result<()> {
        let x = f32_uniform(&[2, 3, 2, 13], -2.0, 2.0, 3)?;
        for (i, act) in ACTS.into_iter().enumerate() {
            check(&x, 9, true, act, [true; 3], 300 + 10 * i as u64)?;
        }
        check(&f32_uniform(&[13], -2.0, 2.0, 4)?, 9, true, Act::Gelu, [true; 3], 400)?;
        check(&f32_uniform(&[13], -2.0, 2.0, 5)?, 9, false, Act::Silu, [true; 3], 410)
    }

    #[test]
    fn gradients_non_contiguous_input() -> Result<()> {
        let x = f32_uniform(&[13, 2, 7], -2.0, 2.0, 6)?.permute((1, 2, 0))?;
        assert!(!x.is_contiguous());
        check(&x, 9, true, Act::Gelu, [true; 3], 600)?;
        check(&x, 9, false, Act::Relu, [true; 3], 610)
    }

    #[test]
    fn gradients_without_input_gradient() -> Result<()> {
        let x = f32_uniform(&[2, 7, 13], -2.0, 2.0, 7)?;
        for (i, act) in ACTS.into_iter().enumerate() {
            check(&x, 9, true, act, [false, true, true], 700 + 10 * i as u64)?;
        }
        check(&x, 9, true, Act::Gelu, [true, false, false], 750)?;
        check(&x, 9, true, Act::Silu, [false, false, true], 760)
    }

    #[test]
    fn no_gradient_for_untracked_input() -> Result<()> {
        let x = f32_uniform(&[14, 13], -2.0, 2.0, 11)?;
        let w = Var::from_tensor(&f32_uniform(&[9, 13], -0.5, 0.5, 12)?)?;
        let b = f32_uniform(&[9], -0.5, 0.5, 13)?;
        let grads = linear(&x, w.as_tensor(), Some(&b), Act::Gelu)?.sum_all()?.backward()?;
        assert!(grads.get(&x).is_none());
        assert!(grads.get(&b).is_none());
        assert!(grads.get(w.as_tensor()).is_some());
        Ok(())
    }

    #[test]
    fn backward_twice_gives_the_same_gradients() -> Result<()> {
        let x = Var::from_tensor(&f32_uniform(&[5, 13], -2.0, 2.0, 14)?)?;
        let w = f32_uniform(&[9, 13], -0.5, 0.5, 15)?;
        let loss = linear(x.as_tensor(), &w, None, Act::Gelu)?.sum_all()?;
        let g1 = values(loss.backward()?.get(x.as_tensor()).expect("gradient"))?;
        let g2 = values(loss.backward()?.get(x.as_tensor()).expect("gradient"))?;
        assert_eq!(g1, g2);
        Ok(())
    }

    #[test]
    fn f64_falls_back_to_the_composed_path() -> Result<()> {
        let dev = Device::Cpu;
        let inputs = [
            uniform((2, 3, 5), -2.0, 2.0, 16, &dev)?,
            uniform((4, 5), -0.5, 0.5, 17, &dev)?,
            uniform(4, -0.5, 0.5, 18, &dev)?,
        ];
        for act in [Act::None, Act::Gelu, Act::Silu] {
            crate::testing::assert_gradients("linear f64", |a| linear(&a[0], &a[1], Some(&a[2]), act), &inputs, 1e-4)?;
        }
        Ok(())
    }

    #[test]
    fn rejects_bad_shapes() -> Result<()> {
        let x = f32_uniform(&[4, 13], -1.0, 1.0, 19)?;
        let w = f32_uniform(&[9, 12], -0.5, 0.5, 20)?;
        let b = f32_uniform(&[8], -0.5, 0.5, 21)?;
        assert!(linear(&x, &w, None, Act::None).is_err());
        let w = f32_uniform(&[9, 13], -0.5, 0.5, 22)?;
        assert!(linear(&x, &w, Some(&b), Act::None).is_err());
        assert!(linear(&x, &w.flatten_all()?, None, Act::None).is_err());
        let empty = Tensor::zeros((0, 13), DType::F32, &Device::Cpu)?;
        assert_eq!(linear(&empty, &w, None, Act::Gelu)?.dims(), &[0, 9]);
        Ok(())
    }
}
