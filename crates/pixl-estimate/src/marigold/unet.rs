//! diffusers' `UNet2DConditionModel` of the Stable Diffusion 2 family, the denoiser of every
//! Marigold checkpoint, written here so that its CPU forward runs on the crate's parallel
//! kernels and so that every config field of the family is honoured ([`UnetConfig`]).
//!
//! Contract of [`UNet2DConditionModel::forward`]: `sample` `(B, in_channels, h, w)` f32, a
//! timestep `t` (the same for the whole batch), `encoder_hidden_states` `(B, tokens,
//! cross_attention_dim)` → `(B, out_channels, h, w)`; any `h`, `w` ≥ 1 (a side that is not a
//! multiple of `2^(levels − 1)` upsamples to the skip connection's size, as diffusers does).
//!
//! The arithmetic is diffusers' (0.42), block by block:
//! - time: `t·exp(−ln(10⁴)·k/(half − freq_shift))` in f32, `[sin, cos]` (flipped to
//!   `[cos, sin]` by `flip_sin_to_cos`), `time_embedding.linear_2(silu(linear_1(·)))`;
//! - `conv_in` (3×3); down blocks (ResNets, each followed by a transformer in
//!   `CrossAttnDownBlock2D`; then a stride-2 3×3 convolution but in the last block), every
//!   output kept as a skip connection; the mid block (ResNet, transformer, ResNet, outputs
//!   divided by `mid_block_scale_factor`); up blocks (`cat[h, skip]`, ResNet, transformer in
//!   `CrossAttnUpBlock2D`; nearest ×2 — or to the next skip's size — and a 3×3 convolution);
//!   `conv_out(silu(conv_norm_out(h)))`;
//! - `ResnetBlock2D`: `x + conv2(silu(gn2(conv1(silu(gn1(x))) + time_emb_proj(silu(temb)))))`,
//!   a 1×1 `conv_shortcut` on `x` when the width changes; GroupNorm with `norm_num_groups`
//!   groups and `norm_eps`;
//! - `Transformer2DModel`: GroupNorm (same groups, ε = 1e-6), `proj_in` (linear, or a 1×1
//!   convolution: the same product), `BasicTransformerBlock`s, `proj_out`, plus the input;
//! - `BasicTransformerBlock`: LayerNorm (ε = 1e-5) → self-attention, LayerNorm → cross-attention
//!   on the text, LayerNorm → GEGLU feed-forward (`ff.net.0.proj` to 2×4C, `value · gelu(gate)`
//!   with the **exact erf** GELU, `ff.net.2`), each with its residual; q, k, v without bias,
//!   `to_out.0` with; heads of `C / attention_head_dim[i]` channels, softmax(q·kᵀ/√d)·v.
//!
//! Tensor names are those diffusers saves: `conv_in`, `time_embedding.linear_{1,2}`,
//! `down_blocks.i.{resnets.j.{norm1, conv1, time_emb_proj, norm2, conv2, conv_shortcut},
//! attentions.j.{norm, proj_in, transformer_blocks.k.{norm1, attn1.{to_q, to_k, to_v, to_out.0},
//! norm2, attn2.…, norm3, ff.net.0.proj, ff.net.2}, proj_out}, downsamplers.0.conv}`,
//! `mid_block.{resnets.0, attentions.0, resnets.1}`, `up_blocks.i.{resnets.j, attentions.j,
//! upsamplers.0.conv}`, `conv_norm_out`, `conv_out`.
//!
//! On the CPU in f32 (the case Marigold runs): 3×3 convolutions through [`Conv3x3`] (Winograd
//! from 64×64 up, bias and skip connection in the same pass), 1×1 shortcuts through
//! [`pixl_nn::fused::conv1x1`], and the rest through the kernels below — GroupNorm with the
//! time embedding added and SiLU in one pass per group, LayerNorm, linear layers as one GEMM
//! into bias- (and residual-) filled outputs, `proj_in`/`proj_out` read and written
//! channels-first by the GEMM itself (no transposed copies), and multi-head attention reading
//! each head in place from the token rows (no head split or merge), blocks of query rows whose
//! scores stay in L2. Other devices take the same arithmetic through candle's ops. Inference
//! only: nothing here has a backward pass.
use super::config::{DownBlockType, UnetConfig, UpBlockType};
use candle_core::{bail, DType, Result, Storage, Tensor, D};
use candle_nn::VarBuilder;
use pixl_nn::conv3x3::Conv3x3;
use pixl_nn::fastmath;
use pixl_nn::fused::{self, Act, Vector};
use rayon::prelude::*;
use std::cell::RefCell;

/// GroupNorm epsilon of `Transformer2DModel.norm` (fixed in diffusers).
const TRANSFORMER_GN_EPS: f64 = 1e-6;
/// LayerNorm epsilon of `BasicTransformerBlock.norm1/2/3` (diffusers' default).
const LAYER_NORM_EPS: f32 = 1e-5;

// ---------------------------------------------------------------------------------------------
// CPU helpers

/// Whether `xs` takes the CPU kernels (f32 on the CPU).
fn cpu(xs: &Tensor) -> bool {
    fused::cpu_f32(xs)
}

/// Runs `f` on the f32 values of a CPU tensor (made contiguous first), borrowed.
fn with_values<R>(xs: &Tensor, f: impl FnOnce(&[f32]) -> Result<R>) -> Result<R> {
    let xs = xs.contiguous()?;
    let (storage, layout) = xs.storage_and_layout();
    let Storage::Cpu(cpu) = &*storage else {
        bail!("expected a CPU tensor");
    };
    let values = cpu.as_slice::<f32>()?;
    let Some((a, b)) = layout.contiguous_offsets() else {
        bail!("expected a contiguous tensor");
    };
    f(&values[a..b])
}

/// The `gemm` crate's parallelism over rayon's pool.
fn parallel() -> gemm::Parallelism {
    match rayon::current_num_threads() {
        0 | 1 => gemm::Parallelism::None,
        n => gemm::Parallelism::Rayon(n),
    }
}

/// A matrix operand inside a slice: element `(i, j)` is `data[i·rs + j·cs]`.
#[derive(Clone, Copy)]
struct Mat<'a> {
    data: &'a [f32],
    rs: usize,
    cs: usize,
}

impl Mat<'_> {
    /// Errors unless an `r × c` matrix with these strides lies inside the slice.
    fn check(&self, r: usize, c: usize, what: &str) -> Result<()> {
        if r > 0 && c > 0 && (r - 1) * self.rs + (c - 1) * self.cs >= self.data.len() {
            bail!("{what}: a {r}x{c} operand does not fit its {} values", self.data.len());
        }
        Ok(())
    }
}

/// `dst = [dst +] lhs · rhs`: `lhs` m×k, `rhs` k×n, `dst` m×n with strides `(rs, cs)`, its old
/// values kept (added to) when `accumulate`.
#[allow(clippy::too_many_arguments)]
fn matmul(
    (m, n, k): (usize, usize, usize),
    dst: &mut [f32],
    (rs, cs): (usize, usize),
    accumulate: bool,
    lhs: Mat,
    rhs: Mat,
    par: gemm::Parallelism,
) -> Result<()> {
    Mat { data: dst, rs, cs }.check(m, n, "matmul output")?;
    lhs.check(m, k, "matmul lhs")?;
    rhs.check(k, n, "matmul rhs")?;
    if m == 0 || n == 0 {
        return Ok(());
    }
    if k == 0 {
        if !accumulate {
            for i in 0..m {
                for j in 0..n {
                    dst[i * rs + j * cs] = 0.0;
                }
            }
        }
        return Ok(());
    }
    // SAFETY: the three checks above keep every element the GEMM touches inside its slice, and
    // `dst` is borrowed mutably for the call.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            cs as isize,
            rs as isize,
            accumulate,
            lhs.data.as_ptr(),
            lhs.cs as isize,
            lhs.rs as isize,
            rhs.data.as_ptr(),
            rhs.cs as isize,
            rhs.rs as isize,
            1.0f32,
            1.0f32,
            false,
            false,
            false,
            par,
        );
    }
    Ok(())
}

