//! The training loss (paper eq. 5): `L = ‖Î_T − I_T‖₁ + λ · L_perc(Î_T, I_T)`, λ = 0.2.
//!
//! - The pixel term is the mean absolute error over all `B·3·H·W` values (images in [0, 1]).
//! - The perceptual term is an **L1** distance between VGG16 features (torchvision layout,
//!   [`pixl_nn::backbones::Vgg16`]) of ImageNet-normalised inputs, at the five post-ReLU taps
//!   relu1_2, relu2_2, relu3_3, relu4_3, relu5_3: the mean absolute difference of each tap,
//!   averaged over the five taps with equal weight. The VGG weights are frozen (loaded as
//!   constants, never `Var`s), so only the network receives gradients.
//! - An optional structural term **not in the paper**, `μ · (1 − SSIM(Î_T, I_T))` ([`ssim`]; `[loss]
//!   ssim_weight`, default 0): where no VGG weights are at hand it is the perceptual-side term we can
//!   afford, and it rewards the local contrast a pure L1 objective tends to blur. It uses the
//!   evaluation's SSIM (`pixl_eval::metrics::ssim`: 11×11 Gaussian σ 1.5, valid window, K1 0.01,
//!   K2 0.03), averaged over images and channels.
//! - An optional **scale-corrected** share of the pixel term, **not in the paper** (`[loss]
//!   scale_corrected` = ν, default 0): `(1 − ν)·‖Î_T − I_T‖₁ + ν·‖clip(s ⊙ Î_T, 0, 1) − I_T‖₁`, with
//!   `s` the evaluation's per-image, per-channel least-squares scale (`pixl_eval::metrics::
//!   scale_correct`: `s_c = Σ I_T·Î_T / Σ Î_T²`, held constant in the backward pass and kept within
//!   `[1/4, 4]`). The evaluation forgives a prediction's exposure and per-channel gain; this share
//!   stops spending the gradient on them ([`scale_corrected_l1`]).
use crate::error::{Result, TrainError};
use candle_core::{CpuStorage, CustomOp2, DType, Device, Layout, Shape, Tensor};
use pixl_eval::metrics::{ssim_gaussian_1d, SSIM_K1, SSIM_K2, SSIM_WIN};
use pixl_nn::backbones::{imagenet_normalize, Vgg16};
use std::path::Path;

/// The frozen perceptual network.
pub struct Perceptual {
    vgg: Vgg16,
}

impl Perceptual {
    /// Loads torchvision VGG16 `features.*` weights from a safetensors file.
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        if !path.is_file() {
            return Err(TrainError::File {
                path: path.to_owned(),
                reason: "VGG16 weights file not found".into(),
            });
        }
        // SAFETY-free path: read into memory (no mmap), so a file changed underneath cannot fault.
        let tensors = candle_core::safetensors::load(path, device).map_err(|e| TrainError::File {
            path: path.to_owned(),
            reason: format!("not readable safetensors: {e}"),
        })?;
        let vb = candle_nn::VarBuilder::from_tensors(tensors, DType::F32, device);
        let vgg = Vgg16::new(vb).map_err(|e| TrainError::File {
            path: path.to_owned(),
            reason: format!("not torchvision VGG16 weights (features.N.weight/bias): {e}"),
        })?;
        Ok(Self { vgg })
    }

    /// `mean_i mean|φ_i(pred) − φ_i(target)|` over the five taps. Inputs `(B, 3, H, W)` in [0, 1].
    pub fn distance(&self, pred: &Tensor, target: &Tensor) -> Result<Tensor> {
        let fp = self.vgg.features(&imagenet_normalize(pred)?)?;
        let ft = self.vgg.features(&imagenet_normalize(&target.detach())?)?;
        let n = fp.len() as f64;
        let mut total: Option<Tensor> = None;
        for (a, b) in fp.iter().zip(&ft) {
            let d = (a - b.detach())?.abs()?.mean_all()?;
            total = Some(match total {
                None => d,
                Some(t) => (t + d)?,
            });
        }
        let total = total.ok_or_else(|| TrainError::Other("VGG16 returned no features".into()))?;
        Ok((total / n)?)
    }
}

