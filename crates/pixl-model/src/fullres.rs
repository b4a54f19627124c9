//! Relighting a photo of any size (paper §3.2, Eq. 4): the network runs at a *working
//! resolution* and its per-pixel gain and bias are resized to the photo and applied there,
//! `I_T = clip((1 + g↑) ⊙ I_S + b↑, 0, 1)` at full resolution, so detail is the photo's own and
//! memory is bounded by the working size.
//!
//! - [`working_size`]: the photo's size scaled so its long side is at most `max_side`
//!   (aspect kept, rounded to whole pixels; unchanged if already small enough).
//! - [`area_resize_to_chw`]: box-filter (area-average) resampling of an interleaved image into
//!   planar `C × oh × ow` ([`pixl_core::resample`]) — how the photo and a full-size `C_T` reach
//!   the working size.
//! - [`apply_gain_bias`]: the gain and bias maps `(3, gh, gw)` bilinearly resized (half-pixel
//!   centres, `align_corners = false`, as [`pixl_nn::ops::resize_bilinear`]) and applied to the
//!   photo in place, in f32, clipped to `[0, 1]`. With `g ≡ b ≡ 0` the photo is unchanged bit for bit.
//! - [`gain_bias_staged`]: the network's gain and bias through its segment API, calling back
//!   after every block (for progress bars); bitwise the same values as
//!   [`PixlRelight::gain_bias`], with the encoders' tokens dropped as soon as they are fused.
//! - [`relight_full`]: the three steps together.
//! - [`plan_memory`]: the bytes [`gain_bias_staged`] holds at its peak, derived from the
//!   activation sizes of every stage of the network (module docs of [`MemoryPlan`]).
use crate::config::Config;
use crate::model::PixlRelight;
use candle_core::{DType, Device, Tensor};
use pixl_core::Image;
use pixl_nn::conv3x3::{self, tile_pixels};
use pixl_nn::winograd;

/// A request this module cannot serve.
#[derive(Debug, thiserror::Error)]
pub enum FullResError {
    #[error("{0}")]
    Size(String),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

pub type Result<T, E = FullResError> = std::result::Result<T, E>;

/// `(width, height)` scaled so that the long side is at most `max_side`, aspect kept; each side
/// rounded to the nearest pixel and at least 1. Unchanged when the long side already fits.
/// `max_side = 0` is treated as 1.
pub fn working_size(width: usize, height: usize, max_side: usize) -> (usize, usize) {
    let long = width.max(height);
    let max_side = max_side.max(1);
    if long <= max_side {
        return (width, height);
    }
    let scale = max_side as f64 / long as f64;
    let side = |n: usize| {
        if n == long {
            max_side
        } else {
            ((n as f64 * scale).round() as usize).clamp(1, max_side)
        }
    };
    (side(width), side(height))
}

/// Area-average resampling of `img` (interleaved, any channel count) to `ow × oh`, returned
/// planar (`channels × oh × ow`, the layout tensors use): [`pixl_core::resample::area_resize_to_chw`]
/// with this module's error.
pub fn area_resize_to_chw(img: &Image, ow: usize, oh: usize) -> Result<Vec<f32>> {
    pixl_core::resample::area_resize_to_chw(img, ow, oh).map_err(|e| FullResError::Size(e.to_string()))
}

/// One output coordinate's bilinear taps: `v = a·(1 − f) + b·f` with `a` at `i0`, `b` at `i1`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Tap {
    i0: usize,
    i1: usize,
    f: f32,
}

/// Half-pixel-centre taps from `n_in` samples to `n_out` (`align_corners = false`): source
/// coordinate `(o + 0.5)·n_in/n_out − 0.5`, clamped below at 0, upper neighbour clamped to the
/// last sample (as PyTorch and [`pixl_nn::ops::resize_bilinear`]).
fn bilinear_taps(n_in: usize, n_out: usize) -> Vec<Tap> {
    let scale = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|o| {
            let src = ((o as f64 + 0.5) * scale - 0.5).max(0.0);
            let i0 = (src.floor() as usize).min(n_in - 1);
            let i1 = (i0 + 1).min(n_in - 1);
            Tap {
                i0,
                i1,
                f: (src - i0 as f64).clamp(0.0, 1.0) as f32,
            }
        })
        .collect()
}

