//! Modulation `modulation` (paper §3.2 "Modulation Head", Eq. 4): a 1×1 conv maps the DPT map
//! `F` to six channels, split into gain `g` (channels 0–2) and bias `b` (channels 3–5), and
//! `Î_T = clip((1 + g) ⊙ I_S + b, 0, 1)`.
//!
//! `modulation.conv` is zero-initialised (weight and bias) by [`crate::checkpoint::build_trainable`],
//! so `g ≡ b ≡ 0` and an untrained network returns `I_S` exactly. The affine step runs in f32
//! whatever the network's dtype, on the caller's unpadded f32 source, so the identity is
//! bitwise for any `I_S ∈ [0, 1]`. Gradients pass through the clip where `0 < Î_T < 1`.
use crate::layers::Conv;
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};

#[derive(Clone, Debug)]
pub struct Modulation {
    conv: Conv,
}

impl Modulation {
    pub fn new(hidden: usize, vb: VarBuilder) -> Result<Self> {
        let zero = candle_nn::Init::Const(0.0);
        let weight = vb.pp("conv").get_with_hints((6, hidden, 1, 1), "weight", zero)?;
        let bias = vb.pp("conv").get_with_hints(6, "bias", zero)?;
        Ok(Self {
            conv: Conv(candle_nn::Conv2d::new(weight, Some(bias), Conv2dConfig::default())),
        })
    }

    /// `F` `(B, C', H', W')` → gain and bias maps `(B, 3, H', W')` each, f32.
    pub fn gain_bias(&self, features: &Tensor) -> Result<(Tensor, Tensor)> {
        let gb = self.conv.forward(features)?.to_dtype(DType::F32)?;
        Ok((gb.narrow(1, 0, 3)?, gb.narrow(1, 3, 3)?))
    }

    /// `clip((1 + g) ⊙ src + b, 0, 1)`; `src`, `g`, `b` all `(B, 3, H, W)` f32.
    pub fn apply(src: &Tensor, g: &Tensor, b: &Tensor) -> Result<Tensor> {
        Self::affine(src, g, b)?.clamp(0f32, 1f32)
    }

    /// The affine step before the clip, `(1 + g) ⊙ src + b` (what training takes its pixel loss on).
    pub fn affine(src: &Tensor, g: &Tensor, b: &Tensor) -> Result<Tensor> {
        (g + 1.0)?.mul(src)? + b
    }
}
