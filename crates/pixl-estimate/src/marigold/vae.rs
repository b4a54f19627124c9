//! The Stable Diffusion VAE (diffusers `AutoencoderKL`) as Marigold uses it: the encoder's
//! posterior **mode** (its mean, what `latent_dist.mode()` returns) and the decoder.
//!
//! Written here rather than reused from candle-transformers (whose `AutoEncoderKL` only exposes
//! a sampled posterior) so that the full-resolution layers run on the crate's parallel CPU
//! kernels: 3×3 convolutions through [`Conv3x3`] (bias and skip connection in the same pass)
//! and GroupNorm + SiLU in one pass ([`group_norm_act`]); elsewhere the same layers run on
//! candle's ops. The arithmetic is diffusers': ResNet blocks `x + conv2(silu(gn2(conv1(silu(gn1(x))))))`
//! (a 1×1 `conv_shortcut` on `x` when the width changes), downsampling by a stride-2 3×3
//! convolution after zero-padding right and bottom by one, upsampling by nearest ×2 then a 3×3
//! convolution, a single-head self-attention block in the middle, all norms with ε = 1e-6.
//!
//! Tensor names are those of `vae/diffusion_pytorch_model.safetensors`:
//! `encoder.{conv_in, down_blocks.i.{resnets.j, downsamplers.0.conv}, mid_block.{resnets.0,
//! attentions.0, resnets.1}, conv_norm_out, conv_out}`, `quant_conv`, `post_quant_conv`,
//! `decoder.{conv_in, mid_block, up_blocks.i.{resnets.j, upsamplers.0.conv}, conv_norm_out,
//! conv_out}`; the attention's `group_norm`, `to_q`, `to_k`, `to_v`, `to_out.0` (or the old
//! `query`, `key`, `value`, `proj_attn`). Scaling by `scaling_factor` is the caller's.
use super::config::VaeConfig;
use candle_core::{Module, Result, Tensor};
use candle_nn::{self as nn, VarBuilder};
use pixl_nn::conv3x3::Conv3x3;
use pixl_nn::fused::{group_norm_act, Act, Vector};

/// GroupNorm epsilon of the SD VAE (hard-coded in diffusers' `Encoder`/`Decoder`).
const EPS: f64 = 1e-6;

struct Norm {
    groups: usize,
    gamma: Vector,
    beta: Vector,
}

impl Norm {
    fn new(groups: usize, c: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            groups,
            gamma: Vector::new(vb.get(c, "weight")?)?,
            beta: Vector::new(vb.get(c, "bias")?)?,
        })
    }

    fn forward(&self, xs: &Tensor, act: Act) -> Result<Tensor> {
        group_norm_act(xs, self.groups, EPS, &self.gamma, &self.beta, act)
    }
}

struct Resnet {
    norm1: Norm,
    conv1: Conv3x3,
    norm2: Norm,
    conv2: Conv3x3,
    shortcut: Option<nn::Conv2d>,
}