#[inline]
fn lerp(a: f32, b: f32, f: f32) -> f32 {
    a * (1.0 - f) + b * f
}

/// `photo ← clip((1 + g↑) ⊙ photo + b↑, 0, 1)` in place, where `g↑`, `b↑` are the planar
/// `(3, gh, gw)` maps `gain`, `bias` bilinearly resized to the photo's size (half-pixel
/// centres; at the same size they are used as they are). `photo` must have 3 channels.
pub fn apply_gain_bias(photo: &mut Image, gain: &[f32], bias: &[f32], gw: usize, gh: usize) -> Result<()> {
    let (w, h) = (photo.width, photo.height);
    if photo.channels != 3 || photo.data.len() != w * h * 3 {
        return Err(FullResError::Size(format!(
            "the photo must be RGB (3 channels), got {} channels",
            photo.channels
        )));
    }
    if gw == 0 || gh == 0 || gain.len() != 3 * gw * gh || bias.len() != 3 * gw * gh {
        return Err(FullResError::Size(format!(
            "gain ({} values) and bias ({} values) must both be 3x{gh}x{gw}",
            gain.len(),
            bias.len()
        )));
    }
    let tx = bilinear_taps(gw, w);
    let ty = bilinear_taps(gh, h);
    let plane = gw * gh;
    // One output row at a time: the two working rows it reads, interpolated across first.
    let mut hg = vec![[0f32; 2]; w * 3];
    let mut hb = vec![[0f32; 2]; w * 3];
    for (y, t) in ty.iter().enumerate() {
        for c in 0..3 {
            let (g0, g1) = (c * plane + t.i0 * gw, c * plane + t.i1 * gw);
            for (x, s) in tx.iter().enumerate() {
                hg[x * 3 + c] = [
                    lerp(gain[g0 + s.i0], gain[g0 + s.i1], s.f),
                    lerp(gain[g1 + s.i0], gain[g1 + s.i1], s.f),
                ];
                hb[x * 3 + c] = [
                    lerp(bias[g0 + s.i0], bias[g0 + s.i1], s.f),
                    lerp(bias[g1 + s.i0], bias[g1 + s.i1], s.f),
                ];
            }
        }
        let line = &mut photo.data[y * w * 3..(y + 1) * w * 3];
        for (i, v) in line.iter_mut().enumerate() {
            let g = lerp(hg[i][0], hg[i][1], t.f);
            let b = lerp(hb[i][0], hb[i][1], t.f);
            // The same operations, in the same order, as `Modulation::apply`.
            *v = ((g + 1.0) * *v + b).clamp(0.0, 1.0);
        }
    }
    Ok(())
}

/// What [`gain_bias_staged`] reports after each step: `done` of `total` steps, and the step's name.
pub type StageProgress<'a> = &'a mut dyn FnMut(usize, usize, &str);

/// [`PixlRelight::gain_bias`] computed block by block through the model's segment API, calling
/// `progress(done, total, stage)` after each block (source encoder blocks, the intrinsics
/// encoder, trunk blocks, the head). The values are bitwise those of `gain_bias`; the source and
/// intrinsics tokens are dropped as soon as they are fused, and a trunk block's output is kept
/// only when it is a readout.
pub fn gain_bias_staged(
    model: &PixlRelight,
    src: &Tensor,
    ct: &Tensor,
    progress: StageProgress,
) -> candle_core::Result<(Tensor, Tensor)> {
    let p = model.prepare(src, ct)?;
    let enc = model.src_encoder();
    let trunk = model.trunk();
    let total = enc.depth() + 1 + trunk.depth() + 1;
    let mut done = 0;
    let mut tick = |stage: &str| {
        done += 1;
        progress(done, total, stage);
    };
    let mut xs = enc.embed(&p.src)?;
    for j in 0..enc.depth() {
        xs = enc.block(j, &xs)?;
        tick("source encoder");
    }
    let cond = model.cond_tokens(&p)?;
    tick("intrinsics encoder");
    let mut hs = model.fuse_tokens(&xs, &cond)?;
    drop((xs, cond));
    let readouts = trunk.readouts();
    let mut kept = Vec::with_capacity(readouts.len());
    for i in 0..trunk.depth() {
        hs = trunk.block(i, &hs, &p.grid)?;
        if readouts.contains(&i) {
            kept.push(hs.clone());
        }
        tick("trunk");
    }
    drop(hs);
    let out = model.tail_gain_bias(&kept, &p)?;
    tick("head");
    Ok(out)
}

