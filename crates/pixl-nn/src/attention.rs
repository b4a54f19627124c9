//! Multi-head scaled-dot-product attention: `softmax(q kᵀ / √D) v`.
//!
//! `q`: `(B, H, N, D)`, `k`: `(B, H, M, D)`, `v`: `(B, H, M, Dv)` → `(B, H, N, Dv)`, same dtype.
//! Differentiable; the scale is applied to `q` (`N·D` products rather than `N·M`), and the
//! softmax dispatches through [`crate::ops::softmax_last_dim`] (candle's fused kernel when no
//! gradient is needed). The full `(B, H, N, M)` score matrix is materialised.
use candle_core::{Result, Tensor};

pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    let d = q.dim(candle_core::D::Minus1)?;
    let scale = 1.0 / (d as f64).sqrt();
    let att = (q * scale)?.matmul(&k.t()?)?;
    let att = crate::ops::softmax_last_dim(&att)?;
    att.matmul(v)
}
