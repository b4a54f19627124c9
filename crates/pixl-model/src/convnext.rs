//! Intrinsics encoder `cond_encoder` (paper §3.2 "Asymmetric Feature Encoders"): a ConvNeXt over
//! the 9-channel `C_T`, final-stage features projected to `d`.
//!
//! Input `(B, 9, H, W)` with `H`, `W` multiples of the patch size `p`; output `(B, N, d)` tokens
//! on the same `(H/p, W/p)` grid as the ViT, row-major.
//!
//! Layout (timm `convnext` names): `stem.0` (4×4 conv, stride 4) + `stem.1` (LayerNorm2d);
//! `stages.{s}.downsample.{0,1}` (LayerNorm2d + conv) before stages 1–3; `stages.{s}.blocks.{j}`
//! = depthwise 7×7 `conv_dw` → `norm` (channels-last LayerNorm) → `mlp` (`fc1` 4×, GELU, `fc2`)
//! → per-channel layer scale `gamma` → residual.
//!
//! Choices where the paper is silent:
//! - stride `p` (16 by default), not 32: downsamplings past `p` are dropped so the final stage's
//!   grid equals the ViT's. Such a transition still has to change width (512 → 1024 for
//!   ConvNeXt-B), so it keeps its LayerNorm2d and replaces the 2×2 stride-2 conv by a 1×1
//!   stride-1 conv ([`Config::cond_downsamples`]);
//! - no stochastic depth; the final features go through `norm` (LayerNorm) then `proj`
//!   (Linear `dims[3] → d`), even when `dims[3] == d`.
use crate::config::Config;
use crate::layers::{conv2d, Conv};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};
use pixl_nn::fused;
use pixl_nn::{DepthwiseConv2d, LayerNorm, LayerNorm2d, Linear, Mlp};

/// ConvNeXt block: `x + gamma ⊙ mlp(norm(dwconv7(x)))` (channels-last inside).
#[derive(Clone, Debug)]
pub struct ConvNextBlock {
    conv_dw: DepthwiseConv2d,
    norm: LayerNorm,
    mlp: Mlp,
    gamma: Tensor,
}

impl ConvNextBlock {
    pub fn new(dim: usize, layer_scale_init: f64, eps: f64, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            conv_dw: DepthwiseConv2d::new(dim, 7, vb.pp("conv_dw"))?,
            norm: LayerNorm::new(dim, eps, vb.pp("norm"))?,
            mlp: Mlp::new(dim, 4 * dim, dim, vb.pp("mlp"))?,
            gamma: vb.get_with_hints(dim, "gamma", candle_nn::Init::Const(layer_scale_init))?,
        })
    }

    /// The MLP in 8 bits where the CPU allows; returns how many layers.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        self.mlp.quantize_int8()
    }

    pub fn int8_bytes(&self) -> usize {
        self.mlp.int8_bytes()
    }
}

/// Zero-pads a map narrower or shorter than the 7×7 kernel before the depthwise conv and crops
/// after. Exact (the conv pads with zeros itself); it works around `pixl_nn::depthwise_conv2d`
/// panicking on planes narrower than `k/2` (reported, pixl-nn is not ours to edit).
fn conv_dw_any_size(conv: &DepthwiseConv2d, xs: &Tensor) -> Result<Tensor> {
    let (_b, _c, h, w) = xs.dims4()?;
    let k = conv.kernel;
    if h >= k && w >= k {
        return conv.forward(xs);
    }
    let padded = xs
        .pad_with_zeros(2, 0, k.saturating_sub(h))?
        .pad_with_zeros(3, 0, k.saturating_sub(w))?;
    conv.forward(&padded)?.narrow(2, 0, h)?.narrow(3, 0, w)
}

impl Module for ConvNextBlock {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let ys = fused::to_channels_last(&conv_dw_any_size(&self.conv_dw, xs)?)?;
        let ys = self.mlp.forward(&self.norm.forward(&ys)?)?;
        fused::add_scaled_channels_last(xs, &ys, &self.gamma)
    }
}

