//! The reassemble and fusion stages of a DPT head (Ranftl et al. 2021, as Depth Anything v2 and
//! 3 build it), shared by the PIXLRelight head (`pixl-model`) and the Depth Anything 3 port
//! (`pixl-estimate`). Each model keeps its own `projects` (they read different token layouts)
//! and its own output convolutions after `output_conv1`.
//!
//! [`DptReassemble`] (`resize_layers.*`) brings the four projected maps of a `(gh, gw)` patch
//! grid, `out_channels[i]` channels each, to four scales:
//! `0` transposed conv 4×4 stride 4 (×4), `1` transposed conv 2×2 stride 2 (×2), `2` the identity
//! (no weights), `3` conv 3×3 stride 2 padding 1 (÷2, `⌈g/2⌉`).
//!
//! [`DptFusion`] (`scratch.*`) turns them into one map:
//! 1. `layer{k}_rn`: 3×3 conv `out_channels[k-1] → features`, no bias;
//! 2. `refinenet{4,3,2,1}` ([`FusionBlock`]): `refinenet4` takes the coarsest map alone, the others
//!    add `resConfUnit1(lateral)` to the coarser path; each applies `resConfUnit2`, resizes to the
//!    next finer lateral's size (`refinenet1`: ×2) and applies the 1×1 `out_conv`. A residual unit
//!    ([`ResidualConvUnit`]) is `x + conv2(relu(conv1(relu(x))))` with 3×3 convs;
//! 3. `output_conv1` (3×3, `features → features/2`), resized to the requested `(h, w)`.
//!
//! What differs between the models is a type and a function: the convolution ([`DptConv`]:
//! `pixl-model` trains its head, DA3 only runs inference and keeps its weights in the kernels'
//! layouts) and the bilinear resize ([`ResizeFn`]: half-pixel in `pixl-model`, PyTorch's
//! `align_corners=True` in DA3). `refinenet4` has no `resConfUnit1` (DPT builds one and never
//! uses it); targets are explicit sizes, so odd grids work.
use crate::fused::{self, bias_act_channels, Act, Vector};
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

/// A bilinear resize of `(B, C, H, W)` to `(B, C, h, w)`.
pub type ResizeFn = fn(&Tensor, usize, usize) -> Result<Tensor>;

/// One convolution of a DPT head: `nn.Conv2d(cin, cout, k, stride, padding = k / 2, bias)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvSpec {
    pub cin: usize,
    pub cout: usize,
    pub k: usize,
    pub stride: usize,
    pub bias: bool,
}

impl ConvSpec {
    /// `k × k`, stride 1, with a bias.
    pub fn new(cin: usize, cout: usize, k: usize) -> Self {
        Self {
            cin,
            cout,
            k,
            stride: 1,
            bias: true,
        }
    }

    pub fn stride(self, stride: usize) -> Self {
        Self { stride, ..self }
    }

    pub fn no_bias(self) -> Self {
        Self { bias: false, ..self }
    }
}

/// The convolution a DPT head is built from: PyTorch's `nn.Conv2d` (`weight` `(out, in, k, k)`,
/// `bias` `(out)`).
pub trait DptConv: Sized {
    /// The convolution `spec` with its weights read from `vb`.
    fn load(spec: ConvSpec, vb: VarBuilder) -> Result<Self>;

    /// `act(conv(relu(xs) if input_relu else xs) + residual)`.
    fn forward_fused(&self, xs: &Tensor, input_relu: bool, residual: Option<&Tensor>, act: Act) -> Result<Tensor>;
}

/// `nn.ConvTranspose2d(cin, cout, k, stride=k)`: weight `(cin, cout, k, k)`, bias `(cout)`.
/// `out[b, o, i·k+u, j·k+v] = bias[o] + Σ_c x[b, c, i, j] · w[c, o, u, v]`: one matrix product
/// and a pixel shuffle.
#[derive(Clone, Debug)]
pub struct ConvTransposeK {
    /// `(cin, cout·k·k)`.
    weight: Tensor,
    bias: Vector,
    k: usize,
}

