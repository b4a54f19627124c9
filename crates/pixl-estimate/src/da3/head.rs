//! DA3's DPT head (`model.head`, official `DPT` with `output_dim=1`, a sky head, `norm_type
//! "idt"`, no position embedding, `down_ratio` 1).
//!
//! Input: the four backbone features `(B, N, C)` of a `(gh, gw)` patch grid. Output: depth
//! `exp(logits)` and the sky score (`relu` for the released models), both `(B, 14·gh, 14·gw)`.
//!
//! Steps (official names):
//! 1. `projects.i`: 1×1 conv `C → out_channels[i]`;
//! 2. `resize_layers`: 0 = `ConvTranspose2d(k=4, s=4)`, 1 = `ConvTranspose2d(k=2, s=2)`,
//!    2 = identity, 3 = `Conv2d(3, s=2, p=1)`;
//! 3. `scratch.layerK_rn`: 3×3 conv `out_channels[K-1] → features`, no bias;
//! 4. fusion `refinenet4 → 3 → 2 → 1`: `refinenet4` has no `resConfUnit1`; the others add
//!    `resConfUnit1(lateral)`. Each applies `resConfUnit2`, resizes bilinearly with
//!    `align_corners=True` to the next lateral's size (`refinenet1`: ×2, `int(2·h)`), then the
//!    1×1 `out_conv`. A residual unit is `x + conv2(relu(conv1(relu(x))))`;
//! 5. `output_conv1` (3×3, `features → features/2`), bilinear `align_corners=True` to
//!    `(14·gh, 14·gw)`;
//! 6. depth: `output_conv2` = 3×3 `→ 32`, ReLU, 1×1 `→ 1`, `exp`; sky: `sky_output_conv2`, same
//!    shape, then the sky activation.
//!
//! The two final 3×3 convs read the same map and are evaluated as one 64-channel conv (their
//! weights concatenated at load time), the two 1×1 convs as one block-diagonal matmul.
use super::config::Da3Config;
use super::resize::bilinear_align_corners;
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use pixl_nn::conv3x3::Conv3x3;
use pixl_nn::fused::{self, bias_act_channels, bias_act_rows, Act, Vector};

/// A 1×1 conv as a matrix product: weight `(out, in)`, bias `(out)`.
#[derive(Clone, Debug)]
struct Conv1x1 {
    weight: Tensor,
    bias: Vector,
}

impl Conv1x1 {
    fn new(cin: usize, cout: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get((cout, cin, 1, 1), "weight")?.reshape((cout, cin))?,
            bias: Vector::new(vb.get(cout, "bias")?)?,
        })
    }

    /// `(B, C, H, W)` → `(B, O, H, W)`.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = xs.dims4()?;
        let o = self.weight.dim(0)?;
        let ys = self.weight.broadcast_left(b)?.matmul(&xs.reshape((b, c, h * w))?)?;
        bias_act_channels(&ys, &self.bias, Act::None)?.reshape((b, o, h, w))
    }

    /// Tokens `(B, N, C)` → `(B·N, O)` rows.
    fn forward_rows(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, n, c) = xs.dims3()?;
        let ys = xs.reshape((b * n, c))?.matmul(&self.weight.t()?)?;
        bias_act_rows(&ys, &self.bias, Act::None)
    }
}

/// `ConvTranspose2d(cin, cout, k, stride=k)` on rows `(B·h·w, cin)`: one matmul, then a pixel
/// shuffle. `out[b, o, i·k+u, j·k+v] = bias[o] + Σ_c x[b, c, i, j] · w[c, o, u, v]`.
#[derive(Clone, Debug)]
struct ConvTransposeK {
    /// `(cin, cout·k·k)`.
    weight: Tensor,
    bias: Vector,
    k: usize,
}

impl ConvTransposeK {
    fn new(c: usize, k: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get((c, c, k, k), "weight")?.reshape((c, c * k * k))?,
            bias: Vector::new(vb.get(c, "bias")?)?,
            k,
        })
    }

    fn forward_rows(&self, rows: &Tensor, b: usize, h: usize, w: usize) -> Result<Tensor> {
        let k = self.k;
        let cout = self.bias.len();
        let ys = rows.matmul(&self.weight)?; // (B·h·w, cout·k·k)
        let ys = ys.reshape((b, h, w, cout, k, k))?.permute((0, 3, 1, 4, 2, 5))?;
        let ys = ys.contiguous()?.reshape((b, cout, h * k, w * k))?;
        bias_act_channels(&ys, &self.bias, Act::None)
    }
}