/// `x · σ(x)` with the vectorisable exp.
#[inline(always)]
fn silu(x: f32) -> f32 {
    x / (1.0 + fastmath::exp(-x))
}

/// `v = act(v)` over `out`, in parallel.
fn act_in_place(out: &mut [f32], act: Act) {
    match act {
        Act::None => {}
        Act::Gelu => out.par_chunks_mut(1 << 14).for_each(fastmath::gelu_in_place),
        Act::Silu => out
            .par_chunks_mut(1 << 14)
            .for_each(|c| c.iter_mut().for_each(|v| *v = silu(*v))),
        other => out
            .par_chunks_mut(1 << 14)
            .for_each(|c| c.iter_mut().for_each(|v| *v = other.apply(*v))),
    }
}

/// candle's ops for an activation (the path off the CPU).
fn act_tensor(xs: Tensor, act: Act) -> Result<Tensor> {
    match act {
        Act::None => Ok(xs),
        Act::Gelu => xs.gelu_erf(),
        Act::Relu => xs.relu(),
        Act::Silu => candle_nn::ops::silu(&xs),
    }
}

// ---------------------------------------------------------------------------------------------
// Layers

/// `GroupNorm(groups, C, eps)` over `(B, C, H, W)`, optionally on `x + shift[b, c]` and followed
/// by an activation.
struct GroupNorm {
    groups: usize,
    eps: f64,
    weight: Vector,
    bias: Vector,
}

impl GroupNorm {
    fn new(groups: usize, channels: usize, eps: f64, vb: VarBuilder) -> Result<Self> {
        if groups == 0 || !channels.is_multiple_of(groups) {
            bail!("GroupNorm: {groups} groups do not divide {channels} channels");
        }
        Ok(Self {
            groups,
            eps,
            weight: Vector::new(vb.get(channels, "weight")?)?,
            bias: Vector::new(vb.get(channels, "bias")?)?,
        })
    }

    /// `act(GroupNorm(xs + shift))`, `shift` `(B, C)` broadcast over the pixels. Statistics per
    /// sample and group in f64 (biased variance), `(v − μ)/√(σ² + ε)·γ + β` in f32.
    fn forward(&self, xs: &Tensor, shift: Option<&Tensor>, act: Act) -> Result<Tensor> {
        let (b, c, h, w) = xs.dims4()?;
        if c != self.weight.len() {
            bail!("GroupNorm of {} channels given {c}", self.weight.len());
        }
        if let Some(s) = shift {
            if s.dims() != [b, c] {
                bail!("GroupNorm shift {:?} for an input {:?}", s.dims(), xs.dims());
            }
        }
        if !cpu(xs) || shift.is_some_and(|s| !cpu(s)) {
            let xs = match shift {
                Some(s) => xs.broadcast_add(&s.reshape((b, c, 1, 1))?)?,
                None => xs.clone(),
            };
            let g = xs.reshape((b, self.groups, ()))?;
            let mean = g.mean_keepdim(2)?;
            let centred = g.broadcast_sub(&mean)?;
            let var = centred.sqr()?.mean_keepdim(2)?;
            let normed = centred
                .broadcast_div(&(var + self.eps)?.sqrt()?)?
                .reshape((b, c, h, w))?;
            let y = normed
                .broadcast_mul(&self.weight.tensor.reshape((1, c, 1, 1))?)?
                .broadcast_add(&self.bias.tensor.reshape((1, c, 1, 1))?)?;
            return act_tensor(y, act);
        }
        let _t = pixl_nn::profile::span("group norm");
        let shift = shift.map(|s| s.flatten_all()?.to_vec1::<f32>()).transpose()?;
        let (hw, cg) = (h * w, c / self.groups);
        let mut out = vec![0f32; b * c * hw];
        if out.is_empty() {
            return Tensor::from_vec(out, (b, c, h, w), xs.device());
        }
        let (gamma, beta) = (self.weight.values(), self.bias.values());
        let groups = self.groups;
        with_values(xs, |x| {
            out.par_chunks_mut(cg * hw)
                .zip(x.par_chunks(cg * hw))
                .enumerate()
                .for_each(|(k, (dst, src))| {
                    let (bi, c0) = (k / groups, (k % groups) * cg);
                    let sh = |j: usize| shift.as_ref().map_or(0.0, |s| s[bi * c + c0 + j]);
                    let (mut sum, mut sq) = (0f64, 0f64);
                    for j in 0..cg {
                        let s = sh(j);
                        sum += lane_sum(&src[j * hw..(j + 1) * hw], s, |v| v);
                    }
                    let mean = sum / (cg * hw) as f64;
                    for j in 0..cg {
                        sq += lane_sum(&src[j * hw..(j + 1) * hw], sh(j), |v| (v - mean) * (v - mean));
                    }
                    let rstd = 1.0 / (sq / (cg * hw) as f64 + self.eps).sqrt();
                    for j in 0..cg {
                        let ch = c0 + j;
                        let a = (rstd * gamma[ch] as f64) as f32;
                        let off = beta[ch] - (mean as f32) * a;
                        let s = sh(j);
                        normalise(
                            &src[j * hw..(j + 1) * hw],
                            &mut dst[j * hw..(j + 1) * hw],
                            s,
                            (a, off),
                            act,
                        );
                    }
                });
            Ok(())
        })?;
        Tensor::from_vec(out, (b, c, h, w), xs.device())
    }
}

/// `Σ f(x + s)` over `xs`: f32 values, f64 lane accumulators.
#[inline(always)]
fn lane_sum(xs: &[f32], s: f32, f: impl Fn(f64) -> f64) -> f64 {
    const L: usize = 8;
    let mut acc = [0f64; L];
    let mut chunks = xs.chunks_exact(L);
    for ch in &mut chunks {
        for (a, &v) in acc.iter_mut().zip(ch) {
            *a += f((v + s) as f64);
        }
    }
    acc.iter().sum::<f64>() + chunks.remainder().iter().map(|&v| f((v + s) as f64)).sum::<f64>()
}

