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
//! - [`attention_qkv_rows`]: on fused qkv rows `(B, N, 3·H·D)`, reading the heads in place and
//!   writing `(B, N, H·D)` directly (no head split or merge copies); with AVX-512 its products
//!   run on [`crate::packed`]'s tile kernel (keys and values packed once per head, queries
//!   scaled by `1/√D` as they are packed), elsewhere the same blocks as above.
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
    assert!(q.len() == rows * d && k.len() == m * d && v.len() == m * dv);
    assert!(scores.len() == rows * m && inv.len() == rows && out.len() == rows * dv);
    let views = Views {
        q: q.as_ptr(),
        k: k.as_ptr(),
        v: v.as_ptr(),
        out: out.as_mut_ptr(),
        ldq: d,
        ldk: d,
        ldv: dv,
        ldo: dv,
    };
    // SAFETY: the slices checked above hold the row-major matrices the views describe.
    unsafe { block_raw(&views, (rows, m, d, dv), scale, scores, inv) }
}

/// Row-major matrices by first element and row stride: the block's queries `(rows, d)`, the
/// head's keys `(m, d)` and values `(m, dv)`, and the block's output `(rows, dv)`.
struct Views {
    q: *const f32,
    k: *const f32,
    v: *const f32,
    out: *mut f32,
    ldq: usize,
    ldk: usize,
    ldv: usize,
    ldo: usize,
}

/// [`block`] on strided views: `S = scale·Q·Kᵀ`, the row softmax numerators and sums, then
/// `O = S·V` with each row divided by its sum.
///
/// # Safety
/// The views describe matrices inside live allocations, the output's not read or written by
/// anyone else meanwhile; `scores` holds `rows·m` values and `inv` `rows`.
unsafe fn block_raw(
    x: &Views,
    (rows, m, d, dv): (usize, usize, usize, usize),
    scale: f32,
    scores: &mut [f32],
    inv: &mut [f32],
) {
    debug_assert!(scores.len() == rows * m && inv.len() == rows);
    // S (rows×m, row stride m) = scale · Q (rows×d, row stride ldq) · Kᵀ, where
    // Kᵀ(i, j) = K[j·ldk + i] (column stride ldk, row stride 1).
    gemm::gemm(
        rows,
        m,
        d,
        scores.as_mut_ptr(),
        1,
        m as isize,
        false,
        x.q,
        1,
        x.ldq as isize,
        x.k,
        x.ldk as isize,
        1,
        0.0f32,
        scale,
        false,
        false,
        false,
        gemm::Parallelism::None,
    );
    crate::fastmath::softmax_rows_unnormalised(scores, m, inv);
    // O (rows×dv, row stride ldo) = S (rows×m, row stride m) · V (m×dv, row stride ldv).
    gemm::gemm(
        rows,
        dv,
        m,
        x.out,
        1,
        x.ldo as isize,
        false,
        scores.as_ptr(),
        1,
        m as isize,
        x.v,
        1,
        x.ldv as isize,
        0.0f32,
        1.0f32,
        false,
        false,
        false,
        gemm::Parallelism::None,
    );
    for (r, &s) in inv.iter().enumerate().take(rows) {
        let row = std::slice::from_raw_parts_mut(x.out.add(r * x.ldo), dv);
        row.iter_mut().for_each(|v| *v *= s);
    }
}

/// The output pointer shared by [`attention_qkv_rows`]' tasks (disjoint blocks of columns and
/// rows).
#[derive(Clone, Copy)]
struct SharedOut(*mut f32);
// SAFETY: every task writes its own head's columns of its own rows of one live allocation.
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl SharedOut {
    /// The pointer (a method, so that closures capture the whole `Sync` wrapper).
    fn ptr(&self) -> *mut f32 {
        self.0
    }
}

/// Multi-head softmax attention straight from fused qkv rows, on the CPU in f32 without
/// gradients: `qkv` `(B, N, 3·H·D)` row-major (queries, keys, values, each `H` heads of `D`) →
/// `(B, N, H·D)`, heads concatenated, the same as splitting the heads, [`attention`] and merging
/// them. The fused kernel's blocks read `q`, `k`, `v` in place with row stride `3·H·D` and
/// write each head's columns of the output in place: no split or merge copies.
pub fn attention_qkv_rows(qkv: &[f32], (b, n, heads, d): (usize, usize, usize, usize)) -> Result<Vec<f32>> {
    let c = heads * d;
    if qkv.len() != b * n * 3 * c {
        candle_core::bail!("attention: {} qkv values for ({b}, {n}, 3·{heads}·{d})", qkv.len());
    }
    let len = b * n * c;
    let mut out = Vec::<f32>::with_capacity(len);
    if len == 0 {
        return Ok(out);
    }
    let scale = 1.0 / (d as f32).sqrt();
    if !crate::packed::available() {
        portable_qkv_rows(qkv, (b, n, heads, d), scale, &mut out);
        return Ok(out);
    }
    {
        let dst = SharedOut(out.as_mut_ptr());
        (0..b * heads).into_par_iter().for_each(|bh| {
            let (bb, hh) = (bh / heads, bh % heads);
            let head = &qkv[bb * n * 3 * c + hh * d..];
            // SAFETY: image bb's rows, head hh's columns of `out`, written by this task alone.
            unsafe { packed_head(head, (n, c, d), scale, dst.ptr().add(bb * n * c + hh * d)) };
        });
        // SAFETY: every (image, head) task wrote its columns of every row.
        unsafe { out.set_len(len) };
    }
    Ok(out)
}

