//! DPT head `head` (paper §3.2 "Modulation Head"; Ranftl et al. 2021, as in Depth Anything v2):
//! turns the four trunk readouts into one dense map `F` of `C' = head.hidden` channels at full
//! resolution.
//!
//! Input four `(B, d, gh, gw)` readouts and the padded image size `(H, W) = (p·gh, p·gw)` (`p` the patch size);
//! output `F`: `(B, C', H, W)`, non-negative (ReLU).
//!
//! Steps and names (Depth Anything v2 `DPTHead`):
//! 1. `projects.{i}`: 1×1 conv `d → out_channels[i]`;
//! 2. `resize_layers`: `0` transposed conv 4×4 stride 4 (stride 16 → 4), `1` transposed conv
//!    2×2 stride 2 (→ 8), index `2` is the identity (stride 16, no weights), `3` conv 3×3 stride 2
//!    (→ 32);
//! 3. `scratch.layer{k}_rn`: 3×3 conv `out_channels[k-1] → features`, no bias;
//! 4. `scratch.refinenet{4,3,2,1}`: fusion blocks. `refinenet4` takes the coarsest map alone;
//!    the others add `resConfUnit1(skip)` to the coarser path. Each then applies
//!    `resConfUnit2`, resizes to the next finer map's size (×2 for `refinenet1`, ending at
//!    stride 2) and applies `out_conv` (1×1). A residual conv unit is
//!    `x + conv2(relu(conv1(relu(x))))` with 3×3 convs;
//! 5. `scratch.output_conv1` (3×3, `features → features/2`), bilinear resize to `(H, W)`,
//!    `scratch.output_conv2.0` (3×3, `features/2 → C'`), ReLU.
//!
//! Choices: resizes use half-pixel bilinear (`align_corners=False`, [`pixl_nn::ops::resize_bilinear`],
//! differentiable) where DPT uses `align_corners=True`; `refinenet4` has no `resConfUnit1`
//! (DPT builds one and never uses it); targets are explicit sizes, so odd grids work.
//! Transposed convs with kernel = stride are computed as one matmul plus a pixel shuffle
//! ([`ConvTransposeK`]).
use crate::config::Config;
use crate::layers::{conv2d, conv2d_no_bias, Conv};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};
use pixl_nn::fused::Act;
use pixl_nn::ops::resize_bilinear;

/// `nn.ConvTranspose2d(cin, cout, k, stride=k)`: weight `(cin, cout, k, k)`, bias `(cout)`.
/// `out[b, o, i·k+u, j·k+v] = bias[o] + Σ_c x[b, c, i, j] · w[c, o, u, v]`.
#[derive(Clone, Debug)]
pub struct ConvTransposeK {
    weight: Tensor,
    bias: Tensor,
    k: usize,
}

impl ConvTransposeK {
    pub fn new(cin: usize, cout: usize, k: usize, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get_with_hints((cin, cout, k, k), "weight", candle_nn::init::DEFAULT_KAIMING_NORMAL)?;
        let bias = vb.get_with_hints(cout, "bias", candle_nn::Init::Const(0.0))?;
        Ok(Self { weight, bias, k })
    }
}

impl Module for ConvTransposeK {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let _t = pixl_nn::profile::span("transposed conv");
        let (b, cin, h, w) = xs.dims4()?;
        let (_, cout, k, _) = self.weight.dims4()?;
        let rows = xs.permute((0, 2, 3, 1))?.reshape((b * h * w, cin))?;
        let ys = rows.matmul(&self.weight.reshape((cin, cout * k * k))?)?;
        let ys = ys.reshape((b, h, w, cout, k, k))?.permute((0, 3, 1, 4, 2, 5))?;
        let ys = ys.reshape((b, cout, h * self.k, w * self.k))?;
        ys.broadcast_add(&self.bias.reshape((1, cout, 1, 1))?)
    }
}