/// `x + conv2(relu(conv1(relu(x))))`.
#[derive(Clone, Debug)]
struct ResidualConvUnit {
    conv1: Conv3x3,
    conv2: Conv3x3,
}

impl ResidualConvUnit {
    fn new(f: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            conv1: Conv3x3::new(f, f, 1, true, vb.pp("conv1"))?,
            conv2: Conv3x3::new(f, f, 1, true, vb.pp("conv2"))?,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let ys = self.conv1.forward(&fused::relu(xs)?, Act::Relu)?;
        self.conv2.forward_residual(&ys, xs)
    }
}

/// Official `FeatureFusionBlock` (`align_corners=True`, no expansion).
#[derive(Clone, Debug)]
struct FusionBlock {
    res_conf_unit1: Option<ResidualConvUnit>,
    res_conf_unit2: ResidualConvUnit,
    out_conv: Conv1x1,
}

impl FusionBlock {
    fn new(f: usize, has_residual: bool, vb: VarBuilder) -> Result<Self> {
        let res_conf_unit1 = if has_residual {
            Some(ResidualConvUnit::new(f, vb.pp("resConfUnit1"))?)
        } else {
            None
        };
        Ok(Self {
            res_conf_unit1,
            res_conf_unit2: ResidualConvUnit::new(f, vb.pp("resConfUnit2"))?,
            out_conv: Conv1x1::new(f, f, vb.pp("out_conv"))?,
        })
    }

    fn forward(&self, path: &Tensor, lateral: Option<&Tensor>, size: (usize, usize)) -> Result<Tensor> {
        let xs = match (&self.res_conf_unit1, lateral) {
            (Some(rcu), Some(l)) => fused::add_act(path, &rcu.forward(l)?, Act::None)?,
            _ => path.clone(),
        };
        let xs = self.res_conf_unit2.forward(&xs)?;
        let xs = bilinear_align_corners(&xs, size.0, size.1)?;
        self.out_conv.forward(&xs)
    }
}

/// Sky activation of the config.
#[derive(Clone, Copy, Debug)]
enum SkyActivation {
    Relu,
    Sigmoid,
    Linear,
}

/// The DPT head.
#[derive(Clone, Debug)]
pub struct DptHead {
    projects: Vec<Conv1x1>,
    resize0: ConvTransposeK,
    resize1: ConvTransposeK,
    resize3: Conv3x3,
    layer_rn: Vec<Conv3x3>,
    /// `refinenets[i]` is `refinenet{i+1}`.
    refinenets: Vec<FusionBlock>,
    output_conv1: Conv3x3,
    /// `output_conv2.0` and `sky_output_conv2.0` stacked: `(64, features/2, 3, 3)`.
    final3x3: Conv3x3,
    /// `output_conv2.2` and `sky_output_conv2.2` as a block-diagonal `(2, 64)` matrix.
    final1x1: Tensor,
    final1x1_bias: Tensor,
    sky_activation: SkyActivation,
    patch: usize,
}