/// `dst = act((src + s)·a + off)`, the GroupNorm's per-channel affine step.
#[inline(always)]
fn normalise_generic(src: &[f32], dst: &mut [f32], s: f32, (a, off): (f32, f32), act: Act) {
    match act {
        Act::Silu => {
            for (d, &v) in dst.iter_mut().zip(src) {
                *d = silu((v + s) * a + off);
            }
        }
        _ => {
            for (d, &v) in dst.iter_mut().zip(src) {
                *d = act.apply((v + s) * a + off);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn normalise_avx512(src: &[f32], dst: &mut [f32], s: f32, coef: (f32, f32), act: Act) {
    normalise_generic(src, dst, s, coef, act)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn normalise_avx2(src: &[f32], dst: &mut [f32], s: f32, coef: (f32, f32), act: Act) {
    normalise_generic(src, dst, s, coef, act)
}

/// [`normalise_generic`] compiled for the widest vector unit the CPU has.
fn normalise(src: &[f32], dst: &mut [f32], s: f32, coef: (f32, f32), act: Act) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { normalise_avx512(src, dst, s, coef, act) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { normalise_avx2(src, dst, s, coef, act) };
        }
    }
    normalise_generic(src, dst, s, coef, act)
}

/// PyTorch `nn.LayerNorm(C, eps = 1e-5)` over the last dim of token rows `(B, N, C)`.
struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
}

impl LayerNorm {
    fn new(dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get(dim, "weight")?,
            bias: vb.get(dim, "bias")?,
        })
    }

    /// Per row: mean, then the biased variance of the centred values (f32, 16 lanes), then
    /// `(x − μ)/√(σ² + ε)·γ + β`.
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        if !(cpu(xs) && cpu(&self.weight) && cpu(&self.bias)) {
            return candle_nn::ops::layer_norm(&xs.contiguous()?, &self.weight, &self.bias, LAYER_NORM_EPS);
        }
        let _t = pixl_nn::profile::span("layer norm");
        let c = xs.dim(D::Minus1)?;
        if c != self.weight.dim(0)? {
            bail!("LayerNorm of {} given rows of {c}", self.weight.dim(0)?);
        }
        let mut out = vec![0f32; xs.elem_count()];
        if out.is_empty() {
            return Tensor::from_vec(out, xs.dims(), xs.device());
        }
        with_values(&self.weight, |gamma| {
            with_values(&self.bias, |beta| {
                with_values(xs, |x| {
                    out.par_chunks_mut(c)
                        .zip(x.par_chunks(c))
                        .with_min_len(16)
                        .for_each(|(dst, row)| layer_norm_row(row, dst, gamma, beta));
                    Ok(())
                })
            })
        })?;
        Tensor::from_vec(out, xs.dims(), xs.device())
    }
}

fn layer_norm_row(row: &[f32], dst: &mut [f32], gamma: &[f32], beta: &[f32]) {
    const L: usize = 16;
    let n = row.len() as f32;
    let lanes = |f: &dyn Fn(f32) -> f32| -> f32 {
        let mut acc = [0f32; L];
        let mut chunks = row.chunks_exact(L);
        for ch in &mut chunks {
            for (a, &v) in acc.iter_mut().zip(ch) {
                *a += f(v);
            }
        }
        acc.iter().sum::<f32>() + chunks.remainder().iter().map(|&v| f(v)).sum::<f32>()
    };
    let mean = lanes(&|v| v) / n;
    let var = lanes(&|v| (v - mean) * (v - mean)) / n;
    let rstd = 1.0 / (var + LAYER_NORM_EPS).sqrt();
    for (((d, &v), &g), &b) in dst.iter_mut().zip(row).zip(gamma).zip(beta) {
        *d = (v - mean) * rstd * g + b;
    }
}

/// A linear layer `W (out, in)`, `b (out)` (or a 1×1 convolution's `(out, in, 1, 1)` weight read
/// as one).
struct Dense {
    weight: Tensor,
    bias: Option<Vector>,
}

/// How a transformer's `proj_in` / `proj_out` is stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Projection {
    /// `nn.Linear` (`use_linear_projection`): weight `(out, in)`.
    Linear,
    /// `nn.Conv2d(in, out, 1)`: weight `(out, in, 1, 1)`.
    Conv1x1,
}

impl Dense {
    fn new(cin: usize, cout: usize, bias: bool, vb: VarBuilder) -> Result<Self> {
        Self::load(cin, cout, bias, Projection::Linear, vb)
    }

    fn load(cin: usize, cout: usize, bias: bool, kind: Projection, vb: VarBuilder) -> Result<Self> {
        let weight = match kind {
            Projection::Linear => vb.get((cout, cin), "weight")?,
            Projection::Conv1x1 => vb.get((cout, cin, 1, 1), "weight")?.reshape((cout, cin))?,
        };
        let bias = if bias {
            Some(Vector::new(vb.get(cout, "bias")?)?)
        } else {
            None
        };
        Ok(Self { weight, bias })
    }

    fn dims(&self) -> Result<(usize, usize)> {
        self.weight.dims2()
    }

    /// `act(xs · Wᵀ + b [+ residual])` over the last dim of `xs` `(…, in)`.
    fn forward(&self, xs: &Tensor, residual: Option<&Tensor>, act: Act) -> Result<Tensor> {
        let (cout, cin) = self.dims()?;
        let Some((&k, lead)) = xs.dims().split_last() else {
            bail!("linear layer given a scalar");
        };
        if k != cin {
            bail!("linear layer {cin} → {cout} given rows of {k}");
        }
        let mut out_dims = lead.to_vec();
        out_dims.push(cout);
        if let Some(r) = residual {
            if r.dims() != out_dims.as_slice() {
                bail!("residual {:?} for a linear output {out_dims:?}", r.dims());
            }
        }
        if !(cpu(xs) && cpu(&self.weight) && residual.is_none_or(cpu)) {
            let mut y = xs.broadcast_matmul(&self.weight.t()?)?;
            if let Some(b) = &self.bias {
                y = y.broadcast_add(&b.tensor)?;
            }
            if let Some(r) = residual {
                y = (y + r)?;
            }
            return act_tensor(y, act);
        }
        let _t = pixl_nn::profile::span("linear");
        let rows: usize = lead.iter().product();
        let mut out = match residual {
            Some(r) => r.flatten_all()?.to_vec1::<f32>()?,
            None => vec![0f32; rows * cout],
        };
        if let Some(b) = &self.bias {
            let b = b.values();
            out.par_chunks_mut(cout)
                .with_min_len(16)
                .for_each(|row| row.iter_mut().zip(b).for_each(|(o, &v)| *o += v));
        }
        let accumulate = residual.is_some() || self.bias.is_some();
        with_values(&self.weight, |w| {
            with_values(xs, |x| {
                matmul(
                    (rows, cout, cin),
                    &mut out,
                    (cout, 1),
                    accumulate,
                    Mat {
                        data: x,
                        rs: cin,
                        cs: 1,
                    },
                    // Wᵀ (in × out): element (i, j) = W[j·in + i].
                    Mat {
                        data: w,
                        rs: 1,
                        cs: cin,
                    },
                    parallel(),
                )
            })
        })?;
        act_in_place(&mut out, act);
        Tensor::from_vec(out, out_dims, xs.device())
    }

    /// `(B, in, H, W)` channels-first → token rows `(B, H·W, out)`: the GEMM reads the pixels
    /// of each image as the rows of `Xᵀ` in place.
    fn forward_from_channels_first(&self, xs: &Tensor) -> Result<Tensor> {
        let (cout, cin) = self.dims()?;
        let (b, c, h, w) = xs.dims4()?;
        if c != cin {
            bail!("projection {cin} → {cout} given {c} channels");
        }
        let hw = h * w;
        if !(cpu(xs) && cpu(&self.weight)) {
            let tokens = xs.reshape((b, c, hw))?.transpose(1, 2)?;
            return self.forward(&tokens, None, Act::None);
        }
        let _t = pixl_nn::profile::span("linear");
        let mut out = vec![0f32; b * hw * cout];
        if let Some(bias) = &self.bias {
            let bias = bias.values();
            out.par_chunks_mut(cout)
                .with_min_len(16)
                .for_each(|row| row.copy_from_slice(bias));
        }
        with_values(&self.weight, |wv| {
            with_values(xs, |x| {
                for (dst, img) in out.chunks_mut(hw * cout).zip(x.chunks(c * hw)) {
                    matmul(
                        (hw, cout, cin),
                        dst,
                        (cout, 1),
                        self.bias.is_some(),
                        // Xᵀ (pixels × in): element (p, ch) = X[ch·hw + p].
                        Mat {
                            data: img,
                            rs: 1,
                            cs: hw,
                        },
                        Mat {
                            data: wv,
                            rs: 1,
                            cs: cin,
                        },
                        parallel(),
                    )?;
                }
                Ok(())
            })
        })?;
        Tensor::from_vec(out, (b, hw, cout), xs.device())
    }