/// The loss terms of one batch (scalars, f32); `total` carries the graph.
pub struct LossTerms {
    pub total: Tensor,
    pub l1: f32,
    pub perceptual: Option<f32>,
}

/// One micro-batch's objective (eq. 5): the L1 term plus `weight` × the perceptual distance when
/// `perceptual` is given and `weight > 0`.
#[derive(Clone, Copy)]
pub struct Objective<'a> {
    pub perceptual: Option<&'a Perceptual>,
    pub weight: f64,
    /// μ of the optional `μ · (1 − SSIM)` term (0: off, the paper's objective).
    pub ssim_weight: f64,
    /// ν, the share of the pixel term taken after the scale correction (0: off, the paper's).
    pub scale_corrected: f64,
}

impl Objective<'_> {
    /// L1 alone.
    pub fn l1_only() -> Self {
        Objective {
            perceptual: None,
            weight: 0.0,
            ssim_weight: 0.0,
            scale_corrected: 0.0,
        }
    }
}

/// Eq. 5 for `pred`, the network's output **before** the final clip
/// (`PixlRelight::forward_unclipped`), against `target` in `[0, 1]`: both terms see the clipped
/// output `Î_T = clip((1 + g) ⊙ I_S + b, 0, 1)`, so gradients pass through the clip only where the
/// prediction lies inside `[0, 1]` (§3.2; candle's clamp gives none outside the range and half at
/// exactly 0 or 1). Taking the L1 on the unclipped output instead (it bounds the clipped L1 from
/// above and keeps a gradient on saturated pixels) measured no better (`BENCHMARKS.md`, training
/// step section), so the paper's form is the only one.
pub fn loss(pred: &Tensor, target: &Tensor, objective: &Objective) -> Result<LossTerms> {
    let perceptual = objective.perceptual.filter(|_| objective.weight > 0.0);
    let fused = perceptual.is_none() && cpu_f32(pred) && cpu_f32(target) && pred.dims() == target.dims();
    // `Î_T`, made once for whichever terms read it (the fused L1 clips inside its kernel).
    let corrected = objective.scale_corrected > 0.0;
    let clipped = if !fused || objective.ssim_weight > 0.0 || corrected {
        Some(pred.clamp(0f32, 1f32)?)
    } else {
        None
    };
    let l1 = match &clipped {
        Some(c) if !fused => (c - target)?.abs()?.mean_all()?,
        _ => pred
            .contiguous()?
            .apply_op2(&target.detach().contiguous()?, ClippedL1)?,
    };
    let l1_value = l1.to_scalar::<f32>()?;
    let mut total = l1;
    if let (Some(c), true) = (&clipped, corrected) {
        let nu = objective.scale_corrected;
        total = ((total * (1.0 - nu))? + (scale_corrected_l1(c, target)? * nu)?)?;
    }
    if let (Some(c), true) = (&clipped, objective.ssim_weight > 0.0) {
        let s = ssim(c, &target.detach())?;
        total = (total + ((1.0 - s)? * objective.ssim_weight)?)?;
    }
    let mut perceptual_value = None;
    if let (Some(p), Some(c)) = (perceptual, &clipped) {
        let d = p.distance(c, target)?;
        perceptual_value = Some(d.to_scalar::<f32>()?);
        total = (total + (d * objective.weight)?)?;
    }
    Ok(LossTerms {
        total,
        l1: l1_value,
        perceptual: perceptual_value,
    })
}

/// Bounds of the scale in [`scale_corrected_l1`]: a prediction that far off in exposure is not
/// forgiven further (and a black one does not divide by zero).
const SCALE_BOUNDS: (f32, f32) = (0.25, 4.0);

