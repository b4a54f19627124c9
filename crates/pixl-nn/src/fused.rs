//! Fused elementwise steps for inference (the relighting network, DA3, Marigold's VAE), parallel
//! on the CPU, without a backward pass: callers take them only when no gradient is needed.
//!
//! candle's CPU elementwise kernels run on one thread, and every bias add, GELU, ReLU, LayerScale
//! and residual add would be a separate pass over memory. These ops do each step in one
//! parallel pass, with the same arithmetic per element as the unfused ops (`x + b` then the
//! activation, `x + y·γ`), so results are unchanged up to GELU's vectorised `erf` (within
//! 3e-7·max(|x|, 1)). On other devices (or dtypes), or when gradients are needed, they fall back
//! to the equivalent candle ops.
//!
//! Also: [`linear`] and [`conv1x1`], one GEMM each added in place to bias-filled outputs, the
//! activation in place; [`attention_qkv`] / [`attention_qkv_rope`], multi-head attention straight
//! from fused qkv rows, the head split (with 2D RoPE) and the head merge done as single parallel
//! copies; [`to_channels_last`] / [`to_channels_first`] and [`add_scaled_channels_last`]
//! (ConvNeXt's layer-scaled residual back in channels-first layout) as blocked parallel passes.
//!
//! Layouts: "rows" tensors are `(…, N)` with a per-column vector of length `N`; "channels"
//! tensors are `(B, C, …)` with a per-channel vector of length `C`.
use candle_core::{CpuStorage, CustomOp1, CustomOp2, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Activation applied after the sum.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Act {
    None,
    /// Exact GELU, `0.5·x·(1 + erf(x/√2))` (candle's `gelu_erf` order of operations, with the
    /// vectorisable [`crate::fastmath::erf`]: within 3e-7·max(|x|, 1) of the exact value).
    Gelu,
    Relu,
    /// SiLU, `x / (1 + e^(−x))` (candle's `silu` arithmetic).
    Silu,
}

impl Act {
    #[inline]
    pub fn apply(self, v: f32) -> f32 {
        match self {
            Act::None => v,
            Act::Gelu => (crate::fastmath::erf(v * std::f32::consts::FRAC_1_SQRT_2) + 1.0) * 0.5 * v,
            Act::Relu => v.max(0.0),
            Act::Silu => v / (1.0 + (-v).exp()),
        }
    }

    fn apply_tensor(self, xs: Tensor) -> Result<Tensor> {
        match self {
            Act::None => Ok(xs),
            Act::Gelu => xs.gelu_erf(),
            Act::Relu => xs.relu(),
            Act::Silu => candle_nn::ops::silu(&xs),
        }
    }
}

/// Elements per parallel task.
const CHUNK: usize = 1 << 14;

pub fn cpu_f32(xs: &Tensor) -> bool {
    xs.device().is_cpu() && xs.dtype() == DType::F32
}

/// The f32 values of a contiguous CPU storage under `layout`, borrowed; `what` names the
/// operand in the error otherwise.
pub(crate) fn slice<'a>(storage: &'a CpuStorage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    let CpuStorage::F32(v) = storage else {
        candle_core::bail!("{what}: expected f32");
    };
    match layout.contiguous_offsets() {
        Some((a, b)) => Ok(&v[a..b]),
        None => candle_core::bail!("{what}: expected a contiguous input"),
    }
}

/// The f32 values of a contiguous CPU tensor's storage, as `storage_and_layout` gives it,
/// borrowed; `what` names the operand in the error otherwise.
pub(crate) fn storage_slice<'a>(storage: &'a candle_core::Storage, layout: &Layout, what: &str) -> Result<&'a [f32]> {
    let candle_core::Storage::Cpu(cpu) = storage else {
        candle_core::bail!("{what}: expected a CPU tensor");
    };
    slice(cpu, layout, what)
}

/// The `gemm` crate's parallelism over rayon's current pool.
pub(crate) fn gemm_parallelism() -> gemm::Parallelism {
    match rayon::current_num_threads() {
        0 | 1 => gemm::Parallelism::None,
        threads => gemm::Parallelism::Rayon(threads),
    }
}

/// Which axis a per-element vector indexes.
#[derive(Clone, Copy, Debug)]
enum Axis {
    /// The last dim.
    Column,
    /// Dim 1 of `(B, C, rest…)`; `inner` = product of the dims after it.
    Channel { inner: usize },
}

impl Axis {
    fn of(xs: &Tensor, rows: bool) -> Result<Self> {
        if rows {
            return Ok(Axis::Column);
        }
        let dims = xs.dims();
        if dims.len() < 2 {
            candle_core::bail!("per-channel op on a tensor of shape {dims:?}");
        }
        Ok(Axis::Channel {
            inner: dims[2..].iter().product(),
        })
    }

    /// Length of the runs of elements that share a vector pattern: a row (each element its own
    /// entry) or a channel plane (one entry for all).
    fn segment(self, len: usize) -> usize {
        match self {
            Axis::Column => len,
            Axis::Channel { inner } => inner,
        }
    }

    /// Vector entry of element `j` of segment `s`.
    #[inline]
    fn entry(self, s: usize, j: usize, len: usize) -> usize {
        match self {
            Axis::Column => j,
            Axis::Channel { .. } => s % len,
        }
    }
}

/// Calls `f(segment index, offset, segment)` on consecutive segments of `out` of length `seg`,
/// in parallel over groups of about `CHUNK` elements.
fn for_segments(out: &mut [f32], seg: usize, f: impl Fn(usize, usize, &mut [f32]) + Sync) {
    let seg = seg.max(1);
    let per_task = (CHUNK / seg).max(1) * seg;
    out.par_chunks_mut(per_task).enumerate().for_each(|(t, chunk)| {
        for (k, s) in chunk.chunks_mut(seg).enumerate() {
            let si = t * (per_task / seg) + k;
            f(si, si * seg, s);
        }
    });
}

