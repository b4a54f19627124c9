//! Small private layer helpers.
//!
//! [`Conv`]: candle's `Conv2d` plus CPU paths for f32 inference (no gradient needed):
//! - a 3×3, padding-1, stride-1 or -2 conv runs in [`pixl_nn::winograd`] (stride 1, outputs from
//!   64×64: F(4×4, 3×3), the weights transformed on each call, 1.8 ms for 256 → 256 channels) or
//!   [`pixl_nn::conv3x3`] (im2col tiles that stay in L2, one single-threaded GEMM per tile written
//!   straight into the output), the bias, a skip connection and the activation applied on the
//!   way (several times faster than candle's CPU conv2d), and can take the ReLU of its input on
//!   the way ([`Conv::forward_fused`]);
//! - a 1×1, stride-1, unpadded conv is one matrix product `W · X` per image on the
//!   channels-first input (no im2col copy, no transpose back), the bias and activation fused.
//!
//! candle 0.11's CPU conv2d feeds its im2col tiles to a matmul kernel that has no bf16 variant,
//! so on the CPU a bf16 conv runs in f32 (input and weights widened, result narrowed back); other
//! dtypes and devices go straight through. Weight names and layout are PyTorch's `nn.Conv2d`
//! (`weight` `(out, in, k, k)`, `bias` `(out)`).
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use pixl_nn::conv3x3::{conv3x3_tiled, tile_pixels, Epilogue, Im2colWeight};
use pixl_nn::fused::{self, Act};
use pixl_nn::winograd::{self, WinogradWeight};

impl Conv {
    /// Whether the CPU f32 inference paths may take `xs` (no gradient anywhere).
    fn cpu_inference(&self, xs: &Tensor) -> bool {
        let (w, b) = (self.0.weight(), self.0.bias());
        xs.device().is_cpu()
            && xs.dtype() == DType::F32
            && w.dtype() == DType::F32
            && xs.rank() == 4
            && !pixl_nn::needs_grad(&[xs, w])
            && !b.is_some_and(|b| b.track_op())
    }

    /// The fast 3×3 CPU path, when it applies (see the module notes).
    fn forward_conv3x3(
        &self,
        xs: &Tensor,
        input_relu: bool,
        residual: Option<&Tensor>,
        act: Act,
    ) -> Result<Option<Tensor>> {
        let (w, b, cfg) = (self.0.weight(), self.0.bias(), self.0.config());
        let fits = self.cpu_inference(xs)
            && cfg.padding == 1
            && (cfg.stride == 1 || cfg.stride == 2)
            && cfg.dilation == 1
            && cfg.groups == 1
            && matches!(w.dims(), [_, _, 3, 3])
            && residual.is_none_or(fused::cpu_f32);
        if !fits {
            return Ok(None);
        }
        let bias = b.map(|b| b.to_vec1::<f32>()).transpose()?;
        let residual = residual.map(|r| r.contiguous()).transpose()?;
        let skip = residual
            .as_ref()
            .map(|r| r.flatten_all()?.to_vec1::<f32>())
            .transpose()?;
        let epi = Epilogue {
            bias: bias.as_deref(),
            residual: skip.as_deref(),
            act,
        };
        let (_, cin, h, wd) = xs.dims4()?;
        if winograd::suits(cfg.stride, h, wd) {
            let wt = WinogradWeight::new(w)?;
            let block = winograd::block_tiles(wt.cin(), wt.cout());
            return winograd::conv3x3_winograd(xs, &wt, input_relu, &epi, block).map(Some);
        }
        conv3x3_tiled(
            xs,
            &Im2colWeight::new(w)?,
            cfg.stride,
            input_relu,
            &epi,
            tile_pixels(cin),
        )
        .map(Some)
    }

