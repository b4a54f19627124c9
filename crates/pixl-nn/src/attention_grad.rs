//! Differentiable multi-head attention on fused qkv rows, with 2D RoPE: the training counterpart
//! of [`crate::fused::attention_qkv_rope`] (same values, and a gradient with respect to `qkv`).
//!
//! `qkv` `(B, N, 3·C)`, each row laid out as `(3, H, D)` (queries, keys, values; `H` heads of
//! width `D = C/H`) → `(B, N, C)`, the heads concatenated: per head,
//! `softmax(q̃·k̃ᵀ/√D)·v`, where `q̃`, `k̃` are the queries and keys of tokens `prefix..N` rotated
//! by the RoPE tables ([`crate::Rope2d::apply`]'s arithmetic, row `t − prefix` of `cos`/`sin` for
//! token `t`) and those of the first `prefix` tokens (registers) as they are.
//!
//! Paths:
//! - No gradient needed, or not f32 on the CPU (CUDA, f16/bf16/f64), or RoPE tables that are not
//!   f32 on the CPU: [`crate::fused::attention_qkv_rope`] itself: its fused inference kernels, or
//!   its composed candle ops (reshape, permute, `Rope2d::apply`, [`crate::attention`]'s candle
//!   path, merge), which candle differentiates. (It hands exactly the remaining case, CPU f32
//!   with a gradient, to this module, so neither calls the other back.)
//! - CPU f32 with a gradient: one `CustomOp1` on `qkv` ([`QkvAttention`]), flash-attention style.
//!   Forward, parallel over (batch, head, block of `R` query rows): the block's rotated queries
//!   and the head's rotated keys are gathered, `S = q̃·k̃ᵀ/√D` (`R × N`, one single-threaded GEMM),
//!   the row maxima, `exp(S − max)` and the sums in one vectorised pass, `O = P·v` (a second GEMM
//!   reading `v` in place in `qkv`), each row divided by its sum and written straight into its
//!   columns of the `(B, N, C)` output. Kept for the backward pass: the output (the op's result,
//!   which candle keeps anyway), the input `qkv` (likewise), a copy of the RoPE tables, and each
//!   row's log-sum-exp `lse = max + ln Σ` — `B·H·N` floats, held in the op (a `Mutex` filled by
//!   the forward pass; each call builds a new op) and read, not taken, so a second backward over
//!   the same graph works. No `N × N` scores outlive a block.
//! - Its backward, parallel over (batch, head) and, within a head, over blocks of query rows
//!   (a rayon fold: each worker sums its blocks' `dK`, `dV` into its own `N × D` pair, the pairs
//!   are added at the end): `S` again, `P = exp(S − lse)`, `dV += Pᵀ·dO`, `dP = dO·vᵀ`,
//!   `dS = P ⊙ (dP − δ)/√D` with `δ = rowsum(dO ⊙ O)`, `dq̃ = dS·k̃`, `dk̃ += dSᵀ·q̃` (five GEMMs
//!   per block, the `R × N` blocks `P` and `dS` in per-thread scratch); then `dq̃`, `dk̃` go back
//!   through the transpose of the rotation (for each rotated pair, rotation by `−θ`), and `dq`,
//!   `dk`, `dv` are written into their columns of `d(qkv)` `(B, N, 3·C)`.
//!
//! Memory: at `B = 2`, `N = 1028`, 6 heads of 64, the statistics kept are 48 KiB and the tables
//! 512 KiB, where the composed path keeps `(B, H, N, N)` score and probability matrices of
//! 48 MiB each. Transient: per thread, `R × N` blocks of up to 512 KiB each (`R ≈ 128 Ki / N`
//! rows, 64 to 256); per head, the rotated `q̃`, `k̃` and the `dK`, `dV` sums (`N × D` each).
//!
//! Rounding: the forward pass has [`crate::attention`]'s fused kernel's per-row arithmetic (its
//! exp pass also returns each row's log-sum-exp), so it equals the inference path within f32
//! rounding (tested to 1e-5). The gradient is tested against central differences of a naive
//! f64 implementation and against candle's autograd of the composed path. The backward pass is
//! not itself differentiable (no second derivatives).
use crate::fused::{cpu_f32, storage_slice};
use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;
use std::cell::RefCell;
use std::ops::Range;
use std::sync::Mutex;

/// Differentiable `fused::attention_qkv_rope`: same values, gradient w.r.t. qkv.
///
/// `rope = (tables, prefix)`: tables of `N − prefix` rows of width `D` (a multiple of 4). See
/// the module notes for the paths taken.
pub fn qkv_attention(qkv: &Tensor, heads: usize, rope: Option<(&crate::Rope2d, usize)>) -> Result<Tensor> {
    let n = qkv.dims3()?.1;
    qkv_attention_blocked(qkv, heads, rope, rows_per_block(n))
}