/// `act(xs + v[axis])`.
struct VecAct {
    v: Vec<f32>,
    axis: Axis,
    act: Act,
}

impl CustomOp1 for VecAct {
    fn name(&self) -> &'static str {
        "pixl-bias-act"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let xs = slice(s, l, self.name())?;
        let n = self.v.len();
        let mut out = vec![0f32; xs.len()];
        for_segments(&mut out, self.axis.segment(n), |si, off, seg| {
            if self.act == Act::Gelu {
                // The sum, then the vectorised GELU over the segment.
                for (j, o) in seg.iter_mut().enumerate() {
                    *o = xs[off + j] + self.v[self.axis.entry(si, j, n)];
                }
                crate::fastmath::gelu_in_place(seg);
                return;
            }
            for (j, o) in seg.iter_mut().enumerate() {
                *o = self.act.apply(xs[off + j] + self.v[self.axis.entry(si, j, n)]);
            }
        });
        Ok((CpuStorage::F32(out), l.shape().clone()))
    }
}

/// `act(xs + ys·v[axis])` (`v` empty: `act(xs + ys)`).
struct AddScaled {
    v: Vec<f32>,
    axis: Axis,
    act: Act,
}

impl CustomOp2 for AddScaled {
    fn name(&self) -> &'static str {
        "pixl-add-scaled"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let xs = slice(s1, l1, self.name())?;
        let ys = slice(s2, l2, self.name())?;
        if l1.shape() != l2.shape() {
            candle_core::bail!("{}: shapes {:?} and {:?} differ", self.name(), l1.shape(), l2.shape());
        }
        let n = self.v.len();
        let mut out = vec![0f32; xs.len()];
        let seg = if n == 0 { CHUNK } else { self.axis.segment(n) };
        for_segments(&mut out, seg, |si, off, dst| {
            for (j, o) in dst.iter_mut().enumerate() {
                let y = if n == 0 {
                    ys[off + j]
                } else {
                    ys[off + j] * self.v[self.axis.entry(si, j, n)]
                };
                *o = self.act.apply(xs[off + j] + y);
            }
        });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// `act((xs + v[axis]) + ys)`.
struct BiasAdd {
    v: Vec<f32>,
    axis: Axis,
    act: Act,
}

impl CustomOp2 for BiasAdd {
    fn name(&self) -> &'static str {
        "pixl-bias-add"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let xs = slice(s1, l1, self.name())?;
        let ys = slice(s2, l2, self.name())?;
        if l1.shape() != l2.shape() {
            candle_core::bail!("{}: shapes {:?} and {:?} differ", self.name(), l1.shape(), l2.shape());
        }
        let n = self.v.len();
        let mut out = vec![0f32; xs.len()];
        for_segments(&mut out, self.axis.segment(n), |si, off, dst| {
            for (j, o) in dst.iter_mut().enumerate() {
                *o = self
                    .act
                    .apply((xs[off + j] + self.v[self.axis.entry(si, j, n)]) + ys[off + j]);
            }
        });
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }
}

/// A per-column or per-channel vector kept both as a tensor (fallback) and as host values.
#[derive(Clone, Debug)]
pub struct Vector {
    pub tensor: Tensor,
    values: Vec<f32>,
}

impl Vector {
    pub fn new(tensor: Tensor) -> Result<Self> {
        let values = tensor.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        Ok(Self { tensor, values })
    }

    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// The values on the host.
    pub fn values(&self) -> &[f32] {
        &self.values
    }

    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }

    /// Shape to broadcast against `xs`: `(N)` for rows, `(1, C, 1, …)` for channels.
    fn broadcastable(&self, xs: &Tensor, rows: bool) -> Result<Tensor> {
        if rows {
            return Ok(self.tensor.clone());
        }
        let mut shape = vec![1usize; xs.rank()];
        shape[1] = self.len();
        self.tensor.reshape(shape)
    }

    fn check(&self, xs: &Tensor, rows: bool) -> Result<()> {
        let dim = if rows {
            xs.dims().last().copied()
        } else {
            xs.dims().get(1).copied()
        };
        if dim != Some(self.len()) {
            candle_core::bail!(
                "vector of {} does not fit a tensor of shape {:?}",
                self.len(),
                xs.dims()
            );
        }
        Ok(())
    }
}

fn vec_act(xs: &Tensor, v: &Vector, rows: bool, act: Act) -> Result<Tensor> {
    v.check(xs, rows)?;
    if !cpu_f32(xs) {
        return act.apply_tensor(xs.broadcast_add(&v.broadcastable(xs, rows)?)?);
    }
    let op = VecAct {
        v: v.values.clone(),
        axis: Axis::of(xs, rows)?,
        act,
    };
    xs.contiguous()?.apply_op1_no_bwd(&op)
}

/// `act(xs + bias)`, `bias` over the last dim (a linear layer's bias).
pub fn bias_act_rows(xs: &Tensor, bias: &Vector, act: Act) -> Result<Tensor> {
    vec_act(xs, bias, true, act)
}

/// `act(xs + bias[c])` on `(B, C, …)` (a convolution's bias).
pub fn bias_act_channels(xs: &Tensor, bias: &Vector, act: Act) -> Result<Tensor> {
    vec_act(xs, bias, false, act)
}

/// `act((xs + bias[c]) + residual)` on `(B, C, …)`: a convolution's bias, then a skip connection.
pub fn bias_residual_channels(xs: &Tensor, bias: &Vector, residual: &Tensor, act: Act) -> Result<Tensor> {
    bias.check(xs, false)?;
    if !cpu_f32(xs) || !cpu_f32(residual) {
        return act.apply_tensor((xs.broadcast_add(&bias.broadcastable(xs, false)?)? + residual)?);
    }
    let op = BiasAdd {
        v: bias.values.clone(),
        axis: Axis::of(xs, false)?,
        act,
    };
    xs.contiguous()?.apply_op2_no_bwd(&residual.contiguous()?, &op)
}

