//! Source encoder `src_encoder` (paper §3.2 "Asymmetric Feature Encoders"): a ViT that patchifies
//! `I_S` with patch size 16.
//!
//! Input `(B, 3, H, W)` with `H`, `W` multiples of 16 (the model pads before calling); output
//! `(B, N, d)` tokens, `N = (H/16)·(W/16)` in row-major grid order.
//!
//! Choices where the paper is silent:
//! - no class token (nothing reads it: the fusion is per location);
//! - a learned position embedding stored on a `pos_grid × pos_grid` grid and resized bilinearly
//!   (half-pixel centres, as `F.interpolate(align_corners=False)`) to each image's grid, so any
//!   aspect ratio works;
//! - pre-norm blocks (timm `Block`: `x + attn(norm1(x))`, `x + mlp(norm2(x))`), no layer scale,
//!   and a final `norm`.
//!
//! A checkpoint in the official release's layout may carry DINOv2's class token and LayerScale
//! ([`crate::config::VitConfig::cls_token`], `layer_scale`): the class token (plus its own
//! position row, which is never resized) is prepended before block 0 and dropped after the final
//! norm, so the output is the same `(B, N, d)` patch tokens either way.
//!
//! The blocks are [`pixl_nn::vit::Block`], shared with the trunk, which adds 2D RoPE, and with
//! the Depth Anything 3 backbone.
use crate::config::Config;
use crate::layers::{conv2d, Conv};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};
use pixl_nn::vit::BlockConfig;
use pixl_nn::LayerNorm;

pub use pixl_nn::vit::{Block, PatchRope};

/// The blocks' shape: `heads` heads, an MLP `mlp_ratio` times `cfg.dim` wide, LayerScale or not.
pub(crate) fn block_config(cfg: &Config, heads: usize, mlp_ratio: usize, layer_scale: bool) -> BlockConfig {
    BlockConfig {
        dim: cfg.dim,
        heads,
        mlp_hidden: mlp_ratio * cfg.dim,
        norm_eps: cfg.norm_eps,
        layer_scale,
    }
}

/// The ViT source encoder (`src_encoder.*`).
#[derive(Clone, Debug)]
pub struct VitEncoder {
    patch_embed: Conv,
    /// `(1, pos_grid², d)`: the patch rows (the class token's row is in `cls`).
    pos_embed: Tensor,
    /// The class token and its position row, `(1, 1, d)` each, when the config has one (added
    /// at each forward: both are views of trainable variables).
    cls: Option<(Tensor, Tensor)>,
    blocks: Vec<Block>,
    norm: LayerNorm,
    dim: usize,
    pos_grid: usize,
}

