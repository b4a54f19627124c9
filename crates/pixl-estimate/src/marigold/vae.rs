//! The Stable Diffusion VAE (diffusers `AutoencoderKL`) as Marigold uses it: the encoder's
//! posterior **mode** (its mean, what `latent_dist.mode()` returns) and the decoder.
//!
//! candle-transformers' `AutoEncoderKL` only exposes a sampled posterior, so the two halves are
//! assembled here from its public blocks (`DownEncoderBlock2D`, `UNetMidBlock2D`,
//! `UpDecoderBlock2D`), with the layer names of `vae/diffusion_pytorch_model.safetensors`:
//! `encoder.{conv_in, down_blocks.i, mid_block, conv_norm_out, conv_out}`, `quant_conv`,
//! `post_quant_conv`, `decoder.{conv_in, mid_block, up_blocks.i, conv_norm_out, conv_out}`.
//! Scaling by `scaling_factor` is the caller's ([`super::Marigold`]).
use super::config::VaeConfig;
use candle_core::{Result, Tensor};
use candle_nn::{self as nn, Module, VarBuilder};
use candle_transformers::models::stable_diffusion::unet_2d_blocks::{
    DownEncoderBlock2D, DownEncoderBlock2DConfig, UNetMidBlock2D, UNetMidBlock2DConfig, UpDecoderBlock2D,
    UpDecoderBlock2DConfig,
};

/// GroupNorm / ResNet epsilon of the SD VAE (hard-coded in diffusers' `Encoder`/`Decoder`).
const EPS: f64 = 1e-6;

fn conv3(cin: usize, cout: usize, vb: VarBuilder) -> Result<nn::Conv2d> {
    let cfg = nn::Conv2dConfig {
        padding: 1,
        ..Default::default()
    };
    nn::conv2d(cin, cout, 3, cfg, vb)
}

fn mid_block(channels: usize, groups: usize, vb: VarBuilder) -> Result<UNetMidBlock2D> {
    let cfg = UNetMidBlock2DConfig {
        resnet_eps: EPS,
        output_scale_factor: 1.0,
        attn_num_head_channels: None,
        resnet_groups: Some(groups),
        ..Default::default()
    };
    UNetMidBlock2D::new(vb, channels, None, cfg)
}

/// Encoder + `quant_conv`: image in [−1, 1] → posterior mean.
pub struct VaeEncoder {
    conv_in: nn::Conv2d,
    down: Vec<DownEncoderBlock2D>,
    mid: UNetMidBlock2D,
    norm_out: nn::GroupNorm,
    conv_out: nn::Conv2d,
    quant_conv: Option<nn::Conv2d>,
    latent_channels: usize,
}

impl VaeEncoder {
    /// `vb` is the VAE's root (tensors `encoder.*`, `quant_conv.*`).
    pub fn new(cfg: &VaeConfig, vb: VarBuilder) -> Result<Self> {
        let ch = &cfg.block_out_channels;
        let g = cfg.norm_num_groups;
        let e = vb.pp("encoder");
        let conv_in = conv3(cfg.in_channels, ch[0], e.pp("conv_in"))?;
        let mut down = Vec::with_capacity(ch.len());
        for (i, &out) in ch.iter().enumerate() {
            let cin = if i == 0 { ch[0] } else { ch[i - 1] };
            let bcfg = DownEncoderBlock2DConfig {
                num_layers: cfg.layers_per_block,
                resnet_eps: EPS,
                resnet_groups: g,
                output_scale_factor: 1.0,
                add_downsample: i + 1 < ch.len(),
                downsample_padding: 0,
            };
            down.push(DownEncoderBlock2D::new(e.pp("down_blocks").pp(i.to_string()), cin, out, bcfg)?);
        }
        let last = ch[ch.len() - 1];
        let mid = mid_block(last, g, e.pp("mid_block"))?;
        let norm_out = nn::group_norm(g, last, EPS, e.pp("conv_norm_out"))?;
        let conv_out = conv3(last, 2 * cfg.latent_channels, e.pp("conv_out"))?;
        let quant_conv = if cfg.use_quant_conv {
            let l2 = 2 * cfg.latent_channels;
            Some(nn::conv2d(l2, l2, 1, Default::default(), vb.pp("quant_conv"))?)
        } else {
            None
        };
        Ok(Self {
            conv_in,
            down,
            mid,
            norm_out,
            conv_out,
            quant_conv,
            latent_channels: cfg.latent_channels,
        })
    }