/// `mean |clip(s ⊙ x, 0, 1) − target|` for `x` = the clipped output `(B, C, H, W)`, with
/// `s_{b,c} = Σ target·x / Σ x²` over each image's channel (the evaluation's least-squares scale),
/// clamped to [`SCALE_BOUNDS`] and held constant in the backward pass: the gradient is that of
/// the L1 of a prediction multiplied by a fixed gain, so it carries no push towards an exposure.
pub fn scale_corrected_l1(clipped: &Tensor, target: &Tensor) -> Result<Tensor> {
    let target = target.detach();
    let num = (clipped * &target)?.sum_keepdim((2, 3))?;
    let den = clipped.sqr()?.sum_keepdim((2, 3))?;
    let scale = (num / (den + 1e-12)?)?.clamp(SCALE_BOUNDS.0, SCALE_BOUNDS.1)?.detach();
    let corrected = clipped.broadcast_mul(&scale)?.clamp(0f32, 1f32)?;
    Ok((corrected - target)?.abs()?.mean_all()?)
}

/// The `(n − 10) × n` matrix whose row `i` holds the evaluation's normalised 11-tap Gaussian
/// (`pixl_eval::metrics::ssim_gaussian_1d`) at columns `i..i + 11`: left-multiplying a plane by it
/// is the "valid" Gaussian filter along that axis.
fn valid_gaussian_matrix(n: usize, dtype: DType, device: &Device) -> Result<Tensor> {
    let g = ssim_gaussian_1d();
    let m = n + 1 - SSIM_WIN;
    let mut data = vec![0f64; m * n];
    for i in 0..m {
        data[i * n + i..i * n + i + SSIM_WIN].copy_from_slice(&g);
    }
    Ok(Tensor::from_vec(data, (m, n), device)?.to_dtype(dtype)?)
}

/// Mean SSIM of `(B, C, H, W)` images in `[0, 1]` (a scalar tensor that carries the graph of
/// `pred`), with the evaluation's window and constants (`pixl_eval::metrics`): the SSIM map of each
/// channel with valid Gaussian windows, averaged over the map, channels and images. The local
/// moments come from one separable filter pass, written as two matrix products with banded
/// Gaussian matrices, on `[x, y, x², y², xy]` stacked along channels. Images smaller than 11×11
/// are an error.
pub fn ssim(pred: &Tensor, target: &Tensor) -> Result<Tensor> {
    let (_, c, h, w) = pred.dims4()?;
    if h < SSIM_WIN || w < SSIM_WIN {
        return Err(TrainError::Other(format!(
            "SSIM needs images of at least {SSIM_WIN}x{SSIM_WIN}, got {w}x{h}"
        )));
    }
    let (c1, c2) = (SSIM_K1 * SSIM_K1, SSIM_K2 * SSIM_K2);
    let (dtype, device) = (pred.dtype(), pred.device());
    let gh = valid_gaussian_matrix(h, dtype, device)?;
    let gw_t = valid_gaussian_matrix(w, dtype, device)?.t()?;
    let stack = Tensor::cat(&[pred, target, &pred.sqr()?, &target.sqr()?, &(pred * target)?], 1)?;
    let filtered = gh.broadcast_matmul(&stack.contiguous()?)?.broadcast_matmul(&gw_t)?;
    let moment = |i: usize| filtered.narrow(1, i * c, c);
    let (mx, my) = (moment(0)?, moment(1)?);
    let (mxx, myy, mxy) = (mx.sqr()?, my.sqr()?, (&mx * &my)?);
    let vx = (moment(2)? - &mxx)?;
    let vy = (moment(3)? - &myy)?;
    let cxy = (moment(4)? - &mxy)?;
    let num = (((mxy * 2.0)? + c1)? * ((cxy * 2.0)? + c2)?)?;
    let den = (((mxx + myy)? + c1)? * ((vx + vy)? + c2)?)?;
    Ok((num / den)?.mean_all()?)
}

fn cpu_f32(t: &Tensor) -> bool {
    t.device().is_cpu() && t.dtype() == DType::F32
}

