//! `Linear(in → hidden) – GELU – Linear(hidden → out)`, weights `fc1.*`, `fc2.*` (timm naming).
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
        self.fc2.forward(&crate::ops::gelu(&self.fc1.forward(xs)?)?)
    }
}