    /// Token rows `(B, H·W, in)` → `residual + (tokens · Wᵀ + b)` channels-first
    /// `(B, out, H, W)` (`residual`'s shape): the GEMM writes each image's channel planes.
    fn forward_to_channels_first(&self, tokens: &Tensor, residual: &Tensor) -> Result<Tensor> {
        let (cout, cin) = self.dims()?;
        let (b, c, h, w) = residual.dims4()?;
        let hw = h * w;
        if tokens.dims() != [b, hw, cin] || c != cout {
            bail!(
                "projection {cin} → {cout} of tokens {:?} onto {:?}",
                tokens.dims(),
                residual.dims()
            );
        }
        if !(cpu(tokens) && cpu(&self.weight) && cpu(residual)) {
            let y = self.forward(tokens, None, Act::None)?;
            return residual + y.transpose(1, 2)?.reshape((b, c, h, w))?;
        }
        let _t = pixl_nn::profile::span("linear");
        let mut out = residual.flatten_all()?.to_vec1::<f32>()?;
        if let Some(bias) = &self.bias {
            let bias = bias.values();
            out.par_chunks_mut(hw.max(1))
                .enumerate()
                .for_each(|(i, plane)| plane.iter_mut().for_each(|v| *v += bias[i % cout]));
        }
        with_values(&self.weight, |wv| {
            with_values(tokens, |t| {
                for (dst, img) in out.chunks_mut(cout * hw).zip(t.chunks(hw * cin)) {
                    matmul(
                        (cout, hw, cin),
                        dst,
                        (hw, 1),
                        true,
                        Mat {
                            data: wv,
                            rs: cin,
                            cs: 1,
                        },
                        // tokensᵀ (in × pixels): element (i, p) = t[p·in + i].
                        Mat {
                            data: img,
                            rs: 1,
                            cs: cin,
                        },
                        parallel(),
                    )?;
                }
                Ok(())
            })
        })?;
        Tensor::from_vec(out, (b, c, h, w), residual.device())
    }
}

/// Score floats per block of query rows: 512 Ki floats (2 MiB), but never fewer than
/// [`MIN_BLOCK_ROWS`] rows. Each block repacks all of a head's keys and values for its two GEMMs,
/// so larger blocks pay for that less often, even once the scores leave L2: on the SD2 UNet
/// (2 threads) the attention took, at a 64×64 latent, 3.2 s with blocks of 128 Ki floats, 2.2 s
/// with 512 Ki or 1 Mi, 6.2 s with 32 Ki; at 96×96 (9216 keys), 8.9 s with 56 rows per block,
/// 7.6 s with 128, 7.1 s with 256, 7.3 s with 512.
const BLOCK_SCORES: usize = 512 * 1024;
/// Fewest query rows per block (see [`BLOCK_SCORES`]).
const MIN_BLOCK_ROWS: usize = 256;

thread_local! {
    /// Per-thread scratch: one block's scores and its rows' inverse sums.
    static SCRATCH: RefCell<(Vec<f32>, Vec<f32>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

/// The output buffer shared by the attention workers, each writing its own rows of one head.
#[derive(Clone, Copy)]
struct OutPtr(*mut f32);
// SAFETY: the workers write disjoint elements of one live allocation.
unsafe impl Send for OutPtr {}
unsafe impl Sync for OutPtr {}

/// Multi-head `softmax(q·kᵀ/√d)·v` on token rows: `q` `(B, N, C)`, `k`, `v` `(B, M, C)`,
/// `C = heads·d`, head `h` in columns `h·d .. (h + 1)·d` → `(B, N, C)`, heads side by side.
fn multi_head_attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize) -> Result<Tensor> {
    let (b, n, c) = q.dims3()?;
    let (bk, m, ck) = k.dims3()?;
    if (bk, ck) != (b, c) || v.dims() != k.dims() || heads == 0 || c % heads != 0 {
        bail!(
            "attention: q {:?}, k {:?}, v {:?} with {heads} heads do not fit",
            q.dims(),
            k.dims(),
            v.dims()
        );
    }
    let d = c / heads;
    if !(cpu(q) && cpu(k) && cpu(v)) {
        let split = |t: &Tensor, rows| t.reshape((b, rows, heads, d))?.transpose(1, 2)?.contiguous();
        let o = pixl_nn::attention(&split(q, n)?, &split(k, m)?, &split(v, m)?)?;
        return o.transpose(1, 2)?.reshape((b, n, c));
    }
    let _t = pixl_nn::profile::span("attention");
    let mut out = vec![0f32; b * n * c];
    if out.is_empty() {
        return Tensor::from_vec(out, (b, n, c), q.device());
    }
    if m == 0 {
        bail!("attention over no keys");
    }
    let scale = 1.0 / (d as f32).sqrt();
    let rows_per_block = (BLOCK_SCORES / m).clamp(MIN_BLOCK_ROWS, 1024);
    let blocks = n.div_ceil(rows_per_block);
    let dst = OutPtr(out.as_mut_ptr());
    with_values(q, |qv| {
        with_values(k, |kv| {
            with_values(v, |vv| {
                (0..b * heads * blocks).into_par_iter().for_each(|unit| {
                    let (bh, blk) = (unit / blocks, unit % blocks);
                    let (bi, hi) = (bh / heads, bh % heads);
                    let r0 = blk * rows_per_block;
                    let rows = rows_per_block.min(n - r0);
                    let q0 = (bi * n + r0) * c + hi * d;
                    let kv0 = bi * m * c + hi * d;
                    SCRATCH.with_borrow_mut(|(scores, inv)| {
                        scores.resize(rows * m, 0.0);
                        inv.resize(rows, 0.0);
                        let o = dst;
                        // SAFETY: q rows r0..r0+rows, columns of head hi (row stride c) and the
                        // keys/values of head hi of image bi (m rows, stride c) lie inside
                        // their slices (q0 + (rows−1)·c + d ≤ b·n·c, kv0 + (m−1)·c + d ≤ b·m·c);
                        // the output block has q's indices in `out`, written by this unit only.
                        unsafe {
                            gemm::gemm(
                                rows,
                                m,
                                d,
                                scores.as_mut_ptr(),
                                1,
                                m as isize,
                                false,
                                qv.as_ptr().add(q0),
                                1,
                                c as isize,
                                // kᵀ (d × m): element (i, j) = k[kv0 + j·c + i].
                                kv.as_ptr().add(kv0),
                                c as isize,
                                1,
                                0.0f32,
                                scale,
                                false,
                                false,
                                false,
                                gemm::Parallelism::None,
                            );
                            fastmath::softmax_rows_unnormalised(scores, m, inv);
                            gemm::gemm(
                                rows,
                                d,
                                m,
                                o.0.add(q0),
                                1,
                                c as isize,
                                false,
                                scores.as_ptr(),
                                1,
                                m as isize,
                                vv.as_ptr().add(kv0),
                                1,
                                c as isize,
                                0.0f32,
                                1.0f32,
                                false,
                                false,
                                false,
                                gemm::Parallelism::None,
                            );
                            for (r, &s) in inv.iter().enumerate() {
                                let row = std::slice::from_raw_parts_mut(o.0.add(q0 + r * c), d);
                                row.iter_mut().for_each(|x| *x *= s);
                            }
                        }
                    });
                });
                Ok(())
            })
        })
    })?;
    Tensor::from_vec(out, (b, n, c), q.device())
}

/// diffusers `Attention` as the transformer blocks use it: q from the tokens, k and v from the
/// tokens (`attn1`) or the text (`attn2`), no q/k/v bias, `to_out.0` with one.
struct Attention {
    heads: usize,
    to_q: Dense,
    to_k: Dense,
    to_v: Dense,
    to_out: Dense,
}

impl Attention {
    fn new(dim: usize, context_dim: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            heads,
            to_q: Dense::new(dim, dim, false, vb.pp("to_q"))?,
            to_k: Dense::new(context_dim, dim, false, vb.pp("to_k"))?,
            to_v: Dense::new(context_dim, dim, false, vb.pp("to_v"))?,
            to_out: Dense::new(dim, dim, true, vb.pp("to_out").pp("0"))?,
        })
    }

    /// `residual + to_out(attention(q(xs), k(ctx), v(ctx)))`, `ctx` = `xs` for self-attention.
    fn forward(&self, xs: &Tensor, context: &Tensor, residual: &Tensor) -> Result<Tensor> {
        let q = self.to_q.forward(xs, None, Act::None)?;
        let k = self.to_k.forward(context, None, Act::None)?;
        let v = self.to_v.forward(context, None, Act::None)?;
        let o = multi_head_attention(&q, &k, &v, self.heads)?;
        self.to_out.forward(&o, Some(residual), Act::None)
    }
}