/// `act(GroupNorm(xs))` on `(B, C, …)`: per sample and group of `C/groups` channels, the mean
/// and biased variance over the group (accumulated in f64), `(x − μ)/√(σ² + eps)·γ[c] + β[c]`,
/// then the activation; one parallel pass per group. Elsewhere candle's ops.
pub fn group_norm_act(xs: &Tensor, groups: usize, eps: f64, gamma: &Vector, beta: &Vector, act: Act) -> Result<Tensor> {
    gamma.check(xs, false)?;
    beta.check(xs, false)?;
    let dims = xs.dims().to_vec();
    let (b, c) = (dims[0], dims[1]);
    if groups == 0 || c % groups != 0 {
        candle_core::bail!("group norm: {groups} groups do not divide {c} channels");
    }
    if !cpu_f32(xs) {
        let g = xs.reshape((b, groups, ()))?;
        let mean = g.mean_keepdim(2)?;
        let centred = g.broadcast_sub(&mean)?;
        let var = centred.sqr()?.mean_keepdim(2)?;
        let normed = centred.broadcast_div(&(var + eps)?.sqrt()?)?.reshape(dims.as_slice())?;
        let y = normed
            .broadcast_mul(&gamma.broadcastable(xs, false)?)?
            .broadcast_add(&beta.broadcastable(xs, false)?)?;
        return act.apply_tensor(y);
    }
    let src = xs.contiguous()?.flatten_all()?.to_vec1::<f32>()?;
    let plane = src.len() / (b * c).max(1);
    let per_group = (c / groups) * plane;
    let mut out = vec![0f32; src.len()];
    let (gv, bv) = (gamma.values(), beta.values());
    out.par_chunks_mut(per_group)
        .zip(src.par_chunks(per_group))
        .enumerate()
        .for_each(|(k, (dst, x))| {
            let n = x.len().max(1) as f64;
            let mean = x.iter().map(|&v| v as f64).sum::<f64>() / n;
            let var = x.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n;
            let rstd = (1.0 / (var + eps).sqrt()) as f32;
            let mean = mean as f32;
            let first = (k % groups) * (c / groups);
            for (j, (d, &v)) in dst.iter_mut().zip(x).enumerate() {
                let ch = first + j / plane;
                *d = act.apply((v - mean) * rstd * gv[ch] + bv[ch]);
            }
        });
    Tensor::from_vec(out, dims, xs.device())
}

/// `xs + ys·gamma`, `gamma` over the last dim (LayerScale on a residual branch).
pub fn add_scaled_rows(xs: &Tensor, ys: &Tensor, gamma: &Vector) -> Result<Tensor> {
    let _t = crate::profile::span("residual add");
    gamma.check(ys, true)?;
    if !cpu_f32(xs) || !cpu_f32(ys) {
        return xs + ys.broadcast_mul(&gamma.tensor)?;
    }
    let op = AddScaled {
        v: gamma.values.clone(),
        axis: Axis::Column,
        act: Act::None,
    };
    xs.contiguous()?.apply_op2_no_bwd(&ys.contiguous()?, &op)
}

/// `act(xs + ys)`.
pub fn add_act(xs: &Tensor, ys: &Tensor, act: Act) -> Result<Tensor> {
    if !cpu_f32(xs) || !cpu_f32(ys) {
        return act.apply_tensor((xs + ys)?);
    }
    let op = AddScaled {
        v: Vec::new(),
        axis: Axis::Column,
        act,
    };
    xs.contiguous()?.apply_op2_no_bwd(&ys.contiguous()?, &op)
}

/// `v = act(v)` over `out`, in parallel (the vectorised GELU for [`Act::Gelu`]).
pub(crate) fn act_in_place(out: &mut [f32], act: Act) {
    if act == Act::None {
        return;
    }
    out.par_chunks_mut(CHUNK).for_each(|c| match act {
        Act::Gelu => crate::fastmath::gelu_in_place(c),
        _ => c.iter_mut().for_each(|v| *v = act.apply(*v)),
    });
}

