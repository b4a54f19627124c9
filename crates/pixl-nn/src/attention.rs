//! Multi-head scaled-dot-product attention: `softmax(q kᵀ / √D) v` over `(B, H, N, D)` tensors.
use candle_core::{Result, Tensor};

pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    let d = q.dim(candle_core::D::Minus1)?;
    let scale = 1.0 / (d as f64).sqrt();
    let att = (q.matmul(&k.t()?)? * scale)?;
    let att = crate::ops::softmax_last_dim(&att)?;
    att.matmul(v)
}
