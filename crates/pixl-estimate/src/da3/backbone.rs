//! DA3's DINOv2 ViT backbone (`model.backbone.pretrained`, official
//! `DinoVisionTransformer` as built by `DinoV2` for the single-view models).
//!
//! Input `(B, 3, H, W)` f32, ImageNet-normalised, `H`, `W` multiples of the patch size (14).
//! Output: the four `out_layers` block outputs, each passed through the final `norm` with the
//! class token dropped, as `(B, N, C)` tokens, `N = (H/14)·(W/14)` in row-major grid order —
//! what the official `get_intermediate_layers` hands to the DPT head.
//!
//! Numerics as the official code:
//! - patch embedding `Conv2d(3, C, 14, stride 14)` (computed as one matmul);
//! - class token prepended, then the position embedding added: the stored `(1 + M², C)` table
//!   (M = img_size / 14 = 37 for the released models) is used as is when the grid is M×M, and
//!   otherwise its patch part is resized bicubically with scale factors
//!   `((H/14 + 0.1) / M, (W/14 + 0.1) / M)` (`interpolate_offset` 0.1, no antialiasing), see
//!   [`super::resize::bicubic_scale`];
//! - pre-norm blocks `x + ls1·attn(norm1(x))`, `x + ls2·mlp(norm2(x))`: LayerNorm eps 1e-6,
//!   multi-head softmax attention with scale `1/√(C/heads)`, biases on qkv / proj / fc, exact
//!   (erf) GELU, LayerScale `gamma`;
//! - final `norm`: `nn.LayerNorm(C)` with PyTorch's default eps **1e-5** (the blocks use 1e-6).
//!
//! Blocks after the last out layer do not change the outputs; they are not evaluated.
//!
//! On CPUs with AVX-512F the blocks' linear layers are packed at load time
//! ([`pixl_nn::Linear::pack_f32`]): same arithmetic up to the order of the sums.
use super::config::Da3Config;
use super::resize::bicubic_scale;
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::VarBuilder;
use pixl_nn::fused::{bias_act_rows, Act, Vector};
use pixl_nn::vit::{Block, BlockConfig};
use pixl_nn::LayerNorm;

/// LayerNorm eps of the blocks (`Block(ln_eps=1e-6)`).
pub const BLOCK_LN_EPS: f64 = 1e-6;
/// LayerNorm eps of the final norm (`nn.LayerNorm` default).
pub const FINAL_LN_EPS: f64 = 1e-5;
/// `DinoVisionTransformer.interpolate_offset`.
pub const INTERPOLATE_OFFSET: f64 = 0.1;

/// The blocks' shape: DINOv2's pre-norm block with LayerScale ([`pixl_nn::vit::Block`]).
fn block_config(cfg: &Da3Config) -> BlockConfig {
    BlockConfig {
        dim: cfg.net().embed_dim,
        heads: cfg.net().num_heads,
        mlp_hidden: cfg.mlp_hidden(),
        norm_eps: BLOCK_LN_EPS,
        layer_scale: true,
    }
}

/// The ViT backbone.
#[derive(Clone, Debug)]
pub struct Backbone {
    /// Patch-embedding weight as a `(3·p·p, C)` matrix (rows in `(channel, dy, dx)` order).
    patch_w: Tensor,
    patch_b: Vector,
    cls_token: Tensor,
    pos_embed: Tensor,
    blocks: Vec<Block>,
    norm: LayerNorm,
    out_layers: [usize; 4],
    patch: usize,
    pos_grid: usize,
    dim: usize,
}