/// Relights `photo` (RGB, values in `[0, 1]`, any size) under `ct_work` (planar `9 × wh × ww`,
/// the C_T at the working size): the photo is area-averaged to `(ww, wh)`, the network predicts
/// gain and bias there ([`gain_bias_staged`]), and they are applied to the full-size photo
/// ([`apply_gain_bias`]). The photo's buffer becomes the output (no second full-size copy).
pub fn relight_full(
    model: &PixlRelight,
    mut photo: Image,
    ct_work: &[f32],
    work: (usize, usize),
    device: &Device,
    progress: StageProgress,
) -> Result<Image> {
    let (ww, wh) = work;
    if ct_work.len() != 9 * ww * wh {
        return Err(FullResError::Size(format!(
            "C_T has {} values, expected 9x{wh}x{ww} at the working size",
            ct_work.len()
        )));
    }
    let src = area_resize_to_chw(&photo, ww, wh)?;
    let src = Tensor::from_vec(src, (1, 3, wh, ww), device)?;
    let ct = Tensor::from_vec(ct_work.to_vec(), (1, 9, wh, ww), device)?;
    let (g, b) = gain_bias_staged(model, &src, &ct, progress)?;
    drop((src, ct));
    let flat =
        |t: &Tensor| -> candle_core::Result<Vec<f32>> { t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>() };
    let (g, b) = (flat(&g)?, flat(&b)?);
    apply_gain_bias(&mut photo, &g, &b, ww, wh)?;
    Ok(photo)
}

/// The memory [`gain_bias_staged`] needs at its peak for one image, by stage.
///
/// Each stage's figure is the sum of the tensors alive at that stage's worst moment, counted
/// from the activation shapes the config and the padded size give (`N` tokens of width `d`, `T
/// = N + registers` in the trunk, `h` heads, feature maps of the DPT head at strides `p/4 … 2`
/// and at full size), plus what stays alive across stages: the weights, the inputs, the RoPE
/// tables, kept readouts. Dominant terms: in bf16 the attention scores and their softmax, `2·h·T²`
/// elements per block (in f32 the fused attention kernel holds only one block of query rows'
/// scores per thread), and the head's last two full-resolution convolutions, `(C/2 + 2C')·H·W`.
/// The buffers candle's kernels use inside one op are counted: the channels-last copy of a
/// convolution's input, one im2col tile per thread, the bias added after a matmul, and per
/// thread [`KERNEL_WORKSPACE_PER_THREAD`] and [`KERNEL_SCRATCH_PER_THREAD`] for the kernels'
/// own buffers. Checked against a counting allocator
/// in `tests/memory_plan.rs`.
#[derive(Clone, Debug, PartialEq)]
pub struct MemoryPlan {
    /// Working size the plan is for.
    pub width: usize,
    pub height: usize,
    /// Tokens per image (`N`, without registers).
    pub tokens: usize,
    /// Bytes of the weights.
    pub weights: u64,
    /// `(stage, bytes alive at its peak, weights and inputs included)`, in forward order.
    pub stages: Vec<(&'static str, u64)>,
}

impl MemoryPlan {
    /// The largest stage: its name and bytes.
    pub fn peak(&self) -> (&'static str, u64) {
        self.stages
            .iter()
            .copied()
            .max_by_key(|s| s.1)
            .unwrap_or(("weights", self.weights))
    }

