//! Depthwise `k×k` convolution, stride 1, "same" padding `k/2`: weight `(C, 1, k, k)`, bias `(C)`
//! (PyTorch `nn.Conv2d(C, C, k, padding=k//2, groups=C)` layout and names), as in ConvNeXt blocks
//! (paper §3.2, image encoder).
//!
//! Input `(B, C, H, W)`, output `(B, C, H, W)`; `out[b,c,i,j] = bias[c] + Σ_{u,v} w[c,0,u,v] ·
//! x[b,c,i+u-k/2,j+v-k/2]` with zeros outside the image (cross-correlation, as PyTorch).
//!
//! candle's grouped `conv2d` splits the input into `C` single-channel convolutions, one kernel
//! launch each, which is about 40× slower than a direct loop on CPU. On CPU, for an odd `k` and
//! f32/f64 data, [`depthwise_conv2d`] runs its own kernel ([`DwConvOp`]): planes `(b, c)` in
//! parallel (rayon); within a plane (zero-padded copy), blocks of 16 output columns accumulate
//! all `k²` taps in registers and are stored once (`k` = 3, 5, 7; other odd `k` and rows narrower
//! than 16 use unit-stride `axpy`s per tap). Its backward pass uses the same
//! kernel with the flipped weight for the input gradient, a second kernel ([`DwConvWeightGradOp`],
//! f64 accumulation) for the weight gradient, and a sum for the bias gradient. f16/bf16 go through
//! f32. Other devices (CUDA, Metal) and even kernels fall back to candle's grouped convolution.
use candle_core::{CpuStorage, CustomOp2, CustomOp3, DType, Layout, Module, Result, Shape, Tensor, WithDType};
use candle_nn::VarBuilder;
use rayon::prelude::*;

#[derive(Clone, Debug)]
pub struct DepthwiseConv2d {
    pub weight: Tensor,
    pub bias: Tensor,
    pub kernel: usize,
}

impl DepthwiseConv2d {
    pub fn new(channels: usize, kernel: usize, vb: VarBuilder) -> Result<Self> {
        let bound = 1.0 / ((kernel * kernel) as f64).sqrt();
        let init = candle_nn::Init::Uniform { lo: -bound, up: bound };
        let weight = vb.get_with_hints((channels, 1, kernel, kernel), "weight", init)?;
        let bias = vb.get_with_hints(channels, "bias", init)?;
        Ok(Self { weight, bias, kernel })
    }
}

impl Module for DepthwiseConv2d {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let _t = crate::profile::span("depthwise conv");
        depthwise_conv2d(xs, &self.weight, &self.bias)
    }
}

/// Depthwise convolution of `xs` `(B, C, H, W)` with `weight` `(C, 1, k, k)` and `bias` `(C)`,
/// stride 1, padding `k/2`. Differentiable in all three arguments. Dispatches to the CPU kernel
/// when it can (see the module docs), otherwise to [`grouped_conv2d`].
pub fn depthwise_conv2d(xs: &Tensor, weight: &Tensor, bias: &Tensor) -> Result<Tensor> {
    let (_b, c, _h, _w) = xs.dims4()?;
    let (wc, one, kh, kw) = weight.dims4()?;
    if wc != c || one != 1 || kh != kw {
        candle_core::bail!(
            "depthwise conv: weight {:?} does not match input {:?} (expected ({c}, 1, k, k))",
            weight.shape(),
            xs.shape()
        );
    }
    if bias.dims1()? != c {
        candle_core::bail!("depthwise conv: bias {:?} does not match {c} channels", bias.shape());
    }
    if weight.dtype() != xs.dtype() || bias.dtype() != xs.dtype() {
        candle_core::bail!(
            "depthwise conv: dtypes differ (input {:?}, weight {:?}, bias {:?})",
            xs.dtype(),
            weight.dtype(),
            bias.dtype()
        );
    }
    if !xs.device().is_cpu() || kh % 2 == 0 {
        return grouped_conv2d(xs, weight, bias);
    }
    let op = DwConvOp {
        kernel: kh,
        flip: false,
    };
    match xs.dtype() {
        DType::F32 | DType::F64 => xs
            .contiguous()?
            .apply_op3(&weight.contiguous()?, &bias.contiguous()?, op),
        DType::F16 | DType::BF16 => {
            let f = |t: &Tensor| t.to_dtype(DType::F32)?.contiguous();
            f(xs)?.apply_op3(&f(weight)?, &f(bias)?, op)?.to_dtype(xs.dtype())
        }
        dt => candle_core::bail!("depthwise conv: unsupported dtype {dt:?}"),
    }
}