/// `ff.net.0` (GEGLU: `proj` to `2·inner`, `value · gelu(gate)`) and `ff.net.2`.
struct FeedForward {
    proj: Dense,
    out: Dense,
}

impl FeedForward {
    fn new(dim: usize, vb: VarBuilder) -> Result<Self> {
        let inner = 4 * dim;
        Ok(Self {
            proj: Dense::new(dim, 2 * inner, true, vb.pp("net").pp("0").pp("proj"))?,
            out: Dense::new(inner, dim, true, vb.pp("net").pp("2"))?,
        })
    }

    fn forward(&self, xs: &Tensor, residual: &Tensor) -> Result<Tensor> {
        let h = self.proj.forward(xs, None, Act::None)?;
        self.out.forward(&geglu(&h)?, Some(residual), Act::None)
    }
}

/// `(…, 2I)` → `(…, I)`: `h[.., :I] · gelu(h[.., I:])`, the exact (erf) GELU.
fn geglu(h: &Tensor) -> Result<Tensor> {
    let two = h.dim(D::Minus1)?;
    if !two.is_multiple_of(2) {
        bail!("GEGLU of an odd width {two}");
    }
    let inner = two / 2;
    if !cpu(h) {
        let value = h.narrow(D::Minus1, 0, inner)?;
        let gate = h.narrow(D::Minus1, inner, inner)?;
        return value * gate.gelu_erf()?;
    }
    let _t = pixl_nn::profile::span("geglu");
    let mut dims = h.dims().to_vec();
    if let Some(last) = dims.last_mut() {
        *last = inner;
    }
    let mut out = vec![0f32; h.elem_count() / 2];
    if out.is_empty() {
        return Tensor::from_vec(out, dims, h.device());
    }
    with_values(h, |x| {
        out.par_chunks_mut(inner)
            .zip(x.par_chunks(two))
            .with_min_len(8)
            .for_each(|(o, row)| {
                o.copy_from_slice(&row[inner..]);
                fastmath::gelu_in_place(o);
                o.iter_mut().zip(&row[..inner]).for_each(|(g, &v)| *g *= v);
            });
        Ok(())
    })?;
    Tensor::from_vec(out, dims, h.device())
}

/// diffusers `BasicTransformerBlock` (layer norms, self-attention, cross-attention, GEGLU).
struct BasicTransformerBlock {
    norm1: LayerNorm,
    attn1: Attention,
    norm2: LayerNorm,
    attn2: Attention,
    norm3: LayerNorm,
    ff: FeedForward,
}

impl BasicTransformerBlock {
    fn new(dim: usize, context_dim: usize, heads: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            norm1: LayerNorm::new(dim, vb.pp("norm1"))?,
            attn1: Attention::new(dim, dim, heads, vb.pp("attn1"))?,
            norm2: LayerNorm::new(dim, vb.pp("norm2"))?,
            attn2: Attention::new(dim, context_dim, heads, vb.pp("attn2"))?,
            norm3: LayerNorm::new(dim, vb.pp("norm3"))?,
            ff: FeedForward::new(dim, vb.pp("ff"))?,
        })
    }

    fn forward(&self, xs: &Tensor, context: &Tensor) -> Result<Tensor> {
        let h = self.norm1.forward(xs)?;
        let xs = self.attn1.forward(&h, &h, xs)?;
        let h = self.norm2.forward(&xs)?;
        let xs = self.attn2.forward(&h, context, &xs)?;
        let h = self.norm3.forward(&xs)?;
        self.ff.forward(&h, &xs)
    }
}

/// diffusers `Transformer2DModel` on continuous `(B, C, H, W)` input.
struct Transformer2DModel {
    norm: GroupNorm,
    proj_in: Dense,
    transformer_blocks: Vec<BasicTransformerBlock>,
    proj_out: Dense,
}

impl Transformer2DModel {
    fn new(channels: usize, heads: usize, layers: usize, cfg: &UnetConfig, vb: VarBuilder) -> Result<Self> {
        let kind = if cfg.use_linear_projection {
            Projection::Linear
        } else {
            Projection::Conv1x1
        };
        let blocks = vb.pp("transformer_blocks");
        Ok(Self {
            norm: GroupNorm::new(cfg.norm_num_groups, channels, TRANSFORMER_GN_EPS, vb.pp("norm"))?,
            proj_in: Dense::load(channels, channels, true, kind, vb.pp("proj_in"))?,
            transformer_blocks: (0..layers)
                .map(|k| BasicTransformerBlock::new(channels, cfg.cross_attention_dim, heads, blocks.pp(k)))
                .collect::<Result<_>>()?,
            proj_out: Dense::load(channels, channels, true, kind, vb.pp("proj_out"))?,
        })
    }

    fn forward(&self, xs: &Tensor, context: &Tensor) -> Result<Tensor> {
        let h = self.norm.forward(xs, None, Act::None)?;
        let mut tokens = self.proj_in.forward_from_channels_first(&h)?;
        for block in &self.transformer_blocks {
            tokens = block.forward(&tokens, context)?;
        }
        self.proj_out.forward_to_channels_first(&tokens, xs)
    }
}

/// A 1×1 convolution with bias (a ResNet's `conv_shortcut`).
struct Conv1x1 {
    weight: Tensor,
    bias: Tensor,
}

impl Conv1x1 {
    fn new(cin: usize, cout: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self {
            weight: vb.get((cout, cin, 1, 1), "weight")?,
            bias: vb.get(cout, "bias")?,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        if let Some(y) = fused::conv1x1(xs, &self.weight, Some(&self.bias), Act::None)? {
            return Ok(y);
        }
        let y = xs.conv2d(&self.weight, 0, 1, 1, 1)?;
        y.broadcast_add(&self.bias.reshape((1, (), 1, 1))?)
    }
}

/// diffusers `ResnetBlock2D` with a time embedding (`resnet_time_scale_shift` "default").
struct ResnetBlock2D {
    norm1: GroupNorm,
    conv1: Conv3x3,
    time_emb_proj: Dense,
    norm2: GroupNorm,
    conv2: Conv3x3,
    conv_shortcut: Option<Conv1x1>,
    output_scale_factor: f64,
}

impl ResnetBlock2D {
    fn new(cin: usize, cout: usize, cfg: &UnetConfig, output_scale_factor: f64, vb: VarBuilder) -> Result<Self> {
        let (g, eps) = (cfg.norm_num_groups, cfg.norm_eps);
        Ok(Self {
            norm1: GroupNorm::new(g, cin, eps, vb.pp("norm1"))?,
            conv1: Conv3x3::new(cin, cout, 1, true, vb.pp("conv1"))?,
            time_emb_proj: Dense::new(cfg.time_embed_dim(), cout, true, vb.pp("time_emb_proj"))?,
            norm2: GroupNorm::new(g, cout, eps, vb.pp("norm2"))?,
            conv2: Conv3x3::new(cout, cout, 1, true, vb.pp("conv2"))?,
            conv_shortcut: if cin != cout {
                Some(Conv1x1::new(cin, cout, vb.pp("conv_shortcut"))?)
            } else {
                None
            },
            output_scale_factor,
        })
    }