/// [`qkv_attention`] with `block_rows` query rows per block of the CPU kernels.
fn qkv_attention_blocked(
    qkv: &Tensor,
    heads: usize,
    rope: Option<(&crate::Rope2d, usize)>,
    block_rows: usize,
) -> Result<Tensor> {
    let (_, n, c3) = qkv.dims3()?;
    if heads == 0 || c3 % (3 * heads) != 0 {
        candle_core::bail!("qkv width {c3} is not 3 × {heads} heads");
    }
    let tables_on_cpu = rope.is_none_or(|(r, _)| cpu_f32(&r.cos) && cpu_f32(&r.sin));
    if !cpu_f32(qkv) || !crate::needs_grad(&[qkv]) || !tables_on_cpu {
        return crate::fused::attention_qkv_rope(qkv, heads, rope);
    }
    let d = c3 / (3 * heads);
    let rope = match rope {
        Some((r, prefix)) => {
            let fits = prefix <= n && r.cos.dims() == [n - prefix, d] && r.sin.dims() == r.cos.dims();
            if !d.is_multiple_of(4) || !fits {
                candle_core::bail!(
                    "RoPE tables {:?} / {:?} for {n} tokens after {prefix} registers, head dim {d}",
                    r.cos.dims(),
                    r.sin.dims()
                );
            }
            Some(Tables {
                cos: r.cos.contiguous()?.flatten_all()?.to_vec1::<f32>()?,
                sin: r.sin.contiguous()?.flatten_all()?.to_vec1::<f32>()?,
                prefix,
            })
        }
        None => None,
    };
    let op = QkvAttention {
        heads,
        rope,
        block_rows: block_rows.max(1),
        lse: Mutex::new(None),
    };
    let _t = crate::profile::span("attention (differentiable)");
    qkv.contiguous()?.apply_op1(op)
}

/// Score floats per `R × N` block, at most: 128 Ki floats = 512 KiB (the backward pass holds
/// two). Fewer rows make the GEMMs that sum over a block's rows (`Pᵀ·dO`, `dSᵀ·q̃`) slower.
const BLOCK_SCORES: usize = 128 * 1024;

/// Query rows per block for `n` keys: `BLOCK_SCORES / n` clamped to 64..=256, then evened out
/// over the blocks that takes (260 rows: two blocks of 130, not 256 and 4).
fn rows_per_block(n: usize) -> usize {
    let n = n.max(1);
    let rows = (BLOCK_SCORES / n).clamp(64, 256);
    n.div_ceil(n.div_ceil(rows))
}

/// RoPE tables `(N − prefix, D)`, row-major, and the number of unrotated leading tokens.
struct Tables {
    cos: Vec<f32>,
    sin: Vec<f32>,
    prefix: usize,
}

impl Tables {
    /// `(cos, sin)` rows of token `t`, `None` for a register.
    #[inline]
    fn row(&self, t: usize, d: usize) -> Option<(&[f32], &[f32])> {
        let i = t.checked_sub(self.prefix)?;
        Some((&self.cos[i * d..][..d], &self.sin[i * d..][..d]))
    }
}

/// Shape of one call: batch, tokens, heads, head width.
#[derive(Clone, Copy, Debug)]
struct Geom {
    b: usize,
    n: usize,
    h: usize,
    d: usize,
}

impl Geom {
    fn c(self) -> usize {
        self.h * self.d
    }

    fn c3(self) -> usize {
        3 * self.h * self.d
    }

    /// Offset in `qkv` of row `t` of part `which` (0 q, 1 k, 2 v) of head `hh` in batch `bb`.
    fn qkv_at(self, bb: usize, t: usize, which: usize, hh: usize) -> usize {
        (bb * self.n + t) * self.c3() + (which * self.h + hh) * self.d
    }

    /// Offset in the `(B, N, C)` output of row `t` of head `hh` in batch `bb`.
    fn out_at(self, bb: usize, t: usize, hh: usize) -> usize {
        (bb * self.n + t) * self.c() + hh * self.d
    }
}

/// The differentiable op on contiguous CPU f32 `qkv` `(B, N, 3·C)`.
pub struct QkvAttention {
    heads: usize,
    rope: Option<Tables>,
    block_rows: usize,
    /// Per (batch, head, query row) log-sum-exp of the scaled scores, `(B, H, N)`, stored by
    /// the forward pass for the backward pass (recomputed there if absent).
    lse: Mutex<Option<Vec<f32>>>,
}

impl QkvAttention {
    fn geom(&self, shape: &Shape) -> Result<Geom> {
        let (b, n, c3) = shape.dims3()?;
        let h = self.heads;
        if h == 0 || c3 % (3 * h) != 0 {
            candle_core::bail!("qkv width {c3} is not 3 × {h} heads");
        }
        let d = c3 / (3 * h);
        if let Some(t) = &self.rope {
            if !d.is_multiple_of(4) || t.prefix > n || t.cos.len() != (n - t.prefix) * d || t.sin.len() != t.cos.len() {
                candle_core::bail!(
                    "RoPE tables of {} values for {} rotated tokens of head dim {d}",
                    t.cos.len(),
                    n.saturating_sub(t.prefix)
                );
            }
        }
        Ok(Geom { b, n, h, d })
    }
}

