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
//!
//! Steps 2 to 5 are the DPT stages shared with the PIXLRelight head ([`pixl_nn::dpt`]), built
//! here from `HeadConv` and [`bilinear_align_corners`]; the projections read the backbone's
//! tokens as rows, which the transposed convs of step 2 take as they are.
use super::config::Da3Config;
use super::resize::bilinear_align_corners;
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;
use pixl_nn::conv3x3::Conv3x3;
use pixl_nn::dpt::{ConvSpec, DptConv, DptFusion, DptReassemble};
use pixl_nn::fused::{bias_act_channels, bias_act_rows, Act, Vector};

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
    fn forward(&self, xs: &Tensor, act: Act) -> Result<Tensor> {
        let (b, c, h, w) = xs.dims4()?;
        let o = self.weight.dim(0)?;
        let ys = self.weight.broadcast_left(b)?.matmul(&xs.reshape((b, c, h * w))?)?;
        bias_act_channels(&ys, &self.bias, act)?.reshape((b, o, h, w))
    }

    /// Tokens `(B, N, C)` → `(B·N, O)` rows.
    fn forward_rows(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, n, c) = xs.dims3()?;
        let ys = xs.reshape((b * n, c))?.matmul(&self.weight.t()?)?;
        bias_act_rows(&ys, &self.bias, Act::None)
    }
}

/// The head's convolutions as the shared DPT stages ([`pixl_nn::dpt`]) take them: 3×3 ones in
/// [`Conv3x3`] (weights arranged for its kernels at load time), 1×1 ones as a matrix product.
#[derive(Clone, Debug)]
enum HeadConv {
    K3(Conv3x3),
    K1(Conv1x1),
}

impl DptConv for HeadConv {
    fn load(spec: ConvSpec, vb: VarBuilder) -> Result<Self> {
        let ConvSpec {
            cin,
            cout,
            k,
            stride,
            bias,
        } = spec;
        match (k, stride, bias) {
            (3, _, _) => Ok(Self::K3(Conv3x3::new(cin, cout, stride, bias, vb)?)),
            (1, 1, true) => Ok(Self::K1(Conv1x1::new(cin, cout, vb)?)),
            _ => candle_core::bail!("DA3 head: no {k}x{k} stride-{stride} convolution (bias: {bias})"),
        }
    }

    fn forward_fused(&self, xs: &Tensor, input_relu: bool, residual: Option<&Tensor>, act: Act) -> Result<Tensor> {
        match self {
            Self::K3(conv) => conv.apply_relu_input(xs, input_relu, residual, act),
            Self::K1(conv) if !input_relu && residual.is_none() => conv.forward(xs, act),
            Self::K1(_) => candle_core::bail!("DA3 head: a 1x1 convolution takes no input ReLU or skip connection"),
        }
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
    resize_layers: DptReassemble<HeadConv>,
    scratch: DptFusion<HeadConv>,
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
        let s = vb.pp("scratch");
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
            resize_layers: DptReassemble::new(oc, vb.pp("resize_layers"))?,
            scratch: DptFusion::new(oc, f, bilinear_align_corners, s)?,
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
        let layers = feats.iter().zip(&self.projects).enumerate().map(|(i, (xs, project))| {
            let rows = project.forward_rows(xs)?; // (B·N, O)
            self.resize_layers.forward_rows(i, &rows, b, gh, gw)
        });
        let (h, w) = (gh * self.patch, gw * self.patch);
        let out = self.scratch.forward(layers, h, w)?;
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
