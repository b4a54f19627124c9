//! The pre-norm transformer block of a ViT (timm `Block`, DINOv2's `Block`), shared by the
//! PIXLRelight source encoder and trunk (`pixl-model`) and the Depth Anything 3 backbone
//! (`pixl-estimate`):
//!
//! `x ← x + ls1 ⊙ attn(norm1(x))`, then `x ← x + ls2 ⊙ mlp(norm2(x))`
//!
//! on `(B, N, C)` tokens, same shape out. `norm1`, `norm2`: [`LayerNorm`] with the model's eps;
//! `attn`: multi-head softmax attention (scale `1/√(C/heads)`) with a fused, biased `qkv`
//! projection and `proj`, queries and keys optionally rotated by 2D RoPE ([`PatchRope`]);
//! `mlp`: [`Mlp`], `fc1 – GELU (erf) – fc2`; `ls1`, `ls2`: LayerScale, only in models that have
//! it ([`BlockConfig::layer_scale`]), otherwise 1.
//!
//! Weights under the block's prefix, as both checkpoints name them: `norm1.{weight,bias}`,
//! `attn.qkv.{weight,bias}`, `attn.proj.{weight,bias}`, `ls1.gamma`, `norm2.{weight,bias}`,
//! `mlp.fc1.{weight,bias}`, `mlp.fc2.{weight,bias}`, `ls2.gamma`.
//!
//! With no gradient needed, on the CPU in f32, every step takes pixl-nn's fused path (parallel
//! norm, GEMM with bias and GELU in place, 8-bit linear layers after [`Block::quantize_int8`],
//! fused attention, parallel residual adds); after [`Block::pack_f32`] the linear layers run
//! the packed AVX-512 kernel with the bias, GELU and LayerScale residual add in its epilogue;
//! otherwise candle's differentiable ops.
use crate::fused::{self, Act, Vector};
use crate::{LayerNorm, Linear, Mlp, Rope2d};
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

/// Shape and options of one [`Block`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BlockConfig {
    /// Token width `C`.
    pub dim: usize,
    /// Attention heads (`C` must be a multiple).
    pub heads: usize,
    /// Hidden width of the MLP.
    pub mlp_hidden: usize,
    /// LayerNorm eps of `norm1` and `norm2`.
    pub norm_eps: f64,
    /// Whether the residual branches are scaled by learned `ls1.gamma`, `ls2.gamma` (DINOv2).
    pub layer_scale: bool,
}

/// Rotary embedding for the patch tokens of a sequence whose first `prefix` tokens (registers)
/// are left unrotated.
pub struct PatchRope<'a> {
    pub rope: &'a Rope2d,
    pub prefix: usize,
}

/// Multi-head self-attention, fused `qkv` projection then `proj` (timm names).
#[derive(Clone, Debug)]
pub struct Attention {
    qkv: Linear,
    proj: Linear,
    heads: usize,
}

impl Attention {
    pub fn new(dim: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        let qkv = Linear::load(dim, 3 * dim, vb.pp("qkv"))?;
        let proj = Linear::load(dim, dim, vb.pp("proj"))?;
        Ok(Self { qkv, proj, heads })
    }

