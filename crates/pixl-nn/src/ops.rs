//! Elementwise and resampling ops with a differentiable path.
//!
//! - [`softmax_last_dim`]: fast path candle's fused kernel (no backward); differentiable path
//!   `exp(x − max) / Σ exp(x − max)` from candle primitives (the max is detached: softmax is
//!   shift-invariant, so this does not change the gradient).
//! - [`gelu`]: exact erf form, differentiable everywhere.
//! - [`relu`]: with a one-pass backward on the CPU.
//! - [`resize_bilinear`]: PyTorch `F.interpolate(mode="bilinear", align_corners=False)`.
use candle_core::{DType, Device, Result, Tensor, D};
use rayon::prelude::*;

/// Softmax over the last dimension.
pub fn softmax_last_dim(xs: &Tensor) -> Result<Tensor> {
    if !crate::needs_grad(&[xs]) {
        return candle_nn::ops::softmax_last_dim(&xs.contiguous()?);
    }
    let max = xs.max_keepdim(D::Minus1)?.detach();
    let e = xs.broadcast_sub(&max)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
}

/// `max(x, 0)`. On the CPU in f32 with a gradient: one op whose backward is one pass,
/// `grad ⊙ [x ≥ 0]` (candle's convention at 0), instead of candle's compare, cast and multiply;
/// otherwise candle's `relu`.
pub fn relu(xs: &Tensor) -> Result<Tensor> {
    if crate::fused::cpu_f32(xs) && crate::needs_grad(&[xs]) {
        return xs.contiguous()?.apply_op1(Relu);
    }
    xs.relu()
}

/// [`relu`]'s CPU op; its backward is [`ReluGrad`] on `(grad, x)`.
struct Relu;

impl candle_core::CustomOp1 for Relu {
    fn name(&self) -> &'static str {
        "relu"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let x = crate::fused::slice(s, l, self.name())?;
        let mut out = vec![0f32; x.len()];
        out.par_chunks_mut(ELEMENTWISE_CHUNK)
            .zip(x.par_chunks(ELEMENTWISE_CHUNK))
            .for_each(|(o, x)| o.iter_mut().zip(x).for_each(|(o, &x)| *o = x.max(0.0)));
        Ok((candle_core::CpuStorage::F32(out), l.shape().clone()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        Ok(Some(grad.contiguous()?.apply_op2_no_bwd(arg, &ReluGrad)?))
    }
}

/// `grad ⊙ [x ≥ 0]` for `(grad, x)`.
struct ReluGrad;

impl candle_core::CustomOp2 for ReluGrad {
    fn name(&self) -> &'static str {
        "relu-grad"
    }

    fn cpu_fwd(
        &self,
        gs: &candle_core::CpuStorage,
        gl: &candle_core::Layout,
        xs: &candle_core::CpuStorage,
        xl: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let (g, x) = (
            crate::fused::slice(gs, gl, self.name())?,
            crate::fused::slice(xs, xl, self.name())?,
        );
        let mut out = vec![0f32; g.len()];
        out.par_chunks_mut(ELEMENTWISE_CHUNK)
            .zip(g.par_chunks(ELEMENTWISE_CHUNK).zip(x.par_chunks(ELEMENTWISE_CHUNK)))
            .for_each(|(o, (g, x))| {
                for ((o, &g), &x) in o.iter_mut().zip(g).zip(x) {
                    *o = if x >= 0.0 { g } else { 0.0 };
                }
            });
        Ok((candle_core::CpuStorage::F32(out), gl.shape().clone()))
    }
}

/// Values per parallel task of the elementwise ops here.
const ELEMENTWISE_CHUNK: usize = 1 << 15;

/// GELU, exact (erf) form, as PyTorch's default `nn.GELU()`.
pub fn gelu(xs: &Tensor) -> Result<Tensor> {
    xs.gelu_erf()
}