/// `act(xs · Wᵀ + b)` for a candle `Linear` over the last dim of `xs`, on any number of leading
/// dims. With no gradient needed, on the CPU in f32: the output rows are filled with the bias,
/// one parallel GEMM over all rows adds `xs · Wᵀ` to them in place (reading `W` as stored, no
/// transposed copy), and the activation runs in place, so the output is the only buffer written.
/// Training on the CPU in f32: [`crate::linear_grad::linear`] (one op with its own backward).
/// Otherwise (other devices or dtypes): candle's `Linear`, then the activation, differentiable.
pub fn linear(xs: &Tensor, layer: &candle_nn::Linear, act: Act) -> Result<Tensor> {
    let (w, b) = (layer.weight(), layer.bias());
    let grad = crate::needs_grad(&[xs, w]) || b.is_some_and(|b| b.track_op());
    let all_f32 = cpu_f32(xs) && cpu_f32(w) && b.is_none_or(cpu_f32);
    if grad && all_f32 && matches!(act, Act::None | Act::Relu | Act::Gelu) {
        return crate::linear_grad::linear(xs, w, b, act);
    }
    if grad || !all_f32 {
        return act.apply_tensor(candle_core::Module::forward(layer, xs)?);
    }
    let dims = xs.dims();
    let Some((&k, lead)) = dims.split_last() else {
        candle_core::bail!("linear: a scalar input");
    };
    let (n, wk) = w.dims2()?;
    if wk != k {
        candle_core::bail!("linear: input width {k}, weight {:?}", w.dims());
    }
    let rows: usize = lead.iter().product();
    let bias = b.map(|b| b.to_vec1::<f32>()).transpose()?;
    if bias.as_ref().is_some_and(|b| b.len() != n) {
        candle_core::bail!(
            "linear: bias of {} values for {n} outputs",
            bias.as_ref().map_or(0, Vec::len)
        );
    }
    let mut out = vec![0f32; rows * n];
    {
        let _t = crate::profile::span("bias + activation");
        if let Some(bias) = &bias {
            out.par_chunks_mut(n)
                .with_min_len(16)
                .for_each(|row| row.copy_from_slice(bias));
        }
    }
    {
        let _t = crate::profile::span("matmul (linear)");
        let xs = xs.contiguous()?;
        let w = w.contiguous()?;
        let (xs_storage, xs_layout) = xs.storage_and_layout();
        let (w_storage, w_layout) = w.storage_and_layout();
        let x = storage_slice(&xs_storage, xs_layout, "linear input")?;
        let wv = storage_slice(&w_storage, w_layout, "linear weight")?;
        if rows > 0 && n > 0 {
            // SAFETY: dst (rows × n, row stride n) is `out`; lhs (rows × k, row stride k) is `x`;
            // rhs = Wᵀ (k × n): element (i, j) is W[j·k + i] (row stride 1, column stride k).
            unsafe {
                gemm::gemm(
                    rows,
                    n,
                    k,
                    out.as_mut_ptr(),
                    1,
                    n as isize,
                    bias.is_some(),
                    x.as_ptr(),
                    1,
                    k as isize,
                    wv.as_ptr(),
                    k as isize,
                    1,
                    1.0f32,
                    1.0f32,
                    false,
                    false,
                    false,
                    gemm_parallelism(),
                );
            }
        }
    }
    if act != Act::None {
        let _t = crate::profile::span("bias + activation");
        act_in_place(&mut out, act);
    }
    let mut out_dims = lead.to_vec();
    out_dims.push(n);
    Tensor::from_vec(out, out_dims, xs.device())
}

/// `act(W · x + b)` per pixel: a 1×1, stride-1, unpadded convolution of `xs` `(B, C, H, W)`
/// with `weight` `(O, C, 1, 1)` and an optional `bias` `(O)`, on the CPU in f32 without
/// gradients: per image, the output planes are filled with the bias, one parallel GEMM
/// `W (O, C) · X (C, H·W)` adds to them in place, and the activation runs in place. `None` when
/// it does not apply (gradients, other devices or dtypes): the caller takes candle's conv.
pub fn conv1x1(xs: &Tensor, weight: &Tensor, bias: Option<&Tensor>, act: Act) -> Result<Option<Tensor>> {
    let tensors = [Some(xs), Some(weight), bias];
    let tensors: Vec<&Tensor> = tensors.into_iter().flatten().collect();
    if tensors.iter().any(|t| !cpu_f32(t)) || crate::needs_grad(&tensors) {
        return Ok(None);
    }
    let (b, c, h, w) = xs.dims4()?;
    let (o, wc, kh, kw) = weight.dims4()?;
    if (wc, kh, kw) != (c, 1, 1) {
        candle_core::bail!("1x1 convolution of {c} channels with a {:?} weight", weight.dims());
    }
    let bias = bias.map(|b| b.to_vec1::<f32>()).transpose()?;
    if bias.as_ref().is_some_and(|bv| bv.len() != o) {
        candle_core::bail!(
            "1x1 convolution: bias of {} values for {o} outputs",
            bias.as_ref().map_or(0, Vec::len)
        );
    }
    let px = h * w;
    let mut out = vec![0f32; b * o * px];
    if let Some(bv) = &bias {
        out.par_chunks_mut(px.max(1))
            .enumerate()
            .for_each(|(i, plane)| plane.fill(bv[i % o]));
    }
    let xs = xs.contiguous()?;
    let weight = weight.contiguous()?;
    {
        let (xs_storage, xs_layout) = xs.storage_and_layout();
        let (w_storage, w_layout) = weight.storage_and_layout();
        let x = storage_slice(&xs_storage, xs_layout, "1x1 convolution input")?;
        let wv = storage_slice(&w_storage, w_layout, "1x1 convolution weight")?;
        let par = gemm_parallelism();
        if px > 0 && o > 0 && c > 0 {
            for bi in 0..b {
                // SAFETY: dst (o × px, row stride px) is image bi's planes of `out`; lhs (o × c,
                // row stride c) is the weight; rhs (c × px, row stride px) is image bi of `x`.
                unsafe {
                    gemm::gemm(
                        o,
                        px,
                        c,
                        out.as_mut_ptr().add(bi * o * px),
                        1,
                        px as isize,
                        bias.is_some(),
                        wv.as_ptr(),
                        1,
                        c as isize,
                        x.as_ptr().add(bi * c * px),
                        1,
                        px as isize,
                        1.0f32,
                        1.0f32,
                        false,
                        false,
                        false,
                        par,
                    );
                }
            }
        }
    }
    if act != Act::None {
        out.par_chunks_mut(CHUNK).for_each(|chunk| match act {
            Act::Gelu => crate::fastmath::gelu_in_place(chunk),
            _ => chunk.iter_mut().for_each(|v| *v = act.apply(*v)),
        });
    }
    Tensor::from_vec(out, (b, o, h, w), xs.device()).map(Some)
}

/// `xs + ys` (a residual connection): [`add_act`]'s parallel pass when no gradient is needed,
/// candle's differentiable add otherwise.
pub fn residual(xs: &Tensor, ys: &Tensor) -> Result<Tensor> {
    let _t = crate::profile::span("residual add");
    if crate::needs_grad(&[xs, ys]) || xs.dims() != ys.dims() {
        return xs + ys;
    }
    add_act(xs, ys, Act::None)
}