/// [`attention_qkv_rows`] on any CPU (the generic blocked kernel): fills `out`, empty with
/// capacity for `B·N·H·D` values.
fn portable_qkv_rows(qkv: &[f32], (b, n, heads, d): (usize, usize, usize, usize), scale: f32, out: &mut Vec<f32>) {
    let c = heads * d;
    let len = b * n * c;
    debug_assert!(out.is_empty() && out.capacity() >= len && qkv.len() == b * n * 3 * c);
    let rpb = rows_per_block(n);
    let blocks = n.div_ceil(rpb);
    let dst = SharedOut(out.as_mut_ptr());
    (0..b * heads * blocks).into_par_iter().for_each(|t| {
        let (bh, blk) = (t / blocks, t % blocks);
        let (bb, hh) = (bh / heads, bh % heads);
        let row0 = blk * rpb;
        let rows = rpb.min(n - row0);
        let base = bb * n * 3 * c + hh * d;
        // SAFETY: every view lies inside `qkv` (rows bb·n.., columns of head hh of q, k, v) or
        // `out` (rows row0.. of image bb, columns of head hh), which this task alone writes.
        unsafe {
            let views = Views {
                q: qkv.as_ptr().add(base + row0 * 3 * c),
                k: qkv.as_ptr().add(base + c),
                v: qkv.as_ptr().add(base + 2 * c),
                out: dst.ptr().add((bb * n + row0) * c + hh * d),
                ldq: 3 * c,
                ldk: 3 * c,
                ldv: 3 * c,
                ldo: c,
            };
            SCRATCH.with_borrow_mut(|(scores, inv)| {
                scores.resize(rows * n, 0.0);
                inv.resize(rows, 0.0);
                block_raw(&views, (rows, n, d, d), scale, scores, inv);
            });
        }
    });
    // SAFETY: the tasks above wrote every value: each (image, head, block of rows) once, the
    // second product (read_dst false) storing its whole output block.
    unsafe { out.set_len(len) };
}

/// Query rows per block of [`packed_head`]: a multiple of the kernel's tile rows.
const PACKED_BLOCK_ROWS: usize = 8 * crate::packed::TILE_ROWS;

/// Per-thread scratch of [`packed_head`]: the head's keys and values as panels, a block's packed
/// queries, scores, packed probabilities and row sums.
#[derive(Default)]
struct HeadScratch {
    keys: crate::packed::AlignedScratch,
    values: crate::packed::AlignedScratch,
    queries: Vec<f32>,
    scores: Vec<f32>,
    probs: Vec<f32>,
    inv: Vec<f32>,
}

thread_local! {
    static HEAD_SCRATCH: RefCell<HeadScratch> = RefCell::new(HeadScratch::default());
}

