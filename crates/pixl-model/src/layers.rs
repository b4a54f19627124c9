//! Small private layer helpers.
//!
//! [`Conv`]: candle's `Conv2d` plus a bf16 path. candle 0.11's CPU conv2d feeds its im2col
//! tiles to a matmul kernel that has no bf16 variant, so on the CPU a bf16 conv runs in f32
//! (input and weights widened, result narrowed back); other dtypes and devices go straight
//! through. Weight names and layout are PyTorch's `nn.Conv2d` (`weight` `(out, in, k, k)`,
//! `bias` `(out)`).
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};

#[derive(Clone, Debug)]
pub struct Conv(pub Conv2d);

impl Module for Conv {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        if xs.dtype() != DType::BF16 || !xs.device().is_cpu() {
            return self.0.forward(xs);
        }
        let w = self.0.weight().to_dtype(DType::F32)?;
        let b = self.0.bias().map(|b| b.to_dtype(DType::F32)).transpose()?;
        let conv = Conv2d::new(w, b, *self.0.config());
        conv.forward(&xs.to_dtype(DType::F32)?)?.to_dtype(DType::BF16)
    }
}

/// `nn.Conv2d(cin, cout, k, **cfg)` with bias.
pub fn conv2d(cin: usize, cout: usize, k: usize, cfg: Conv2dConfig, vb: VarBuilder) -> Result<Conv> {
    Ok(Conv(candle_nn::conv2d(cin, cout, k, cfg, vb)?))
}

/// `nn.Conv2d(cin, cout, k, bias=False, **cfg)`.
pub fn conv2d_no_bias(cin: usize, cout: usize, k: usize, cfg: Conv2dConfig, vb: VarBuilder) -> Result<Conv> {
    Ok(Conv(candle_nn::conv2d_no_bias(cin, cout, k, cfg, vb)?))
}