    /// 8-bit `qkv` and `proj` where the CPU allows ([`Linear::quantize_int8`]); returns how many.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        Ok(usize::from(self.qkv.quantize_int8()?) + usize::from(self.proj.quantize_int8()?))
    }

    pub fn int8_bytes(&self) -> usize {
        self.qkv.int8_bytes() + self.proj.int8_bytes()
    }

    /// `qkv` and `proj` packed for the AVX-512 f32 kernel ([`Linear::pack_f32`]); returns how
    /// many.
    pub fn pack_f32(&mut self) -> Result<usize> {
        Ok(usize::from(self.qkv.pack_f32()?) + usize::from(self.proj.pack_f32()?))
    }

    /// `residual + ls ⊙ attn(xs)`, the add in `proj`'s epilogue when its weights are packed
    /// ([`Linear::forward_residual`]), a separate pass otherwise.
    pub fn forward_residual(
        &self,
        xs: &Tensor,
        rope: Option<&PatchRope>,
        residual: &Tensor,
        ls: Option<&LayerScale>,
    ) -> Result<Tensor> {
        let qkv = self.qkv.forward_act(xs, Act::None)?;
        let out = fused::attention_qkv_rope(&qkv, self.heads, rope.map(|r| (r.rope, r.prefix)))?;
        drop(qkv);
        linear_residual(&self.proj, &out, residual, ls)
    }

    /// `(B, N, C)` → `(B, N, C)`; RoPE rotates queries and keys when given. On the CPU in f32
    /// the head split and the rotation are one pass ([`fused::attention_qkv_rope`]).
    pub fn forward(&self, xs: &Tensor, rope: Option<&PatchRope>) -> Result<Tensor> {
        let qkv = self.qkv.forward_act(xs, Act::None)?;
        let out = fused::attention_qkv_rope(&qkv, self.heads, rope.map(|r| (r.rope, r.prefix)))?;
        self.proj.forward_act(&out, Act::None)
    }
}

/// LayerScale: a learned per-channel factor `gamma` on a residual branch.
#[derive(Clone, Debug)]
pub struct LayerScale {
    gamma: Vector,
}

impl LayerScale {
    pub fn new(dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            gamma: Vector::new(vb.get(dim, "gamma")?)?,
        })
    }

    /// `xs + ys ⊙ gamma` (`gamma` over the last dim): one parallel pass
    /// ([`fused::add_scaled_rows`]) when no gradient is needed, candle's ops otherwise.
    pub fn add_to(&self, xs: &Tensor, ys: &Tensor) -> Result<Tensor> {
        if crate::needs_grad(&[xs, ys, &self.gamma.tensor]) {
            return xs + ys.broadcast_mul(&self.gamma.tensor)?;
        }
        fused::add_scaled_rows(xs, ys, &self.gamma)
    }
}

/// The pre-norm block (see the module notes).
#[derive(Clone, Debug)]
pub struct Block {
    norm1: LayerNorm,
    attn: Attention,
    ls1: Option<LayerScale>,
    norm2: LayerNorm,
    mlp: Mlp,
    ls2: Option<LayerScale>,
}

impl Block {
    pub fn new(cfg: &BlockConfig, vb: VarBuilder) -> Result<Self> {
        let c = cfg.dim;
        let layer_scale = |name: &str| cfg.layer_scale.then(|| LayerScale::new(c, vb.pp(name))).transpose();
        Ok(Self {
            norm1: LayerNorm::new(c, cfg.norm_eps, vb.pp("norm1"))?,
            attn: Attention::new(c, cfg.heads, vb.pp("attn"))?,
            ls1: layer_scale("ls1")?,
            norm2: LayerNorm::new(c, cfg.norm_eps, vb.pp("norm2"))?,
            mlp: Mlp::new(c, cfg.mlp_hidden, c, vb.pp("mlp"))?,
            ls2: layer_scale("ls2")?,
        })
    }

    /// The attention's and the MLP's linear layers in 8 bits where the CPU allows; returns how
    /// many.
    pub fn quantize_int8(&mut self) -> Result<usize> {
        Ok(self.attn.quantize_int8()? + self.mlp.quantize_int8()?)
    }

    pub fn int8_bytes(&self) -> usize {
        self.attn.int8_bytes() + self.mlp.int8_bytes()
    }

    /// The attention's and the MLP's linear layers packed for the AVX-512 f32 kernel
    /// ([`Linear::pack_f32`], inference only); returns how many.
    pub fn pack_f32(&mut self) -> Result<usize> {
        Ok(self.attn.pack_f32()? + usize::from(self.mlp.fc1.pack_f32()?) + usize::from(self.mlp.fc2.pack_f32()?))
    }