/// One stage: optional downsampling, then blocks.
#[derive(Clone, Debug)]
struct Stage {
    downsample: Option<(LayerNorm2d, Conv)>,
    blocks: Vec<ConvNextBlock>,
}

impl Module for Stage {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let mut xs = match &self.downsample {
            Some((norm, conv)) => conv.forward(&norm.forward(xs)?)?,
            None => xs.clone(),
        };
        for block in &self.blocks {
            xs = block.forward(&xs)?;
        }
        Ok(xs)
    }
}

/// The ConvNeXt intrinsics encoder (`cond_encoder.*`).
#[derive(Clone, Debug)]
pub struct ConvNextEncoder {
    stem_conv: Conv,
    stem_norm: LayerNorm2d,
    stages: Vec<Stage>,
    norm: LayerNorm,
    proj: Linear,
}

impl ConvNextEncoder {
    /// Every linear layer (the blocks' MLPs, `proj`) in 8 bits where the CPU allows and the
    /// layer is wide enough ([`Linear::quantize_int8`]); returns how many.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        let mut n = usize::from(self.proj.quantize_int8()?);
        for block in self.stages.iter_mut().flat_map(|s| s.blocks.iter_mut()) {
            n += block.quantize_int8()?;
        }
        Ok(n)
    }

    pub fn int8_bytes(&self) -> usize {
        let blocks: usize = self
            .stages
            .iter()
            .flat_map(|s| s.blocks.iter())
            .map(|b| b.int8_bytes())
            .sum();
        self.proj.int8_bytes() + blocks
    }

    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        let c = &cfg.cond_encoder;
        let eps = cfg.norm_eps;
        let stem_cfg = Conv2dConfig {
            stride: 4,
            ..Default::default()
        };
        let stem_conv = conv2d(9, c.dims[0], 4, stem_cfg, vb.pp("stem").pp(0))?;
        let stem_norm = LayerNorm2d::new(c.dims[0], eps, vb.pp("stem").pp(1))?;
        let mut stages = Vec::with_capacity(4);
        for s in 0..4 {
            let vs = vb.pp("stages").pp(s);
            let downsample = if s == 0 {
                None
            } else {
                let (k, stride) = if cfg.cond_downsamples(s) { (2, 2) } else { (1, 1) };
                let vd = vs.pp("downsample");
                let norm = LayerNorm2d::new(c.dims[s - 1], eps, vd.pp(0))?;
                let conv_cfg = Conv2dConfig {
                    stride,
                    ..Default::default()
                };
                Some((norm, conv2d(c.dims[s - 1], c.dims[s], k, conv_cfg, vd.pp(1))?))
            };
            let blocks = (0..c.depths[s])
                .map(|j| ConvNextBlock::new(c.dims[s], c.layer_scale_init, eps, vs.pp("blocks").pp(j)))
                .collect::<Result<Vec<_>>>()?;
            stages.push(Stage { downsample, blocks });
        }
        let norm = LayerNorm::new(c.dims[3], eps, vb.pp("norm"))?;
        let proj = Linear::load(c.dims[3], cfg.dim, vb.pp("proj"))?;
        Ok(Self {
            stem_conv,
            stem_norm,
            stages,
            norm,
            proj,
        })
    }

    /// `(B, 9, H, W)` → `(B, (H/p)(W/p), d)`.
    pub fn forward(&self, ct: &Tensor) -> Result<Tensor> {
        let mut xs = self.stem_norm.forward(&self.stem_conv.forward(ct)?)?;
        for stage in &self.stages {
            xs = stage.forward(&xs)?;
        }
        let tokens = crate::vit::grid_to_tokens(&xs)?;
        self.proj.forward(&self.norm.forward(&tokens)?)
    }
}