/// candle's grouped convolution (`groups = C`) plus bias: the reference and non-CPU fallback.
pub fn grouped_conv2d(xs: &Tensor, weight: &Tensor, bias: &Tensor) -> Result<Tensor> {
    let c = weight.dim(0)?;
    let k = weight.dim(2)?;
    let ys = xs.conv2d(weight, k / 2, 1, 1, c)?;
    ys.broadcast_add(&bias.reshape((1, c, 1, 1))?)
}

/// The CPU forward kernel, `(x, weight, bias) → y`. With `flip`, the kernel is rotated by 180°
/// (the input-gradient pass); that variant has no backward of its own.
#[derive(Clone, Copy, Debug)]
pub struct DwConvOp {
    pub kernel: usize,
    pub flip: bool,
}

/// The CPU weight-gradient kernel, `(x, grad_y) → grad_weight (C, 1, k, k)`.
#[derive(Clone, Copy, Debug)]
pub struct DwConvWeightGradOp {
    pub kernel: usize,
}

fn contiguous<'a, T: WithDType>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [T]> {
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&s.as_slice::<T>()?[a..b]),
        None => candle_core::bail!("depthwise conv: {what} must be contiguous"),
    }
}

impl CustomOp3 for DwConvOp {
    fn name(&self) -> &'static str {
        "pixl-depthwise-conv2d"
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
        let (b, c, h, w) = l1.shape().dims4()?;
        let k = self.kernel;
        if l2.shape().dims() != [c, 1, k, k] || l3.shape().dims() != [c] {
            candle_core::bail!("depthwise conv: bad weight {:?} / bias {:?}", l2.shape(), l3.shape());
        }
        let dims = Geometry { b, c, h, w, k };
        let out = match (s1, s2, s3) {
            (CpuStorage::F32(_), CpuStorage::F32(_), CpuStorage::F32(_)) => CpuStorage::F32(conv_forward::<f32>(
                contiguous(s1, l1, "input")?,
                contiguous(s2, l2, "weight")?,
                contiguous(s3, l3, "bias")?,
                dims,
                self.flip,
            )),
            (CpuStorage::F64(_), CpuStorage::F64(_), CpuStorage::F64(_)) => CpuStorage::F64(conv_forward::<f64>(
                contiguous(s1, l1, "input")?,
                contiguous(s2, l2, "weight")?,
                contiguous(s3, l3, "bias")?,
                dims,
                self.flip,
            )),
            _ => candle_core::bail!("depthwise conv kernel: needs f32 or f64 operands of one dtype"),
        };
        Ok((out, l1.shape().clone()))
    }

    fn bwd(
        &self,
        xs: &Tensor,
        weight: &Tensor,
        bias: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        if self.flip {
            candle_core::bail!("the flipped depthwise conv (an input-gradient pass) has no backward");
        }
        let grad = grad.contiguous()?;
        let zero = bias.zeros_like()?;
        let k = self.kernel;
        let grad_x = grad.apply_op3_no_bwd(weight, &zero, &DwConvOp { kernel: k, flip: true })?;
        let grad_w = xs.apply_op2_no_bwd(&grad, &DwConvWeightGradOp { kernel: k })?;
        // Reducing the contiguous last dim first: candle's strided `sum((0, 2, 3))` is ~20× slower.
        let (b, c, h, w) = grad.dims4()?;
        let grad_b = grad.reshape((b, c, h * w))?.sum(2)?.sum(0)?;
        Ok((Some(grad_x), Some(grad_w), Some(grad_b)))
    }
}