/// One head of [`attention_qkv_rows`] with the packed AVX-512 kernel ([`crate::packed`]):
/// `head` starts at the head's first query value, rows `3c` apart (keys at `+c`, values at
/// `+2c`), `n` tokens of `d` values; the output (`n` rows of `d`, `c` apart) at `out`. The keys
/// are packed once per head as the kernel's panels (32 keys each, `d`-major), the values as
/// panels of 32 of their `d` columns (token-major); per block of query rows: the queries packed
/// (times `scale`), `S = Q·Kᵀ` by the kernel, the row softmax numerators and sums, the
/// probabilities packed, `O = P·V` by the kernel, each row divided by its sum.
///
/// # Safety
/// `out` is valid for the head's output, which nobody else touches meanwhile; `head` holds the
/// rows described; the CPU has AVX-512F.
unsafe fn packed_head(head: &[f32], (n, c, d): (usize, usize, usize), scale: f32, out: *mut f32) {
    use crate::packed::{pack_tiles, tile_product, NR, TILE_ROWS as MR};
    let ld = 3 * c;
    let (kp, vp) = (n.div_ceil(NR), d.div_ceil(NR));
    let np = kp * NR;
    HEAD_SCRATCH.with_borrow_mut(|s| {
        let keys = s.keys.floats_mut(kp * d * NR);
        keys.fill(0.0);
        for j in 0..n {
            let (p, cc) = (j / NR, j % NR);
            for (e, &v) in head[c + j * ld..][..d].iter().enumerate() {
                keys[(p * d + e) * NR + cc] = v;
            }
        }
        let values = s.values.floats_mut(vp * n * NR);
        values.fill(0.0);
        for j in 0..n {
            for (e, &v) in head[2 * c + j * ld..][..d].iter().enumerate() {
                values[((e / NR) * n + j) * NR + e % NR] = v;
            }
        }
        let (keys, values) = (keys.as_ptr(), values.as_ptr());
        for r0 in (0..n).step_by(PACKED_BLOCK_ROWS) {
            let rows = PACKED_BLOCK_ROWS.min(n - r0);
            let tiles = rows.div_ceil(MR);
            s.queries.resize(tiles * d * MR, 0.0);
            pack_tiles(&head[r0 * ld..], rows, d, ld, scale, &mut s.queries);
            s.scores.resize(tiles * MR * np, 0.0);
            for i in 0..tiles {
                for p in 0..kp {
                    tile_product(
                        d,
                        s.queries[i * d * MR..].as_ptr(),
                        keys.add(p * d * NR),
                        s.scores[i * MR * np + p * NR..].as_mut_ptr(),
                        np,
                    );
                }
            }
            s.inv.resize(rows, 0.0);
            for (r, inv) in s.inv.iter_mut().enumerate() {
                let row = &mut s.scores[r * np..r * np + n];
                crate::fastmath::softmax_rows_unnormalised(row, n, std::slice::from_mut(inv));
            }
            s.probs.resize(tiles * n * MR, 0.0);
            pack_tiles(&s.scores, rows, n, np, 1.0, &mut s.probs);
            for i in 0..tiles {
                let h = MR.min(rows - i * MR);
                for p in 0..vp {
                    let w = NR.min(d - p * NR);
                    let mut tmp = [0f32; MR * NR];
                    tile_product(
                        n,
                        s.probs[i * n * MR..].as_ptr(),
                        values.add(p * n * NR),
                        tmp.as_mut_ptr(),
                        NR,
                    );
                    for r in 0..h {
                        let inv = s.inv[i * MR + r];
                        let dst = std::slice::from_raw_parts_mut(out.add((r0 + i * MR + r) * c + p * NR), w);
                        for (o, &v) in dst.iter_mut().zip(&tmp[r * NR..r * NR + w]) {
                            *o = v * inv;
                        }
                    }
                }
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Straight from qkv rows against an f64 computation of the definition.
    #[test]
    fn qkv_rows_match_f64() {
        let (b, n, heads, d) = (2, 300, 3, 8);
        let c = heads * d;
        let qkv: Vec<f32> = (0..b * n * 3 * c)
            .map(|i| ((i * 7919 % 1000) as f32 / 500.0 - 1.0) * 1.5)
            .collect();
        let fast = attention_qkv_rows(&qkv, (b, n, heads, d)).unwrap();
        // The kernel of CPUs without AVX-512, whatever this one has.
        let mut portable = Vec::with_capacity(fast.len());
        portable_qkv_rows(&qkv, (b, n, heads, d), 1.0 / (d as f32).sqrt(), &mut portable);
        for got in [fast, portable] {
            let at = |bb: usize, t: usize, which: usize, hh: usize, j: usize| {
                qkv[(bb * n + t) * 3 * c + which * c + hh * d + j] as f64
            };
            for bb in 0..b {
                for hh in 0..heads {
                    for i in (0..n).step_by(7) {
                        let s: Vec<f64> = (0..n)
                            .map(|j| {
                                (0..d).map(|e| at(bb, i, 0, hh, e) * at(bb, j, 1, hh, e)).sum::<f64>()
                                    / (d as f64).sqrt()
                            })
                            .collect();
                        let max = s.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                        let w: Vec<f64> = s.iter().map(|v| (v - max).exp()).collect();
                        let sum: f64 = w.iter().sum();
                        for e in 0..d {
                            let want: f64 = (0..n).map(|j| w[j] * at(bb, j, 2, hh, e)).sum::<f64>() / sum;
                            let g = got[(bb * n + i) * c + hh * d + e] as f64;
                            assert!((g - want).abs() < 2e-5, "({bb}, {hh}, {i}, {e}): {g} vs {want}");
                        }
                    }
                }
            }
        }
        assert!(attention_qkv_rows(&qkv[1..], (b, n, heads, d)).is_err());
    }
}
