//! Transformer trunk `trunk` (paper §3.2 "Transformer Trunk"): `L` pre-norm self-attention
//! blocks over the fused tokens, with `registers` learnable tokens prepended and 2D RoPE
//! (base 100) on the patch tokens only.
//!
//! Input `(B, N, d)` fused tokens of a `(gh, gw)` grid; output the four readouts (blocks
//! `trunk.readouts`, zero-based) as `(B, d, gh, gw)` maps, register tokens dropped.
//!
//! Choices where the paper is silent:
//! - registers (`trunk.registers`, `(1, R, d)`) carry no position and are not rotated; RoPE
//!   rotates queries and keys of patch tokens by their (row, column) ([`pixl_nn::Rope2d`]);
//! - each readout goes through one shared final LayerNorm `trunk.norm`, as Depth Anything
//!   normalises the intermediate layers it reads from DINOv2;
//! - the last readout must be the last block (a block after it would be dead weight);
//!   [`Config::validate`] checks it.
use crate::config::Config;
use crate::vit::{tokens_to_grid, Block, PatchRope};
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;
use pixl_nn::{LayerNorm, Rope2d};

#[derive(Clone, Debug)]
pub struct Trunk {
    registers: Tensor,
    blocks: Vec<Block>,
    norm: LayerNorm,
    readouts: [usize; 4],
    head_dim: usize,
    rope_base: f64,
}

impl Trunk {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        let t = &cfg.trunk;
        let init = candle_nn::Init::Randn { mean: 0.0, stdev: 0.02 };
        let registers = vb.get_with_hints((1, t.registers, cfg.dim), "registers", init)?;
        let blocks = (0..t.depth)
            .map(|i| Block::new(cfg.dim, t.heads, t.mlp_ratio, cfg.norm_eps, vb.pp("blocks").pp(i)))
            .collect::<Result<Vec<_>>>()?;
        let norm = LayerNorm::new(cfg.dim, cfg.norm_eps, vb.pp("norm"))?;
        Ok(Self {
            registers,
            blocks,
            norm,
            readouts: t.readouts,
            head_dim: cfg.trunk_head_dim(),
            rope_base: t.rope_base,
        })
    }

    /// Fused tokens `(B, gh·gw, d)` → the four readout maps `(B, d, gh, gw)`.
    pub fn forward(&self, tokens: &Tensor, gh: usize, gw: usize) -> Result<Vec<Tensor>> {
        let (b, n, d) = tokens.dims3()?;
        if n != gh * gw {
            candle_core::bail!("trunk: {n} tokens do not form a {gh}×{gw} grid");
        }
        let r = self.registers.dim(1)?;
        let rope = Rope2d::new(self.head_dim, gh, gw, self.rope_base, tokens.device())?;
        let rope = PatchRope { rope: &rope, prefix: r };
        let registers = self.registers.to_dtype(tokens.dtype())?.broadcast_as((b, r, d))?;
        let mut xs = if r == 0 {
            tokens.clone()
        } else {
            Tensor::cat(&[&registers, tokens], 1)?
        };
        let mut outs = Vec::with_capacity(4);
        for (i, block) in self.blocks.iter().enumerate() {
            xs = block.forward(&xs, Some(&rope))?;
            if self.readouts.contains(&i) {
                let patches = self.norm.forward(&xs.narrow(1, r, n)?.contiguous()?)?;
                outs.push(tokens_to_grid(&patches, gh, gw)?);
            }
        }
        Ok(outs)
    }
}
