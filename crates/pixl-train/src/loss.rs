//! The training loss (paper eq. 5): `L = ‖Î_T − I_T‖₁ + λ · L_perc(Î_T, I_T)`, λ = 0.2.
//!
//! - The pixel term is the mean absolute error over all `B·3·H·W` values (images in [0, 1]).
//! - The perceptual term is an **L1** distance between VGG16 features (torchvision layout,
//!   [`pixl_nn::backbones::Vgg16`]) of ImageNet-normalised inputs, at the five post-ReLU taps
//!   relu1_2, relu2_2, relu3_3, relu4_3, relu5_3: the mean absolute difference of each tap,
//!   averaged over the five taps with equal weight. The VGG weights are frozen (loaded as
//!   constants, never `Var`s), so only the network receives gradients.
use crate::error::{Result, TrainError};
use candle_core::{DType, Device, Tensor};
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

/// `L1 + weight · perceptual` (the perceptual term only when `perceptual` is given and
/// `weight > 0`).
///
/// `pred` is the network's output **before** the final clip (`PixlRelight::forward_unclipped`):
/// the L1 term is taken on it, so saturated pixels keep a gradient (for targets in `[0, 1]` it
/// bounds the L1 of the clipped output from above, with the same minimisers); the perceptual
/// term sees the clipped image, as VGG would at inference.
pub fn loss(pred: &Tensor, target: &Tensor, perceptual: Option<&Perceptual>, weight: f64) -> Result<LossTerms> {
    let l1 = (pred - target)?.abs()?.mean_all()?;
    let l1_value = l1.to_scalar::<f32>()?;
    match perceptual {
        Some(p) if weight > 0.0 => {
            let d = p.distance(&pred.clamp(0f32, 1f32)?, target)?;
            let d_value = d.to_scalar::<f32>()?;
            Ok(LossTerms {
                total: (l1 + (d * weight)?)?,
                l1: l1_value,
                perceptual: Some(d_value),
            })
        }
        _ => Ok(LossTerms {
            total: l1,
            l1: l1_value,
            perceptual: None,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Var;

    /// A pixel pushed past the clip still gets the L1 gradient `sign(x − t)/n`, where a loss on
    /// the clipped output would give exactly 0; unsaturated pixels get the same gradient either way.
    #[test]
    fn saturated_pixels_keep_their_gradient() {
        let dev = Device::Cpu;
        let x = Var::from_vec(vec![1.5f32, -0.25, 0.3, 0.9], (1, 1, 2, 2), &dev).unwrap();
        let t = Tensor::from_vec(vec![0.5f32, 0.2, 0.6, 0.4], (1, 1, 2, 2), &dev).unwrap();
        let terms = loss(x.as_tensor(), &t, None, 0.0).unwrap();
        // Hand value: (1.0 + 0.45 + 0.3 + 0.5) / 4.
        assert!((terms.l1 - 2.25 / 4.0).abs() < 1e-6, "{}", terms.l1);
        let grad = |l: &Tensor| -> Vec<f32> {
            let store = l.backward().unwrap();
            store
                .get(x.as_tensor())
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1()
                .unwrap()
        };
        assert_eq!(grad(&terms.total), vec![0.25, -0.25, -0.25, 0.25]);
        // The clipped loss would have frozen the two saturated pixels.
        let clipped = (x.as_tensor().clamp(0f32, 1f32).unwrap() - &t)
            .unwrap()
            .abs()
            .unwrap()
            .mean_all()
            .unwrap();
        let gc = grad(&clipped);
        assert_eq!(&gc[..2], &[0.0, 0.0]);
    }
}
