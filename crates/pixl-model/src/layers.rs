//! Small private layer helpers.
//!
//! [`Conv`]: candle's `Conv2d` plus two CPU paths. A 3×3, padding-1, stride-1 or -2 conv in f32
//! with no gradient needed runs in [`pixl_nn::conv3x3`] (banded im2col, one parallel matrix
//! product per band of about [`CONV_TILE`] output pixels per thread, the bias added on the way;
//! several times faster than candle's CPU conv2d). candle 0.11's CPU conv2d feeds its im2col
//! tiles to a matmul kernel that has no bf16 variant, so on the CPU a bf16 conv runs in f32
//! (input and weights widened, result narrowed back); other dtypes and devices go straight
//! through. Weight names and layout are PyTorch's `nn.Conv2d` (`weight` `(out, in, k, k)`,
//! `bias` `(out)`).
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use pixl_nn::conv3x3::{conv3x3_banded, Epilogue, Im2colWeight};
use pixl_nn::fused::Act;

/// Output pixels per thread in one im2col band of a convolution (candle's tile, and the band
/// of the 3×3 kernel per worker thread); the memory plan counts one band.
pub const CONV_TILE: usize = 512;

impl Conv {
    /// The fast 3×3 CPU path, when it applies (see the module notes).
    fn forward_conv3x3(&self, xs: &Tensor) -> Result<Option<Tensor>> {
        let (w, b, cfg) = (self.0.weight(), self.0.bias(), self.0.config());
        let fits = xs.device().is_cpu()
            && xs.dtype() == DType::F32
            && w.dtype() == DType::F32
            && !pixl_nn::needs_grad(&[xs, w])
            && !b.is_some_and(|b| b.track_op())
            && cfg.padding == 1
            && (cfg.stride == 1 || cfg.stride == 2)
            && cfg.dilation == 1
            && cfg.groups == 1
            && matches!(w.dims(), [_, _, 3, 3])
            && xs.rank() == 4;
        if !fits {
            return Ok(None);
        }
        let bias = b.map(|b| b.to_vec1::<f32>()).transpose()?;
        let epi = Epilogue {
            bias: bias.as_deref(),
            residual: None,
            act: Act::None,
        };
        let cin = xs.dim(1)?;
        let band = candle_core::utils::get_num_threads().max(1) * CONV_TILE * 9 * cin;
        conv3x3_banded(xs, &Im2colWeight::new(w)?, cfg.stride, &epi, band).map(Some)
    }
}

#[derive(Clone, Debug)]
pub struct Conv(pub Conv2d);

impl Module for Conv {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        if let Some(ys) = self.forward_conv3x3(xs)? {
            return Ok(ys);
        }
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