impl ConvTransposeK {
    pub fn new(cin: usize, cout: usize, k: usize, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get_with_hints((cin, cout, k, k), "weight", candle_nn::init::DEFAULT_KAIMING_NORMAL)?;
        let bias = vb.get_with_hints(cout, "bias", candle_nn::Init::Const(0.0))?;
        Self::from_parts(weight, bias)
    }

    /// From the `(cin, cout, k, k)` weight and the `(cout)` bias.
    pub fn from_parts(weight: Tensor, bias: Tensor) -> Result<Self> {
        let (cin, cout, k, _) = weight.dims4()?;
        Ok(Self {
            weight: weight.reshape((cin, cout * k * k))?,
            bias: Vector::new(bias)?,
            k,
        })
    }

    /// `(B, cin, h, w)` → `(B, cout, k·h, k·w)`.
    pub fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let (b, cin, h, w) = xs.dims4()?;
        let rows = xs.permute((0, 2, 3, 1))?.reshape((b * h * w, cin))?;
        self.forward_rows(&rows, b, h, w)
    }

    /// The same on the input's pixels as rows `(B·h·w, cin)` in row-major order.
    pub fn forward_rows(&self, rows: &Tensor, b: usize, h: usize, w: usize) -> Result<Tensor> {
        let _t = crate::profile::span("transposed conv");
        let (k, cout) = (self.k, self.bias.len());
        let trained = crate::needs_grad(&[rows, &self.weight, &self.bias.tensor]);
        if trained && [rows, &self.weight, &self.bias.tensor].into_iter().all(fused::cpu_f32) {
            let cin = self.weight.dim(0)?;
            let xs = rows.reshape((b, h, w, cin))?.permute((0, 3, 1, 2))?;
            let weight = self.weight.reshape((cin, cout, k, k))?;
            return crate::conv_grad::conv_transpose_k(&xs, &weight, Some(&self.bias.tensor));
        }
        let ys = rows.matmul(&self.weight)?; // (B·h·w, cout·k·k)
        let ys = ys.reshape((b, h, w, cout, k, k))?.permute((0, 3, 1, 4, 2, 5))?;
        let ys = ys.contiguous()?.reshape((b, cout, h * k, w * k))?;
        if crate::needs_grad(&[&ys, &self.bias.tensor]) {
            return ys.broadcast_add(&self.bias.tensor.reshape((1, cout, 1, 1))?);
        }
        bias_act_channels(&ys, &self.bias, Act::None)
    }
}

/// `resize_layers.*`: the four projected maps to strides ×4, ×2, ×1 and ÷2 of the patch grid.
#[derive(Clone, Debug)]
pub struct DptReassemble<C> {
    resize0: ConvTransposeK,
    resize1: ConvTransposeK,
    resize3: C,
}

impl<C: DptConv> DptReassemble<C> {
    /// Reads `resize_layers.{0,1,3}` under `vb` (the `resize_layers` prefix).
    pub fn new(out_channels: [usize; 4], vb: VarBuilder) -> Result<Self> {
        let oc = out_channels;
        Ok(Self {
            resize0: ConvTransposeK::new(oc[0], oc[0], 4, vb.pp(0))?,
            resize1: ConvTransposeK::new(oc[1], oc[1], 2, vb.pp(1))?,
            resize3: C::load(ConvSpec::new(oc[3], oc[3], 3).stride(2), vb.pp(3))?,
        })
    }

    /// Level `i`'s projected map `(B, C_i, gh, gw)` → its scale.
    pub fn forward(&self, i: usize, xs: &Tensor) -> Result<Tensor> {
        match i {
            0 => self.resize0.forward(xs),
            1 => self.resize1.forward(xs),
            2 => Ok(xs.clone()),
            3 => self.resize3.forward_fused(&pad_to_even(xs)?, false, None, Act::None),
            _ => candle_core::bail!("DPT reassemble: no level {i} (levels 0 to 3)"),
        }
    }

