//! `Linear(in → hidden) – GELU – Linear(hidden → out)`, weights `fc1.*`, `fc2.*` (timm naming).
//! Each linear goes through [`crate::fused::linear`]: with no gradient needed on the CPU, the
//! bias and the GELU are one parallel pass after the matmul.
use crate::fused::{self, Act};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Linear, VarBuilder};

#[derive(Clone, Debug)]
pub struct Mlp {
    pub fc1: Linear,
    pub fc2: Linear,
}

impl Mlp {
    pub fn new(in_dim: usize, hidden: usize, out_dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            fc1: candle_nn::linear(in_dim, hidden, vb.pp("fc1"))?,
            fc2: candle_nn::linear(hidden, out_dim, vb.pp("fc2"))?,
        })
    }
}

impl Module for Mlp {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let hidden = fused::linear(xs, &self.fc1, Act::Gelu)?;
        fused::linear(&hidden, &self.fc2, Act::None)
    }
}