/// `mean |clip(pred, 0, 1) − target|` as one CPU op (arguments `(pred, target)`, contiguous
/// f32, same shape), summed in f64; its backward is candle's composition's:
/// `sign(clip(p) − t) / n` (+1 at 0) times the clamp's derivative (1 inside `(0, 1)`, ½ at
/// exactly 0 or 1, 0 outside), nothing for the target.
struct ClippedL1;

fn f32s<'a>(s: &'a CpuStorage, l: &Layout) -> candle_core::Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        _ => candle_core::bail!("L1 loss: expected contiguous f32 tensors"),
    }
}

impl CustomOp2 for ClippedL1 {
    fn name(&self) -> &'static str {
        "clipped-l1"
    }

    fn cpu_fwd(
        &self,
        ps: &CpuStorage,
        pl: &Layout,
        ts: &CpuStorage,
        tl: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (p, t) = (f32s(ps, pl)?, f32s(ts, tl)?);
        let sum: f64 = p
            .iter()
            .zip(t)
            .map(|(&p, &t)| (p.clamp(0.0, 1.0) - t).abs() as f64)
            .sum();
        let mean = if p.is_empty() {
            f32::NAN
        } else {
            (sum / p.len() as f64) as f32
        };
        Ok((CpuStorage::F32(vec![mean]), Shape::from(())))
    }

    fn bwd(
        &self,
        pred: &Tensor,
        target: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let scale = grad.to_dtype(DType::F32)?.to_scalar::<f32>()?;
        let d = pred.apply_op2_no_bwd(target, &ClippedL1Grad { scale })?;
        Ok((Some(d), None))
    }
}

/// The backward of [`ClippedL1`], times the incoming scalar gradient `scale`.
struct ClippedL1Grad {
    scale: f32,
}