/// Bilinear resize of `(B, C, H, W)` to `(B, C, h, w)`, PyTorch `F.interpolate(mode="bilinear",
/// align_corners=False)` semantics: half-pixel centres, source coordinate
/// `(o + 0.5)·(n_in / n_out) − 0.5` clamped below at 0, upper neighbour clamped to the last pixel,
/// no antialiasing when downsampling.
///
/// On the CPU in f32: one direct parallel pass over output rows with PyTorch's f32 index and
/// weight arithmetic; when a gradient is needed, the same pass as a custom op whose backward is
/// its adjoint (each output gradient spread back onto the two × two input samples it read, with
/// the same weights). Elsewhere: candle's `upsample_bilinear2d(h, w, align_corners = false)`
/// without a gradient (candle's CPU kernel is single-threaded), and with one `Wy · X · Wxᵀ` with
/// the interpolation matrices of [`interp_matrix`], differentiable through candle's matmul
/// backward (cost `O(C·H·W·(h + w))`). All are checked against the matrix path in the tests.
pub fn resize_bilinear(xs: &Tensor, h: usize, w: usize) -> Result<Tensor> {
    let (_b, _c, ih, iw) = xs.dims4()?;
    if ih == h && iw == w {
        return Ok(xs.clone());
    }
    if ih == 0 || iw == 0 || h == 0 || w == 0 {
        candle_core::bail!("bilinear resize from {ih}x{iw} to {h}x{w}: sizes must be positive");
    }
    let _t = crate::profile::span("bilinear resize");
    if crate::fused::cpu_f32(xs) {
        if !crate::needs_grad(&[xs]) {
            return resize_bilinear_cpu(xs, h, w);
        }
        return xs.contiguous()?.apply_op1(Resize { h, w });
    }
    if !crate::needs_grad(&[xs]) {
        return xs.upsample_bilinear2d(h, w, false);
    }
    let dtype = xs.dtype();
    let matrix = |n_in, n_out| Tensor::from_vec(interp_weights(n_in, n_out), (n_out, n_in), xs.device());
    let wy = matrix(ih, h)?.to_dtype(dtype)?; // (h, ih)
    let wx = matrix(iw, w)?.to_dtype(dtype)?; // (w, iw)
    let t = xs.broadcast_matmul(&wx.t()?)?; // (B, C, ih, w)
    wy.broadcast_matmul(&t)
}

/// `(n_out, n_in)` f32 matrix whose row `o` holds the weights of the input samples that output
/// `o` interpolates (two non-zeros at most, summing to 1). Errors if a size is 0.
pub fn interp_matrix(n_in: usize, n_out: usize, device: &Device) -> Result<Tensor> {
    if n_in == 0 || n_out == 0 {
        candle_core::bail!("interpolation matrix from {n_in} to {n_out} samples: sizes must be positive");
    }
    Tensor::from_vec(interp_weights(n_in, n_out), (n_out, n_in), device)?.to_dtype(DType::F32)
}

/// Row-major `(n_out, n_in)` weights in f64; `n_in, n_out > 0`.
fn interp_weights(n_in: usize, n_out: usize) -> Vec<f64> {
    let mut m = vec![0f64; n_out * n_in];
    let scale = n_in as f64 / n_out as f64;
    for o in 0..n_out {
        let src = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
        let i0 = (src.floor() as usize).min(n_in - 1);
        let i1 = (i0 + 1).min(n_in - 1);
        let f = (src - i0 as f64).clamp(0.0, 1.0);
        m[o * n_in + i0] += 1.0 - f;
        m[o * n_in + i1] += f;
    }
    m
}

/// One output sample's two input samples and their weights, as PyTorch's CPU kernel computes
/// them in f32: `src = max(scale·(o + 0.5) − 0.5, 0)`, `scale = n_in / n_out`.
fn taps(n_in: usize, n_out: usize) -> Vec<(usize, usize, f32, f32)> {
    let scale = n_in as f32 / n_out as f32;
    (0..n_out)
        .map(|o| {
            let src = (scale * (o as f32 + 0.5) - 0.5).max(0.0);
            let i0 = (src as usize).min(n_in - 1);
            let i1 = if i0 + 1 < n_in { i0 + 1 } else { i0 };
            let l1 = src - i0 as f32;
            (i0, i1, 1.0 - l1, l1)
        })
        .collect()
}

/// [`resize_bilinear`] for a CPU f32 tensor with positive sizes, parallel over planes: each
/// input row a plane's output reads is resized horizontally once, `hx = wx0·r[x0] + wx1·r[x1]`,
/// then each output row blends two of those, `wy0·hx(y0) + wy1·hx(y1)` (PyTorch's arithmetic,
/// in its order; the blend runs over contiguous rows, so it vectorises).
fn resize_bilinear_cpu(xs: &Tensor, h: usize, w: usize) -> Result<Tensor> {
    let (b, c, ih, iw) = xs.dims4()?;
    let xs = xs.contiguous()?;
    let out = {
        let (storage, layout) = xs.storage_and_layout();
        let src = crate::fused::storage_slice(&storage, layout, "bilinear resize")?;
        resize_planes(src, b * c, (ih, iw), (h, w))
    };
    Tensor::from_vec(out, (b, c, h, w), xs.device())
}

