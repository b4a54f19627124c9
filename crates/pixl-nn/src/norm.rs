//! Layer normalisation.
//!
//! [`LayerNorm`] normalises the last dimension (PyTorch `nn.LayerNorm(dim)`, weights `weight`,
//! `bias`). [`LayerNorm2d`] normalises the channel dimension of a `(B, C, H, W)` tensor, as
//! ConvNeXt's "channels_first" LayerNorm does, with the same weight names.
use candle_core::{DType, Module, Result, Tensor, D};
use candle_nn::VarBuilder;

/// PyTorch `nn.LayerNorm(dim, eps)` over the last dimension.
#[derive(Clone, Debug)]
pub struct LayerNorm {
    pub weight: Tensor,
    pub bias: Tensor,
    pub eps: f64,
}

impl LayerNorm {
    pub fn new(dim: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get_with_hints(dim, "weight", candle_nn::Init::Const(1.0))?;
        let bias = vb.get_with_hints(dim, "bias", candle_nn::Init::Const(0.0))?;
        Ok(Self { weight, bias, eps })
    }
}

impl Module for LayerNorm {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        layer_norm(xs, &self.weight, &self.bias, self.eps)
    }
}

/// Layer norm over the last dimension: `(x - mean) / sqrt(var + eps) * w + b`, biased variance,
/// `eps` inside the square root (PyTorch semantics). `w`, `b`: `(D)`, same dtype as `xs`.
///
/// Fast path (no gradient, f32/f16/bf16): candle's fused kernel, which accumulates in f32 and
/// computes the variance as `E[x²] − E[x]²` (fine unless `|mean| ≫ std`, ~1e3×). f64 inputs
/// always take the composed path, which keeps full f64 precision (candle's kernel would round to
/// f32). Differentiable path: on the CPU in f32 one fused op with its own backward
/// ([`crate::norm_grad`]); elsewhere composed candle ops, statistics in f32 (f64 for f64 inputs).
pub fn layer_norm(xs: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    let _t = crate::profile::span("layer norm");
    let fast_dtype = matches!(xs.dtype(), DType::F32 | DType::F16 | DType::BF16);
    if !crate::needs_grad(&[xs, w, b]) && fast_dtype {
        return candle_nn::ops::layer_norm(&xs.contiguous()?, &w.contiguous()?, &b.contiguous()?, eps as f32);
    }
    if [xs, w, b].into_iter().all(crate::fused::cpu_f32) {
        return crate::norm_grad::layer_norm(xs, w, b, eps);
    }
    let dtype = xs.dtype();
    let xs = if dtype == DType::F64 {
        xs.clone()
    } else {
        xs.to_dtype(DType::F32)?
    };
    let mean = xs.mean_keepdim(D::Minus1)?;
    let xc = xs.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
    let xn = xc.broadcast_div(&(var + eps)?.sqrt()?)?;
    xn.to_dtype(dtype)?.broadcast_mul(w)?.broadcast_add(b)
}

/// Layer norm over the channels of a `(B, C, H, W)` tensor, each pixel on its own (ConvNeXt's
/// "channels_first" LayerNorm). Output `(B, C, H, W)` (a permuted, non-contiguous view).
#[derive(Clone, Debug)]
pub struct LayerNorm2d {
    pub inner: LayerNorm,
}

impl LayerNorm2d {
    pub fn new(channels: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            inner: LayerNorm::new(channels, eps, vb)?,
        })
    }
}

impl Module for LayerNorm2d {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let xs = crate::fused::to_channels_last(xs)?;
        crate::fused::to_channels_first(&self.inner.forward(&xs)?)
    }
}