impl CustomOp2 for ClippedL1Grad {
    fn name(&self) -> &'static str {
        "clipped-l1-grad"
    }

    fn cpu_fwd(
        &self,
        ps: &CpuStorage,
        pl: &Layout,
        ts: &CpuStorage,
        tl: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (p, t) = (f32s(ps, pl)?, f32s(ts, tl)?);
        let k = self.scale / p.len().max(1) as f32;
        let out = p
            .iter()
            .zip(t)
            .map(|(&p, &t)| {
                let inside = if p > 0.0 && p < 1.0 {
                    1.0
                } else if p == 0.0 || p == 1.0 {
                    0.5
                } else {
                    0.0
                };
                let d = p.clamp(0.0, 1.0) - t;
                // candle's |·|′: +1 at exactly 0.
                let sign = if d >= 0.0 { 1.0 } else { -1.0 };
                k * sign * inside
            })
            .collect();
        Ok((CpuStorage::F32(out), pl.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Var, WithDType};

    /// The gradient of the scalar `total` with respect to `x`, flattened.
    fn grad_of<T: WithDType>(total: &Tensor, x: &Var) -> Vec<T> {
        let store = total.backward().unwrap();
        store
            .get(x.as_tensor())
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1()
            .unwrap()
    }

    /// The fused CPU op against candle's composed clamp/sub/abs/mean on the same values, value
    /// and gradient, with pixels outside, inside and exactly on the clip bounds and ties with
    /// the target.
    #[test]
    fn fused_clipped_l1_equals_the_composed_ops() {
        let dev = Device::Cpu;
        let mut p: Vec<f32> = (0..60).map(|i| (i as f32 * 0.377).sin() * 1.4 + 0.3).collect();
        let t: Vec<f32> = (0..60).map(|i| (i as f32 * 0.91).cos() * 0.5 + 0.5).collect();
        (p[0], p[1], p[2], p[3]) = (0.0, 1.0, t[2], t[3].clamp(0.0, 1.0));
        let x = Var::from_vec(p, (1, 3, 4, 5), &dev).unwrap();
        let t = Tensor::from_vec(t, (1, 3, 4, 5), &dev).unwrap();
        let fused = loss(x.as_tensor(), &t, &Objective::l1_only()).unwrap();
        let composed = (&x.as_tensor().clamp(0f32, 1f32).unwrap() - &t)
            .unwrap()
            .abs()
            .unwrap()
            .mean_all()
            .unwrap();
        let want = composed.to_scalar::<f32>().unwrap();
        assert!((fused.l1 - want).abs() < 1e-6, "{} vs {want}", fused.l1);
        let grad = |total: &Tensor| -> Vec<f32> { grad_of(&(total * 3.0).unwrap(), &x) };
        // Same signs and masks; the scale 1/n rounds differently.
        for (a, b) in grad(&fused.total).iter().zip(grad(&composed)) {
            assert!((a - b).abs() <= 1e-6 * b.abs().max(1e-3), "{a} vs {b}");
        }
    }

    /// Pixels pushed past the clip get exactly no gradient (the paper's form), the others
    /// `sign(x − t)/n`; the value is the L1 of the clipped output.
    #[test]
    fn l1_of_the_clipped_output_and_its_gradient() {
        let dev = Device::Cpu;
        let x = Var::from_vec(vec![1.5f32, -0.25, 0.3, 0.9], (1, 1, 2, 2), &dev).unwrap();
        let t = Tensor::from_vec(vec![0.5f32, 0.2, 0.6, 0.4], (1, 1, 2, 2), &dev).unwrap();
        let terms = loss(x.as_tensor(), &t, &Objective::l1_only()).unwrap();
        // Hand value: (|1 − 0.5| + |0 − 0.2| + |0.3 − 0.6| + |0.9 − 0.4|) / 4.
        assert!((terms.l1 - 1.5 / 4.0).abs() < 1e-6, "{}", terms.l1);
        let g: Vec<f32> = grad_of(&terms.total, &x);
        assert_eq!(g, vec![0.0, 0.0, -0.25, 0.25]);
    }

    /// `(B, C, H, W)` f64 values in [0, 1] from a small LCG, and the `pixl_core::Image` (HWC) of image `b`.
    fn random_images(b: usize, c: usize, h: usize, w: usize, seed: u64) -> (Vec<f64>, Vec<pixl_core::Image>) {
        let mut state = seed;
        let v: Vec<f64> = (0..b * c * h * w)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                // Representable in f32, so the f64 path sees exactly the images' values.
                ((state >> 11) as f64 / (1u64 << 53) as f64) as f32 as f64
            })
            .collect();
        let images = (0..b)
            .map(|n| {
                let mut data = vec![0f32; h * w * c];
                for ch in 0..c {
                    for y in 0..h {
                        for x in 0..w {
                            data[(y * w + x) * c + ch] = v[((n * c + ch) * h + y) * w + x] as f32;
                        }
                    }
                }
                pixl_core::Image::from_vec(w, h, c, data).unwrap()
            })
            .collect();
        (v, images)
    }

    #[test]
    fn ssim_term_equals_the_evaluation_metric() {
        let (b, c, h, w) = (2, 3, 17, 23);
        let (pv, pi) = random_images(b, c, h, w, 1);
        let (tv, ti) = random_images(b, c, h, w, 2);
        // Make the target resemble the prediction so the score is far from 0.
        let tv: Vec<f64> = pv
            .iter()
            .zip(&tv)
            .map(|(p, t)| (0.8 * *p as f32 + 0.2 * *t as f32) as f64)
            .collect();
        let ti: Vec<pixl_core::Image> = pi
            .iter()
            .zip(&ti)
            .map(|(p, t)| {
                let data = p.data.iter().zip(&t.data).map(|(a, b)| 0.8 * a + 0.2 * b).collect();
                pixl_core::Image::from_vec(w, h, c, data).unwrap()
            })
            .collect();
        let expected: f64 = pi
            .iter()
            .zip(&ti)
            .map(|(p, t)| pixl_eval::metrics::ssim(p, t).unwrap())
            .sum::<f64>()
            / b as f64;
        assert!(expected > 0.3 && expected < 0.99, "{expected}");
        let dev = Device::Cpu;
        for dtype in [DType::F64, DType::F32] {
            let p = Tensor::from_vec(pv.clone(), (b, c, h, w), &dev)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let t = Tensor::from_vec(tv.clone(), (b, c, h, w), &dev)
                .unwrap()
                .to_dtype(dtype)
                .unwrap();
            let score = |a: &Tensor, b: &Tensor| {
                ssim(a, b)
                    .unwrap()
                    .to_dtype(DType::F64)
                    .unwrap()
                    .to_scalar::<f64>()
                    .unwrap()
            };
            let got = score(&p, &t);
            let tol = if dtype == DType::F64 { 1e-9 } else { 1e-5 };
            assert!((got - expected).abs() < tol, "{dtype:?}: {got} vs {expected}");
            let same = score(&p, &p);
            assert!((same - 1.0).abs() < tol, "{same}");
        }
        let small = Tensor::zeros((1, 3, 10, 40), DType::F32, &dev).unwrap();
        assert!(ssim(&small, &small).is_err());
    }

    #[test]
    fn ssim_gradient_matches_finite_differences() {
        let (b, c, h, w) = (1, 2, 12, 13);
        let (pv, _) = random_images(b, c, h, w, 3);
        let (tv, _) = random_images(b, c, h, w, 4);
        let dev = Device::Cpu;
        let t = Tensor::from_vec(tv, (b, c, h, w), &dev).unwrap();
        let x = Var::from_tensor(&Tensor::from_vec(pv.clone(), (b, c, h, w), &dev).unwrap()).unwrap();
        let g: Vec<f64> = grad_of(&ssim(x.as_tensor(), &t).unwrap(), &x);
        let eval = |v: Vec<f64>| {
            let p = Tensor::from_vec(v, (b, c, h, w), &dev).unwrap();
            ssim(&p, &t).unwrap().to_scalar::<f64>().unwrap()
        };
        let eps = 1e-6;
        for idx in [0, 5, 77, 150, 211, pv.len() - 1] {
            let (mut up, mut down) = (pv.clone(), pv.clone());
            up[idx] += eps;
            down[idx] -= eps;
            let fd = (eval(up) - eval(down)) / (2.0 * eps);
            assert!(
                (fd - g[idx]).abs() < 1e-7 + 1e-5 * fd.abs(),
                "{idx}: {fd} vs {}",
                g[idx]
            );
        }
    }

    #[test]
    fn ssim_weight_adds_its_term_to_the_l1() {
        let dev = Device::Cpu;
        let (pv, _) = random_images(2, 3, 16, 16, 5);
        let (tv, _) = random_images(2, 3, 16, 16, 6);
        // Values outside [0, 1] so the clip matters.
        let p = (Tensor::from_vec(pv, (2, 3, 16, 16), &dev)
            .unwrap()
            .to_dtype(DType::F32)
            .unwrap()
            .affine(1.4, -0.2))
        .unwrap();
        let t = Tensor::from_vec(tv, (2, 3, 16, 16), &dev)
            .unwrap()
            .to_dtype(DType::F32)
            .unwrap();
        let plain = loss(&p, &t, &Objective::l1_only()).unwrap();
        let objective = Objective {
            ssim_weight: 0.5,
            ..Objective::l1_only()
        };
        let with = loss(&p, &t, &objective).unwrap();
        let s = ssim(&p.clamp(0f32, 1f32).unwrap(), &t)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap();
        let expected = plain.l1 + 0.5 * (1.0 - s);
        let got = with.total.to_scalar::<f32>().unwrap();
        assert!((got - expected).abs() < 1e-6, "{got} vs {expected}");
        assert_eq!(with.l1, plain.l1);
    }

    /// The scale-corrected share against a naive f64 evaluation: per image and channel the
    /// least-squares scale of the clipped output (clamped to [1/4, 4]), the L1 of the rescaled and
    /// re-clipped output, mixed with the plain L1 by ν; its gradient is `ν · s · sign(s·x − t) / n`
    /// where `0 < x < 1` and `s·x < 1`, plus the plain term's `(1 − ν) · sign(x − t) / n`.
    #[test]
    fn scale_corrected_share_matches_a_naive_evaluation() {
        let dev = Device::Cpu;
        let (b, c, hw) = (2usize, 3usize, 6usize);
        let p: Vec<f32> = (0..b * c * hw)
            .map(|i| (i as f32 * 0.713).sin() * 0.6 + 0.45 + if i / hw == 4 { -0.3 } else { 0.0 })
            .collect();
        let t: Vec<f32> = (0..b * c * hw).map(|i| (i as f32 * 1.37).cos() * 0.35 + 0.5).collect();
        let x = Var::from_vec(p.clone(), (b, c, 2, 3), &dev).unwrap();
        let tt = Tensor::from_vec(t.clone(), (b, c, 2, 3), &dev).unwrap();
        let nu = 0.75f64;
        let objective = Objective {
            scale_corrected: nu,
            ..Objective::l1_only()
        };
        let terms = loss(x.as_tensor(), &tt, &objective).unwrap();
        let n = p.len() as f64;
        let (mut plain, mut corr) = (0f64, 0f64);
        let mut grad = vec![0f64; p.len()];
        for plane in 0..b * c {
            let r = plane * hw..(plane + 1) * hw;
            let xs: Vec<f64> = p[r.clone()].iter().map(|&v| (v as f64).clamp(0.0, 1.0)).collect();
            let ts: Vec<f64> = t[r.clone()].iter().map(|&v| v as f64).collect();
            let num: f64 = xs.iter().zip(&ts).map(|(a, b)| a * b).sum();
            let den: f64 = xs.iter().map(|a| a * a).sum();
            let s = (num / den).clamp(0.25, 4.0);
            for k in 0..hw {
                let (xv, tv, raw) = (xs[k], ts[k], p[plane * hw + k] as f64);
                plain += (xv - tv).abs();
                let sx = (s * xv).clamp(0.0, 1.0);
                corr += (sx - tv).abs();
                let inside = raw > 0.0 && raw < 1.0;
                if inside {
                    grad[plane * hw + k] += (1.0 - nu) * (xv - tv).signum() / n;
                    if s * xv < 1.0 {
                        grad[plane * hw + k] += nu * s * (sx - tv).signum() / n;
                    }
                }
            }
        }
        let want = (1.0 - nu) * plain / n + nu * corr / n;
        let got = terms.total.to_scalar::<f32>().unwrap() as f64;
        assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        assert!(
            (terms.l1 as f64 - plain / n).abs() < 1e-6,
            "the logged L1 stays the plain one"
        );
        // The scale was not all ones, or the test would not tell the two terms apart.
        assert!((corr - plain).abs() > 1e-3 * n);
        let g: Vec<f32> = grad_of(&terms.total, &x);
        for (k, (a, w)) in g.iter().zip(&grad).enumerate() {
            assert!((*a as f64 - w).abs() < 1e-6, "gradient {k}: {a} vs {w}");
        }
        // Scaling a prediction that stays inside (0, 1) leaves the corrected term unchanged.
        let half = Tensor::from_vec(
            p.iter().map(|v| v.clamp(0.01, 0.99) * 0.5).collect::<Vec<f32>>(),
            (b, c, 2, 3),
            &dev,
        )
        .unwrap();
        let full = (&half * 2.0).unwrap();
        let a = scale_corrected_l1(&half, &tt).unwrap().to_scalar::<f32>().unwrap();
        let c2 = scale_corrected_l1(&full, &tt).unwrap().to_scalar::<f32>().unwrap();
        assert!((a - c2).abs() < 1e-6, "{a} vs {c2}");
    }
}
