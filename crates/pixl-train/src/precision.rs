//! Mixed precision (paper App. A: bf16 compute, f32 master weights).
//!
//! The trainable network's `Var`s — the master weights — and the AdamW moments stay f32. With
//! [`Precision::Bf16`], every micro-batch runs a *compute copy* of the network built by
//! [`compute_model`] from `var.to_dtype(BF16)` of every master weight. candle records that cast
//! as a graph node whose backward casts the incoming gradient back to the source dtype, so one
//! `backward()` of the loss yields gradients **in f32, on the f32 `Var`s**, with no copying back
//! and no second parameter list. Everything between the cast weights and the network's output
//! runs in bf16; the modulation (the gain/bias split and `(1 + g) ⊙ I_S + b`) and the loss run
//! in f32 (`PixlRelight` already widens the gain and bias maps to f32 before the affine step).
//!
//! No loss scaling: bf16 has f32's exponent range, so gradients do not underflow the way f16
//! gradients do.
//!
//! On the CPU every op the network hits accepts bf16 (checked by `tests/recompute.rs`): candle
//! 0.11's elementwise ops, reductions and casts have bf16 kernels; its matmul widens bf16
//! operands to f32 for the gemm and narrows the product back; its conv2d is widened to f32 by
//! pixl-model's `Conv` (candle's CPU im2col matmul has no bf16 variant), and pixl-nn's depthwise
//! conv does the same. So the CPU bf16 path is correct but gains nothing there; it exists for
//! CUDA, where it halves activation memory and uses the tensor cores. pixl-nn's LayerNorm
//! computes its statistics in f32 whatever the input dtype.
use crate::error::{Result, TrainError};
use crate::optim::Param;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use pixl_model::{Config, PixlRelight};
use std::collections::HashMap;

/// The dtype the network computes in during training (`[optim] precision`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// Everything f32 (the default; bit-exact resume on the CPU).
    #[default]
    F32,
    /// bf16 compute, f32 master weights, optimiser state, modulation and loss.
    Bf16,
}

impl Precision {
    pub fn dtype(self) -> DType {
        match self {
            Precision::F32 => DType::F32,
            Precision::Bf16 => DType::BF16,
        }
    }
}

/// A network over the master weights `params` that computes in `dtype`: each parameter is
/// `var.as_tensor().to_dtype(dtype)` (for f32 the `Var` itself), so gradients of anything it
/// computes land on the f32 `Var`s. Build one per micro-batch (the casts are taken when it is
/// built; after an optimiser step the copy is stale).
pub fn compute_model(cfg: &Config, params: &[Param], dtype: DType, device: &Device) -> Result<PixlRelight> {
    let mut tensors: HashMap<String, Tensor> = HashMap::with_capacity(params.len());
    for p in params {
        tensors.insert(p.name.clone(), p.var.as_tensor().to_dtype(dtype)?);
    }
    PixlRelight::new(cfg, VarBuilder::from_tensors(tensors, dtype, device))
        .map_err(|e| TrainError::Other(format!("building the {dtype:?} compute network: {e}")))
}