    /// The same on the projected tokens as rows `(B·gh·gw, C_i)` in row-major grid order (the
    /// transposed convs read them as they are).
    pub fn forward_rows(&self, i: usize, rows: &Tensor, b: usize, gh: usize, gw: usize) -> Result<Tensor> {
        match i {
            0 => self.resize0.forward_rows(rows, b, gh, gw),
            1 => self.resize1.forward_rows(rows, b, gh, gw),
            _ => {
                let c = rows.dim(1)?;
                let grid = rows.reshape((b, gh, gw, c))?.permute((0, 3, 1, 2))?.contiguous()?;
                self.forward(i, &grid)
            }
        }
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

/// `x + conv2(relu(conv1(relu(x))))`, `resConfUnit*.conv{1,2}`.
#[derive(Clone, Debug)]
pub struct ResidualConvUnit<C> {
    conv1: C,
    conv2: C,
}

impl<C: DptConv> ResidualConvUnit<C> {
    pub fn new(features: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            conv1: C::load(ConvSpec::new(features, features, 3), vb.pp("conv1"))?,
            conv2: C::load(ConvSpec::new(features, features, 3), vb.pp("conv2"))?,
        })
    }

    /// Two convolutions: the ReLUs and the skip connection ride inside them.
    pub fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let ys = self.conv1.forward_fused(xs, true, None, Act::Relu)?;
        self.conv2.forward_fused(&ys, false, Some(xs), Act::None)
    }
}

/// DPT feature fusion block `refinenet{k}` (no expansion).
#[derive(Clone, Debug)]
pub struct FusionBlock<C> {
    res_conf_unit1: Option<ResidualConvUnit<C>>,
    res_conf_unit2: ResidualConvUnit<C>,
    out_conv: C,
    resize: ResizeFn,
}

impl<C: DptConv> FusionBlock<C> {
    /// `with_lateral`: whether the block has `resConfUnit1` (all but `refinenet4`).
    pub fn new(features: usize, with_lateral: bool, resize: ResizeFn, vb: VarBuilder) -> Result<Self> {
        let res_conf_unit1 = if with_lateral {
            Some(ResidualConvUnit::new(features, vb.pp("resConfUnit1"))?)
        } else {
            None
        };
        Ok(Self {
            res_conf_unit1,
            res_conf_unit2: ResidualConvUnit::new(features, vb.pp("resConfUnit2"))?,
            out_conv: C::load(ConvSpec::new(features, features, 1), vb.pp("out_conv"))?,
            resize,
        })
    }

    /// `path` (coarser), optional `lateral` (same size as `path`), output resized to `size`.
    pub fn forward(&self, path: &Tensor, lateral: Option<&Tensor>, size: (usize, usize)) -> Result<Tensor> {
        let xs = match (&self.res_conf_unit1, lateral) {
            (Some(rcu), Some(lateral)) => fused::residual(path, &rcu.forward(lateral)?)?,
            _ => path.clone(),
        };
        let xs = self.res_conf_unit2.forward(&xs)?;
        let xs = (self.resize)(&xs, size.0, size.1)?;
        self.out_conv.forward_fused(&xs, false, None, Act::None)
    }
}

/// `scratch.*` up to `output_conv1`: the four reassembled maps → one `features/2`-channel map.
#[derive(Clone, Debug)]
pub struct DptFusion<C> {
    layer_rn: Vec<C>,
    /// `refinenets[i]` is `refinenet{i+1}`.
    refinenets: Vec<FusionBlock<C>>,
    output_conv1: C,
    resize: ResizeFn,
}

