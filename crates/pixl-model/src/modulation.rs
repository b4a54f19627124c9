//! Modulation `modulation` (paper §3.2 "Modulation Head", Eq. 4): a 1×1 conv maps the DPT map
//! `F` to six channels, split into gain `g` (channels 0–2) and bias `b` (channels 3–5), and
//! `Î_T = clip((1 + g) ⊙ I_S + b, 0, 1)`.
//!
//! `modulation.conv` is zero-initialised (weight and bias) by [`crate::checkpoint::build_trainable`],
//! so `g ≡ b ≡ 0` and an untrained network returns `I_S` exactly. The affine step runs in f32
//! whatever the network's dtype, on the caller's unpadded f32 source, so the identity is
//! bitwise for any `I_S ∈ [0, 1]`. Gradients pass through the clip where `0 < Î_T < 1`.
//!
//! Training takes the affine step straight from the conv's padded output ([`affine_padded`]):
//! on the CPU in f32 one op (split, crop, `(1 + g) ⊙ I_S + b`) with its own backward instead of
//! six of candle's, each with a full-size gradient.
use crate::layers::Conv;
use candle_core::{CpuStorage, CustomOp2, DType, Layout, Module, Result, Shape, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};

#[derive(Clone, Debug)]
pub struct Modulation {
    conv: Conv,
}

impl Modulation {
    pub fn new(hidden: usize, vb: VarBuilder) -> Result<Self> {
        let zero = candle_nn::Init::Const(0.0);
        let weight = vb.pp("conv").get_with_hints((6, hidden, 1, 1), "weight", zero)?;
        let bias = vb.pp("conv").get_with_hints(6, "bias", zero)?;
        Ok(Self {
            conv: Conv(candle_nn::Conv2d::new(weight, Some(bias), Conv2dConfig::default())),
        })
    }

    /// `F` `(B, C', H', W')` → gain and bias maps `(B, 3, H', W')` each, f32.
    pub fn gain_bias(&self, features: &Tensor) -> Result<(Tensor, Tensor)> {
        let gb = self.gain_bias_stacked(features)?;
        Ok((gb.narrow(1, 0, 3)?, gb.narrow(1, 3, 3)?))
    }

    /// `F` → gain (channels 0–2) and bias (3–5) in one `(B, 6, H', W')` f32 map.
    pub fn gain_bias_stacked(&self, features: &Tensor) -> Result<Tensor> {
        self.conv.forward(features)?.to_dtype(DType::F32)
    }

    /// `clip((1 + g) ⊙ src + b, 0, 1)`; `src`, `g`, `b` all `(B, 3, H, W)` f32.
    pub fn apply(src: &Tensor, g: &Tensor, b: &Tensor) -> Result<Tensor> {
        Self::affine(src, g, b)?.clamp(0f32, 1f32)
    }

    /// The affine step before the clip, `(1 + g) ⊙ src + b` (what training takes its pixel loss on).
    pub fn affine(src: &Tensor, g: &Tensor, b: &Tensor) -> Result<Tensor> {
        (g + 1.0)?.mul(src)? + b
    }
}

/// `(1 + g) ⊙ src + b` for `src` `(B, 3, H, W)` f32 and the stacked gain/bias map `gb`
/// `(B, 6, H', W')` f32 at the padded size (`H' ≥ H`, `W' ≥ W`), cropped to `H × W`: the same
/// values as [`Modulation::affine`] on `gb`'s narrowed and cropped halves. On the CPU one op whose
/// backward gives `∂/∂g = grad ⊙ src`, `∂/∂b = grad` (zero on the padding) and nothing for `src`
/// (the photo); elsewhere the composed ops.
pub fn affine_padded(src: &Tensor, gb: &Tensor) -> Result<Tensor> {
    let (b, c, h, w) = src.dims4()?;
    let (gb_b, gb_c, ph, pw) = gb.dims4()?;
    if c != 3 || gb_c != 6 || gb_b != b || ph < h || pw < w {
        candle_core::bail!(
            "modulation: source {:?} and gain/bias {:?} do not fit",
            src.dims(),
            gb.dims()
        );
    }
    let cpu_f32 = |t: &Tensor| t.device().is_cpu() && t.dtype() == DType::F32;
    if !(cpu_f32(src) && cpu_f32(gb)) || src.track_op() {
        let crop = |t: Tensor| -> Result<Tensor> { t.narrow(2, 0, h)?.narrow(3, 0, w) };
        let (g, bias) = (crop(gb.narrow(1, 0, 3)?)?, crop(gb.narrow(1, 3, 3)?)?);
        return Modulation::affine(src, &g, &bias);
    }
    gb.contiguous()?.apply_op2(&src.contiguous()?, AffinePadded)
}

/// The CPU op of [`affine_padded`]: arguments `(gb, src)`.
struct AffinePadded;

