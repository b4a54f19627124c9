//! [`PixlRelight`] (paper §3.2, Fig. 2): `Î_T = f_θ(I_S, C_T)`.
//!
//! `forward(src, ct)`: `src` `(B, 3, H, W)` in `[0, 1]`, `ct` `(B, 9, H, W)` = `[A_T; S_T; R_T]`,
//! any `H, W ≥ 1` (aspect 1:3 to 3:1 and beyond); returns `(B, 3, H, W)` f32 in `[0, 1]`.
//!
//! Pipeline: pad both inputs on the bottom and right to multiples of the patch size `p` (16) by
//! **replicating the edge** (reflection is undefined for a 1-pixel image; replication never invents new values),
//! `src_encoder` (ViT) and `cond_encoder` (ConvNeXt) → per-location `fuse` → `trunk` (registers,
//! 2D RoPE) → four readouts → `head` (DPT) → `modulation` (1×1 conv → gain, bias), cropped back
//! to `(H, W)` and applied to the unpadded source in f32.
//!
//! Inputs are cast to the weights' dtype (f32 or bf16) for the network itself.
use crate::config::Config;
use crate::convnext::ConvNextEncoder;
use crate::dpt::DptHead;
use crate::fusion::Fusion;
use crate::modulation::Modulation;
use crate::trunk::{Trunk, TrunkGrid};
use crate::vit::VitEncoder;
use candle_core::{DType, Result, Tensor};
use candle_nn::VarBuilder;

/// The PIXLRelight network. Field names are the checkpoint's top-level prefixes.
#[derive(Clone, Debug)]
pub struct PixlRelight {
    src_encoder: VitEncoder,
    cond_encoder: ConvNextEncoder,
    fuse: Fusion,
    trunk: Trunk,
    head: DptHead,
    modulation: Modulation,
    cfg: Config,
    dtype: DType,
}

/// Pads `(B, C, H, W)` on the bottom/right to `(ph, pw)` by edge replication.
fn pad_replicate(xs: &Tensor, ph: usize, pw: usize) -> Result<Tensor> {
    let (_b, _c, h, w) = xs.dims4()?;
    let xs = if ph > h {
        xs.pad_with_same(2, 0, ph - h)?
    } else {
        xs.clone()
    };
    if pw > w {
        xs.pad_with_same(3, 0, pw - w)
    } else {
        Ok(xs)
    }
}