impl CustomOp1 for QkvAttention {
    fn name(&self) -> &'static str {
        "pixl-qkv-attention"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let src = crate::fused::slice(s, l, self.name())?;
        let g = self.geom(l.shape())?;
        let mut out = vec![0f32; g.b * g.n * g.c()];
        let mut lse = vec![0f32; g.b * g.h * g.n];
        if !out.is_empty() {
            forward(src, g, self.rope.as_ref(), self.block_rows, &mut out, &mut lse);
        }
        *self.lse.lock().unwrap_or_else(|e| e.into_inner()) = Some(lse);
        Ok((CpuStorage::F32(out), Shape::from((g.b, g.n, g.c()))))
    }

    fn bwd(&self, arg: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let g = self.geom(arg.shape())?;
        if res.dims() != [g.b, g.n, g.c()] || grad_res.dims() != res.dims() {
            candle_core::bail!(
                "{}: output {:?} and its gradient {:?} do not fit qkv {:?}",
                self.name(),
                res.dims(),
                grad_res.dims(),
                arg.dims()
            );
        }
        let (arg, res, grad) = (arg.contiguous()?, res.contiguous()?, grad_res.contiguous()?);
        let (s_arg, l_arg) = arg.storage_and_layout();
        let (s_res, l_res) = res.storage_and_layout();
        let (s_grad, l_grad) = grad.storage_and_layout();
        let src = storage_slice(&s_arg, l_arg, "attention backward: qkv")?;
        let out = storage_slice(&s_res, l_res, "attention backward: output")?;
        let dout = storage_slice(&s_grad, l_grad, "attention backward: output gradient")?;
        let mut dqkv = vec![0f32; src.len()];
        if !out.is_empty() {
            let saved = self.lse.lock().unwrap_or_else(|e| e.into_inner()).clone();
            let lse = match saved {
                Some(lse) if lse.len() == g.b * g.h * g.n => lse,
                _ => {
                    // Not run by this op's forward pass: recompute the statistics.
                    let mut o = vec![0f32; out.len()];
                    let mut lse = vec![0f32; g.b * g.h * g.n];
                    forward(src, g, self.rope.as_ref(), self.block_rows, &mut o, &mut lse);
                    lse
                }
            };
            backward(src, out, dout, &lse, g, self.rope.as_ref(), self.block_rows, &mut dqkv);
        }
        drop((s_arg, s_res, s_grad));
        Tensor::from_vec(dqkv, arg.shape(), arg.device()).map(Some)
    }
}

/// An output pointer shared by workers that write disjoint parts of one live allocation.
#[derive(Clone, Copy)]
struct SyncPtr(*mut f32);
// SAFETY: every user writes only its own, disjoint part of the allocation, which outlives the
// parallel section.
unsafe impl Send for SyncPtr {}
unsafe impl Sync for SyncPtr {}

impl SyncPtr {
    #[inline]
    fn at(self, offset: usize) -> *mut f32 {
        self.0.wrapping_add(offset)
    }
}

/// A read-only strided matrix operand: element `(i, j)` at `ptr + i·rs + j·cs`.
#[derive(Clone, Copy)]
struct View {
    ptr: *const f32,
    rs: usize,
    cs: usize,
}

impl View {
    fn rows(ptr: *const f32, rs: usize) -> Self {
        Self { ptr, rs, cs: 1 }
    }

    /// The transpose of the row-major matrix at `ptr` with row stride `rs`.
    fn transposed(ptr: *const f32, rs: usize) -> Self {
        Self { ptr, rs: 1, cs: rs }
    }
}