impl<C: DptConv> DptFusion<C> {
    /// Reads `layer{1..4}_rn`, `refinenet{1..4}` and `output_conv1` under `vb` (the `scratch`
    /// prefix).
    pub fn new(out_channels: [usize; 4], features: usize, resize: ResizeFn, vb: VarBuilder) -> Result<Self> {
        let layer_rn = (0..4)
            .map(|i| {
                let spec = ConvSpec::new(out_channels[i], features, 3).no_bias();
                C::load(spec, vb.pp(format!("layer{}_rn", i + 1)))
            })
            .collect::<Result<Vec<_>>>()?;
        let refinenets = (0..4)
            .map(|i| FusionBlock::new(features, i < 3, resize, vb.pp(format!("refinenet{}", i + 1))))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self {
            layer_rn,
            refinenets,
            output_conv1: C::load(ConvSpec::new(features, features / 2, 3), vb.pp("output_conv1"))?,
            resize,
        })
    }

    /// The four reassembled maps (finest first) → `output_conv1`'s map resized to `(h, w)`,
    /// `(B, features/2, h, w)`. Each map is turned into its lateral as the iterator yields it,
    /// so a lazy iterator (reassembling level by level) holds one reassembled map at a time; a
    /// lateral is dropped once its fusion block has read it, and the fused path before the
    /// final resize (the largest maps come last).
    pub fn forward(&self, layers: impl IntoIterator<Item = Result<Tensor>>, h: usize, w: usize) -> Result<Tensor> {
        let mut laterals = Vec::with_capacity(4);
        for (xs, conv) in layers.into_iter().zip(&self.layer_rn) {
            laterals.push(conv.forward_fused(&xs?, false, None, Act::None)?);
        }
        if laterals.len() != 4 {
            candle_core::bail!("DPT fusion expects 4 maps, got {}", laterals.len());
        }
        let size = |t: &Tensor| -> Result<(usize, usize)> { Ok((t.dim(2)?, t.dim(3)?)) };
        // refinenet4 reads the coarsest map alone and resizes to the next finer one's size;
        // refinenet{k} (k = 3, 2, 1) adds lateral k-1 and resizes to lateral k-2's size (×2 for
        // refinenet1).
        let (h1, w1) = size(&laterals[0])?;
        let mut path = self.refinenets[3].forward(&laterals[3], None, size(&laterals[2])?)?;
        laterals.truncate(3);
        while let Some(lateral) = laterals.pop() {
            let k = laterals.len();
            let target = match laterals.last() {
                Some(finer) => size(finer)?,
                None => (2 * h1, 2 * w1),
            };
            path = self.refinenets[k].forward(&path, Some(&lateral), target)?;
        }
        let out = self.output_conv1.forward_fused(&path, false, None, Act::None)?;
        drop(path);
        (self.resize)(&out, h, w)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Module};

    #[test]
    fn kernel_stride_transposed_conv_matches_candle() -> Result<()> {
        let dev = Device::Cpu;
        for k in [2usize, 4] {
            let xs = Tensor::randn(0f32, 1.0, (2, 3, 3, 5), &dev)?;
            let w = Tensor::randn(0f32, 1.0, (3, 4, k, k), &dev)?;
            let b = Tensor::randn(0f32, 1.0, 4, &dev)?;
            let ours = ConvTransposeK::from_parts(w.clone(), b.clone())?.forward(&xs)?;
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

    /// Trained weights take the differentiable path: gradients reach both.
    #[test]
    fn transposed_conv_passes_gradients_to_its_weights() -> Result<()> {
        let dev = Device::Cpu;
        let w = candle_core::Var::randn(0f32, 1.0, (3, 2, 2, 2), &dev)?;
        let b = candle_core::Var::randn(0f32, 1.0, 2, &dev)?;
        let conv = ConvTransposeK::from_parts(w.as_tensor().clone(), b.as_tensor().clone())?;
        let xs = Tensor::randn(0f32, 1.0, (1, 3, 2, 3), &dev)?;
        let grads = conv.forward(&xs)?.sqr()?.sum_all()?.backward()?;
        assert!(grads.get(w.as_tensor()).is_some());
        assert!(grads.get(b.as_tensor()).is_some());
        Ok(())
    }
}