impl CustomOp2 for DwConvWeightGradOp {
    fn name(&self) -> &'static str {
        "pixl-depthwise-conv2d-weight-grad"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, c, h, w) = l1.shape().dims4()?;
        if l2.shape() != l1.shape() {
            candle_core::bail!(
                "depthwise conv weight grad: input {:?} vs grad {:?}",
                l1.shape(),
                l2.shape()
            );
        }
        let k = self.kernel;
        let dims = Geometry { b, c, h, w, k };
        let out = match (s1, s2) {
            (CpuStorage::F32(_), CpuStorage::F32(_)) => CpuStorage::F32(weight_grad::<f32>(
                contiguous(s1, l1, "input")?,
                contiguous(s2, l2, "grad")?,
                dims,
            )),
            (CpuStorage::F64(_), CpuStorage::F64(_)) => CpuStorage::F64(weight_grad::<f64>(
                contiguous(s1, l1, "input")?,
                contiguous(s2, l2, "grad")?,
                dims,
            )),
            _ => candle_core::bail!("depthwise conv weight grad: needs f32 or f64 operands of one dtype"),
        };
        Ok((out, Shape::from_dims(&[c, 1, k, k])))
    }
}

#[derive(Clone, Copy, Debug)]
struct Geometry {
    b: usize,
    c: usize,
    h: usize,
    w: usize,
    k: usize,
}

/// For kernel column `v` (padding `p`) on rows of width `w`: the first output column, the first
/// input column, and how many columns overlap.
#[inline]
fn col_span(v: usize, p: usize, w: usize) -> (usize, usize, usize) {
    let len = w.saturating_sub(v.abs_diff(p));
    if v >= p {
        (0, v - p, len)
    } else {
        (p - v, 0, len)
    }
}

/// Input row for output row `i` and kernel row `u`, if inside the image.
#[inline]
fn src_row(i: usize, u: usize, p: usize, h: usize) -> Option<usize> {
    (i + u).checked_sub(p).filter(|&r| r < h)
}

fn conv_forward<T: WithDType>(x: &[T], wt: &[T], bias: &[T], g: Geometry, flip: bool) -> Vec<T> {
    let plane = g.h * g.w;
    let kk = g.k * g.k;
    let mut out = vec![T::zero(); g.b * g.c * plane];
    if plane == 0 {
        return out;
    }
    let planes = out.par_chunks_mut(plane).zip(x.par_chunks(plane)).enumerate();
    planes.for_each_init(Vec::new, |padded, (bc, (y, xp))| {
        let ch = bc % g.c;
        let mut k2 = wt[ch * kk..(ch + 1) * kk].to_vec();
        if flip {
            k2.reverse();
        }
        match g.k {
            3 if g.w >= BLOCK => conv_plane_fixed::<T, 3>(xp, &k2, bias[ch], y, g, padded),
            5 if g.w >= BLOCK => conv_plane_fixed::<T, 5>(xp, &k2, bias[ch], y, g, padded),
            7 if g.w >= BLOCK => conv_plane_fixed::<T, 7>(xp, &k2, bias[ch], y, g, padded),
            _ => conv_plane(xp, &k2, bias[ch], y, g),
        }
    });
    out
}

/// Output columns computed together, in registers, by [`conv_plane_fixed`].
const BLOCK: usize = 16;