/// `dst (m × n, row stride dst_rs, unit column stride) = beta · lhs (m × k) · rhs (k × n)`, or
/// `+=` with `accumulate`, on the calling thread.
///
/// # Safety
/// Every element the views and `dst` address lies in a live allocation, `dst` overlaps neither
/// operand, and no other thread touches `dst`'s elements meanwhile.
unsafe fn gemm_into(
    (m, n, k): (usize, usize, usize),
    dst: *mut f32,
    dst_rs: usize,
    accumulate: bool,
    lhs: View,
    rhs: View,
    beta: f32,
) {
    // SAFETY: forwarded from the caller.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst,
            1,
            dst_rs as isize,
            accumulate,
            lhs.ptr,
            lhs.cs as isize,
            lhs.rs as isize,
            rhs.ptr,
            rhs.cs as isize,
            rhs.rs as isize,
            if accumulate { 1.0 } else { 0.0 },
            beta,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// `x̃ = x ⊙ cos + rotate_half(x) ⊙ sin` ([`crate::Rope2d::apply`]'s arithmetic, the same as
/// the fused inference split): within each half of `D`, pairs `(j, j + D/4)`.
#[inline]
fn rotate(x: &[f32], c: &[f32], s: &[f32], dst: &mut [f32]) {
    let d = x.len();
    let q = d / 4;
    for base in [0, 2 * q] {
        for j in base..base + q {
            let j2 = j + q;
            dst[j] = x[j] * c[j] + -x[j2] * s[j];
            dst[j2] = x[j2] * c[j2] + x[j] * s[j2];
        }
    }
}

/// The transpose of [`rotate`], in place: `dx_j = dy_j·c_j + dy_{j+q}·s_{j+q}`,
/// `dx_{j+q} = dy_{j+q}·c_{j+q} − dy_j·s_j` (rotation by `−θ` where a pair shares its angle).
#[inline]
fn unrotate(x: &mut [f32], c: &[f32], s: &[f32]) {
    let d = x.len();
    let q = d / 4;
    for base in [0, 2 * q] {
        for j in base..base + q {
            let j2 = j + q;
            let (a, b) = (x[j], x[j2]);
            x[j] = a * c[j] + b * s[j2];
            x[j2] = b * c[j2] - a * s[j];
        }
    }
}

/// Rows `rows` of part `which` (0 q, 1 k) of head `hh` in batch `bb`, rotated where the tables
/// say so, into `dst` (`rows.len() × D`, row-major).
fn gather(
    src: &[f32],
    g: Geom,
    (bb, which, hh): (usize, usize, usize),
    rows: Range<usize>,
    rope: Option<&Tables>,
    dst: &mut [f32],
) {
    let d = g.d;
    for (t, row) in rows.zip(dst.chunks_exact_mut(d)) {
        let x = &src[g.qkv_at(bb, t, which, hh)..][..d];
        match rope.and_then(|r| r.row(t, d)) {
            Some((c, s)) => rotate(x, c, s, row),
            None => row.copy_from_slice(x),
        }
    }
}

thread_local! {
    /// Per-thread scratch of the block kernels (grown on first use, then reused).
    static SCRATCH: RefCell<Vec<f32>> = const { RefCell::new(Vec::new()) };
}

/// The forward pass: `out` `(B, N, C)` and `lse` `(B, H, N)`.
fn forward(src: &[f32], g: Geom, rope: Option<&Tables>, block_rows: usize, out: &mut [f32], lse: &mut [f32]) {
    let Geom { n, d, .. } = g;
    let scale = 1.0 / (d as f32).sqrt();
    let dst = SyncPtr(out.as_mut_ptr());
    lse.par_chunks_mut(n).enumerate().for_each(|(bh, lse_head)| {
        let (bb, hh) = (bh / g.h, bh % g.h);
        let mut k = vec![0f32; n * d];
        gather(src, g, (bb, 1, hh), 0..n, rope, &mut k);
        let v = &src[g.qkv_at(bb, 0, 2, hh)..];
        lse_head
            .par_chunks_mut(block_rows)
            .enumerate()
            .for_each(|(blk, lse_blk)| {
                let (i0, r) = (blk * block_rows, lse_blk.len());
                SCRATCH.with_borrow_mut(|scratch| {
                    scratch.resize(scratch.len().max(r * n + r * d + r), 0.0);
                    let (scores, rest) = scratch.split_at_mut(r * n);
                    let (q, rest) = rest.split_at_mut(r * d);
                    let inv = &mut rest[..r];
                    gather(src, g, (bb, 0, hh), i0..i0 + r, rope, q);
                    let o = dst.at(g.out_at(bb, i0, hh));
                    // SAFETY: S (r × n) is `scores`; q (r × d) and k (n × d) are row-major buffers,
                    // kᵀ read in place; v (n × d, row stride 3C) lies in `src` from head hh's first
                    // value; O's rows i0..i0+r (row stride C, d columns from head hh's) lie in
                    // `out` and belong to this block alone.
                    unsafe {
                        gemm_into(
                            (r, n, d),
                            scores.as_mut_ptr(),
                            n,
                            false,
                            View::rows(q.as_ptr(), d),
                            View::transposed(k.as_ptr(), d),
                            scale,
                        );
                        softmax_lse(scores, n, inv, lse_blk);
                        gemm_into(
                            (r, d, n),
                            o,
                            g.c(),
                            false,
                            View::rows(scores.as_ptr(), n),
                            View::rows(v.as_ptr(), g.c3()),
                            1.0,
                        );
                        for (i, &s) in inv.iter().enumerate() {
                            std::slice::from_raw_parts_mut(o.add(i * g.c()), d)
                                .iter_mut()
                                .for_each(|x| *x *= s);
                        }
                    }
                });
            });
    });
}

/// The backward pass into `dqkv` `(B, N, 3·C)`, zero-filled on entry.
#[allow(clippy::too_many_arguments)]
fn backward(
    src: &[f32],
    out: &[f32],
    dout: &[f32],
    lse: &[f32],
    g: Geom,
    rope: Option<&Tables>,
    block_rows: usize,
    dqkv: &mut [f32],
) {
    let Geom { n, d, .. } = g;
    let scale = 1.0 / (d as f32).sqrt();
    let (c, c3) = (g.c(), g.c3());
    let dst = SyncPtr(dqkv.as_mut_ptr());
    (0..g.b * g.h).into_par_iter().for_each(|bh| {
        let (bb, hh) = (bh / g.h, bh % g.h);
        let mut q = vec![0f32; n * d];
        let mut k = vec![0f32; n * d];
        gather(src, g, (bb, 0, hh), 0..n, rope, &mut q);
        gather(src, g, (bb, 1, hh), 0..n, rope, &mut k);
        let lse_head = &lse[bh * n..][..n];
        let v = &src[g.qkv_at(bb, 0, 2, hh)..];
        let o_head = &out[g.out_at(bb, 0, hh)..];
        let do_head = &dout[g.out_at(bb, 0, hh)..];
        let sums = (0..n.div_ceil(block_rows))
            .into_par_iter()
            .fold(
                || (vec![0f32; n * d], vec![0f32; n * d]),
                |(mut dk, mut dv), blk| {
                    let i0 = blk * block_rows;
                    let r = block_rows.min(n - i0);
                    SCRATCH.with_borrow_mut(|scratch| {
                        scratch.resize(scratch.len().max(2 * r * n + r), 0.0);
                        let (p, rest) = scratch.split_at_mut(r * n);
                        let (ds, rest) = rest.split_at_mut(r * n);
                        let delta = &mut rest[..r];
                        for (i, dl) in delta.iter_mut().enumerate() {
                            let (o, go) = (&o_head[(i0 + i) * c..][..d], &do_head[(i0 + i) * c..][..d]);
                            *dl = o.iter().zip(go).map(|(a, b)| a * b).sum();
                        }
                        let q_blk = View::rows(q[i0 * d..].as_ptr(), d);
                        let do_blk = View::rows(do_head[i0 * c..].as_ptr(), c);
                        let dq = dst.at(g.qkv_at(bb, i0, 0, hh));
                        // SAFETY: p and ds (r × n) are scratch; q, k, dk, dv (n × d) are
                        // row-major buffers of this head (q from row i0); v (n × d, row stride
                        // 3C) and dO (rows i0.., row stride C) lie in `src` and `dout` from head
                        // hh's columns; dq's rows i0..i0+r (row stride 3C, head hh's query
                        // columns) lie in `dqkv` and belong to this block alone.
                        unsafe {
                            gemm_into(
                                (r, n, d),
                                p.as_mut_ptr(),
                                n,
                                false,
                                q_blk,
                                View::transposed(k.as_ptr(), d),
                                scale,
                            );
                            exp_shifted(p, n, &lse_head[i0..i0 + r]);
                            gemm_into(
                                (n, d, r),
                                dv.as_mut_ptr(),
                                d,
                                true,
                                View::transposed(p.as_ptr(), n),
                                do_blk,
                                1.0,
                            );
                            gemm_into(
                                (r, n, d),
                                ds.as_mut_ptr(),
                                n,
                                false,
                                do_blk,
                                View::transposed(v.as_ptr(), c3),
                                1.0,
                            );
                            softmax_grad(p, ds, n, delta, scale);
                            gemm_into(
                                (r, d, n),
                                dq,
                                c3,
                                false,
                                View::rows(ds.as_ptr(), n),
                                View::rows(k.as_ptr(), d),
                                1.0,
                            );
                            gemm_into(
                                (n, d, r),
                                dk.as_mut_ptr(),
                                d,
                                true,
                                View::transposed(ds.as_ptr(), n),
                                q_blk,
                                1.0,
                            );
                            for i in 0..r {
                                if let Some((cs, sn)) = rope.and_then(|t| t.row(i0 + i, d)) {
                                    unrotate(std::slice::from_raw_parts_mut(dq.add(i * c3), d), cs, sn);
                                }
                            }
                        }
                    });
                    (dk, dv)
                },
            )
            .reduce_with(|(mut dk, mut dv), (dk2, dv2)| {
                dk.iter_mut().zip(&dk2).for_each(|(a, b)| *a += b);
                dv.iter_mut().zip(&dv2).for_each(|(a, b)| *a += b);
                (dk, dv)
            });
        let Some((mut dk, dv)) = sums else {
            return;
        };
        for (t, (dk_row, dv_row)) in dk.chunks_exact_mut(d).zip(dv.chunks_exact(d)).enumerate() {
            if let Some((cs, sn)) = rope.and_then(|r| r.row(t, d)) {
                unrotate(dk_row, cs, sn);
            }
            // SAFETY: row t's key and value columns of head hh in batch bb lie in `dqkv` and
            // belong to this head alone.
            unsafe {
                std::slice::from_raw_parts_mut(dst.at(g.qkv_at(bb, t, 1, hh)), d).copy_from_slice(dk_row);
                std::slice::from_raw_parts_mut(dst.at(g.qkv_at(bb, t, 2, hh)), d).copy_from_slice(dv_row);
            }
        }
    });
}

/// Lanes of the accumulators in the row loops: wide enough for one AVX-512 register.
const LANES: usize = 16;

/// Each row `x` of a row-major `(rows, cols)` block becomes `exp(x − max x)` in place;
/// `inv[i] = 1/Σ exp(x − max x)`, `lse[i] = max x + ln Σ exp(x − max x)`.
#[inline(always)]
fn softmax_lse_generic(scores: &mut [f32], cols: usize, inv: &mut [f32], lse: &mut [f32]) {
    for ((row, inv), lse) in scores.chunks_exact_mut(cols).zip(inv.iter_mut()).zip(lse.iter_mut()) {
        let mut maxes = [f32::NEG_INFINITY; LANES];
        let mut chunks = row.chunks_exact(LANES);
        for c in &mut chunks {
            for (m, &v) in maxes.iter_mut().zip(c) {
                *m = m.max(v);
            }
        }
        let tail_max = chunks.remainder().iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
        let max = maxes.iter().fold(tail_max, |m, &v| m.max(v));
        let mut sums = [0f32; LANES];
        let mut chunks = row.chunks_exact_mut(LANES);
        for c in &mut chunks {
            for (s, v) in sums.iter_mut().zip(c.iter_mut()) {
                *v = crate::fastmath::exp(*v - max);
                *s += *v;
            }
        }
        let mut sum = 0f32;
        for v in chunks.into_remainder() {
            *v = crate::fastmath::exp(*v - max);
            sum += *v;
        }
        let sum = sum + sums.iter().sum::<f32>();
        *inv = 1.0 / sum;
        *lse = max + sum.ln();
    }
}

/// `x ← exp(x − lse[i])` on each row `i` of a row-major `(rows, cols)` block.
#[inline(always)]
fn exp_shifted_generic(scores: &mut [f32], cols: usize, lse: &[f32]) {
    for (row, &l) in scores.chunks_exact_mut(cols).zip(lse) {
        row.iter_mut().for_each(|v| *v = crate::fastmath::exp(*v - l));
    }
}

/// `dS ← P ⊙ (dP − δ[i])·scale` on each row `i` (`ds` holds `dP` on entry).
#[inline(always)]
fn softmax_grad_generic(p: &[f32], ds: &mut [f32], cols: usize, delta: &[f32], scale: f32) {
    for ((pr, dr), &dl) in p.chunks_exact(cols).zip(ds.chunks_exact_mut(cols)).zip(delta) {
        for (x, &pv) in dr.iter_mut().zip(pr) {
            *x = pv * (*x - dl) * scale;
        }
    }
}

/// Defines `$name`, which runs `$generic` compiled for AVX-512 or AVX2+FMA when the CPU has
/// them (checked at run time), the baseline build otherwise.
macro_rules! dispatched {
    ($(#[$meta:meta])* fn $name:ident($($arg:ident: $ty:ty),* $(,)?) => $generic:ident) => {
        $(#[$meta])*
        fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                unsafe fn wide($($arg: $ty),*) {
                    $generic($($arg),*)
                }
                #[target_feature(enable = "avx2,fma")]
                unsafe fn narrow($($arg: $ty),*) {
                    $generic($($arg),*)
                }
                if std::arch::is_x86_feature_detected!("avx512f") {
                    // SAFETY: the CPU supports the features the function is compiled for.
                    return unsafe { wide($($arg),*) };
                }
                if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                    // SAFETY: as above.
                    return unsafe { narrow($($arg),*) };
                }
            }
            $generic($($arg),*)
        }
    };
}