/// `relu(xs)`, parallel.
pub fn relu(xs: &Tensor) -> Result<Tensor> {
    let _t = crate::profile::span("bias + activation");
    if !cpu_f32(xs) {
        return xs.relu();
    }
    let zero = Vector::new(Tensor::zeros(1, DType::F32, xs.device())?)?;
    let op = VecAct {
        v: zero.values,
        axis: Axis::Column,
        act: Act::Relu,
    };
    xs.contiguous()?.apply_op1_no_bwd(&op)
}

/// Pixels per block of the channels-first ↔ channels-last passes: each block reads or writes
/// `C` contiguous segments of this many pixels and one contiguous `(pixels, C)` block.
const LAYOUT_BLOCK: usize = 64;

/// Runs `f(image, first pixel, pixels)` over blocks of [`LAYOUT_BLOCK`] pixels of every image,
/// in parallel; `f` returns the block's values to store at `(image, first pixel)` in `out`,
/// `(pixels, C)` channels-last (`to_last`) or `C` planes' segments channels-first.
fn by_pixel_blocks(
    b: usize,
    c: usize,
    px: usize,
    to_last: bool,
    f: impl Fn(usize, usize, usize, &mut [f32]) + Sync,
) -> Vec<f32> {
    let mut out = vec![0f32; b * c * px];
    let blocks = px.div_ceil(LAYOUT_BLOCK);
    let dst = SharedOut(out.as_mut_ptr());
    (0..b * blocks).into_par_iter().for_each(|i| {
        let (bi, p0) = (i / blocks, (i % blocks) * LAYOUT_BLOCK);
        let n = LAYOUT_BLOCK.min(px - p0);
        let mut tile = vec![0f32; n * c];
        f(bi, p0, n, &mut tile);
        let d = dst;
        if to_last {
            // SAFETY: rows p0..p0+n of image bi, channels-last, belong to this block only.
            let out = unsafe { std::slice::from_raw_parts_mut(d.0.add((bi * px + p0) * c), n * c) };
            out.copy_from_slice(&tile);
        } else {
            for ch in 0..c {
                // SAFETY: pixels p0..p0+n of plane (bi, ch) belong to this block only.
                let out = unsafe { std::slice::from_raw_parts_mut(d.0.add((bi * c + ch) * px + p0), n) };
                out.copy_from_slice(&tile[ch * n..(ch + 1) * n]);
            }
        }
    });
    out
}

/// The output pointer shared by [`by_pixel_blocks`]'s workers (disjoint blocks).
#[derive(Clone, Copy)]
struct SharedOut(*mut f32);
// SAFETY: every worker writes its own block of one live allocation.
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

/// `(B, C, H, W)` → `(B, H, W, C)` contiguous (`permute(0, 2, 3, 1)`), one parallel blocked pass
/// on the CPU in f32 without gradients, candle's permute and copy otherwise.
pub fn to_channels_last(xs: &Tensor) -> Result<Tensor> {
    let _t = crate::profile::span("layout copy");
    if !cpu_f32(xs) || crate::needs_grad(&[xs]) {
        return xs.permute((0, 2, 3, 1))?.contiguous();
    }
    let (b, c, h, w) = xs.dims4()?;
    let xs = xs.contiguous()?;
    let px = h * w;
    let out = {
        let (storage, layout) = xs.storage_and_layout();
        let src = storage_slice(&storage, layout, "channels-last copy")?;
        by_pixel_blocks(b, c, px, true, |bi, p0, n, tile| {
            for ch in 0..c {
                let plane = &src[(bi * c + ch) * px + p0..][..n];
                for (j, &v) in plane.iter().enumerate() {
                    tile[j * c + ch] = v;
                }
            }
        })
    };
    Tensor::from_vec(out, (b, h, w, c), xs.device())
}

/// `(B, H, W, C)` → `(B, C, H, W)` (`permute(0, 3, 1, 2)`): contiguous, by one parallel blocked
/// pass, on the CPU in f32 without gradients; otherwise candle's permuted view (no copy).
pub fn to_channels_first(xs: &Tensor) -> Result<Tensor> {
    let _t = crate::profile::span("layout copy");
    if !cpu_f32(xs) || crate::needs_grad(&[xs]) {
        return xs.permute((0, 3, 1, 2));
    }
    let (b, h, w, c) = xs.dims4()?;
    let xs = xs.contiguous()?;
    let px = h * w;
    let out = {
        let (storage, layout) = xs.storage_and_layout();
        let src = storage_slice(&storage, layout, "channels-first copy")?;
        by_pixel_blocks(b, c, px, false, |bi, p0, n, tile| {
            let rows = &src[(bi * px + p0) * c..][..n * c];
            for ch in 0..c {
                for (j, d) in tile[ch * n..(ch + 1) * n].iter_mut().enumerate() {
                    *d = rows[j * c + ch];
                }
            }
        })
    };
    Tensor::from_vec(out, (b, c, h, w), xs.device())
}

