//! Fused elementwise steps for inference (the relighting network, DA3, Marigold's VAE), parallel
//! on the CPU, without a backward pass: callers take them only when no gradient is needed.
//!
//! candle's CPU elementwise kernels run on one thread, and every bias add, GELU, ReLU, LayerScale
//! and residual add would be a separate pass over memory. These ops do each step in one
//! parallel pass, with the same arithmetic per element as the unfused ops (`x + b` then the
//! activation, `x + y·γ`), so results are unchanged. On other devices (or dtypes) they fall
//! back to the equivalent candle ops.
//!
//! Also [`attention_qkv`]: multi-head attention straight from fused qkv rows, with the head
//! split and the head merge done as single parallel copies.
//!
//! Layouts: "rows" tensors are `(…, N)` with a per-column vector of length `N`; "channels"
//! tensors are `(B, C, …)` with a per-channel vector of length `C`.
use candle_core::{CpuStorage, CustomOp1, CustomOp2, DType, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Activation applied after the sum.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Act {
    None,
    /// Exact GELU, `0.5·x·(1 + erf(x/√2))` (candle's `gelu_erf` arithmetic).
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
            Act::Gelu => (candle_core::cpu::erf::erf_f32(v * std::f32::consts::FRAC_1_SQRT_2) + 1.0) * 0.5 * v,
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

/// `act(xs · Wᵀ + b)` for a candle `Linear` over the last dim of `xs`, on any number of leading
/// dims. With no gradient needed, on the CPU in f32: one matmul over all rows, then the bias and
/// activation in one parallel pass ([`bias_act_rows`]). Otherwise (training, other devices or
/// dtypes): candle's `Linear`, then the activation, differentiable.
pub fn linear(xs: &Tensor, layer: &candle_nn::Linear, act: Act) -> Result<Tensor> {
    let (w, b) = (layer.weight(), layer.bias());
    let grad = crate::needs_grad(&[xs, w]) || b.is_some_and(|b| b.track_op());
    if grad || !cpu_f32(xs) || !cpu_f32(w) {
        return act.apply_tensor(candle_core::Module::forward(layer, xs)?);
    }
    let dims = xs.dims();
    let Some((&k, lead)) = dims.split_last() else {
        candle_core::bail!("linear: a scalar input");
    };
    let rows: usize = lead.iter().product();
    let ys = xs.contiguous()?.reshape((rows, k))?.matmul(&w.t()?)?;
    let ys = match b {
        Some(b) => bias_act_rows(&ys, &Vector::new(b.clone())?, act)?,
        None => act.apply_tensor(ys)?,
    };
    let mut out_dims = lead.to_vec();
    out_dims.push(ys.dim(1)?);
    ys.reshape(out_dims)
}

/// `xs + ys` (a residual connection): [`add_act`]'s parallel pass when no gradient is needed,
/// candle's differentiable add otherwise.
pub fn residual(xs: &Tensor, ys: &Tensor) -> Result<Tensor> {
    if crate::needs_grad(&[xs, ys]) || xs.dims() != ys.dims() {
        return xs + ys;
    }
    add_act(xs, ys, Act::None)
}

/// `relu(xs)`, parallel.
pub fn relu(xs: &Tensor) -> Result<Tensor> {
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

/// `(B, N, 3·H·D)` fused qkv rows → `(3, B, H, N, D)` contiguous.
struct SplitHeads {
    heads: usize,
}

impl CustomOp1 for SplitHeads {
    fn name(&self) -> &'static str {
        "pixl-split-heads"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = slice(s, l, self.name())?;
        let (b, n, c3) = l.shape().dims3()?;
        let h = self.heads;
        let d = c3 / (3 * h);
        let mut out = vec![0f32; src.len()];
        // Destination rows (which, batch, head, token) of length D, in parallel.
        out.par_chunks_mut(d).enumerate().for_each(|(r, dst)| {
            let t = r % n;
            let hh = (r / n) % h;
            let bb = (r / (n * h)) % b;
            let which = r / (n * h * b);
            let off = (bb * n + t) * c3 + (which * h + hh) * d;
            dst.copy_from_slice(&src[off..off + d]);
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
    let (b, n, c3) = qkv.dims3()?;
    if c3 % (3 * heads) != 0 {
        candle_core::bail!("qkv width {c3} is not 3 × {heads} heads");
    }
    let d = c3 / (3 * heads);
    let (q, k, v) = if cpu_f32(qkv) {
        let t = qkv.contiguous()?.apply_op1_no_bwd(&SplitHeads { heads })?;
        (t.get(0)?, t.get(1)?, t.get(2)?)
    } else {
        let t = qkv.reshape((b, n, 3, heads, d))?.permute((2, 0, 3, 1, 4))?;
        (
            t.get(0)?.contiguous()?,
            t.get(1)?.contiguous()?,
            t.get(2)?.contiguous()?,
        )
    };
    let out = crate::attention(&q, &k, &v)?; // (B, H, N, D)
    if cpu_f32(&out) {
        out.apply_op1_no_bwd(&MergeHeads)
    } else {
        out.transpose(1, 2)?.reshape((b, n, heads * d))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        assert_eq!(a.dims(), b.dims());
        (a - b)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap()
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
            let want = act.apply_tensor(x.broadcast_add(&bc).unwrap()).unwrap();
            assert_eq!(
                max_diff(&bias_act_channels(&x, &vc, act).unwrap(), &want),
                0.0,
                "{act:?}"
            );
            let want = act.apply_tensor(x.broadcast_add(&vr.tensor).unwrap()).unwrap();
            assert_eq!(max_diff(&bias_act_rows(&x, &vr, act).unwrap(), &want), 0.0, "{act:?}");
            let want = act.apply_tensor((x.broadcast_add(&bc).unwrap() + &y).unwrap()).unwrap();
            assert_eq!(max_diff(&bias_residual_channels(&x, &vc, &y, act).unwrap(), &want), 0.0);
            let want = act.apply_tensor((&x + &y).unwrap()).unwrap();
            assert_eq!(max_diff(&add_act(&x, &y, act).unwrap(), &want), 0.0);
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
        // A vector that does not fit is an error, not a panic.
        assert!(bias_act_channels(&x, &vr, Act::None).is_err());
    }
}
