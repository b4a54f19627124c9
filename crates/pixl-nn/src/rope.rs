//! 2D rotary position embedding (RoPE) for patch tokens on an `(h, w)` grid.
//!
//! The head dimension `D` is split in two halves: the first half rotates by the token's row
//! `y`, the second by its column `x`. Within a half of size `D/2`, pairs `(i, i + D/4)` rotate
//! by angle `pos · base^(-i / (D/4))` ("rotate-half" convention), `i < D/4`.
use candle_core::{Device, Result, Tensor, D};

#[derive(Clone, Debug)]
pub struct Rope2d {
    /// `(N, D)` cos and sin tables, `N = h·w` tokens in row-major order.
    pub cos: Tensor,
    pub sin: Tensor,
}

impl Rope2d {
    /// Tables for `grid_h × grid_w` tokens with `head_dim` channels per head (a multiple of 4);
    /// `base` sets the frequencies `base^(-i / (head_dim/4))` (e.g. 100 for patch grids).
    pub fn new(head_dim: usize, grid_h: usize, grid_w: usize, base: f64, device: &Device) -> Result<Self> {
        if !head_dim.is_multiple_of(4) {
            candle_core::bail!("2D RoPE needs a head dimension divisible by 4, got {head_dim}");
        }
        let q = head_dim / 4;
        let n = grid_h * grid_w;
        let mut cos = vec![0f32; n * head_dim];
        let mut sin = vec![0f32; n * head_dim];
        for y in 0..grid_h {
            for x in 0..grid_w {
                let t = y * grid_w + x;
                for (half, pos) in [(0, y as f64), (1, x as f64)] {
                    for i in 0..q {
                        let ang = pos * base.powf(-(i as f64) / q as f64);
                        for j in [i, i + q] {
                            cos[t * head_dim + half * 2 * q + j] = ang.cos() as f32;
                            sin[t * head_dim + half * 2 * q + j] = ang.sin() as f32;
                        }
                    }
                }
            }
        }
        Ok(Self {
            cos: Tensor::from_vec(cos, (n, head_dim), device)?,
            sin: Tensor::from_vec(sin, (n, head_dim), device)?,
        })
    }

    /// Rotates `(B, H, N, D)` queries or keys (any leading dims; the last two must be the
    /// table's `(N, D)`). Differentiable (elementwise ops), output same shape and dtype.
    pub fn apply(&self, xs: &Tensor) -> Result<Tensor> {
        let d = xs.dim(D::Minus1)?;
        let n = xs.dim(D::Minus2)?;
        let (tn, td) = self.cos.dims2()?;
        if (n, d) != (tn, td) {
            candle_core::bail!("2D RoPE built for {tn} tokens of dim {td}, applied to {n} tokens of dim {d}");
        }
        let q = d / 4;
        let dtype = xs.dtype();
        let (cos, sin) = (self.cos.to_dtype(dtype)?, self.sin.to_dtype(dtype)?);
        // rotate_half within each of the two halves
        let a1 = xs.narrow(D::Minus1, 0, q)?;
        let a2 = xs.narrow(D::Minus1, q, q)?;
        let b1 = xs.narrow(D::Minus1, 2 * q, q)?;
        let b2 = xs.narrow(D::Minus1, 3 * q, q)?;
        let rot = Tensor::cat(&[&a2.neg()?, &a1, &b2.neg()?, &b1], D::Minus1)?;
        xs.broadcast_mul(&cos)?.add(&rot.broadcast_mul(&sin)?)
    }
}