    /// `temb` is `silu(time embedding)` `(B, time_embed_dim)`.
    fn forward(&self, xs: &Tensor, temb: &Tensor) -> Result<Tensor> {
        let h = self
            .conv1
            .forward(&self.norm1.forward(xs, None, Act::Silu)?, Act::None)?;
        let t = self.time_emb_proj.forward(temb, None, Act::None)?;
        let h = self.norm2.forward(&h, Some(&t), Act::Silu)?;
        let skip = match &self.conv_shortcut {
            Some(c) => c.forward(xs)?,
            None => xs.clone(),
        };
        let out = self.conv2.forward_residual(&h, &skip)?;
        if self.output_scale_factor == 1.0 {
            Ok(out)
        } else {
            out.affine(1.0 / self.output_scale_factor, 0.0)
        }
    }
}

/// diffusers `Downsample2D` with a convolution: 3×3, stride 2, `downsample_padding`.
enum Downsample2D {
    /// Padding 1: the parallel 3×3 kernel.
    Padded(Conv3x3),
    /// Padding 0 (one zero row and column added at the bottom and right first) or above 1:
    /// candle's convolution.
    Other {
        weight: Tensor,
        bias: Tensor,
        padding: usize,
    },
}

impl Downsample2D {
    fn new(channels: usize, padding: usize, vb: VarBuilder) -> Result<Self> {
        let vb = vb.pp("conv");
        if padding == 1 {
            return Ok(Self::Padded(Conv3x3::new(channels, channels, 2, true, vb)?));
        }
        Ok(Self::Other {
            weight: vb.get((channels, channels, 3, 3), "weight")?,
            bias: vb.get(channels, "bias")?,
            padding,
        })
    }

    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        match self {
            Self::Padded(conv) => conv.forward(xs, Act::None),
            Self::Other { weight, bias, padding } => {
                let xs = if *padding == 0 {
                    xs.pad_with_zeros(3, 0, 1)?.pad_with_zeros(2, 0, 1)?
                } else {
                    xs.clone()
                };
                let y = xs.conv2d(weight, *padding, 2, 1, 1)?;
                y.broadcast_add(&bias.reshape((1, (), 1, 1))?)
            }
        }
    }
}

/// Nearest-neighbour resize of `(B, C, H, W)` to `(B, C, oh, ow)` with PyTorch's index
/// arithmetic (`min(⌊i · (in/out)⌋, in − 1)` in f32).
fn upsample_nearest(xs: &Tensor, oh: usize, ow: usize) -> Result<Tensor> {
    let (b, c, h, w) = xs.dims4()?;
    if !cpu(xs) {
        return xs.upsample_nearest2d(oh, ow);
    }
    let _t = pixl_nn::profile::span("upsample");
    let index = |n_in: usize, n_out: usize| -> Vec<usize> {
        let scale = n_in as f32 / n_out as f32;
        (0..n_out)
            .map(|i| ((i as f32 * scale).floor() as usize).min(n_in - 1))
            .collect()
    };
    let (ys, xs_idx) = (index(h, oh), index(w, ow));
    let mut out = vec![0f32; b * c * oh * ow];
    if out.is_empty() || h == 0 || w == 0 {
        return Tensor::from_vec(out, (b, c, oh, ow), xs.device());
    }
    with_values(xs, |src| {
        out.par_chunks_mut(oh * ow)
            .zip(src.par_chunks(h * w))
            .for_each(|(dst, plane)| {
                for (row, &sy) in dst.chunks_mut(ow).zip(&ys) {
                    let line = &plane[sy * w..(sy + 1) * w];
                    row.iter_mut().zip(&xs_idx).for_each(|(d, &sx)| *d = line[sx]);
                }
            });
        Ok(())
    })?;
    Tensor::from_vec(out, (b, c, oh, ow), xs.device())
}

/// diffusers `Upsample2D` with a convolution: nearest ×2 (or to `size`), then a 3×3 convolution.
struct Upsample2D {
    conv: Conv3x3,
}

impl Upsample2D {
    fn forward(&self, xs: &Tensor, size: Option<(usize, usize)>) -> Result<Tensor> {
        let (_, _, h, w) = xs.dims4()?;
        let (oh, ow) = size.unwrap_or((2 * h, 2 * w));
        self.conv.forward(&upsample_nearest(xs, oh, ow)?, Act::None)
    }
}

/// `CrossAttnDownBlock2D` (a transformer after each ResNet) or `DownBlock2D` (none).
struct DownBlock {
    resnets: Vec<ResnetBlock2D>,
    attentions: Vec<Transformer2DModel>,
    downsampler: Option<Downsample2D>,
}

impl DownBlock {
    fn new(cfg: &UnetConfig, i: usize, vb: VarBuilder) -> Result<Self> {
        let ch = &cfg.block_out_channels;
        let (cin, cout) = (if i == 0 { ch[0] } else { ch[i - 1] }, ch[i]);
        let layers = cfg.layers_per_block[i];
        let resnets = (0..layers)
            .map(|j| {
                let c = if j == 0 { cin } else { cout };
                ResnetBlock2D::new(c, cout, cfg, 1.0, vb.pp("resnets").pp(j))
            })
            .collect::<Result<_>>()?;
        let attentions = match cfg.down_block_types[i] {
            DownBlockType::CrossAttnDownBlock2D => (0..layers)
                .map(|j| {
                    let (heads, depth) = (cfg.attention_head_dim[i], cfg.transformer_layers_per_block[i]);
                    Transformer2DModel::new(cout, heads, depth, cfg, vb.pp("attentions").pp(j))
                })
                .collect::<Result<_>>()?,
            DownBlockType::DownBlock2D => Vec::new(),
        };
        let downsampler = if i + 1 < ch.len() {
            Some(Downsample2D::new(
                cout,
                cfg.downsample_padding,
                vb.pp("downsamplers").pp("0"),
            )?)
        } else {
            None
        };
        Ok(Self {
            resnets,
            attentions,
            downsampler,
        })
    }

    /// Pushes each ResNet's (or transformer's) output and the downsampled one onto `skips`.
    fn forward(&self, xs: &Tensor, temb: &Tensor, context: &Tensor, skips: &mut Vec<Tensor>) -> Result<Tensor> {
        let mut h = xs.clone();
        for (j, resnet) in self.resnets.iter().enumerate() {
            h = resnet.forward(&h, temb)?;
            if let Some(attn) = self.attentions.get(j) {
                h = attn.forward(&h, context)?;
            }
            skips.push(h.clone());
        }
        if let Some(d) = &self.downsampler {
            h = d.forward(&h)?;
            skips.push(h.clone());
        }
        Ok(h)
    }
}

/// `UNetMidBlock2DCrossAttn` with one layer: ResNet, transformer, ResNet.
struct MidBlock {
    resnets: [ResnetBlock2D; 2],
    attention: Transformer2DModel,
}

impl MidBlock {
    fn new(cfg: &UnetConfig, vb: VarBuilder) -> Result<Self> {
        let n = cfg.block_out_channels.len();
        let c = cfg.block_out_channels[n - 1];
        let scale = cfg.mid_block_scale_factor;
        let r = vb.pp("resnets");
        Ok(Self {
            resnets: [
                ResnetBlock2D::new(c, c, cfg, scale, r.pp(0))?,
                ResnetBlock2D::new(c, c, cfg, scale, r.pp(1))?,
            ],
            attention: Transformer2DModel::new(
                c,
                cfg.attention_head_dim[n - 1],
                cfg.transformer_layers_per_block[n - 1],
                cfg,
                vb.pp("attentions").pp(0),
            )?,
        })
    }

