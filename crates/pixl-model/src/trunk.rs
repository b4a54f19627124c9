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
use crate::vit::{block_config, tokens_to_grid, Block, PatchRope};
use candle_core::{Device, Module, Result, Tensor};
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
    /// Every block's linear layers in 8 bits where the CPU allows; returns how many.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        self.blocks.iter_mut().map(Block::quantize_int8).sum()
    }

    pub fn int8_bytes(&self) -> usize {
        self.blocks.iter().map(Block::int8_bytes).sum()
    }

    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        let t = &cfg.trunk;
        let init = candle_nn::Init::Randn { mean: 0.0, stdev: 0.02 };
        let registers = vb.get_with_hints((1, t.registers, cfg.dim), "registers", init)?;
        let block_cfg = block_config(cfg, t.heads, t.mlp_ratio, t.layer_scale);
        let blocks = (0..t.depth)
            .map(|i| Block::new(&block_cfg, vb.pp("blocks").pp(i)))
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
        let (_b, n, _d) = tokens.dims3()?;
        if n != gh * gw {
            candle_core::bail!("trunk: {n} tokens do not form a {gh}×{gw} grid");
        }
        let grid = self.grid(gh, gw, tokens.device())?;
        let mut xs = self.with_registers(tokens)?;
        let mut outs = Vec::with_capacity(4);
        for i in 0..self.blocks.len() {
            xs = self.block(i, &xs, &grid)?;
            if self.readouts.contains(&i) {
                outs.push(self.readout(&xs, &grid)?);
            }
        }
        Ok(outs)
    }

    // Segment API (gradient checkpointing). `forward` is exactly `with_registers`, then
    // `block(i)` for every `i`, with `readout` applied to the outputs of the `readouts` blocks;
    // a caller that runs the same calls on the same values gets bitwise the same results.

    /// Number of blocks.
    pub fn depth(&self) -> usize {
        self.blocks.len()
    }

    /// The (zero-based, increasing) blocks whose outputs are read out.
    pub fn readouts(&self) -> [usize; 4] {
        self.readouts
    }

    /// The RoPE tables and token layout of a `(gh, gw)` grid (tokens `(B, gh·gw, d)`).
    pub fn grid(&self, gh: usize, gw: usize, device: &Device) -> Result<TrunkGrid> {
        let rope = Rope2d::new(self.head_dim, gh, gw, self.rope_base, device)?;
        Ok(TrunkGrid {
            rope,
            prefix: self.registers.dim(1)?,
            gh,
            gw,
        })
    }

    /// The registers prepended to `tokens`: `(B, R + N, d)`, the input of block 0.
    pub fn with_registers(&self, tokens: &Tensor) -> Result<Tensor> {
        let (b, _n, d) = tokens.dims3()?;
        let r = self.registers.dim(1)?;
        if r == 0 {
            return Ok(tokens.clone());
        }
        let registers = self.registers.to_dtype(tokens.dtype())?.broadcast_as((b, r, d))?;
        Tensor::cat(&[&registers, tokens], 1)
    }

    /// Block `i` on `(B, R + N, d)`.
    pub fn block(&self, i: usize, xs: &Tensor, grid: &TrunkGrid) -> Result<Tensor> {
        let block = self
            .blocks
            .get(i)
            .ok_or_else(|| candle_core::Error::Msg(format!("trunk: no block {i} (depth {})", self.blocks.len())))?;
        let rope = PatchRope {
            rope: &grid.rope,
            prefix: grid.prefix,
        };
        block.forward(xs, Some(&rope))
    }

    /// A block output `(B, R + N, d)` (`N = gh·gw` of `grid`) → its readout map `(B, d, gh, gw)` (registers dropped,
    /// shared final norm).
    pub fn readout(&self, xs: &Tensor, grid: &TrunkGrid) -> Result<Tensor> {
        let n = grid.gh * grid.gw;
        let patches = self.norm.forward(&xs.narrow(1, grid.prefix, n)?.contiguous()?)?;
        tokens_to_grid(&patches, grid.gh, grid.gw)
    }
}

/// What the trunk's blocks need to know about one input grid (see [`Trunk::grid`]).
#[derive(Clone, Debug)]
pub struct TrunkGrid {
    rope: Rope2d,
    prefix: usize,
    gh: usize,
    gw: usize,
}