    /// The posterior's mode (mean) for `(B, 3, H, W)` input: `(B, latent, H/8, W/8)`.
    pub fn mode(&self, xs: &Tensor) -> Result<Tensor> {
        let mut h = self.conv_in.forward(xs)?;
        for b in &self.down {
            h = b.forward(&h)?;
        }
        let h = self.mid.forward(&h, None)?;
        let h = nn::ops::silu(&self.norm_out.forward(&h)?)?;
        let mut moments = self.conv_out.forward(&h)?;
        if let Some(q) = &self.quant_conv {
            moments = q.forward(&moments)?;
        }
        moments.narrow(1, 0, self.latent_channels)
    }
}

/// `post_quant_conv` + decoder: latent → image in about [−1, 1].
pub struct VaeDecoder {
    post_quant_conv: Option<nn::Conv2d>,
    conv_in: nn::Conv2d,
    mid: UNetMidBlock2D,
    up: Vec<UpDecoderBlock2D>,
    norm_out: nn::GroupNorm,
    conv_out: nn::Conv2d,
}

impl VaeDecoder {
    /// `vb` is the VAE's root (tensors `decoder.*`, `post_quant_conv.*`).
    pub fn new(cfg: &VaeConfig, vb: VarBuilder) -> Result<Self> {
        let ch = &cfg.block_out_channels;
        let g = cfg.norm_num_groups;
        let l = cfg.latent_channels;
        let post_quant_conv = if cfg.use_post_quant_conv {
            Some(nn::conv2d(l, l, 1, Default::default(), vb.pp("post_quant_conv"))?)
        } else {
            None
        };
        let d = vb.pp("decoder");
        let last = ch[ch.len() - 1];
        let conv_in = conv3(l, last, d.pp("conv_in"))?;
        let mid = mid_block(last, g, d.pp("mid_block"))?;
        let rev: Vec<usize> = ch.iter().rev().copied().collect();
        let mut up = Vec::with_capacity(rev.len());
        for (i, &out) in rev.iter().enumerate() {
            let cin = if i == 0 { rev[0] } else { rev[i - 1] };
            let bcfg = UpDecoderBlock2DConfig {
                num_layers: cfg.layers_per_block + 1,
                resnet_eps: EPS,
                resnet_groups: g,
                output_scale_factor: 1.0,
                add_upsample: i + 1 < rev.len(),
            };
            up.push(UpDecoderBlock2D::new(d.pp("up_blocks").pp(i.to_string()), cin, out, bcfg)?);
        }
        let norm_out = nn::group_norm(g, ch[0], EPS, d.pp("conv_norm_out"))?;
        let conv_out = conv3(ch[0], cfg.out_channels, d.pp("conv_out"))?;
        Ok(Self {
            post_quant_conv,
            conv_in,
            mid,
            up,
            norm_out,
            conv_out,
        })
    }

    /// `(B, latent, h, w)` → `(B, out_channels, 8h, 8w)`.
    pub fn decode(&self, z: &Tensor) -> Result<Tensor> {
        let z = match &self.post_quant_conv {
            Some(p) => p.forward(z)?,
            None => z.clone(),
        };
        let mut h = self.mid.forward(&self.conv_in.forward(&z)?, None)?;
        for b in &self.up {
            h = b.forward(&h)?;
        }
        let h = nn::ops::silu(&self.norm_out.forward(&h)?)?;
        self.conv_out.forward(&h)
    }
}