impl Resnet {
    fn new(cin: usize, cout: usize, groups: usize, vb: VarBuilder) -> Result<Self> {
        let shortcut = if cin != cout {
            Some(nn::conv2d(cin, cout, 1, Default::default(), vb.pp("conv_shortcut"))?)
        } else {
            None
        };
        Ok(Self {
            norm1: Norm::new(groups, cin, vb.pp("norm1"))?,
            conv1: Conv3x3::new(cin, cout, 1, true, vb.pp("conv1"))?,
            norm2: Norm::new(groups, cout, vb.pp("norm2"))?,
            conv2: Conv3x3::new(cout, cout, 1, true, vb.pp("conv2"))?,
            shortcut,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let h = self.conv1.forward(&self.norm1.forward(xs, Act::Silu)?, Act::None)?;
        let h = self.norm2.forward(&h, Act::Silu)?;
        let skip = match &self.shortcut {
            Some(c) => c.forward(xs)?,
            None => xs.clone(),
        };
        self.conv2.forward_residual(&h, &skip)
    }
}

/// The mid block's single-head self-attention over the `H·W` positions, with its residual.
struct Attention {
    norm: Norm,
    q: nn::Linear,
    k: nn::Linear,
    v: nn::Linear,
    out: nn::Linear,
}

impl Attention {
    fn new(c: usize, groups: usize, vb: VarBuilder) -> Result<Self> {
        let names = if vb.contains_tensor("to_q.weight") {
            ["to_q", "to_k", "to_v", "to_out.0"]
        } else {
            ["query", "key", "value", "proj_attn"]
        };
        Ok(Self {
            norm: Norm::new(groups, c, vb.pp("group_norm"))?,
            q: nn::linear(c, c, vb.pp(names[0]))?,
            k: nn::linear(c, c, vb.pp(names[1]))?,
            v: nn::linear(c, c, vb.pp(names[2]))?,
            out: nn::linear(c, c, vb.pp(names[3]))?,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = xs.dims4()?;
        let t = self
            .norm
            .forward(xs, Act::None)?
            .reshape((b, c, h * w))?
            .transpose(1, 2)?
            .contiguous()?;
        let q = self.q.forward(&t)?;
        let k = self.k.forward(&t)?;
        let v = self.v.forward(&t)?;
        let scores = (q.matmul(&k.t()?)? * (1.0 / (c as f64).sqrt()))?;
        let att = candle_nn::ops::softmax_last_dim(&scores)?;
        let o = self.out.forward(&att.matmul(&v)?)?;
        let o = o.transpose(1, 2)?.reshape((b, c, h, w))?;
        o + xs
    }
}

struct Mid {
    res0: Resnet,
    attn: Attention,
    res1: Resnet,
}

impl Mid {
    fn new(c: usize, groups: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            res0: Resnet::new(c, c, groups, vb.pp("resnets").pp("0"))?,
            attn: Attention::new(c, groups, vb.pp("attentions").pp("0"))?,
            res1: Resnet::new(c, c, groups, vb.pp("resnets").pp("1"))?,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        self.res1.forward(&self.attn.forward(&self.res0.forward(xs)?)?)
    }
}

/// Encoder + `quant_conv`: image in [−1, 1] → posterior mean.
pub struct VaeEncoder {
    conv_in: Conv3x3,
    /// Per level: its ResNets and (all but the last level) the stride-2 convolution.
    down: Vec<(Vec<Resnet>, Option<nn::Conv2d>)>,
    mid: Mid,
    norm_out: Norm,
    conv_out: Conv3x3,
    quant_conv: Option<nn::Conv2d>,
    latent_channels: usize,
}

impl VaeEncoder {
    /// `vb` is the VAE's root (tensors `encoder.*`, `quant_conv.*`).
    pub fn new(cfg: &VaeConfig, vb: VarBuilder) -> Result<Self> {
        let ch = &cfg.block_out_channels;
        let g = cfg.norm_num_groups;
        let e = vb.pp("encoder");
        let conv_in = Conv3x3::new(cfg.in_channels, ch[0], 1, true, e.pp("conv_in"))?;
        let mut down = Vec::with_capacity(ch.len());
        for (i, &out) in ch.iter().enumerate() {
            let b = e.pp("down_blocks").pp(i.to_string());
            let mut resnets = Vec::with_capacity(cfg.layers_per_block);
            for j in 0..cfg.layers_per_block {
                let cin = if j == 0 {
                    if i == 0 {
                        ch[0]
                    } else {
                        ch[i - 1]
                    }
                } else {
                    out
                };
                resnets.push(Resnet::new(cin, out, g, b.pp("resnets").pp(j.to_string()))?);
            }
            let downsample = if i + 1 < ch.len() {
                let cfg = nn::Conv2dConfig {
                    stride: 2,
                    ..Default::default()
                };
                Some(nn::conv2d(out, out, 3, cfg, b.pp("downsamplers").pp("0").pp("conv"))?)
            } else {
                None
            };
            down.push((resnets, downsample));
        }
        let last = ch[ch.len() - 1];
        let l2 = 2 * cfg.latent_channels;
        Ok(Self {
            conv_in,
            down,
            mid: Mid::new(last, g, e.pp("mid_block"))?,
            norm_out: Norm::new(g, last, e.pp("conv_norm_out"))?,
            conv_out: Conv3x3::new(last, l2, 1, true, e.pp("conv_out"))?,
            quant_conv: if cfg.use_quant_conv {
                Some(nn::conv2d(l2, l2, 1, Default::default(), vb.pp("quant_conv"))?)
            } else {
                None
            },
            latent_channels: cfg.latent_channels,
        })
    }

    /// The posterior's mode (mean) for `(B, 3, H, W)` input: `(B, latent, H/8, W/8)`.
    pub fn mode(&self, xs: &Tensor) -> Result<Tensor> {
        let mut h = self.conv_in.forward(xs, Act::None)?;
        for (resnets, downsample) in &self.down {
            for r in resnets {
                h = r.forward(&h)?;
            }
            if let Some(d) = downsample {
                // diffusers' Downsample2D(padding=0): pad right and bottom by one zero.
                h = d.forward(&h.pad_with_zeros(3, 0, 1)?.pad_with_zeros(2, 0, 1)?)?;
            }
        }
        let h = self.mid.forward(&h)?;
        let h = self.norm_out.forward(&h, Act::Silu)?;
        let mut moments = self.conv_out.forward(&h, Act::None)?;
        if let Some(q) = &self.quant_conv {
            moments = q.forward(&moments)?;
        }
        moments.narrow(1, 0, self.latent_channels)
    }
}

/// `post_quant_conv` + decoder: latent → image in about [−1, 1].
pub struct VaeDecoder {
    post_quant_conv: Option<nn::Conv2d>,
    conv_in: Conv3x3,
    mid: Mid,
    /// Per level (widest first): its ResNets and (all but the last) the upsampling convolution.
    up: Vec<(Vec<Resnet>, Option<Conv3x3>)>,
    norm_out: Norm,
    conv_out: Conv3x3,
}

impl VaeDecoder {
    /// `vb` is the VAE's root (tensors `decoder.*`, `post_quant_conv.*`).
    pub fn new(cfg: &VaeConfig, vb: VarBuilder) -> Result<Self> {
        let ch = &cfg.block_out_channels;
        let g = cfg.norm_num_groups;
        let l = cfg.latent_channels;
        let d = vb.pp("decoder");
        let last = ch[ch.len() - 1];
        let rev: Vec<usize> = ch.iter().rev().copied().collect();
        let mut up = Vec::with_capacity(rev.len());
        for (i, &out) in rev.iter().enumerate() {
            let b = d.pp("up_blocks").pp(i.to_string());
            let mut resnets = Vec::with_capacity(cfg.layers_per_block + 1);
            for j in 0..cfg.layers_per_block + 1 {
                let cin = if j == 0 {
                    if i == 0 {
                        rev[0]
                    } else {
                        rev[i - 1]
                    }
                } else {
                    out
                };
                resnets.push(Resnet::new(cin, out, g, b.pp("resnets").pp(j.to_string()))?);
            }
            let upsample = if i + 1 < rev.len() {
                Some(Conv3x3::new(out, out, 1, true, b.pp("upsamplers").pp("0").pp("conv"))?)
            } else {
                None
            };
            up.push((resnets, upsample));
        }
        Ok(Self {
            post_quant_conv: if cfg.use_post_quant_conv {
                Some(nn::conv2d(l, l, 1, Default::default(), vb.pp("post_quant_conv"))?)
            } else {
                None
            },
            conv_in: Conv3x3::new(l, last, 1, true, d.pp("conv_in"))?,
            mid: Mid::new(last, g, d.pp("mid_block"))?,
            up,
            norm_out: Norm::new(g, ch[0], d.pp("conv_norm_out"))?,
            conv_out: Conv3x3::new(ch[0], cfg.out_channels, 1, true, d.pp("conv_out"))?,
        })
    }

    /// `(B, latent, h, w)` → `(B, out_channels, 8h, 8w)`.
    pub fn decode(&self, z: &Tensor) -> Result<Tensor> {
        let z = match &self.post_quant_conv {
            Some(p) => p.forward(z)?,
            None => z.clone(),
        };
        let mut h = self.mid.forward(&self.conv_in.forward(&z, Act::None)?)?;
        for (resnets, upsample) in &self.up {
            for r in resnets {
                h = r.forward(&h)?;
            }
            if let Some(u) = upsample {
                let (_, _, hh, ww) = h.dims4()?;
                h = u.forward(&h.upsample_nearest2d(2 * hh, 2 * ww)?, Act::None)?;
            }
        }
        let h = self.norm_out.forward(&h, Act::Silu)?;
        self.conv_out.forward(&h, Act::None)
    }
}
