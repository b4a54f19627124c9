//! Per-location fusion `fuse` (paper §3.2 "Asymmetric Feature Encoders"): at every grid
//! position the source token and the conditioning token are concatenated channel-wise and
//! projected to `d` by a small MLP.
//!
//! Input two `(B, N, d)` token grids in the same order; output `(B, N, d)`.
//! The paper says "a small MLP"; we use `Linear(2d → d) – GELU – Linear(d → d)` (`fuse.fc1`,
//! `fuse.fc2`).
use crate::config::Config;
use candle_core::{Module, Result, Tensor, D};
use candle_nn::VarBuilder;
use pixl_nn::Mlp;

#[derive(Clone, Debug)]
pub struct Fusion {
    mlp: Mlp,
}

impl Fusion {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            mlp: Mlp::new(2 * cfg.dim, cfg.dim, cfg.dim, vb)?,
        })
    }

    /// The MLP in 8 bits where the CPU allows; returns how many layers.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        self.mlp.quantize_int8()
    }

    pub fn int8_bytes(&self) -> usize {
        self.mlp.int8_bytes()
    }

    pub fn forward(&self, src_tokens: &Tensor, cond_tokens: &Tensor) -> Result<Tensor> {
        if src_tokens.dims() != cond_tokens.dims() {
            candle_core::bail!(
                "fusion: source tokens {:?} and conditioning tokens {:?} differ",
                src_tokens.shape(),
                cond_tokens.shape()
            );
        }
        self.mlp.forward(&Tensor::cat(&[src_tokens, cond_tokens], D::Minus1)?)
    }
}