impl Backbone {
    /// Every block's linear layers as 8-bit products where the CPU allows
    /// ([`pixl_nn::Linear::quantize_int8`]); returns how many.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        self.blocks.iter_mut().map(Block::quantize_int8).sum()
    }

    /// Reads `model.backbone.pretrained.*` under `vb` (already prefixed).
    pub fn new(cfg: &Da3Config, vb: VarBuilder) -> Result<Self> {
        let n = cfg.net();
        let (c, p, g) = (n.embed_dim, n.patch_size, cfg.pos_grid());
        let proj = vb.pp("patch_embed").pp("proj");
        let patch_w = proj
            .get((c, 3, p, p), "weight")?
            .reshape((c, 3 * p * p))?
            .t()?
            .contiguous()?;
        let patch_b = Vector::new(proj.get(c, "bias")?)?;
        let last = n.out_layers.iter().copied().max().unwrap_or(0);
        let block_cfg = block_config(cfg);
        let mut blocks = (0..=last)
            .map(|i| Block::new(&block_cfg, vb.pp("blocks").pp(i)))
            .collect::<Result<Vec<_>>>()?;
        // Inference only: on CPUs with AVX-512 the blocks' f32 weights live in the packed
        // kernel's layout (no dense copy kept), with bias, GELU and LayerScale residual fused.
        for block in &mut blocks {
            block.pack_f32()?;
        }
        Ok(Self {
            patch_w,
            patch_b,
            cls_token: vb.get((1, 1, c), "cls_token")?,
            pos_embed: vb.get((1, g * g + 1, c), "pos_embed")?,
            blocks,
            norm: LayerNorm::new(c, FINAL_LN_EPS, vb.pp("norm"))?,
            out_layers: n.out_layers,
            patch: p,
            pos_grid: g,
            dim: c,
        })
    }

    /// Patch size.
    pub fn patch(&self) -> usize {
        self.patch
    }

    /// `(B, 3, H, W)` → `(B, N, C)` patch tokens (no class token, no position embedding).
    fn patch_embed(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = xs.dims4()?;
        let p = self.patch;
        let (gh, gw) = (h / p, w / p);
        let rows = xs
            .reshape((b, c, gh, p, gw, p))?
            .permute((0, 2, 4, 1, 3, 5))?
            .contiguous()?
            .reshape((b * gh * gw, c * p * p))?;
        bias_act_rows(&rows.matmul(&self.patch_w)?, &self.patch_b, Act::None)?.reshape((b, gh * gw, self.dim))
    }

    /// The position embedding for a `(gh, gw)` grid, `(1, 1 + gh·gw, C)`, as
    /// `interpolate_pos_encoding`.
    pub fn pos_embed_for(&self, gh: usize, gw: usize) -> Result<Tensor> {
        let g = self.pos_grid;
        if gh == g && gw == g {
            return Ok(self.pos_embed.clone());
        }
        let c = self.dim;
        let cls = self.pos_embed.narrow(1, 0, 1)?;
        let grid = self
            .pos_embed
            .narrow(1, 1, g * g)?
            .reshape((g * g, c))?
            .t()?
            .contiguous()?; // (C, g²)
        let data = grid.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        let sy = (gh as f64 + INTERPOLATE_OFFSET) / g as f64;
        let sx = (gw as f64 + INTERPOLATE_OFFSET) / g as f64;
        let (out, oh, ow) = bicubic_scale(&data, c, g, g, sy, sx);
        if (oh, ow) != (gh, gw) {
            candle_core::bail!("position embedding resized to {oh}x{ow}, expected {gh}x{gw}");
        }
        let patch = Tensor::from_vec(out, (c, gh * gw), self.pos_embed.device())?
            .t()?
            .unsqueeze(0)?
            .to_dtype(self.pos_embed.dtype())?;
        Tensor::cat(&[&cls, &patch], 1)
    }

    /// Tokens entering block 0: `[cls; patches] + pos`, `(B, 1 + N, C)`.
    pub fn embed(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, _, h, w) = xs.dims4()?;
        let (gh, gw) = (h / self.patch, w / self.patch);
        let patches = self.patch_embed(xs)?;
        let cls = self.cls_token.broadcast_as((b, 1, self.dim))?;
        Tensor::cat(&[&cls, &patches], 1)?.broadcast_add(&self.pos_embed_for(gh, gw)?)
    }

    /// The four normalised out-layer features, each `(B, N, C)` (class token dropped).
    pub fn forward_features(&self, xs: &Tensor) -> Result<Vec<Tensor>> {
        let (_, c, h, w) = xs.dims4()?;
        if c != 3 {
            candle_core::bail!("DA3 backbone: expected a (B, 3, H, W) input, got {c} channels");
        }
        if h % self.patch != 0 || w % self.patch != 0 || h == 0 || w == 0 {
            candle_core::bail!(
                "DA3 backbone: input {w}x{h} is not a multiple of the patch size {}",
                self.patch
            );
        }
        let mut xs = self.embed(xs)?;
        // As the official `blocks_to_take`: outputs in block order.
        let mut feats = Vec::with_capacity(4);
        for (i, block) in self.blocks.iter().enumerate() {
            xs = block.forward(&xs, None)?;
            if self.out_layers.contains(&i) {
                let n = xs.dim(1)? - 1;
                feats.push(self.norm.forward(&xs.narrow(1, 1, n)?)?);
            }
        }
        Ok(feats)
    }
}