impl PixlRelight {
    /// Builds the network from `vb` (a `VarMap` for training, loaded tensors for inference).
    /// The weights' dtype is `vb.dtype()`. Validates `cfg` first.
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        cfg.validate().map_err(candle_core::Error::wrap)?;
        Ok(Self {
            src_encoder: VitEncoder::new(cfg, vb.pp("src_encoder"))?,
            cond_encoder: ConvNextEncoder::new(cfg, vb.pp("cond_encoder"))?,
            fuse: Fusion::new(cfg, vb.pp("fuse"))?,
            trunk: Trunk::new(cfg, vb.pp("trunk"))?,
            head: DptHead::new(cfg, vb.pp("head"))?,
            modulation: Modulation::new(cfg.head.hidden, vb.pp("modulation"))?,
            cfg: cfg.clone(),
            dtype: vb.dtype(),
        })
    }

    pub fn config(&self) -> &Config {
        &self.cfg
    }

    /// Switches inference on the CPU to 8-bit matrix products for the linear layers of the
    /// encoders, the fusion and the trunk ([`pixl_nn::int8`]: weights per output channel,
    /// activations per token, AVX-512 VNNI), leaving convolutions, attention and norms in f32.
    /// Returns how many layers were quantized: 0 where the CPU has no kernel (everything stays
    /// f32). Refused for a network being trained. See `BENCHMARKS.md` for its speed and its
    /// error against f32.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        Ok(self.src_encoder.quantize_int8()?
            + self.cond_encoder.quantize_int8()?
            + self.fuse.quantize_int8()?
            + self.trunk.quantize_int8()?)
    }

    /// Bytes the 8-bit copies of [`PixlRelight::quantize_int8`] hold besides the f32 weights
    /// (about a quarter of the quantized layers' f32 bytes; 0 before quantizing). Not in
    /// [`crate::fullres::plan_memory`], which plans the f32 network: add it.
    pub fn int8_bytes(&self) -> u64 {
        (self.src_encoder.int8_bytes()
            + self.cond_encoder.int8_bytes()
            + self.fuse.int8_bytes()
            + self.trunk.int8_bytes()) as u64
    }

    /// The dtype the network computes in.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// `Î_T = clip((1 + g) ⊙ I_S + b, 0, 1)` for `src` `(B, 3, H, W)`, `ct` `(B, 9, H, W)`.
    pub fn forward(&self, src: &Tensor, ct: &Tensor) -> Result<Tensor> {
        let (g, b) = self.gain_bias(src, ct)?;
        Modulation::apply(&src.to_dtype(DType::F32)?, &g, &b)
    }

    /// `(1 + g) ⊙ I_S + b` **before** the clip, f32 `(B, 3, H, W)`: what training hands to its
    /// loss, which applies the clip itself (`pixl_train::loss::loss`), so the loss sees the
    /// clipped output and a pixel pushed past 0 or 1 passes no gradient (the paper's form).
    pub fn forward_unclipped(&self, src: &Tensor, ct: &Tensor) -> Result<Tensor> {
        let gb = self.modulation.gain_bias_stacked(&self.padded_features(src, ct)?)?;
        crate::modulation::affine_padded(&src.to_dtype(DType::F32)?, &gb)
    }

    /// The unclipped gain and bias maps `(B, 3, H, W)` each, f32 (for inspection and tests).
    pub fn gain_bias(&self, src: &Tensor, ct: &Tensor) -> Result<(Tensor, Tensor)> {
        let (_b, _c, h, w) = src.dims4()?;
        let (g, bias) = self.modulation.gain_bias(&self.padded_features(src, ct)?)?;
        let crop = |t: Tensor| -> Result<Tensor> { t.narrow(2, 0, h)?.narrow(3, 0, w) };
        Ok((crop(g)?, crop(bias)?))
    }

    /// The DPT map `F` `(B, C', H, W)` fed to the modulation conv, cropped to the input size.
    pub fn features(&self, src: &Tensor, ct: &Tensor) -> Result<Tensor> {
        let (_b, _c, h, w) = src.dims4()?;
        self.padded_features(src, ct)?.narrow(2, 0, h)?.narrow(3, 0, w)
    }

    /// `F` at the padded size `(B, C', p⌈H/p⌉, p⌈W/p⌉)`.
    fn padded_features(&self, src: &Tensor, ct: &Tensor) -> Result<Tensor> {
        let p = self.prepare(src, ct)?;
        let src_tokens = self.src_encoder.forward(&p.src)?;
        let cond_tokens = self.cond_encoder.forward(&p.ct)?;
        let tokens = self.fuse.forward(&src_tokens, &cond_tokens)?;
        let readouts = self.trunk.forward(&tokens, p.gh, p.gw)?;
        self.head.forward(&readouts, p.ph, p.pw)
    }

    // ---- Segment API (gradient checkpointing in pixl-train) ----
    //
    // `forward_unclipped(src, ct)` is exactly, in this order of operations:
    //   p = prepare(src, ct)
    //   x = src_encoder().embed(&p.src); x = src_encoder().block(j, &x) for every j
    //   h = fuse_tokens(&x, &cond_tokens(&p))
    //   h = trunk().block(i, &h, &p.grid) for every i, keeping the outputs of trunk().readouts()
    //   tail_unclipped(&those four outputs, src, &p)
    // so a caller that cuts the pass at these points (and recomputes a segment from its stored
    // input) gets bitwise the same values as the plain forward. Tensor names are unchanged.

    /// Checks shapes, pads to multiples of the patch size (edge replication) and casts to the weights' dtype.
    pub fn prepare(&self, src: &Tensor, ct: &Tensor) -> Result<Prepared> {
        let (b, c, h, w) = src.dims4()?;
        let (cb, cc, ch, cw) = ct.dims4()?;
        if c != 3 || cc != 9 || (b, h, w) != (cb, ch, cw) {
            candle_core::bail!(
                "PixlRelight: source must be (B, 3, H, W) and C_T (B, 9, H, W) of the same B, H, W; got {:?} and {:?}",
                src.shape(),
                ct.shape()
            );
        }
        if h == 0 || w == 0 {
            candle_core::bail!("PixlRelight: empty image {h}×{w}");
        }
        let p = self.cfg.patch;
        let (ph, pw) = (h.div_ceil(p) * p, w.div_ceil(p) * p);
        let (gh, gw) = (ph / p, pw / p);
        Ok(Prepared {
            src: pad_replicate(&src.to_dtype(self.dtype)?, ph, pw)?,
            ct: pad_replicate(&ct.to_dtype(self.dtype)?, ph, pw)?,
            h,
            w,
            ph,
            pw,
            gh,
            gw,
            grid: self.trunk.grid(gh, gw, src.device())?,
        })
    }

    /// The source encoder (its `embed`, `block`, `depth` are segment points).
    pub fn src_encoder(&self) -> &VitEncoder {
        &self.src_encoder
    }

    /// The trunk (its `block`, `depth`, `readouts` are segment points).
    pub fn trunk(&self) -> &Trunk {
        &self.trunk
    }

    /// The intrinsics encoder's tokens `(B, N, d)` of the padded C_T.
    pub fn cond_tokens(&self, p: &Prepared) -> Result<Tensor> {
        self.cond_encoder.forward(&p.ct)
    }

    /// Last source-encoder block output and conditioning tokens → trunk block 0's input
    /// `(B, R + N, d)` (the encoder's final norm, the fusion MLP, the registers).
    pub fn fuse_tokens(&self, src_blocks_out: &Tensor, cond_tokens: &Tensor) -> Result<Tensor> {
        let src_tokens = self.src_encoder.finish(src_blocks_out)?;
        let tokens = self.fuse.forward(&src_tokens, cond_tokens)?;
        self.trunk.with_registers(&tokens)
    }

    /// The outputs of the four readout blocks (in `trunk().readouts()` order) → the unclipped
    /// prediction `(1 + g) ⊙ I_S + b`, f32 `(B, 3, H, W)`, as [`Self::forward_unclipped`].
    pub fn tail_unclipped(&self, readout_blocks: &[Tensor], src: &Tensor, p: &Prepared) -> Result<Tensor> {
        let readouts = readout_blocks
            .iter()
            .map(|xs| self.trunk.readout(xs, &p.grid))
            .collect::<Result<Vec<_>>>()?;
        let gb = self
            .modulation
            .gain_bias_stacked(&self.head.forward(&readouts, p.ph, p.pw)?)?;
        crate::modulation::affine_padded(&src.to_dtype(DType::F32)?, &gb)
    }

    /// The outputs of the four readout blocks → the gain and bias maps `(B, 3, H, W)` f32,
    /// cropped to the input size, as [`Self::gain_bias`] computes them.
    pub fn tail_gain_bias(&self, readout_blocks: &[Tensor], p: &Prepared) -> Result<(Tensor, Tensor)> {
        let readouts = readout_blocks
            .iter()
            .map(|xs| self.trunk.readout(xs, &p.grid))
            .collect::<Result<Vec<_>>>()?;
        let (g, bias) = self.modulation.gain_bias(&self.head.forward(&readouts, p.ph, p.pw)?)?;
        let crop = |t: Tensor| -> Result<Tensor> { t.narrow(2, 0, p.h)?.narrow(3, 0, p.w) };
        Ok((crop(g)?, crop(bias)?))
    }
}

/// One forward pass's padded inputs and grid (see [`PixlRelight::prepare`]).
#[derive(Clone, Debug)]
pub struct Prepared {
    /// `(B, 3, ph, pw)` source in the network's dtype.
    pub src: Tensor,
    /// `(B, 9, ph, pw)` C_T in the network's dtype.
    pub ct: Tensor,
    pub h: usize,
    pub w: usize,
    pub ph: usize,
    pub pw: usize,
    pub gh: usize,
    pub gw: usize,
    pub grid: TrunkGrid,
}