impl DptHead {
    /// Reads `model.head.*` under `vb` (already prefixed).
    pub fn new(cfg: &Da3Config, vb: VarBuilder) -> Result<Self> {
        let h = cfg.head();
        let (c, oc, f) = (h.dim_in, h.out_channels, h.features);
        let projects = (0..4)
            .map(|i| Conv1x1::new(c, oc[i], vb.pp("projects").pp(i)))
            .collect::<Result<Vec<_>>>()?;
        let vr = vb.pp("resize_layers");
        let s = vb.pp("scratch");
        let layer_rn = (0..4)
            .map(|i| Conv3x3::new(oc[i], f, 1, false, s.pp(format!("layer{}_rn", i + 1))))
            .collect::<Result<Vec<_>>>()?;
        let refinenets = (0..4)
            .map(|i| FusionBlock::new(f, i < 3, s.pp(format!("refinenet{}", i + 1))))
            .collect::<Result<Vec<_>>>()?;
        let half = f / 2;
        let (d, k) = (s.pp("output_conv2"), s.pp("sky_output_conv2"));
        let w3 = Tensor::cat(
            &[
                d.pp(0).get((32, half, 3, 3), "weight")?,
                k.pp(0).get((32, half, 3, 3), "weight")?,
            ],
            0,
        )?;
        let b3 = Tensor::cat(&[d.pp(0).get(32, "bias")?, k.pp(0).get(32, "bias")?], 0)?;
        let final3x3 = Conv3x3::from_parts(w3, Some(Vector::new(b3)?), 1)?;
        let wd = d.pp(2).get((1, 32, 1, 1), "weight")?.reshape((1, 32))?;
        let wk = k.pp(2).get((1, 32, 1, 1), "weight")?.reshape((1, 32))?;
        let zeros = wd.zeros_like()?;
        let final1x1 = Tensor::cat(&[Tensor::cat(&[&wd, &zeros], 1)?, Tensor::cat(&[&zeros, &wk], 1)?], 0)?;
        let final1x1_bias = Tensor::cat(&[d.pp(2).get(1, "bias")?, k.pp(2).get(1, "bias")?], 0)?;
        let sky_activation = match h.sky_activation.as_str() {
            "sigmoid" => SkyActivation::Sigmoid,
            "linear" => SkyActivation::Linear,
            _ => SkyActivation::Relu,
        };
        Ok(Self {
            projects,
            resize0: ConvTransposeK::new(oc[0], 4, vr.pp(0))?,
            resize1: ConvTransposeK::new(oc[1], 2, vr.pp(1))?,
            resize3: Conv3x3::new(oc[3], oc[3], 2, true, vr.pp(3))?,
            layer_rn,
            refinenets,
            output_conv1: Conv3x3::new(f, half, 1, true, s.pp("output_conv1"))?,
            final3x3,
            final1x1,
            final1x1_bias,
            sky_activation,
            patch: h.patch_size,
        })
    }

    /// Features `(B, N, C)` ×4 of a `(gh, gw)` grid → `(depth, sky)`, each `(B, 14·gh, 14·gw)`.
    pub fn forward(&self, feats: &[Tensor], gh: usize, gw: usize) -> Result<(Tensor, Tensor)> {
        if feats.len() != 4 {
            candle_core::bail!("DPT head expects 4 features, got {}", feats.len());
        }
        let b = feats[0].dim(0)?;
        let mut laterals = Vec::with_capacity(4);
        for (i, xs) in feats.iter().enumerate() {
            let rows = self.projects[i].forward_rows(xs)?; // (B·N, O)
            let o = rows.dim(1)?;
            let grid = || -> Result<Tensor> { rows.reshape((b, gh, gw, o))?.permute((0, 3, 1, 2))?.contiguous() };
            let xs = match i {
                0 => self.resize0.forward_rows(&rows, b, gh, gw)?,
                1 => self.resize1.forward_rows(&rows, b, gh, gw)?,
                2 => grid()?,
                _ => self.resize3.forward(&grid()?, Act::None)?,
            };
            laterals.push(self.layer_rn[i].forward(&xs, Act::None)?);
        }
        let size = |t: &Tensor| -> Result<(usize, usize)> { Ok((t.dim(2)?, t.dim(3)?)) };
        let path = self.refinenets[3].forward(&laterals[3], None, size(&laterals[2])?)?;
        let path = self.refinenets[2].forward(&path, Some(&laterals[2]), size(&laterals[1])?)?;
        let path = self.refinenets[1].forward(&path, Some(&laterals[1]), size(&laterals[0])?)?;
        let (h1, w1) = size(&laterals[0])?;
        let path = self.refinenets[0].forward(&path, Some(&laterals[0]), (2 * h1, 2 * w1))?;

        let (h, w) = (gh * self.patch, gw * self.patch);
        let out = self.output_conv1.forward(&path, Act::None)?;
        let out = bilinear_align_corners(&out, h, w)?;
        let hidden = self.final3x3.forward(&out, Act::Relu)?; // (B, 64, h, w)
        let logits = self
            .final1x1
            .broadcast_left(b)?
            .matmul(&hidden.reshape((b, 64, h * w))?)?
            .broadcast_add(&self.final1x1_bias.reshape((1, 2, 1))?)?; // (B, 2, h·w)
        let depth = logits.narrow(1, 0, 1)?.exp()?.reshape((b, h, w))?;
        let sky = logits.narrow(1, 1, 1)?;
        let sky = match self.sky_activation {
            SkyActivation::Relu => sky.relu()?,
            SkyActivation::Sigmoid => candle_nn::ops::sigmoid(&sky)?,
            SkyActivation::Linear => sky,
        }
        .reshape((b, h, w))?;
        Ok((depth, sky))
    }
}