    /// Peak bytes.
    pub fn peak_bytes(&self) -> u64 {
        self.peak().1
    }
}

/// Bytes per worker thread of the matrix kernels' own buffers (packing blocks, grown on first
/// use and kept), allowed at every stage. Their size follows the CPU's cache sizes: measured
/// 2.9 MB per thread on an Intel Xeon with 2 MiB of L2 per core and 105 MiB of L3, under 2 MB
/// on CPUs with smaller caches.
pub const KERNEL_WORKSPACE_PER_THREAD: u64 = 4 << 20;
/// Bytes per worker thread of small buffers allocated anew inside every kernel call (measured:
/// 0.3–0.5 MB with two threads), allowed at every stage.
pub const KERNEL_SCRATCH_PER_THREAD: u64 = 512 << 10;
/// Output pixels per im2col tile of candle's CPU convolution (one tile per thread in flight).
const CONV_TILE: u64 = 512;

/// The bytes [`relight_full`] / [`gain_bias_staged`] hold at their peak for a `width × height`
/// working image with the network `cfg` in `dtype` (see [`MemoryPlan`]), with as many
/// convolution tiles in flight as this machine has threads. The full-size photo itself is the
/// caller's to count.
pub fn plan_memory(cfg: &Config, dtype: DType, width: usize, height: usize) -> MemoryPlan {
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    plan_memory_threads(cfg, dtype, width, height, threads)
}

/// [`plan_memory`] for `threads` worker threads (each holds one im2col tile of a convolution).
pub fn plan_memory_threads(cfg: &Config, dtype: DType, width: usize, height: usize, threads: usize) -> MemoryPlan {
    let s = dtype.size_in_bytes() as u64;
    let f = 4u64; // f32 values: inputs, RoPE tables, gain and bias
    let u = |n: usize| n as u64;
    let p = cfg.patch;
    let (ph, pw) = (u(height.div_ceil(p) * p), u(width.div_ceil(p) * p));
    let (gh, gw) = (ph / u(p), pw / u(p));
    let n = gh * gw;
    let t = n + u(cfg.trunk.registers);
    let d = u(cfg.dim);
    let (hw, px) = (u(width) * u(height), ph * pw);
    // f32 and bf16 convolutions on the CPU widen to f32 (layers::Conv); count conv buffers in f32.
    let cs = if dtype == DType::BF16 { f } else { s };

    // One `k × k` convolution's im2col tiles in flight (columns and results, f32): one per
    // thread, at most one per `CONV_TILE` output pixels.
    let threads = u(threads.max(1));
    let tiles = |cin: u64, cout: u64, k: u64, out_px: u64| {
        threads.min(out_px.div_ceil(CONV_TILE)) * CONV_TILE.min(out_px) * (cin * k * k + cout) * f
    };
    // A 3×3 convolution of the CPU f32 path: one im2col tile per thread at work (a single one
    // when there are fewer tiles than threads), written straight into the output
    // (`pixl_nn::conv3x3`), or a Winograd block per thread (`pixl_nn::winograd`); in bf16
    // candle's conv2d as above.
    let fast = dtype == DType::F32;
    let tiles3 = |cin: u64, cout: u64, out_px: u64| {
        if !fast {
            return tiles(cin, cout, 3, out_px);
        }
        let n = out_px.div_ceil(u(tile_pixels(cin as usize)));
        let workers = if n < threads { 1 } else { threads };
        let im2col = workers * f * u(conv3x3::scratch_floats(cin as usize, out_px as usize));
        // Stride 1 from 64×64 up: Winograd blocks (one per thread) and the transformed weights.
        let wino = if out_px >= 64 * 64 {
            threads * f * u(winograd::scratch_floats(cin as usize, cout as usize)) + 36 * cin * cout * f
        } else {
            0
        };
        im2col.max(wino)
    };

    let weights = u(cfg.param_count()) * s;
    let inputs = 12 * hw * f;
    let prepared = if dtype == DType::F32 && px == hw {
        0
    } else {
        12 * px * s
    };
    let rope = 2 * n * u(cfg.trunk_head_dim()) * f;
    // f32 attention runs in the fused kernel, whose per-thread block of scores is kept like the
    // matrix kernels' workspace (sized for the longest sequence, the trunk's).
    let attention_scratch = if dtype == DType::F32 {
        f * u(pixl_nn::attention::fused_scratch_floats(t as usize))
    } else {
        0
    };
    let base = weights
        + inputs
        + prepared
        + rope
        + threads * (KERNEL_WORKSPACE_PER_THREAD + KERNEL_SCRATCH_PER_THREAD + attention_scratch);

    // One transformer block over `k` tokens with `heads` heads and MLP ratio `r`:
    // attention: input, norm, qkv, q, k, v, scores (bf16: scores and softmax of all heads; f32:
    // the fused kernel's blocks, in `base`), output (+ 5 token maps of RoPE temporaries in the
    // trunk); MLP: input, residual, norm, fc1, GELU, fc2 and its bias.
    let attention = |k: u64, heads: u64, rope: bool| {
        let scores = if dtype == DType::F32 { 0 } else { s * 2 * heads * k * k };
        s * (9 * k * d + if rope { 5 * k * d } else { 0 }) + scores
    };
    let mlp = |k: u64, r: u64| s * k * d * (5 + 2 * r);
    let v = &cfg.src_encoder;
    let patch_embed = cs * (3 * px + 2 * n * d) + tiles(3, d, u(p), n);
    let src_blocks = attention(n, u(v.heads), false).max(mlp(n, u(v.mlp_ratio)));

    // Intrinsics encoder: stem conv (channels-last copy of C_T, output, bias), then per stage
    // its transition (LayerNorm2d copies, conv) and ConvNeXt blocks (13 maps of the stage's
    // width: input, dwconv copy, norm, fc1 ×4, GELU ×4, fc2 and bias).
    let c = &cfg.cond_encoder;
    let (mut ah, mut aw) = (ph / 4, pw / 4);
    let mut cond = cs * (9 * px + 2 * u(c.dims[0]) * ah * aw)
        + s * 3 * u(c.dims[0]) * ah * aw
        + tiles(9, u(c.dims[0]), 4, ah * aw);
    for st in 0..4 {
        let ch = u(c.dims[st]);
        if st > 0 {
            let prev = u(c.dims[st - 1]) * ah * aw;
            if cfg.cond_downsamples(st) {
                ah = ah.div_ceil(2);
                aw = aw.div_ceil(2);
            }
            let conv_tiles = if cfg.cond_downsamples(st) {
                tiles(u(c.dims[st - 1]), ch, 2, ah * aw)
            } else {
                0
            };
            cond = cond.max(s * 2 * prev + cs * (prev + 3 * ch * ah * aw) + conv_tiles);
        }
        cond = cond.max(s * 13 * ch * ah * aw);
    }
    let cond = n * d * s + cond; // the source tokens wait for the fusion

    let fuse = s * n * d * 9;
    let tr = &cfg.trunk;
    // Kept across the trunk: up to three readout block outputs before the last block runs.
    let trunk_kept = 3 * t * d * s;
    let trunk_blocks = trunk_kept + attention(t, u(tr.heads), true).max(mlp(t, u(tr.mlp_ratio)));

    // DPT head. Maps: readouts (4 N d), layers at strides p/4, p/2, p, 2p (16N, 4N, N, N/4 of
    // `f` channels), refinenet1 at stride p/4 then ×2 (64N), output_conv1 (f/2 channels at 64N),
    // the resize to full size (f/2 channels) and output_conv2 (C' channels), then modulation.
    let h = &cfg.head;
    let (oc, fe, hid) = (h.out_channels.map(u), u(h.features), u(h.hidden));
    let kept_blocks = 4 * t * d * s;
    let readouts = 4 * n * d * s;
    let n3 = gh.div_ceil(2) * gw.div_ceil(2);
    let layers = fe * (16 * n + 4 * n + n + n3) * cs;
    let project = cs * (n * d + 3 * oc[0] * n);
    let resize0 = cs * (oc[0] * n + 48 * oc[0] * n);
    let rn_px = [16 * n, 4 * n, n, n3];
    let rn_tiles = (0..4)
        .map(|i| tiles3(oc[i], fe, rn_px[i]))
        .max()
        .unwrap_or(0)
        .max(tiles3(oc[3], oc[3], n3));
    let head_layers = kept_blocks + readouts + project.max(resize0 + cs * 16 * fe * n + rn_tiles) + layers;
    // refinenet1: lateral 0 (the coarser laterals and paths are dropped as they are read), the
    // path, its residual units, the ×2 resize and the 1×1 out_conv. f32: a unit is its input and
    // two conv outputs (ReLUs and skip fused), the out_conv the resized map and its output (the
    // matrix product added to the bias in place); bf16: 7 maps per unit, and the out_conv's input
    // copy, matmul result, output and bias.
    let (rcu_maps, out_conv_maps) = if fast { (3, 2) } else { (7, 4) };
    let rcu = |a: u64| cs * rcu_maps * fe * a;
    let refine1 = kept_blocks
        + readouts
        + cs * 16 * fe * n
        + cs * 16 * fe * n * 3
        + (rcu(16 * n) + tiles3(fe, fe, 16 * n)).max(cs * fe * 64 * n * out_conv_maps);
    // output_conv1: refinenet1's output and the conv's (f/2 channels), with the conv's scratch.
    let out1 = kept_blocks + readouts + cs * (fe + fe / 2) * 64 * n + tiles3(fe, fe / 2, 64 * n);
    // The resize of output_conv1's map to full size (refinenet1's output dropped), then
    // output_conv2 on the resized map alone. The conv's scratch is this stage's per-call kernel
    // buffers, already allowed in `base`: only what exceeds that allowance is added.
    let resize_full = cs * (fe / 2 * 64 * n + fe / 2 * px);
    let conv2 = if fast {
        // output_conv2 writes its result straight from the resized map, ReLU fused.
        cs * (fe / 2 * px + hid * px)
    } else {
        cs * (fe / 2 * px + (fe / 2 * px + hid * px).max(2 * hid * px))
    } + tiles3(fe / 2, hid, px).saturating_sub(threads * KERNEL_SCRATCH_PER_THREAD);
    let tail = kept_blocks + readouts + resize_full.max(conv2);
    // Modulation: F, then the six maps (f32: the matrix product added to the bias in place;
    // bf16: F's copy for candle's 1×1 conv, result, output, bias), then the cropped gain and bias
    // as f32 vectors.
    let modulation = if fast {
        cs * (hid * px + 6 * px)
    } else {
        cs * (2 * hid * px + 18 * px)
    } + 2 * 6 * hw * f;

    let stages = vec![
        ("patch embedding", base + patch_embed),
        ("source encoder", base + src_blocks),
        ("intrinsics encoder", base + cond),
        ("fusion", base + fuse),
        ("trunk", base + trunk_blocks),
        ("head (projections)", base + head_layers),
        ("head (refinenet)", base + refine1),
        ("head (stride-2 conv)", base + out1),
        ("head (full-resolution convs)", base + tail),
        ("modulation", base + modulation),
    ];
    MemoryPlan {
        width,
        height,
        tokens: n as usize,
        weights,
        stages,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn working_size_keeps_the_aspect_and_caps_the_long_side() {
        assert_eq!(working_size(4000, 3000, 1024), (1024, 768));
        assert_eq!(working_size(3000, 4000, 1024), (768, 1024));
        assert_eq!(working_size(600, 400, 1024), (600, 400));
        assert_eq!(working_size(1025, 3, 1024), (1024, 3));
        assert_eq!(working_size(5000, 1, 100), (100, 1));
        assert_eq!(working_size(7, 5, 0), (1, 1));
    }
}