/// `xs + (ys · γ)` back in channels-first layout: `xs` `(B, C, H, W)`, `ys` `(B, H, W, C)`,
/// `γ` `(C)` (ConvNeXt's layer scale and residual). One parallel blocked pass on the CPU in f32
/// without gradients (same arithmetic per element); candle's ops otherwise.
pub fn add_scaled_channels_last(xs: &Tensor, ys: &Tensor, gamma: &Tensor) -> Result<Tensor> {
    let _t = crate::profile::span("residual add");
    let (b, c, h, w) = xs.dims4()?;
    if ys.dims() != [b, h, w, c] || gamma.dims() != [c] {
        candle_core::bail!(
            "layer-scaled residual: {:?} + {:?} · {:?} do not fit",
            xs.dims(),
            ys.dims(),
            gamma.dims()
        );
    }
    if !cpu_f32(xs) || !cpu_f32(ys) || !cpu_f32(gamma) || crate::needs_grad(&[xs, ys, gamma]) {
        return xs + ys.broadcast_mul(gamma)?.permute((0, 3, 1, 2))?;
    }
    let g = gamma.to_vec1::<f32>()?;
    let (xs, ys) = (xs.contiguous()?, ys.contiguous()?);
    let px = h * w;
    let out = {
        let (xs_storage, xs_layout) = xs.storage_and_layout();
        let (ys_storage, ys_layout) = ys.storage_and_layout();
        let x = storage_slice(&xs_storage, xs_layout, "layer-scaled residual")?;
        let y = storage_slice(&ys_storage, ys_layout, "layer-scaled residual")?;
        by_pixel_blocks(b, c, px, false, |bi, p0, n, tile| {
            let rows = &y[(bi * px + p0) * c..][..n * c];
            for ch in 0..c {
                let plane = &x[(bi * c + ch) * px + p0..][..n];
                let seg = &mut tile[ch * n..(ch + 1) * n];
                for (j, (d, &xv)) in seg.iter_mut().zip(plane).enumerate() {
                    *d = xv + rows[j * c + ch] * g[ch];
                }
            }
        })
    };
    Tensor::from_vec(out, (b, c, h, w), xs.device())
}

/// `(B, N, 3·H·D)` fused qkv rows → `(3, B, H, N, D)` contiguous, queries and keys of tokens
/// `prefix..N` rotated by `rope` on the way (`x·cos + rotate_half(x)·sin`, [`crate::Rope2d`]'s
/// arithmetic: the same two products and one sum per element).
struct SplitHeads<'a> {
    heads: usize,
    /// `(cos, sin)` tables `(N − prefix, D)` and the number of leading unrotated tokens.
    rope: Option<(&'a [f32], &'a [f32], usize)>,
}

impl CustomOp1 for SplitHeads<'_> {
    fn name(&self) -> &'static str {
        "pixl-split-heads"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = slice(s, l, self.name())?;
        let (b, n, c3) = l.shape().dims3()?;
        let h = self.heads;
        let d = c3 / (3 * h);
        if let Some((cos, sin, prefix)) = self.rope {
            if !d.is_multiple_of(4) || prefix > n || cos.len() != (n - prefix) * d || sin.len() != cos.len() {
                candle_core::bail!(
                    "RoPE tables of {} values for {} rotated tokens of head dim {d}",
                    cos.len(),
                    n.saturating_sub(prefix)
                );
            }
        }
        let mut out = vec![0f32; src.len()];
        // Destination rows (which, batch, head, token) of length D, in parallel.
        out.par_chunks_mut(d).enumerate().for_each(|(r, dst)| {
            let t = r % n;
            let hh = (r / n) % h;
            let bb = (r / (n * h)) % b;
            let which = r / (n * h * b);
            let off = (bb * n + t) * c3 + (which * h + hh) * d;
            let x = &src[off..off + d];
            match self.rope {
                Some((cos, sin, prefix)) if which < 2 && t >= prefix => {
                    let (c, sn) = (&cos[(t - prefix) * d..][..d], &sin[(t - prefix) * d..][..d]);
                    let q = d / 4;
                    for j in 0..d {
                        // rotate_half within each half: (−a2, a1, −b2, b1) by quarters.
                        let rot = match j / q {
                            0 => -x[j + q],
                            1 => x[j - q],
                            2 => -x[j + q],
                            _ => x[j - q],
                        };
                        dst[j] = x[j] * c[j] + rot * sn[j];
                    }
                }
                _ => dst.copy_from_slice(x),
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((3, b, h, n, d))))
    }
}

/// `(B, H, N, D)` → `(B, N, H·D)` contiguous.
struct MergeHeads;

impl CustomOp1 for MergeHeads {
    fn name(&self) -> &'static str {
        "pixl-merge-heads"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = slice(s, l, self.name())?;
        let (b, h, n, d) = l.shape().dims4()?;
        let mut out = vec![0f32; src.len()];
        out.par_chunks_mut(h * d).enumerate().for_each(|(r, dst)| {
            let (bb, t) = (r / n, r % n);
            for (hh, o) in dst.chunks_mut(d).enumerate() {
                let off = ((bb * h + hh) * n + t) * d;
                o.copy_from_slice(&src[off..off + d]);
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((b, n, h * d))))
    }
}

/// Multi-head softmax attention on fused qkv rows `(B, N, 3·C)` (q, k, v, each `heads` heads):
/// `softmax(q·kᵀ/√D)·v` by [`crate::attention`] (its fused blocked kernel on the CPU), output
/// `(B, N, C)` with the heads concatenated.
pub fn attention_qkv(qkv: &Tensor, heads: usize) -> Result<Tensor> {
    attention_qkv_rope(qkv, heads, None)
}