impl VitEncoder {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        let v = &cfg.src_encoder;
        let conv_cfg = Conv2dConfig {
            stride: cfg.patch,
            ..Default::default()
        };
        let patch_embed = conv2d(3, cfg.dim, cfg.patch, conv_cfg, vb.pp("patch_embed").pp("proj"))?;
        let init = candle_nn::Init::Randn { mean: 0.0, stdev: 0.02 };
        let cls_rows = usize::from(v.cls_token);
        let pos_all = vb.get_with_hints((1, cls_rows + v.pos_grid * v.pos_grid, cfg.dim), "pos_embed", init)?;
        let (pos_embed, cls) = if v.cls_token {
            let token = vb.get_with_hints((1, 1, cfg.dim), "cls_token", init)?;
            (
                pos_all.narrow(1, 1, v.pos_grid * v.pos_grid)?,
                Some((token, pos_all.narrow(1, 0, 1)?)),
            )
        } else {
            (pos_all, None)
        };
        let block_cfg = block_config(cfg, v.heads, v.mlp_ratio, v.layer_scale);
        let blocks = (0..v.depth)
            .map(|i| Block::new(&block_cfg, vb.pp("blocks").pp(i)))
            .collect::<Result<Vec<_>>>()?;
        let norm = LayerNorm::new(cfg.dim, cfg.norm_eps, vb.pp("norm"))?;
        Ok(Self {
            patch_embed,
            pos_embed,
            cls,
            blocks,
            norm,
            dim: cfg.dim,
            pos_grid: v.pos_grid,
        })
    }

    /// Every block's linear layers in 8 bits where the CPU allows; returns how many.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        self.blocks.iter_mut().map(Block::quantize_int8).sum()
    }

    pub fn int8_bytes(&self) -> usize {
        self.blocks.iter().map(Block::int8_bytes).sum()
    }

    /// The position embedding resized to a `(gh, gw)` grid, `(1, gh·gw, d)`.
    fn pos_embed_for(&self, gh: usize, gw: usize) -> Result<Tensor> {
        let g = self.pos_grid;
        if gh == g && gw == g {
            return Ok(self.pos_embed.clone());
        }
        let grid = self.pos_embed.reshape((1, g, g, self.dim))?.permute((0, 3, 1, 2))?;
        let resized = pixl_nn::ops::resize_bilinear(&grid.contiguous()?, gh, gw)?;
        resized.flatten_from(2)?.transpose(1, 2)
    }

    /// `(B, 3, H, W)` → `(B, (H/p)(W/p), d)`.
    pub fn forward(&self, src: &Tensor) -> Result<Tensor> {
        let mut xs = self.embed(src)?;
        for i in 0..self.blocks.len() {
            xs = self.block(i, &xs)?;
        }
        self.finish(&xs)
    }

    // Segment API (gradient checkpointing): `forward` is exactly `embed`, `block(i)` for every
    // `i`, then `finish`; the same calls on the same values give bitwise the same results.

    /// Number of blocks.
    pub fn depth(&self) -> usize {
        self.blocks.len()
    }

    /// Patch embedding plus position embedding: `(B, 3, H, W)` → `(B, N, d)` (`(B, 1 + N, d)`
    /// with a class token first), the input of block 0.
    pub fn embed(&self, src: &Tensor) -> Result<Tensor> {
        let xs = self.patch_embed.forward(src)?; // (B, d, gh, gw)
        let (b, _d, gh, gw) = xs.dims4()?;
        let xs = xs
            .flatten_from(2)?
            .transpose(1, 2)?
            .broadcast_add(&self.pos_embed_for(gh, gw)?)?;
        match &self.cls {
            Some((token, pos)) => Tensor::cat(&[&token.add(pos)?.broadcast_as((b, 1, self.dim))?, &xs], 1),
            None => Ok(xs),
        }
    }

    /// Block `i` on `(B, N, d)`.
    pub fn block(&self, i: usize, xs: &Tensor) -> Result<Tensor> {
        let block = self.blocks.get(i).ok_or_else(|| {
            candle_core::Error::Msg(format!("src_encoder: no block {i} (depth {})", self.blocks.len()))
        })?;
        block.forward(xs, None)
    }

    /// The final norm on the last block's output, class token dropped: `(B, N, d)`.
    pub fn finish(&self, xs: &Tensor) -> Result<Tensor> {
        let xs = self.norm.forward(&xs.contiguous()?)?;
        match self.cls {
            Some(_) => {
                let n = xs.dim(1)?;
                xs.narrow(1, 1, n - 1)?.contiguous()
            }
            None => Ok(xs),
        }
    }
}

/// `(B, N, C)` tokens of a `(gh, gw)` grid → `(B, C, gh, gw)`.
pub fn tokens_to_grid(xs: &Tensor, gh: usize, gw: usize) -> Result<Tensor> {
    let (b, _n, c) = xs.dims3()?;
    xs.transpose(1, 2)?.reshape((b, c, gh, gw))
}

/// `(B, C, gh, gw)` → `(B, gh·gw, C)` tokens.
pub fn grid_to_tokens(xs: &Tensor) -> Result<Tensor> {
    xs.flatten_from(2)?.transpose(1, 2)?.contiguous()
}
