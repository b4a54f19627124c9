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
//! ([`pixl_nn::dpt::ConvTransposeK`]). Steps 2 to 5 up to `output_conv1` are the DPT stages
//! shared with the Depth Anything 3 port ([`pixl_nn::dpt`]), built here from `layers::Conv`
//! (trainable, with the CPU fast paths) and [`resize_bilinear`].
use crate::config::Config;
use crate::layers::{conv2d, Conv};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};
use pixl_nn::dpt::{DptFusion, DptReassemble};
use pixl_nn::fused::Act;
use pixl_nn::ops::resize_bilinear;

/// The DPT head (`head.*`).
#[derive(Clone, Debug)]
pub struct DptHead {
    projects: Vec<Conv>,
    resize_layers: DptReassemble<Conv>,
    scratch: DptFusion<Conv>,
    /// `scratch.output_conv2.0`.
    output_conv2: Conv,
}

impl DptHead {
    pub fn new(cfg: &Config, vb: VarBuilder) -> Result<Self> {
        let (oc, f) = (cfg.head.out_channels, cfg.head.features);
        let projects = (0..4)
            .map(|i| conv2d(cfg.dim, oc[i], 1, Conv2dConfig::default(), vb.pp("projects").pp(i)))
            .collect::<Result<Vec<_>>>()?;
        let vs = vb.pp("scratch");
        let pad1 = Conv2dConfig {
            padding: 1,
            ..Default::default()
        };
        Ok(Self {
            projects,
            resize_layers: DptReassemble::new(oc, vb.pp("resize_layers"))?,
            scratch: DptFusion::new(oc, f, resize_bilinear, vs.clone())?,
            output_conv2: conv2d(f / 2, cfg.head.hidden, 3, pad1, vs.pp("output_conv2").pp(0))?,
        })
    }

    /// Four readouts `(B, d, gh, gw)` → `F` `(B, C', h, w)`.
    pub fn forward(&self, readouts: &[Tensor], h: usize, w: usize) -> Result<Tensor> {
        if readouts.len() != 4 {
            candle_core::bail!("DPT head expects 4 readouts, got {}", readouts.len());
        }
        let layers = (0..4).map(|i| self.resize_layers.forward(i, &self.projects[i].forward(&readouts[i])?));
        let out = self.scratch.forward(layers, h, w)?;
        self.output_conv2.forward_fused(&out, false, None, Act::Relu)
    }
}