    /// The 1×1 CPU path, when it applies ([`fused::conv1x1`]).
    fn forward_conv1x1(&self, xs: &Tensor, act: Act) -> Result<Option<Tensor>> {
        let (w, b, cfg) = (self.0.weight(), self.0.bias(), self.0.config());
        let fits = self.cpu_inference(xs)
            && cfg.padding == 0
            && cfg.stride == 1
            && cfg.dilation == 1
            && cfg.groups == 1
            && matches!(w.dims(), [_, _, 1, 1]);
        if !fits {
            return Ok(None);
        }
        let _t = pixl_nn::profile::span("matmul (1x1 conv)");
        fused::conv1x1(xs, w, b, act)
    }

    /// `act(conv(relu?(xs)) + residual)`: the ReLU of the input (when `input_relu`), the skip
    /// connection and the activation fused into the convolution where a CPU path applies, and
    /// composed from candle ops otherwise (same values up to rounding).
    pub fn forward_fused(&self, xs: &Tensor, input_relu: bool, residual: Option<&Tensor>, act: Act) -> Result<Tensor> {
        if let Some(ys) = self.forward_conv3x3(xs, input_relu, residual, act)? {
            return Ok(ys);
        }
        let xs = if input_relu {
            pixl_nn::ops::relu(xs)?
        } else {
            xs.clone()
        };
        if residual.is_none() {
            if let Some(ys) = self.forward_conv1x1(&xs, act)? {
                return Ok(ys);
            }
        }
        let ys = self.forward_plain(&xs)?;
        let ys = match residual {
            Some(r) => (ys + r)?,
            None => ys,
        };
        match act {
            Act::None => Ok(ys),
            Act::Relu => pixl_nn::ops::relu(&ys),
            Act::Gelu => ys.gelu_erf(),
            Act::Silu => candle_nn::ops::silu(&ys),
        }
    }

    /// Training on the CPU in f32 (groups 1, dilation 1): [`pixl_nn::conv_grad::conv2d`], one op
    /// with its own backward; otherwise candle's conv2d (bf16 widened to f32 on the CPU).
    fn forward_plain(&self, xs: &Tensor) -> Result<Tensor> {
        let (w, b, cfg) = (self.0.weight(), self.0.bias(), self.0.config());
        let trained = pixl_nn::needs_grad(&[xs, w]) || b.is_some_and(|b| b.track_op());
        let f32_cpu = fused::cpu_f32(xs) && fused::cpu_f32(w) && b.is_none_or(fused::cpu_f32);
        if trained && f32_cpu && cfg.groups == 1 && cfg.dilation == 1 {
            return pixl_nn::conv_grad::conv2d(xs, w, b, cfg.stride, cfg.padding);
        }
        let _t = pixl_nn::profile::span("conv (candle)");
        if xs.dtype() != DType::BF16 || !xs.device().is_cpu() {
            return self.0.forward(xs);
        }
        let w = self.0.weight().to_dtype(DType::F32)?;
        let b = self.0.bias().map(|b| b.to_dtype(DType::F32)).transpose()?;
        let conv = Conv2d::new(w, b, *self.0.config());
        conv.forward(&xs.to_dtype(DType::F32)?)?.to_dtype(DType::BF16)
    }
}

#[derive(Clone, Debug)]
pub struct Conv(pub Conv2d);

impl Module for Conv {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        self.forward_fused(xs, false, None, Act::None)
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

impl pixl_nn::dpt::DptConv for Conv {
    fn load(spec: pixl_nn::dpt::ConvSpec, vb: VarBuilder) -> Result<Self> {
        let cfg = Conv2dConfig {
            padding: spec.k / 2,
            stride: spec.stride,
            ..Default::default()
        };
        if spec.bias {
            conv2d(spec.cin, spec.cout, spec.k, cfg, vb)
        } else {
            conv2d_no_bias(spec.cin, spec.cout, spec.k, cfg, vb)
        }
    }

    fn forward_fused(&self, xs: &Tensor, input_relu: bool, residual: Option<&Tensor>, act: Act) -> Result<Tensor> {
        Conv::forward_fused(self, xs, input_relu, residual, act)
    }
}
