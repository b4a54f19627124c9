//! Multi-head scaled-dot-product attention: `softmax(q kᵀ / √D) v`.
//!
//! `q`: `(B, H, N, D)`, `k`: `(B, H, M, D)`, `v`: `(B, H, M, Dv)` → `(B, H, N, Dv)`, same dtype.
//!
//! - Differentiable path (any input tracks gradients, or not f32 on the CPU): candle ops; the
//!   scale is applied to `q` (`N·D` products rather than `N·M`), the softmax dispatches through
//!   [`crate::ops::softmax_last_dim`], and the full `(B, H, N, M)` score matrix is materialised.
//! - CPU f32 inference path: a fused kernel that never holds more than one block of query rows'
//!   scores per thread. For each head and block of `R` query rows (`R·M` floats ≈ 512 KiB, so
//!   the block stays in L2): `S = (q_blk · kᵀ) / √D` by one single-threaded GEMM reading `k`
//!   in place (no transposed copy), the row softmax numerators and sums in one vectorised pass
//!   ([`crate::fastmath`]), `O = S · v` by a second GEMM, then each row divided by its sum.
//!   Heads × blocks run in parallel on rayon's pool. Differs from the candle path only by
//!   rounding (tested against an f64 computation).
use crate::fused::slice;
use candle_core::{CpuStorage, CustomOp3, DType, Device, Layout, Result, Shape, Tensor};
use rayon::prelude::*;
use std::cell::RefCell;

pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    let _t = crate::profile::span("attention");
    let fused = matches!(q.device(), Device::Cpu)
        && [q, k, v].iter().all(|t| t.dtype() == DType::F32)
        && !crate::needs_grad(&[q, k, v]);
    if fused {
        return q
            .contiguous()?
            .apply_op3_no_bwd(&k.contiguous()?, &v.contiguous()?, &FusedAttention);
    }
    let d = q.dim(candle_core::D::Minus1)?;
    let scale = 1.0 / (d as f64).sqrt();
    let att = (q * scale)?.matmul(&k.t()?)?;
    let att = crate::ops::softmax_last_dim(&att)?;
    att.matmul(v)
}

/// Score floats per query block: 128 Ki floats = 512 KiB.
const BLOCK_SCORES: usize = 128 * 1024;

/// Query rows per block of the fused kernel for `m` keys.
fn rows_per_block(m: usize) -> usize {
    (BLOCK_SCORES / m.max(1)).clamp(8, 256)
}

/// f32 values of scratch each worker thread of the fused CPU kernel keeps for `m` keys (one
/// block of scores and its rows' sums; grown on first use, then reused by later calls).
pub fn fused_scratch_floats(m: usize) -> usize {
    let rows = rows_per_block(m);
    rows * m + rows
}

struct FusedAttention;

thread_local! {
    /// Per-thread scratch for one block's scores and its rows' inverse sums.
    static SCRATCH: RefCell<(Vec<f32>, Vec<f32>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

impl CustomOp3 for FusedAttention {
    fn name(&self) -> &'static str {
        "pixl-fused-attention"
    }

    fn cpu_fwd(
        &self,
        sq: &CpuStorage,
        lq: &Layout,
        sk: &CpuStorage,
        lk: &Layout,
        sv: &CpuStorage,
        lv: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        let (b, h, n, d) = lq.shape().dims4()?;
        let (bk, hk, m, dk) = lk.shape().dims4()?;
        let (bv, hv, mv, dv) = lv.shape().dims4()?;
        if (bk, hk, dk) != (b, h, d) || (bv, hv, mv) != (b, h, m) {
            candle_core::bail!(
                "attention: shapes q {:?}, k {:?}, v {:?} do not agree",
                lq.shape(),
                lk.shape(),
                lv.shape()
            );
        }
        let (q, k, v) = (
            slice(sq, lq, "attention q")?,
            slice(sk, lk, "attention k")?,
            slice(sv, lv, "attention v")?,
        );
        let mut out = vec![0f32; b * h * n * dv];
        if out.is_empty() {
            return Ok((CpuStorage::F32(out), Shape::from((b, h, n, dv))));
        }
        if m == 0 {
            candle_core::bail!("attention: no keys (M = 0)");
        }
        let scale = 1.0 / (d as f32).sqrt();
        let rows_per_block = rows_per_block(m);
        out.par_chunks_mut(n * dv).enumerate().for_each(|(bh, out_head)| {
            let q_head = &q[bh * n * d..(bh + 1) * n * d];
            let k_head = &k[bh * m * d..(bh + 1) * m * d];
            let v_head = &v[bh * m * dv..(bh + 1) * m * dv];
            out_head
                .par_chunks_mut(rows_per_block * dv)
                .enumerate()
                .for_each(|(blk, out_blk)| {
                    let rows = out_blk.len() / dv;
                    let q_blk = &q_head[blk * rows_per_block * d..][..rows * d];
                    SCRATCH.with_borrow_mut(|(scores, inv)| {
                        scores.resize(rows * m, 0.0);
                        inv.resize(rows, 0.0);
                        block(q_blk, k_head, v_head, (rows, m, d, dv), scale, scores, inv, out_blk);
                    });
                });
        });
        Ok((CpuStorage::F32(out), Shape::from((b, h, n, dv))))
    }
}

/// One block of `rows` query rows against all `m` keys of one head.
#[allow(clippy::too_many_arguments)]
fn block(
    q: &[f32],
    k: &[f32],
    v: &[f32],
    (rows, m, d, dv): (usize, usize, usize, usize),
    scale: f32,
    scores: &mut [f32],
    inv: &mut [f32],
    out: &mut [f32],
) {
    debug_assert!(q.len() == rows * d && k.len() == m * d && v.len() == m * dv);
    debug_assert!(scores.len() == rows * m && inv.len() == rows && out.len() == rows * dv);
    // SAFETY: all strides describe row-major matrices lying inside the slices checked above:
    // S (rows×m, row stride m) = scale · Q (rows×d, row stride d) · Kᵀ, where Kᵀ(i, j) = K[j·d + i]
    // (column stride d, row stride 1).
    unsafe {
        gemm::gemm(
            rows,
            m,
            d,
            scores.as_mut_ptr(),
            1,
            m as isize,
            false,
            q.as_ptr(),
            1,
            d as isize,
            k.as_ptr(),
            d as isize,
            1,
            0.0f32,
            scale,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
    crate::fastmath::softmax_rows_unnormalised(scores, m, inv);
    // SAFETY: O (rows×dv, row stride dv) = S (rows×m, row stride m) · V (m×dv, row stride dv).
    unsafe {
        gemm::gemm(
            rows,
            dv,
            m,
            out.as_mut_ptr(),
            1,
            dv as isize,
            false,
            scores.as_ptr(),
            1,
            m as isize,
            v.as_ptr(),
            1,
            dv as isize,
            0.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
    for (row, &s) in out.chunks_exact_mut(dv).zip(inv.iter()) {
        row.iter_mut().for_each(|x| *x *= s);
    }
}
