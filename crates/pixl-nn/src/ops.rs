//! Elementwise and resampling ops with a differentiable path.
use candle_core::{DType, Device, Result, Tensor, D};

/// Softmax over the last dimension.
pub fn softmax_last_dim(xs: &Tensor) -> Result<Tensor> {
    if !crate::needs_grad(&[xs]) && xs.is_contiguous() {
        return candle_nn::ops::softmax_last_dim(xs);
    }
    let max = xs.max_keepdim(D::Minus1)?.detach();
    let e = xs.broadcast_sub(&max)?.exp()?;
    e.broadcast_div(&e.sum_keepdim(D::Minus1)?)
}

/// GELU, exact (erf) form, as PyTorch's default `nn.GELU()`.
pub fn gelu(xs: &Tensor) -> Result<Tensor> {
    xs.gelu_erf()
}

/// Bilinear resize of `(B, C, H, W)` to `(B, C, h, w)`, PyTorch `F.interpolate(mode="bilinear",
/// align_corners=False)` semantics (half-pixel centres, edge clamping, no antialiasing).
///
/// Written as `Wy · X · Wxᵀ` with sparse-in-effect interpolation matrices, so it is
/// differentiable through candle's matmul backward.
pub fn resize_bilinear(xs: &Tensor, h: usize, w: usize) -> Result<Tensor> {
    let (_b, _c, ih, iw) = xs.dims4()?;
    if ih == h && iw == w {
        return Ok(xs.clone());
    }
    let dtype = xs.dtype();
    let wy = interp_matrix(ih, h, xs.device())?.to_dtype(dtype)?; // (h, ih)
    let wx = interp_matrix(iw, w, xs.device())?.to_dtype(dtype)?; // (w, iw)
    let t = xs.broadcast_matmul(&wx.t()?)?; // (B, C, ih, w)
    wy.broadcast_matmul(&t)
}

/// Row `o` holds the weights of the input samples that output `o` interpolates.
pub fn interp_matrix(n_in: usize, n_out: usize, device: &Device) -> Result<Tensor> {
    let mut m = vec![0f32; n_out * n_in];
    let scale = n_in as f64 / n_out as f64;
    for o in 0..n_out {
        let src = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
        let i0 = (src.floor() as usize).min(n_in - 1);
        let i1 = (i0 + 1).min(n_in - 1);
        let f = (src - i0 as f64) as f32;
        m[o * n_in + i0] += 1.0 - f;
        m[o * n_in + i1] += f;
    }
    Tensor::from_vec(m, (n_out, n_in), device)?.to_dtype(DType::F32)
}