dispatched! {
    /// [`softmax_lse_generic`], vectorised.
    fn softmax_lse(scores: &mut [f32], cols: usize, inv: &mut [f32], lse: &mut [f32]) => softmax_lse_generic
}
dispatched! {
    /// [`exp_shifted_generic`], vectorised.
    fn exp_shifted(scores: &mut [f32], cols: usize, lse: &[f32]) => exp_shifted_generic
}
dispatched! {
    /// [`softmax_grad_generic`], vectorised.
    fn softmax_grad(p: &[f32], ds: &mut [f32], cols: usize, delta: &[f32], scale: f32) => softmax_grad_generic
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{uniform, SplitMix64};
    use crate::Rope2d;
    use candle_core::{DType, Device, Var};

    /// `(B, N, heads, D)`, with RoPE on a `gh × gw` grid after `prefix` registers when given.
    struct Case {
        b: usize,
        n: usize,
        heads: usize,
        d: usize,
        rope: Option<(Rope2d, usize)>,
    }

    impl Case {
        fn new(b: usize, heads: usize, d: usize, grid: (usize, usize), prefix: usize, rope: bool) -> Self {
            let n = grid.0 * grid.1 + prefix;
            let rope = rope.then(|| (Rope2d::new(d, grid.0, grid.1, 100.0, &Device::Cpu).unwrap(), prefix));
            Self { b, n, heads, d, rope }
        }

        fn rope(&self) -> Option<(&Rope2d, usize)> {
            self.rope.as_ref().map(|(r, p)| (r, *p))
        }

        /// Seeded f32 qkv `(B, N, 3C)` in [−2, 2) and output weights `(B, N, C)` in [−1, 1).
        fn inputs(&self, seed: u64) -> (Tensor, Tensor) {
            let c = self.heads * self.d;
            let dev = Device::Cpu;
            let qkv = uniform((self.b, self.n, 3 * c), -2.0, 2.0, seed, &dev).unwrap();
            let w = uniform((self.b, self.n, c), -1.0, 1.0, seed ^ 0xABCD, &dev).unwrap();
            (qkv.to_dtype(DType::F32).unwrap(), w.to_dtype(DType::F32).unwrap())
        }
    }

    /// The composed candle path (head split by reshape and permute, `Rope2d::apply` after the
    /// registers, [`crate::attention`]'s candle ops on tracked inputs, merge), which candle's
    /// autograd differentiates op by op.
    fn composed(qkv: &Tensor, heads: usize, rope: Option<(&Rope2d, usize)>) -> Result<Tensor> {
        let (b, n, c3) = qkv.dims3()?;
        let d = c3 / (3 * heads);
        let t = qkv.reshape((b, n, 3, heads, d))?.permute((2, 0, 3, 1, 4))?;
        let (mut q, mut k) = (t.get(0)?.contiguous()?, t.get(1)?.contiguous()?);
        if let Some((r, prefix)) = rope {
            let rotate = |x: &Tensor| -> Result<Tensor> {
                let patches = r.apply(&x.narrow(2, prefix, n - prefix)?)?;
                Tensor::cat(&[&x.narrow(2, 0, prefix)?, &patches], 2)?.contiguous()
            };
            q = rotate(&q)?;
            k = rotate(&k)?;
        }
        let out = crate::attention(&q, &k, &t.get(2)?.contiguous()?)?;
        out.transpose(1, 2)?.reshape((b, n, heads * d))
    }

    fn values(t: &Tensor) -> Vec<f64> {
        t.to_dtype(DType::F64)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f64>()
            .unwrap()
    }

    /// `max |a − b| / max |b|`.
    fn rel_err(a: &[f64], b: &[f64]) -> f64 {
        assert_eq!(a.len(), b.len());
        let scale = b.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-12);
        a.iter().zip(b).fold(0f64, |m, (x, y)| m.max((x - y).abs())) / scale
    }

    /// d(Σ f(qkv) ⊙ w)/d(qkv) by candle's autograd, `qkv` as a `Var`.
    fn autograd(f: impl Fn(&Tensor) -> Result<Tensor>, qkv: &Tensor, w: &Tensor) -> (Vec<f64>, Vec<f64>) {
        let var = Var::from_tensor(qkv).unwrap();
        let out = f(var.as_tensor()).unwrap();
        let grads = (&out * w).unwrap().sum_all().unwrap().backward().unwrap();
        (values(&out), values(grads.get(var.as_tensor()).unwrap()))
    }

    /// A direct f64 evaluation: per batch and head, rotate, scores, softmax, weighted values.
    fn naive(case: &Case, qkv: &[f64], tables: Option<(&[f64], &[f64], usize)>) -> Vec<f64> {
        let (b, n, h, d) = (case.b, case.n, case.heads, case.d);
        let c = h * d;
        let q4 = d / 4;
        let mut out = vec![0f64; b * n * c];
        let vec_of = |bb: usize, t: usize, which: usize, hh: usize| -> Vec<f64> {
            let x = &qkv[(bb * n + t) * 3 * c + (which * h + hh) * d..][..d];
            match tables {
                Some((cos, sin, prefix)) if which < 2 && t >= prefix => (0..d)
                    .map(|j| {
                        let rot = match j / q4 {
                            0 | 2 => -x[j + q4],
                            _ => x[j - q4],
                        };
                        let r = (t - prefix) * d + j;
                        x[j] * cos[r] + rot * sin[r]
                    })
                    .collect(),
                _ => x.to_vec(),
            }
        };
        for bb in 0..b {
            for hh in 0..h {
                let ks: Vec<Vec<f64>> = (0..n).map(|t| vec_of(bb, t, 1, hh)).collect();
                let vs: Vec<Vec<f64>> = (0..n).map(|t| vec_of(bb, t, 2, hh)).collect();
                for i in 0..n {
                    let q = vec_of(bb, i, 0, hh);
                    let s: Vec<f64> = ks
                        .iter()
                        .map(|k| q.iter().zip(k).map(|(a, b)| a * b).sum::<f64>() / (d as f64).sqrt())
                        .collect();
                    let m = s.iter().fold(f64::NEG_INFINITY, |a, &v| a.max(v));
                    let e: Vec<f64> = s.iter().map(|v| (v - m).exp()).collect();
                    let z: f64 = e.iter().sum();
                    for (j, ej) in e.iter().enumerate() {
                        for (x, &vv) in out[(bb * n + i) * c + hh * d..][..d].iter_mut().zip(&vs[j]) {
                            *x += ej / z * vv;
                        }
                    }
                }
            }
        }
        out
    }

    /// Central differences of `Σ naive(qkv) ⊙ w`, step 1e-6, in f64.
    fn naive_gradient(case: &Case, qkv: &Tensor, w: &Tensor) -> Vec<f64> {
        let x = values(qkv);
        let w = values(w);
        let tables = case.rope.as_ref().map(|(r, p)| (values(&r.cos), values(&r.sin), *p));
        let tables = tables.as_ref().map(|(c, s, p)| (c.as_slice(), s.as_slice(), *p));
        let loss = |x: &[f64]| naive(case, x, tables).iter().zip(&w).map(|(a, b)| a * b).sum::<f64>();
        let h = 1e-6;
        let mut x = x;
        (0..x.len())
            .map(|e| {
                let x0 = x[e];
                x[e] = x0 + h;
                let up = loss(&x);
                x[e] = x0 - h;
                let down = loss(&x);
                x[e] = x0;
                (up - down) / (2.0 * h)
            })
            .collect()
    }

    /// The differentiable op's values equal the fused inference path's (no gradient), with and
    /// without RoPE, in one block or several (with a remainder).
    #[test]
    fn forward_matches_inference_path() {
        for (case, seed) in [
            (Case::new(2, 3, 8, (3, 3), 2, true), 1),
            (Case::new(2, 3, 8, (3, 3), 2, false), 2),
            (Case::new(1, 2, 16, (8, 8), 4, true), 3),
            (Case::new(2, 2, 12, (4, 5), 0, true), 4),
        ] {
            let (qkv, _) = case.inputs(seed);
            let want = crate::fused::attention_qkv_rope(&qkv, case.heads, case.rope()).unwrap();
            let var = Var::from_tensor(&qkv).unwrap();
            for rows in [rows_per_block(case.n), 4, 7] {
                let got = qkv_attention_blocked(var.as_tensor(), case.heads, case.rope(), rows).unwrap();
                assert!(got.track_op(), "the op must be recorded for backward");
                let err = crate::testing::max_abs_diff(&got, &want).unwrap();
                assert!(err <= 1e-5, "N {} rows {rows}: {err:e}", case.n);
            }
            // Without a gradient, the inference path itself.
            let plain = qkv_attention(&qkv, case.heads, case.rope()).unwrap();
            assert_eq!(crate::testing::max_abs_diff(&plain, &want).unwrap(), 0.0);
        }
    }

    /// B = 2, N = 11 (3×3 patches after 2 registers), 3 heads of 8: the gradient against
    /// central differences of a naive f64 implementation, with and without RoPE, one block or
    /// blocks of 4 rows.
    #[test]
    fn gradient_matches_naive_f64() {
        for (rope, seed) in [(true, 11), (false, 12)] {
            let case = Case::new(2, 3, 8, (3, 3), 2, rope);
            let (qkv, w) = case.inputs(seed);
            let want = naive_gradient(&case, &qkv, &w);
            let x = values(&qkv);
            let tables = case.rope.as_ref().map(|(r, p)| (values(&r.cos), values(&r.sin), *p));
            let tables = tables.as_ref().map(|(c, s, p)| (c.as_slice(), s.as_slice(), *p));
            let want_out = naive(&case, &x, tables);
            for rows in [rows_per_block(case.n), 4] {
                let (out, got) = autograd(|t| qkv_attention_blocked(t, case.heads, case.rope(), rows), &qkv, &w);
                assert!(rel_err(&out, &want_out) < 1e-5, "rope {rope} rows {rows}: values");
                let err = rel_err(&got, &want);
                assert!(err < 1e-4, "rope {rope} rows {rows}: gradient off by {err:e}");
            }
        }
    }

    /// Against candle's autograd of the composed path on the same f32 inputs: the test shape and
    /// a larger one over several blocks; a second backward over the same graph agrees.
    #[test]
    fn gradient_matches_composed_autograd() {
        for (case, seed) in [
            (Case::new(2, 3, 8, (3, 3), 2, true), 21),
            (Case::new(2, 3, 8, (3, 3), 2, false), 22),
            (Case::new(2, 2, 16, (8, 8), 4, true), 23),
        ] {
            let (qkv, w) = case.inputs(seed);
            let composed = |t: &Tensor| composed(t, case.heads, case.rope());
            let (want_out, want) = autograd(composed, &qkv, &w);
            for rows in [rows_per_block(case.n), 8] {
                let ours = |t: &Tensor| qkv_attention_blocked(t, case.heads, case.rope(), rows);
                let (out, got) = autograd(ours, &qkv, &w);
                assert!(rel_err(&out, &want_out) < 1e-5);
                let err = rel_err(&got, &want);
                assert!(err < 1e-4, "N {} rows {rows}: gradient off by {err:e}", case.n);
            }
            let var = Var::from_tensor(&qkv).unwrap();
            let loss = (qkv_attention(var.as_tensor(), case.heads, case.rope()).unwrap() * &w)
                .unwrap()
                .sum_all()
                .unwrap();
            let first = values(loss.backward().unwrap().get(var.as_tensor()).unwrap());
            let second = values(loss.backward().unwrap().get(var.as_tensor()).unwrap());
            assert_eq!(first, second);
        }
    }

    /// The op inside a larger graph: qkv from a linear map of tracked tokens, a non-contiguous
    /// upstream gradient (the output transposed before the loss) — against the composed path.
    #[test]
    fn gradient_flows_through_a_graph() {
        let case = Case::new(2, 2, 8, (2, 3), 1, true);
        let dev = Device::Cpu;
        let mut rng = SplitMix64(5);
        let x: Vec<f32> = (0..2 * case.n * 10)
            .map(|_| rng.next_f64() as f32 * 2.0 - 1.0)
            .collect();
        let x = Var::from_vec(x, (2, case.n, 10), &dev).unwrap();
        let wq = Tensor::randn(0f32, 0.5, (48, 10), &dev).unwrap();
        let wt = Tensor::randn(0f32, 1.0, (2, 16, case.n), &dev).unwrap();
        let run = |f: &dyn Fn(&Tensor) -> Result<Tensor>| {
            let qkv = x.as_tensor().broadcast_matmul(&wq.t().unwrap()).unwrap();
            let out = f(&qkv).unwrap().transpose(1, 2).unwrap();
            let grads = (out * &wt).unwrap().sum_all().unwrap().backward().unwrap();
            values(grads.get(x.as_tensor()).unwrap())
        };
        let want = run(&|t| composed(t, case.heads, case.rope()));
        let got = run(&|t| qkv_attention(t, case.heads, case.rope()));
        assert!(rel_err(&got, &want) < 1e-4);
    }

    /// Other dtypes take the composed candle path, which candle differentiates (checked by f64
    /// finite differences).
    #[test]
    fn f64_falls_back_to_the_composed_path() {
        let dev = Device::Cpu;
        let rope = Rope2d::new(4, 2, 2, 100.0, &dev).unwrap();
        let rope = Rope2d {
            cos: rope.cos.to_dtype(DType::F64).unwrap(),
            sin: rope.sin.to_dtype(DType::F64).unwrap(),
        };
        let qkv = uniform((1, 6, 24), -1.0, 1.0, 7, &dev).unwrap();
        crate::testing::assert_gradients(
            "qkv attention (f64)",
            |xs| qkv_attention(&xs[0], 2, Some((&rope, 2))),
            &[qkv],
            1e-6,
        )
        .unwrap();
    }

    /// Shapes that do not fit are errors, not panics.
    #[test]
    fn bad_inputs_are_errors() {
        let case = Case::new(1, 2, 8, (3, 3), 2, true);
        let (qkv, _) = case.inputs(9);
        let var = Var::from_tensor(&qkv).unwrap();
        let t = var.as_tensor();
        let rope = case.rope().map(|(r, _)| r);
        assert!(qkv_attention(t, 5, None).is_err());
        assert!(qkv_attention(t, 0, None).is_err());
        assert!(qkv_attention(t, 2, rope.map(|r| (r, 1))).is_err());
        assert!(qkv_attention(t, 2, rope.map(|r| (r, 20))).is_err());
        let narrow = Rope2d::new(4, 3, 3, 100.0, &Device::Cpu).unwrap();
        assert!(qkv_attention(t, 2, Some((&narrow, 2))).is_err());
        assert!(qkv_attention(t, 2, rope.map(|r| (r, 2))).is_ok());
    }
}
