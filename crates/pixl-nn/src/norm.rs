//! Layer normalisation.
//!
//! [`LayerNorm`] normalises the last dimension (PyTorch `nn.LayerNorm(dim)`, weights `weight`,
//! `bias`). [`LayerNorm2d`] normalises the channel dimension of a `(B, C, H, W)` tensor, as
//! ConvNeXt's "channels_first" LayerNorm does, with the same weight names.
use candle_core::{DType, Module, Result, Tensor, D};
use candle_nn::VarBuilder;

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

/// Layer norm over the last dimension: `(x - mean) / sqrt(var + eps) * w + b`, biased variance.
pub fn layer_norm(xs: &Tensor, w: &Tensor, b: &Tensor, eps: f64) -> Result<Tensor> {
    if !crate::needs_grad(&[xs, w, b]) && xs.is_contiguous() {
        return candle_nn::ops::layer_norm(xs, w, b, eps as f32);
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
        let xs = xs.permute((0, 2, 3, 1))?.contiguous()?;
        self.inner.forward(&xs)?.permute((0, 3, 1, 2))
    }
}