/// Zero-pads `(B, C, h, w)` on the bottom/right to even `h`, `w`. A 3×3 stride-2 pad-1 conv
/// gives the same values with or without it (the added row/column is the padding the conv would
/// read anyway), but candle 0.11's conv2d backward derives the output padding of both axes from
/// the height alone and fails on mixed-parity maps; even sizes avoid that.
fn pad_to_even(xs: &Tensor) -> Result<Tensor> {
    let (_b, _c, h, w) = xs.dims4()?;
    xs.pad_with_zeros(2, 0, h % 2)?.pad_with_zeros(3, 0, w % 2)
}

fn conv3x3(cin: usize, cout: usize, vb: VarBuilder) -> Result<Conv> {
    conv2d(
        cin,
        cout,
        3,
        Conv2dConfig {
            padding: 1,
            ..Default::default()
        },
        vb,
    )
}

/// `x + conv2(relu(conv1(relu(x))))`.
#[derive(Clone, Debug)]
struct ResidualConvUnit {
    conv1: Conv,
    conv2: Conv,
}

impl ResidualConvUnit {
    fn new(f: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            conv1: conv3x3(f, f, vb.pp("conv1"))?,
            conv2: conv3x3(f, f, vb.pp("conv2"))?,
        })
    }
}

impl Module for ResidualConvUnit {
    /// Two convolutions: the ReLUs and the skip connection ride inside them ([`Conv::forward_fused`]).
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let ys = self.conv1.forward_fused(xs, true, None, Act::Relu)?;
        self.conv2.forward_fused(&ys, false, Some(xs), Act::None)
    }
}

/// DPT feature fusion block.
#[derive(Clone, Debug)]
struct FusionBlock {
    res_conf_unit1: Option<ResidualConvUnit>,
    res_conf_unit2: ResidualConvUnit,
    out_conv: Conv,
}

impl FusionBlock {
    fn new(f: usize, with_skip: bool, vb: VarBuilder) -> Result<Self> {
        let res_conf_unit1 = if with_skip {
            Some(ResidualConvUnit::new(f, vb.pp("resConfUnit1"))?)
        } else {
            None
        };
        Ok(Self {
            res_conf_unit1,
            res_conf_unit2: ResidualConvUnit::new(f, vb.pp("resConfUnit2"))?,
            out_conv: conv2d(f, f, 1, Conv2dConfig::default(), vb.pp("out_conv"))?,
        })
    }

    /// `path` (coarser), optional `skip` (same size as `path`), output resized to `size`.
    fn forward(&self, path: &Tensor, skip: Option<&Tensor>, size: (usize, usize)) -> Result<Tensor> {
        let mut xs = path.clone();
        if let (Some(rcu), Some(skip)) = (&self.res_conf_unit1, skip) {
            xs = (xs + rcu.forward(skip)?)?;
        }
        let xs = self.res_conf_unit2.forward(&xs)?;
        let xs = resize_bilinear(&xs, size.0, size.1)?;
        self.out_conv.forward(&xs)
    }
}

/// The DPT head (`head.*`).
#[derive(Clone, Debug)]
pub struct DptHead {
    projects: Vec<Conv>,
    resize0: ConvTransposeK,
    resize1: ConvTransposeK,
    resize3: Conv,
    layer_rn: Vec<Conv>,
    refinenets: Vec<FusionBlock>,
    output_conv1: Conv,
    output_conv2: Conv,
}