    /// `(B, N, C)` → `(B, N, C)`; `rope` rotates the attention's queries and keys when given.
    pub fn forward(&self, xs: &Tensor, rope: Option<&PatchRope>) -> Result<Tensor> {
        let xs = self
            .attn
            .forward_residual(&self.norm1.forward(xs)?, rope, xs, self.ls1.as_ref())?;
        let hidden = self.mlp.fc1.forward_act(&self.norm2.forward(&xs)?, Act::Gelu)?;
        linear_residual(&self.mlp.fc2, &hidden, &xs, self.ls2.as_ref())
    }
}

/// `residual + ls ⊙ linear(xs)`: in the packed kernel's epilogue where it applies, otherwise the
/// linear layer then [`add_branch`].
fn linear_residual(linear: &Linear, xs: &Tensor, residual: &Tensor, ls: Option<&LayerScale>) -> Result<Tensor> {
    let differentiable_scale = ls.is_some_and(|l| crate::needs_grad(&[&l.gamma.tensor]));
    if !differentiable_scale {
        if let Some(out) = linear.forward_residual(xs, residual, ls.map(|l| &l.gamma))? {
            return Ok(out);
        }
    }
    add_branch(residual, &linear.forward(xs)?, ls)
}

/// `xs + ls ⊙ ys`, or the plain residual add without LayerScale.
fn add_branch(xs: &Tensor, ys: &Tensor, ls: Option<&LayerScale>) -> Result<Tensor> {
    match ls {
        Some(ls) => ls.add_to(xs, ys),
        None => fused::residual(xs, ys),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{max_abs_diff, uniform};
    use candle_core::{DType, Device};
    use candle_nn::VarMap;
    use std::collections::HashMap;

    /// With LayerScale, as DINOv2: trained (variables) every weight gets a gradient, and frozen
    /// copies of the same weights (the fused inference path) give the same output.
    #[test]
    fn layer_scale_block_trains_and_matches_its_inference_path() -> Result<()> {
        let dev = Device::Cpu;
        let cfg = BlockConfig {
            dim: 16,
            heads: 2,
            mlp_hidden: 24,
            norm_eps: 1e-6,
            layer_scale: true,
        };
        let varmap = VarMap::new();
        let trained = Block::new(&cfg, VarBuilder::from_varmap(&varmap, DType::F32, &dev))?;
        let mut frozen = HashMap::new();
        for (i, (name, var)) in varmap.data().lock().unwrap().iter().enumerate() {
            var.set(&uniform(var.dims(), -0.5, 0.5, i as u64, &dev)?.to_dtype(DType::F32)?)?;
            frozen.insert(name.clone(), var.as_tensor().copy()?.detach());
        }
        let inference = Block::new(&cfg, VarBuilder::from_tensors(frozen, DType::F32, &dev))?;
        let xs = uniform((2, 5, 16), -1.0, 1.0, 99, &dev)?.to_dtype(DType::F32)?;
        let ys = trained.forward(&xs, None)?;
        let diff = max_abs_diff(&ys, &inference.forward(&xs, None)?)?;
        assert!(diff < 1e-5, "trained and inference paths differ by {diff}");
        // Packed for the AVX-512 kernel (bias, GELU and LayerScale residual in its epilogue).
        let mut packed = inference.clone();
        let layers = packed.pack_f32()?;
        assert_eq!(layers, if crate::packed::available() { 4 } else { 0 });
        let diff = max_abs_diff(&ys, &packed.forward(&xs, None)?)?;
        assert!(diff < 1e-5, "trained and packed paths differ by {diff}");
        let grads = ys.sqr()?.sum_all()?.backward()?;
        let data = varmap.data().lock().unwrap();
        assert_eq!(data.len(), 14, "norms, qkv, proj, fc1, fc2 (weight, bias) and ls1, ls2");
        for (name, var) in data.iter() {
            let g = grads.get(var.as_tensor());
            assert!(g.is_some(), "{name}: no gradient");
        }
        Ok(())
    }
}