    fn forward(&self, xs: &Tensor, temb: &Tensor, context: &Tensor) -> Result<Tensor> {
        let h = self.resnets[0].forward(xs, temb)?;
        let h = self.attention.forward(&h, context)?;
        self.resnets[1].forward(&h, temb)
    }
}

/// `CrossAttnUpBlock2D` or `UpBlock2D`: `cat[h, skip]` before each ResNet.
struct UpBlock {
    resnets: Vec<ResnetBlock2D>,
    attentions: Vec<Transformer2DModel>,
    upsampler: Option<Upsample2D>,
}

impl UpBlock {
    /// Up block `i` (0 = the lowest resolution) works at level `n − 1 − i`.
    fn new(cfg: &UnetConfig, i: usize, vb: VarBuilder) -> Result<Self> {
        let n = cfg.block_out_channels.len();
        let level = n - 1 - i;
        let ch = &cfg.block_out_channels;
        let cout = ch[level];
        let prev = if i == 0 { ch[n - 1] } else { ch[level + 1] };
        let skip_in = ch[level.saturating_sub(1)];
        let layers = cfg.layers_per_block[level] + 1;
        let resnets = (0..layers)
            .map(|j| {
                let skip = if j + 1 == layers { skip_in } else { cout };
                let hin = if j == 0 { prev } else { cout };
                ResnetBlock2D::new(hin + skip, cout, cfg, 1.0, vb.pp("resnets").pp(j))
            })
            .collect::<Result<_>>()?;
        let attentions = match cfg.up_block_types[i] {
            UpBlockType::CrossAttnUpBlock2D => (0..layers)
                .map(|j| {
                    let (heads, depth) = (cfg.attention_head_dim[level], cfg.transformer_layers_per_block[level]);
                    Transformer2DModel::new(cout, heads, depth, cfg, vb.pp("attentions").pp(j))
                })
                .collect::<Result<_>>()?,
            UpBlockType::UpBlock2D => Vec::new(),
        };
        let upsampler = if i + 1 < n {
            Some(Upsample2D {
                conv: Conv3x3::new(cout, cout, 1, true, vb.pp("upsamplers").pp("0").pp("conv"))?,
            })
        } else {
            None
        };
        Ok(Self {
            resnets,
            attentions,
            upsampler,
        })
    }

    /// `skips` are this block's skip connections, the last one first used.
    fn forward(
        &self,
        xs: &Tensor,
        mut skips: Vec<Tensor>,
        temb: &Tensor,
        context: &Tensor,
        upsample_size: Option<(usize, usize)>,
    ) -> Result<Tensor> {
        let mut h = xs.clone();
        for (j, resnet) in self.resnets.iter().enumerate() {
            let Some(skip) = skips.pop() else {
                bail!("up block: {} skip connections for {} ResNets", j, self.resnets.len());
            };
            h = resnet.forward(&Tensor::cat(&[&h, &skip], 1)?, temb)?;
            if let Some(attn) = self.attentions.get(j) {
                h = attn.forward(&h, context)?;
            }
        }
        match &self.upsampler {
            Some(u) => u.forward(&h, upsample_size),
            None => Ok(h),
        }
    }
}

/// The sinusoidal timestep embedding of diffusers' `get_timestep_embedding` for a batch of
/// `batch` equal timesteps: `(batch, dim)`, the frequencies and products in f32 as PyTorch
/// forms them, `sin`/`cos` of those f32 products.
fn timestep_embedding(t: f64, batch: usize, dim: usize, flip_sin_to_cos: bool, freq_shift: f64) -> Vec<f32> {
    let half = dim / 2;
    let log_max = -(10_000f64.ln()) as f32;
    let denom = (half as f64 - freq_shift) as f32;
    let (mut sin, mut cos) = (Vec::with_capacity(half), Vec::with_capacity(half));
    for k in 0..half {
        let exponent = log_max * k as f32 / denom;
        let freq = (exponent as f64).exp() as f32;
        let arg = (t as f32 * freq) as f64;
        sin.push(arg.sin() as f32);
        cos.push(arg.cos() as f32);
    }
    let mut row = if flip_sin_to_cos {
        [cos, sin].concat()
    } else {
        [sin, cos].concat()
    };
    row.resize(dim, 0.0);
    row.repeat(batch)
}

/// diffusers' `UNet2DConditionModel` of the SD2 family; see the module notes.
pub struct UNet2DConditionModel {
    conv_in: Conv3x3,
    time_linear_1: Dense,
    time_linear_2: Dense,
    down_blocks: Vec<DownBlock>,
    mid_block: MidBlock,
    up_blocks: Vec<UpBlock>,
    conv_norm_out: GroupNorm,
    conv_out: Conv3x3,
    config: UnetConfig,
}

impl UNet2DConditionModel {
    /// Builds the network from `vb` (the root of `unet/diffusion_pytorch_model.safetensors`),
    /// with a shape check on every tensor.
    pub fn new(cfg: &UnetConfig, vb: VarBuilder) -> Result<Self> {
        let n = cfg.block_out_channels.len();
        if n == 0 || cfg.down_block_types.len() != n || cfg.up_block_types.len() != n {
            bail!("UNet config: one block type per entry of block_out_channels is needed");
        }
        for (k, len) in [
            ("layers_per_block", cfg.layers_per_block.len()),
            ("attention_head_dim", cfg.attention_head_dim.len()),
            ("transformer_layers_per_block", cfg.transformer_layers_per_block.len()),
        ] {
            if len != n {
                bail!("UNet config: {k} has {len} entries for {n} blocks");
            }
        }
        let c0 = cfg.block_out_channels[0];
        let t = vb.pp("time_embedding");
        Ok(Self {
            conv_in: Conv3x3::new(cfg.in_channels, c0, 1, true, vb.pp("conv_in"))?,
            time_linear_1: Dense::new(c0, cfg.time_embed_dim(), true, t.pp("linear_1"))?,
            time_linear_2: Dense::new(cfg.time_embed_dim(), cfg.time_embed_dim(), true, t.pp("linear_2"))?,
            down_blocks: (0..n)
                .map(|i| DownBlock::new(cfg, i, vb.pp("down_blocks").pp(i)))
                .collect::<Result<_>>()?,
            mid_block: MidBlock::new(cfg, vb.pp("mid_block"))?,
            up_blocks: (0..n)
                .map(|i| UpBlock::new(cfg, i, vb.pp("up_blocks").pp(i)))
                .collect::<Result<_>>()?,
            conv_norm_out: GroupNorm::new(cfg.norm_num_groups, c0, cfg.norm_eps, vb.pp("conv_norm_out"))?,
            conv_out: Conv3x3::new(c0, cfg.out_channels, 1, true, vb.pp("conv_out"))?,
            config: cfg.clone(),
        })
    }

    pub fn config(&self) -> &UnetConfig {
        &self.config
    }

    /// `silu(time_embedding(sinusoid(t)))` for a batch of `b`: what every ResNet projects.
    fn time_embedding(&self, timestep: f64, b: usize, device: &candle_core::Device) -> Result<Tensor> {
        let cfg = &self.config;
        let c0 = cfg.block_out_channels[0];
        let emb = timestep_embedding(timestep, b, c0, cfg.flip_sin_to_cos, cfg.freq_shift);
        let emb = Tensor::from_vec(emb, (b, c0), device)?;
        let emb = self.time_linear_1.forward(&emb, None, Act::Silu)?;
        self.time_linear_2.forward(&emb, None, Act::Silu)
    }