/// The resize of `planes` contiguous `ih × iw` planes of `src` to `h × w` (see
/// [`resize_bilinear_cpu`]).
fn resize_planes(src: &[f32], planes: usize, (ih, iw): (usize, usize), (h, w): (usize, usize)) -> Vec<f32> {
    let (ty, tx) = (taps(ih, h), taps(iw, w));
    let mut out = vec![0f32; planes * h * w];
    {
        // Input rows the output reads (every row when upsampling; some when shrinking).
        let mut used = vec![false; ih];
        for &(y0, y1, _, _) in &ty {
            (used[y0], used[y1]) = (true, true);
        }
        // Planes split into bands of output rows when there are fewer planes than threads.
        let bands = rayon::current_num_threads().div_ceil(planes).clamp(1, h);
        let band = h.div_ceil(bands);
        out.par_chunks_mut(h * w)
            .enumerate()
            .flat_map(|(plane, out_plane)| {
                out_plane
                    .par_chunks_mut(band * w)
                    .enumerate()
                    .map(move |(t, chunk)| (plane, t * band, chunk))
            })
            .for_each(|(plane, y_start, chunk)| {
                let rows = chunk.len() / w;
                let input = &src[plane * ih * iw..(plane + 1) * ih * iw];
                let (first, last) = (ty[y_start].0, ty[y_start + rows - 1].1);
                let mut hx = vec![0f32; (last + 1 - first) * w];
                for (y, row) in hx.chunks_mut(w).enumerate() {
                    let y = first + y;
                    if !used[y] {
                        continue;
                    }
                    let r = &input[y * iw..(y + 1) * iw];
                    for (d, &(x0, x1, wx0, wx1)) in row.iter_mut().zip(&tx) {
                        *d = wx0 * r[x0] + wx1 * r[x1];
                    }
                }
                for (i, row) in chunk.chunks_mut(w).enumerate() {
                    let (y0, y1, wy0, wy1) = ty[y_start + i];
                    let (a, bb) = (&hx[(y0 - first) * w..][..w], &hx[(y1 - first) * w..][..w]);
                    for ((d, &p), &q) in row.iter_mut().zip(a).zip(bb) {
                        *d = wy0 * p + wy1 * q;
                    }
                }
            });
    }
    out
}

/// The adjoint of [`resize_planes`]: `grad` holds `planes` planes of `h × w` output gradients;
/// each is spread back onto the input samples its output read, with the same weights, giving
/// `planes` planes of `ih × iw`. Vertical adjoint into a `ih × w` buffer first, then horizontal.
fn resize_planes_adjoint(grad: &[f32], planes: usize, (ih, iw): (usize, usize), (h, w): (usize, usize)) -> Vec<f32> {
    let (ty, tx) = (taps(ih, h), taps(iw, w));
    let mut out = vec![0f32; planes * ih * iw];
    out.par_chunks_mut(ih * iw).enumerate().for_each(|(plane, dst)| {
        let g = &grad[plane * h * w..(plane + 1) * h * w];
        let mut hx = vec![0f32; ih * w];
        for (row, &(y0, y1, wy0, wy1)) in g.chunks(w).zip(&ty) {
            for (d, &v) in hx[y0 * w..(y0 + 1) * w].iter_mut().zip(row) {
                *d += wy0 * v;
            }
            for (d, &v) in hx[y1 * w..(y1 + 1) * w].iter_mut().zip(row) {
                *d += wy1 * v;
            }
        }
        for (src_row, dst_row) in hx.chunks(w).zip(dst.chunks_mut(iw)) {
            for (&v, &(x0, x1, wx0, wx1)) in src_row.iter().zip(&tx) {
                dst_row[x0] += wx0 * v;
                dst_row[x1] += wx1 * v;
            }
        }
    });
    out
}

/// [`resize_bilinear`] on the CPU in f32 with a gradient: forward [`resize_planes`], backward
/// [`ResizeAdjoint`].
struct Resize {
    h: usize,
    w: usize,
}

impl candle_core::CustomOp1 for Resize {
    fn name(&self) -> &'static str {
        "bilinear-resize"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let src = crate::fused::slice(s, l, self.name())?;
        let (b, c, ih, iw) = l.shape().dims4()?;
        let out = resize_planes(src, b * c, (ih, iw), (self.h, self.w));
        Ok((candle_core::CpuStorage::F32(out), (b, c, self.h, self.w).into()))
    }

    fn bwd(&self, arg: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<Option<Tensor>> {
        let (_b, _c, ih, iw) = arg.dims4()?;
        let op = ResizeAdjoint { ih, iw };
        Ok(Some(grad.contiguous()?.apply_op1_no_bwd(&op)?))
    }
}

/// The backward of [`Resize`]: output gradients `(B, C, h, w)` → input gradients `(B, C, ih, iw)`.
struct ResizeAdjoint {
    ih: usize,
    iw: usize,
}

impl candle_core::CustomOp1 for ResizeAdjoint {
    fn name(&self) -> &'static str {
        "bilinear-resize-adjoint"
    }

    fn cpu_fwd(
        &self,
        s: &candle_core::CpuStorage,
        l: &candle_core::Layout,
    ) -> Result<(candle_core::CpuStorage, candle_core::Shape)> {
        let g = crate::fused::slice(s, l, self.name())?;
        let (b, c, h, w) = l.shape().dims4()?;
        let out = resize_planes_adjoint(g, b * c, (self.ih, self.iw), (h, w));
        Ok((candle_core::CpuStorage::F32(out), (b, c, self.ih, self.iw).into()))
    }
}