fn f32s<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        _ => candle_core::bail!("modulation: expected contiguous f32 tensors"),
    }
}

impl CustomOp2 for AffinePadded {
    fn name(&self) -> &'static str {
        "modulation-affine"
    }

    fn cpu_fwd(&self, gs: &CpuStorage, gl: &Layout, ss: &CpuStorage, sl: &Layout) -> Result<(CpuStorage, Shape)> {
        let (gb, src) = (f32s(gs, gl)?, f32s(ss, sl)?);
        let (b, _, ph, pw) = gl.shape().dims4()?;
        let (_, c, h, w) = sl.shape().dims4()?;
        let mut out = vec![0f32; src.len()];
        for bi in 0..b {
            for ci in 0..c {
                let plane = (bi * c + ci) * h * w;
                let (g0, b0) = ((bi * 6 + ci) * ph * pw, (bi * 6 + 3 + ci) * ph * pw);
                for y in 0..h {
                    let (g, bias) = (&gb[g0 + y * pw..][..w], &gb[b0 + y * pw..][..w]);
                    let (s, o) = (&src[plane + y * w..][..w], &mut out[plane + y * w..][..w]);
                    for x in 0..w {
                        o[x] = (g[x] + 1.0) * s[x] + bias[x];
                    }
                }
            }
        }
        Ok((CpuStorage::F32(out), sl.shape().clone()))
    }

    fn bwd(&self, gb: &Tensor, src: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let d_gb = grad
            .contiguous()?
            .apply_op2_no_bwd(&src.contiguous()?, &AffinePaddedGrad { size: gb.dims4()? })?;
        Ok((Some(d_gb), None))
    }
}

/// The backward of [`AffinePadded`]: `(grad, src)` → `∂/∂gb` `(B, 6, H', W')`.
struct AffinePaddedGrad {
    size: (usize, usize, usize, usize),
}

impl CustomOp2 for AffinePaddedGrad {
    fn name(&self) -> &'static str {
        "modulation-affine-grad"
    }

    fn cpu_fwd(&self, gs: &CpuStorage, gl: &Layout, ss: &CpuStorage, sl: &Layout) -> Result<(CpuStorage, Shape)> {
        let (grad, src) = (f32s(gs, gl)?, f32s(ss, sl)?);
        let (b, six, ph, pw) = self.size;
        let (_, c, h, w) = sl.shape().dims4()?;
        let mut out = vec![0f32; b * six * ph * pw];
        for bi in 0..b {
            for ci in 0..c {
                let plane = (bi * c + ci) * h * w;
                let (g0, b0) = ((bi * 6 + ci) * ph * pw, (bi * 6 + 3 + ci) * ph * pw);
                for y in 0..h {
                    let (gr, s) = (&grad[plane + y * w..][..w], &src[plane + y * w..][..w]);
                    for x in 0..w {
                        out[g0 + y * pw + x] = gr[x] * s[x];
                        out[b0 + y * pw + x] = gr[x];
                    }
                }
            }
        }
        Ok((CpuStorage::F32(out), Shape::from(self.size)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// The CPU op against the composed narrow/crop/affine ops on a padded map: values and the
    /// gradient of `Σ out ⊙ G` with respect to the map (zero on the padding).
    #[test]
    fn affine_padded_equals_the_composed_ops() -> Result<()> {
        let dev = Device::Cpu;
        let (b, h, w, ph, pw) = (2, 5, 7, 8, 9);
        let src = pixl_nn::testing::uniform((b, 3, h, w), 0.0, 1.0, 1, &dev)?.to_dtype(DType::F32)?;
        let gb =
            Var::from_tensor(&pixl_nn::testing::uniform((b, 6, ph, pw), -1.0, 1.0, 2, &dev)?.to_dtype(DType::F32)?)?;
        let g = pixl_nn::testing::uniform((b, 3, h, w), -1.0, 1.0, 3, &dev)?.to_dtype(DType::F32)?;
        let fused = affine_padded(&src, gb.as_tensor())?;
        let crop = |t: Tensor| -> Result<Tensor> { t.narrow(2, 0, h)?.narrow(3, 0, w) };
        let t = gb.as_tensor();
        let composed = Modulation::affine(&src, &crop(t.narrow(1, 0, 3)?)?, &crop(t.narrow(1, 3, 3)?)?)?;
        assert_eq!(pixl_nn::testing::max_abs_diff(&fused, &composed)?, 0.0);
        let grad = |y: &Tensor| -> Result<Tensor> {
            let store = (y * &g)?.sum_all()?.backward()?;
            Ok(store.get(gb.as_tensor()).expect("gradient").clone())
        };
        let d = pixl_nn::testing::max_abs_diff(&grad(&fused)?, &grad(&composed)?)?;
        assert!(d < 1e-7, "{d}");
        Ok(())
    }
}
