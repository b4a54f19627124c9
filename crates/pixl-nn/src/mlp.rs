//! `Linear(in → hidden) – GELU – Linear(hidden → out)`, weights `fc1.*`, `fc2.*` (timm naming).
//! Each linear is a [`crate::Linear`]: with no gradient needed on the CPU, the bias and the GELU
//! are one parallel pass after the matmul, and the matmuls can run in 8 bits
//! ([`Mlp::quantize_int8`]).
use crate::fused::Act;
use crate::Linear;
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

#[derive(Clone, Debug)]
pub struct Mlp {
    pub fc1: Linear,
    pub fc2: Linear,
}

impl Mlp {
    pub fn new(in_dim: usize, hidden: usize, out_dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            fc1: Linear::load(in_dim, hidden, vb.pp("fc1"))?,
            fc2: Linear::load(hidden, out_dim, vb.pp("fc2"))?,
        })
    }

    /// [`Linear::quantize_int8`] on both layers; returns how many were quantized.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        Ok(usize::from(self.fc1.quantize_int8()?) + usize::from(self.fc2.quantize_int8()?))
    }

    /// Bytes of the layers' 8-bit copies.
    pub fn int8_bytes(&self) -> usize {
        self.fc1.int8_bytes() + self.fc2.int8_bytes()
    }
}

impl Module for Mlp {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let hidden = self.fc1.forward_act(xs, Act::Gelu)?;
        self.fc2.forward_act(&hidden, Act::None)
    }
}