/// [`attention_qkv`] with queries and keys rotated by `rope = (tables, prefix)`: tokens
/// `prefix..N` by the tables' rows (the first `prefix` tokens, registers, unrotated). On the CPU
/// in f32 without RoPE the kernel reads the heads in place ([`crate::attention::attention_qkv_rows`]);
/// with it the head split and the rotation are one parallel pass; with a gradient, the whole
/// attention is one op with its own backward ([`crate::attention_grad::qkv_attention`]).
pub fn attention_qkv_rope(qkv: &Tensor, heads: usize, rope: Option<(&crate::Rope2d, usize)>) -> Result<Tensor> {
    let (b, n, c3) = qkv.dims3()?;
    if c3 % (3 * heads) != 0 {
        candle_core::bail!("qkv width {c3} is not 3 × {heads} heads");
    }
    let d = c3 / (3 * heads);
    let tables_f32 = rope.is_none_or(|(r, _)| cpu_f32(&r.cos) && cpu_f32(&r.sin));
    if cpu_f32(qkv) && crate::needs_grad(&[qkv]) && tables_f32 {
        return crate::attention_grad::qkv_attention(qkv, heads, rope);
    }
    if rope.is_none() && cpu_f32(qkv) && !crate::needs_grad(&[qkv]) {
        let _t = crate::profile::span("attention");
        let qkv = qkv.contiguous()?;
        let out = {
            let (storage, layout) = qkv.storage_and_layout();
            let rows = storage_slice(&storage, layout, "attention qkv")?;
            crate::attention::attention_qkv_rows(rows, (b, n, heads, d))?
        };
        return Tensor::from_vec(out, (b, n, heads * d), qkv.device());
    }
    let split = crate::profile::span("qkv split + RoPE, head merge");
    let (q, k, v) = if cpu_f32(qkv) && !crate::needs_grad(&[qkv]) {
        let tables = match rope {
            Some((r, prefix)) if cpu_f32(&r.cos) && cpu_f32(&r.sin) => Some((
                r.cos.contiguous()?.flatten_all()?.to_vec1::<f32>()?,
                r.sin.contiguous()?.flatten_all()?.to_vec1::<f32>()?,
                prefix,
            )),
            Some(_) => candle_core::bail!("RoPE tables must be f32 on the CPU"),
            None => None,
        };
        let op = SplitHeads {
            heads,
            rope: tables.as_ref().map(|(c, s, p)| (c.as_slice(), s.as_slice(), *p)),
        };
        let t = qkv.contiguous()?.apply_op1_no_bwd(&op)?;
        (t.get(0)?, t.get(1)?, t.get(2)?)
    } else {
        let t = qkv.reshape((b, n, 3, heads, d))?.permute((2, 0, 3, 1, 4))?;
        let (mut q, mut k) = (t.get(0)?.contiguous()?, t.get(1)?.contiguous()?);
        if let Some((r, prefix)) = rope {
            let rotate = |x: &Tensor| -> Result<Tensor> {
                if prefix == 0 {
                    return r.apply(x);
                }
                let reg = x.narrow(2, 0, prefix)?;
                let patches = r.apply(&x.narrow(2, prefix, n - prefix)?)?;
                Tensor::cat(&[&reg, &patches], 2)?.contiguous()
            };
            q = rotate(&q)?;
            k = rotate(&k)?;
        }
        (q, k, t.get(2)?.contiguous()?)
    };
    drop(split);
    let out = crate::attention(&q, &k, &v)?; // (B, H, N, D)
    let _t = crate::profile::span("qkv split + RoPE, head merge");
    if cpu_f32(&out) && !crate::needs_grad(&[&out]) {
        out.apply_op1_no_bwd(&MergeHeads)
    } else {
        out.transpose(1, 2)?.reshape((b, n, heads * d))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn max_diff(a: &Tensor, b: &Tensor) -> f64 {
        assert_eq!(a.dims(), b.dims());
        crate::testing::max_abs_diff(a, b).unwrap()
    }

    /// The fused linear (bias prefilled, GEMM in place, activation in place) against an f64
    /// computation, with and without bias, on leading dims, and its error for a wrong width.
    #[test]
    fn linear_matches_f64() {
        let dev = Device::Cpu;
        let (k, n) = (37, 29);
        let x = Tensor::randn(0f32, 1.0, (2, 3, k), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.3, (n, k), &dev).unwrap();
        let b = Tensor::randn(0f32, 1.0, n, &dev).unwrap();
        let xv = x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let wv = w.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let bv = b.to_vec1::<f32>().unwrap();
        for (bias, act) in [(true, Act::Gelu), (false, Act::None), (true, Act::Relu)] {
            let layer = candle_nn::Linear::new(w.clone(), bias.then(|| b.clone()));
            let got = linear(&x, &layer, act).unwrap();
            assert_eq!(got.dims(), &[2, 3, n]);
            let got = got.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            for r in 0..6 {
                for j in 0..n {
                    let mut v: f64 = (0..k).map(|i| xv[r * k + i] as f64 * wv[j * k + i] as f64).sum();
                    if bias {
                        v += bv[j] as f64;
                    }
                    let want = match act {
                        Act::Gelu => 0.5 * v * (1.0 + candle_core::cpu::erf::erf_f64(v / std::f64::consts::SQRT_2)),
                        Act::Relu => v.max(0.0),
                        _ => v,
                    };
                    let g = got[r * n + j] as f64;
                    assert!(
                        (g - want).abs() < 1e-5 * want.abs().max(1.0),
                        "{act:?} ({r}, {j}): {g} vs {want}"
                    );
                }
            }
        }
        let wrong = candle_nn::Linear::new(Tensor::zeros((n, k + 1), DType::F32, &dev).unwrap(), None);
        assert!(linear(&x, &wrong, Act::None).is_err());
    }

    /// The 1×1 convolution against candle's conv2d, with and without bias, two images.
    #[test]
    fn conv1x1_matches_candle() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 5, 7, 9), &dev).unwrap();
        let w = Tensor::randn(0f32, 1.0, (3, 5, 1, 1), &dev).unwrap();
        let b = Tensor::randn(0f32, 1.0, 3, &dev).unwrap();
        for (bias, act) in [(true, Act::Relu), (false, Act::None)] {
            let bias = bias.then(|| b.clone());
            let want = candle_nn::Conv2d::new(w.clone(), bias.clone(), Default::default());
            let want = act
                .apply_tensor(candle_core::Module::forward(&want, &x).unwrap())
                .unwrap();
            let got = conv1x1(&x, &w, bias.as_ref(), act).unwrap().unwrap();
            assert!(max_diff(&got, &want) < 1e-5, "{act:?}");
        }
        let var = candle_core::Var::from_tensor(&w).unwrap();
        assert!(conv1x1(&x, var.as_tensor(), None, Act::None).unwrap().is_none());
        assert!(conv1x1(&x, &w.narrow(1, 0, 4).unwrap(), None, Act::None).is_err());
    }

    /// Each fused op equals the composed candle ops, element for element.
    #[test]
    fn fused_ops_equal_composed_ops() {
        let dev = Device::Cpu;
        // Larger than one task, odd sizes, a non-contiguous input.
        let x = Tensor::randn(0f32, 1.0, (2, 7, 37, 53), &dev).unwrap();
        let y = Tensor::randn(0f32, 1.0, (2, 7, 37, 53), &dev).unwrap();
        let vc = Vector::new(Tensor::randn(0f32, 1.0, 7, &dev).unwrap()).unwrap();
        let vr = Vector::new(Tensor::randn(0f32, 1.0, 53, &dev).unwrap()).unwrap();
        let bc = vc.tensor.reshape((1, 7, 1, 1)).unwrap();
        for act in [Act::None, Act::Gelu, Act::Relu] {
            // Exact, except GELU, whose erf is the vectorised one (inputs here |x| < 7).
            let tol = if act == Act::Gelu { 3e-7 * 8.0 } else { 0.0 };
            let want = act.apply_tensor(x.broadcast_add(&bc).unwrap()).unwrap();
            assert!(
                max_diff(&bias_act_channels(&x, &vc, act).unwrap(), &want) <= tol,
                "{act:?}"
            );
            let want = act.apply_tensor(x.broadcast_add(&vr.tensor).unwrap()).unwrap();
            assert!(max_diff(&bias_act_rows(&x, &vr, act).unwrap(), &want) <= tol, "{act:?}");
            let want = act.apply_tensor((x.broadcast_add(&bc).unwrap() + &y).unwrap()).unwrap();
            assert!(max_diff(&bias_residual_channels(&x, &vc, &y, act).unwrap(), &want) <= tol);
            let want = act.apply_tensor((&x + &y).unwrap()).unwrap();
            assert!(max_diff(&add_act(&x, &y, act).unwrap(), &want) <= tol);
        }
        let want = (&x + y.broadcast_mul(&vr.tensor).unwrap()).unwrap();
        assert_eq!(max_diff(&add_scaled_rows(&x, &y, &vr).unwrap(), &want), 0.0);
        let xt = x.transpose(2, 3).unwrap(); // (2, 7, 53, 37), non-contiguous
        let vr37 = Vector::new(Tensor::randn(0f32, 1.0, 37, &dev).unwrap()).unwrap();
        let want = xt.broadcast_add(&vr37.tensor).unwrap();
        assert_eq!(max_diff(&bias_act_rows(&xt, &vr37, Act::None).unwrap(), &want), 0.0);
        assert_eq!(max_diff(&relu(&xt).unwrap(), &xt.relu().unwrap()), 0.0);
        // Attention against pixl-nn's (split/merge by reshapes, scale on q).
        let qkv = Tensor::randn(0f32, 1.0, (2, 9, 3 * 4 * 5), &dev).unwrap();
        let t = qkv.reshape((2, 9, 3, 4, 5)).unwrap().permute((2, 0, 3, 1, 4)).unwrap();
        let g = |i| t.get(i).unwrap().contiguous().unwrap();
        let want = crate::attention(&g(0), &g(1), &g(2))
            .unwrap()
            .transpose(1, 2)
            .unwrap()
            .reshape((2, 9, 20))
            .unwrap();
        assert!(max_diff(&attention_qkv(&qkv, 4).unwrap(), &want) < 1e-6);
        // With RoPE on the tokens after two registers: the fused split-and-rotate against the
        // composed path (narrow, Rope2d::apply, cat), which tracks gradients.
        let rope = crate::Rope2d::new(8, 2, 3, 100.0, &dev).unwrap();
        let qkv = Tensor::randn(0f32, 1.0, (2, 8, 3 * 2 * 8), &dev).unwrap();
        let fused = attention_qkv_rope(&qkv, 2, Some((&rope, 2))).unwrap();
        let var = candle_core::Var::from_tensor(&qkv).unwrap();
        let composed = attention_qkv_rope(var.as_tensor(), 2, Some((&rope, 2))).unwrap();
        assert!(max_diff(&fused, &composed) < 1e-6);
        let unrotated = attention_qkv(&qkv, 2).unwrap();
        assert!(
            max_diff(&fused, &unrotated) > 1e-3,
            "the rotation must change the result"
        );
        // Channels-last copy and the layer-scaled residual back, against permutes (two pixel
        // blocks and a remainder: 37·53 pixels).
        let cl = to_channels_last(&x).unwrap();
        assert_eq!(max_diff(&to_channels_first(&cl).unwrap(), &x), 0.0);
        assert_eq!(
            max_diff(&cl, &x.permute((0, 2, 3, 1)).unwrap().contiguous().unwrap()),
            0.0
        );
        let ys = Tensor::randn(0f32, 1.0, (2, 37, 53, 7), &dev).unwrap();
        let want = (&x + ys.broadcast_mul(&vc.tensor).unwrap().permute((0, 3, 1, 2)).unwrap()).unwrap();
        assert_eq!(
            max_diff(&add_scaled_channels_last(&x, &ys, &vc.tensor).unwrap(), &want),
            0.0
        );
        assert!(add_scaled_channels_last(&x, &cl.transpose(1, 2).unwrap(), &vc.tensor).is_err());
        // A vector that does not fit is an error, not a panic.
        assert!(bias_act_channels(&x, &vr, Act::None).is_err());
    }
}