    /// The denoiser's output for `sample` at `timestep` conditioned on `encoder_hidden_states`.
    pub fn forward(&self, sample: &Tensor, timestep: f64, encoder_hidden_states: &Tensor) -> Result<Tensor> {
        let cfg = &self.config;
        let (b, c, h, w) = sample.dims4()?;
        if c != cfg.in_channels || sample.dtype() != DType::F32 {
            bail!(
                "UNet input: {c} channels of {:?}, expected {} of f32",
                sample.dtype(),
                cfg.in_channels
            );
        }
        let (bc, _, cc) = encoder_hidden_states.dims3()?;
        if bc != b || cc != cfg.cross_attention_dim {
            bail!(
                "UNet conditioning {:?}: expected ({b}, tokens, {})",
                encoder_hidden_states.dims(),
                cfg.cross_attention_dim
            );
        }
        if h == 0 || w == 0 {
            bail!("UNet input of an empty {h}x{w} latent");
        }
        let context = encoder_hidden_states.contiguous()?;
        let sample = if cfg.center_input_sample {
            sample.affine(2.0, -1.0)?
        } else {
            sample.clone()
        };
        let temb = self.time_embedding(timestep, b, sample.device())?;
        let mut h_ = self.conv_in.forward(&sample, Act::None)?;
        let mut skips = vec![h_.clone()];
        for block in &self.down_blocks {
            h_ = block.forward(&h_, &temb, &context, &mut skips)?;
        }
        h_ = self.mid_block.forward(&h_, &temb, &context)?;
        // diffusers forwards the skip's size to the upsamplers when a side is not a multiple of
        // the overall upsampling factor.
        let factor = 1usize << (self.up_blocks.len() - 1);
        let forward_size = h % factor != 0 || w % factor != 0;
        let last = self.up_blocks.len() - 1;
        for (i, block) in self.up_blocks.iter().enumerate() {
            let take = block.resnets.len();
            if skips.len() < take {
                bail!(
                    "UNet: {} skip connections left for an up block of {take} ResNets",
                    skips.len()
                );
            }
            let mine = skips.split_off(skips.len() - take);
            let size = match skips.last() {
                Some(s) if i < last && forward_size => {
                    let (_, _, sh, sw) = s.dims4()?;
                    Some((sh, sw))
                }
                _ => None,
            };
            h_ = block.forward(&h_, mine, &temb, &context, size)?;
        }
        let h_ = self.conv_norm_out.forward(&h_, None, Act::Silu)?;
        self.conv_out.forward(&h_, Act::None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Module};

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        assert_eq!(a.dims(), b.dims());
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .max_all()
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
    }

    /// The strided attention kernel against pixl-nn's (heads split by reshapes): one block of
    /// query rows, and six (1200 keys: 436 rows per block, the last one short).
    #[test]
    fn attention_reads_heads_in_place() {
        let dev = Device::Cpu;
        for (n, m) in [(37, 5), (2500, 1200)] {
            let q = Tensor::randn(0f32, 1.0, (2, n, 12), &dev).unwrap();
            let k = Tensor::randn(0f32, 1.0, (2, m, 12), &dev).unwrap();
            let v = Tensor::randn(0f32, 1.0, (2, m, 12), &dev).unwrap();
            let split = |t: &Tensor, r| {
                t.reshape((2, r, 3, 4))
                    .unwrap()
                    .transpose(1, 2)
                    .unwrap()
                    .contiguous()
                    .unwrap()
            };
            let want = pixl_nn::attention(&split(&q, n), &split(&k, m), &split(&v, m))
                .unwrap()
                .transpose(1, 2)
                .unwrap()
                .reshape((2, n, 12))
                .unwrap();
            let got = multi_head_attention(&q, &k, &v, 3).unwrap();
            assert!(max_diff(&got, &want) < 1e-5, "{n}x{m}");
        }
    }

    /// GroupNorm with a shift and SiLU against candle's ops; LayerNorm against candle's.
    #[test]
    fn norms_match_candle() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 12, 5, 7), &dev).unwrap();
        let shift = Tensor::randn(0f32, 1.0, (2, 12), &dev).unwrap();
        let gamma = Tensor::randn(1f32, 0.2, 12, &dev).unwrap();
        let beta = Tensor::randn(0f32, 0.2, 12, &dev).unwrap();
        let gn = GroupNorm {
            groups: 3,
            eps: 1e-5,
            weight: Vector::new(gamma.clone()).unwrap(),
            bias: Vector::new(beta.clone()).unwrap(),
        };
        let got = gn.forward(&x, Some(&shift), Act::Silu).unwrap();
        let xs = x.broadcast_add(&shift.reshape((2, 12, 1, 1)).unwrap()).unwrap();
        let want = candle_nn::GroupNorm::new(gamma, beta, 12, 3, 1e-5)
            .unwrap()
            .forward(&xs)
            .unwrap();
        let want = candle_nn::ops::silu(&want).unwrap();
        assert!(max_diff(&got, &want) < 1e-5);
        let t = Tensor::randn(0.5f32, 2.0, (2, 9, 40), &dev).unwrap();
        let ln = LayerNorm {
            weight: Tensor::randn(1f32, 0.2, 40, &dev).unwrap(),
            bias: Tensor::randn(0f32, 0.2, 40, &dev).unwrap(),
        };
        let want = candle_nn::ops::layer_norm(&t, &ln.weight, &ln.bias, LAYER_NORM_EPS).unwrap();
        assert!(max_diff(&ln.forward(&t).unwrap(), &want) < 1e-5);
    }

    /// Channels-first projections in and out equal the token-major linear layer.
    #[test]
    fn projections_read_and_write_channels_first() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 6, 3, 5), &dev).unwrap();
        let dense = Dense {
            weight: Tensor::randn(0f32, 1.0, (4, 6), &dev).unwrap(),
            bias: Some(Vector::new(Tensor::randn(0f32, 1.0, 4, &dev).unwrap()).unwrap()),
        };
        let tokens = x
            .reshape((2, 6, 15))
            .unwrap()
            .transpose(1, 2)
            .unwrap()
            .contiguous()
            .unwrap();
        let want = dense.forward(&tokens, None, Act::None).unwrap();
        let got = dense.forward_from_channels_first(&x).unwrap();
        assert!(max_diff(&got, &want) < 1e-5);
        let back = Dense {
            weight: Tensor::randn(0f32, 1.0, (6, 4), &dev).unwrap(),
            bias: Some(Vector::new(Tensor::randn(0f32, 1.0, 6, &dev).unwrap()).unwrap()),
        };
        let y = back.forward(&want, None, Act::None).unwrap();
        let want = (&x + y.transpose(1, 2).unwrap().reshape((2, 6, 3, 5)).unwrap()).unwrap();
        let got = back.forward_to_channels_first(&got, &x).unwrap();
        assert!(max_diff(&got, &want) < 1e-5);
    }

    /// PyTorch's nearest resize to a size: 2 → 3 rows take rows 0, 0, 1.
    #[test]
    fn nearest_resize_follows_torch() {
        let x = Tensor::arange(0f32, 8.0, &Device::Cpu)
            .unwrap()
            .reshape((1, 1, 2, 4))
            .unwrap();
        let y = upsample_nearest(&x, 3, 8).unwrap();
        let rows: Vec<Vec<f32>> = y.squeeze(0).unwrap().squeeze(0).unwrap().to_vec2().unwrap();
        assert_eq!(rows[0], vec![0., 0., 1., 1., 2., 2., 3., 3.]);
        assert_eq!(rows[1], rows[0]);
        assert_eq!(rows[2], vec![4., 4., 5., 5., 6., 6., 7., 7.]);
    }
}