/// The fast plane kernel for a compile-time kernel size `K` and rows of at least [`BLOCK`]
/// columns: the plane is copied into a zero-padded buffer, then each block of `BLOCK` outputs
/// accumulates all `K²` taps in registers and is stored once. The last block of a row overlaps
/// the previous one when `w` is not a multiple of `BLOCK` (it recomputes, never accumulates).
fn conv_plane_fixed<T: WithDType, const K: usize>(
    x: &[T],
    wk: &[T],
    bias: T,
    y: &mut [T],
    g: Geometry,
    padded: &mut Vec<T>,
) {
    let (h, w, p) = (g.h, g.w, K / 2);
    let pw = w + 2 * p;
    padded.clear();
    padded.resize((h + 2 * p) * pw, T::zero());
    for (r, xrow) in x.chunks_exact(w).enumerate() {
        padded[(r + p) * pw + p..(r + p) * pw + p + w].copy_from_slice(xrow);
    }
    let starts = (0..w / BLOCK)
        .map(|b| b * BLOCK)
        .chain((w % BLOCK != 0).then_some(w - BLOCK));
    let starts: Vec<usize> = starts.collect();
    for (i, yrow) in y.chunks_exact_mut(w).enumerate() {
        for &j0 in &starts {
            let mut acc = [bias; BLOCK];
            for u in 0..K {
                let row = &padded[(i + u) * pw + j0..(i + u) * pw + j0 + BLOCK + K - 1];
                for (v, &wv) in wk[u * K..(u + 1) * K].iter().enumerate() {
                    for (a, xv) in acc.iter_mut().zip(&row[v..v + BLOCK]) {
                        *a += wv * *xv;
                    }
                }
            }
            yrow[j0..j0 + BLOCK].copy_from_slice(&acc);
        }
    }
}

/// The general plane kernel (any odd `k`, any width): per output row, `k²` unit-stride `axpy`s.
fn conv_plane<T: WithDType>(x: &[T], wk: &[T], bias: T, y: &mut [T], g: Geometry) {
    let (h, w, k, p) = (g.h, g.w, g.k, g.k / 2);
    for (i, yrow) in y.chunks_exact_mut(w).enumerate() {
        yrow.fill(bias);
        for u in 0..k {
            let Some(r) = src_row(i, u, p, h) else { continue };
            let xrow = &x[r * w..(r + 1) * w];
            for v in 0..k {
                let (j0, s0, len) = col_span(v, p, w);
                let wv = wk[u * k + v];
                for (o, xv) in yrow[j0..j0 + len].iter_mut().zip(&xrow[s0..s0 + len]) {
                    *o += wv * *xv;
                }
            }
        }
    }
}

fn weight_grad<T: WithDType>(x: &[T], gy: &[T], g: Geometry) -> Vec<T> {
    let plane = g.h * g.w;
    let kk = g.k * g.k;
    let mut out = vec![T::zero(); g.c * kk];
    out.par_chunks_mut(kk).enumerate().for_each(|(ch, gw)| {
        let mut acc = vec![0f64; kk];
        for bi in 0..g.b {
            let off = (bi * g.c + ch) * plane;
            weight_grad_plane(&x[off..off + plane], &gy[off..off + plane], g, &mut acc);
        }
        for (o, a) in gw.iter_mut().zip(acc) {
            *o = T::from_f64(a);
        }
    });
    out
}

fn weight_grad_plane<T: WithDType>(x: &[T], gy: &[T], g: Geometry, acc: &mut [f64]) {
    let (h, w, k, p) = (g.h, g.w, g.k, g.k / 2);
    if w == 0 {
        return;
    }
    for (i, grow) in gy.chunks_exact(w).enumerate() {
        for u in 0..k {
            let Some(r) = src_row(i, u, p, h) else { continue };
            let xrow = &x[r * w..(r + 1) * w];
            for v in 0..k {
                let (j0, s0, len) = col_span(v, p, w);
                acc[u * k + v] += dot(&grow[j0..j0 + len], &xrow[s0..s0 + len]).to_f64();
            }
        }
    }
}

/// Dot product with 8 independent accumulators, so it vectorises.
#[inline]
fn dot<T: WithDType>(a: &[T], b: &[T]) -> T {
    let mut acc = [T::zero(); 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: T = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .fold(T::zero(), |s, (x, y)| s + *x * *y);
    for (x, y) in ca.zip(cb) {
        for ((a, xv), yv) in acc.iter_mut().zip(x).zip(y) {
            *a += *xv * *yv;
        }
    }
    acc.iter().fold(tail, |s, a| s + *a)
}