impl DptHead {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        let (oc, f) = (cfg.head.out_channels, cfg.head.features);
        let projects = (0..4)
            .map(|i| conv2d(cfg.dim, oc[i], 1, Conv2dConfig::default(), vb.pp("projects").pp(i)))
            .collect::<Result<Vec<_>>>()?;
        let vr = vb.pp("resize_layers");
        let resize0 = ConvTransposeK::new(oc[0], oc[0], 4, vr.pp(0))?;
        let resize1 = ConvTransposeK::new(oc[1], oc[1], 2, vr.pp(1))?;
        let s2 = Conv2dConfig {
            padding: 1,
            stride: 2,
            ..Default::default()
        };
        let resize3 = conv2d(oc[3], oc[3], 3, s2, vr.pp(3))?;
        let vs = vb.pp("scratch");
        let pad1 = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        let layer_rn = (0..4)
            .map(|i| conv2d_no_bias(oc[i], f, 3, pad1, vs.pp(format!("layer{}_rn", i + 1))))
            .collect::<Result<Vec<_>>>()?;
        // refinenets[i] is `refinenet{i+1}`.
        let refinenets = (0..4)
            .map(|i| FusionBlock::new(f, i < 3, vs.pp(format!("refinenet{}", i + 1))))
            .collect::<Result<Vec<_>>>()?;
        let output_conv1 = conv3x3(f, f / 2, vs.pp("output_conv1"))?;
        let output_conv2 = conv3x3(f / 2, cfg.head.hidden, vs.pp("output_conv2").pp(0))?;
        Ok(Self {
            projects,
            resize0,
            resize1,
            resize3,
            layer_rn,
            refinenets,
            output_conv1,
            output_conv2,
        })
    }

    /// Four readouts `(B, d, gh, gw)` → `F` `(B, C', h, w)`.
    pub fn forward(&self, readouts: &[Tensor], h: usize, w: usize) -> Result<Tensor> {
        if readouts.len() != 4 {
            candle_core::bail!("DPT head expects 4 readouts, got {}", readouts.len());
        }
        let mut layers = Vec::with_capacity(4);
        for (i, xs) in readouts.iter().enumerate() {
            let xs = self.projects[i].forward(xs)?;
            let xs = match i {
                0 => self.resize0.forward(&xs)?,
                1 => self.resize1.forward(&xs)?,
                2 => xs,
                _ => self.resize3.forward(&pad_to_even(&xs)?)?,
            };
            layers.push(self.layer_rn[i].forward(&xs)?);
        }
        let size = |t: &Tensor| -> Result<(usize, usize)> { Ok((t.dim(2)?, t.dim(3)?)) };
        let path = self.refinenets[3].forward(&layers[3], None, size(&layers[2])?)?;
        let path = self.refinenets[2].forward(&path, Some(&layers[2]), size(&layers[1])?)?;
        let path = self.refinenets[1].forward(&path, Some(&layers[1]), size(&layers[0])?)?;
        let (h1, w1) = size(&layers[0])?;
        let path = self.refinenets[0].forward(&path, Some(&layers[0]), (2 * h1, 2 * w1))?;
        let out = self.output_conv1.forward(&path)?;
        let out = resize_bilinear(&out, h, w)?;
        self.output_conv2.forward_fused(&out, false, None, Act::Relu)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    #[test]
    fn kernel_stride_transposed_conv_matches_candle() -> Result<()> {
        let dev = Device::Cpu;
        for k in [2usize, 4] {
            let xs = Tensor::randn(0f32, 1.0, (2, 3, 3, 5), &dev)?;
            let w = Tensor::randn(0f32, 1.0, (3, 4, k, k), &dev)?;
            let b = Tensor::randn(0f32, 1.0, 4, &dev)?;
            let ours = ConvTransposeK {
                weight: w.clone(),
                bias: b.clone(),
                k,
            }
            .forward(&xs)?;
            let cfg = candle_nn::ConvTranspose2dConfig {
                stride: k,
                ..Default::default()
            };
            let reference = candle_nn::ConvTranspose2d::new(w, Some(b), cfg).forward(&xs)?;
            assert_eq!(ours.dims(), reference.dims());
            let err = (ours - reference)?
                .abs()?
                .max_all()?
                .to_dtype(DType::F64)?
                .to_scalar::<f64>()?;
            assert!(err < 1e-4, "k={k}: max error {err}");
        }
        Ok(())
    }
}
