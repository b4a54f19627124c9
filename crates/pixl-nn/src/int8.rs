//! 8-bit linear layers for CPU inference: weights quantized once per output channel, activations
//! per row on every call, products summed in 32-bit integers by AVX-512 VNNI (`vpdpbusd`,
//! 64 multiply-adds per instruction: four times the f32 FMA rate on the CPUs that have it,
//! where AVX-512 BF16's `vdpbf16ps` runs at half of it).
//!
//! Arithmetic (the usual dynamic W8A8 scheme):
//! - weights `W (N, K)`: symmetric per output channel, `s_j = max_k |W[j,k]| / 127`,
//!   `Wq[j,k] = round(W[j,k] / s_j)` in `[−127, 127]`;
//! - activations `X (M, K)`: asymmetric per row over a range that includes 0,
//!   `t_i = (max(x_i, 0) − min(x_i, 0)) / 255`, zero point `z_i = round(−min(x_i, 0) / t_i)`,
//!   `Xq[i,k] = clamp(round(X[i,k] / t_i) + z_i, 0, 255)` (round half to even);
//! - `Y[i,j] = t_i·s_j·(Σ_k Xq[i,k]·Wq[j,k] − z_i·Σ_k Wq[j,k]) + b_j`, the sum exact in i32
//!   (|Xq·Wq| ≤ 255·127, so `K` up to 2¹⁶ cannot overflow).
//!
//! Layout: `K` is padded to a multiple of 4 (`vpdpbusd` takes four bytes per lane); `Wq` is
//! packed in panels of 32 output channels, four `k` per channel (128 bytes per 4 `k`), when the
//! layer is quantized; `Xq` is written row-major per call. The kernel holds a 12 × 32 tile of
//! sums in 24 registers over the whole `K`, then applies the scales, zero points and bias in
//! f32 on the way out. Tasks (column blocks, split by rows when few) run on rayon's pool.
//!
//! [`available`] says whether this CPU runs it; [`Int8Linear::new`] returns `None` where not,
//! and callers keep the f32 path.
use crate::fused::{self, Act};
use candle_core::{Result, Tensor};
use rayon::prelude::*;

/// Output channels per panel (two 16-lane vectors).
const NR: usize = 32;
/// Rows per register tile.
const MR: usize = 12;
/// Rows a task walks per panel of weights: the task's `MC × K` bytes of `Xq` stay in L2.
const MC: usize = 192;
/// Most output channels per task.
const NC: usize = 256;

/// Whether this CPU runs the 8-bit kernel (AVX-512F with VNNI), detected once.
pub fn available() -> bool {
    static VNNI: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *VNNI.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512vnni")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// A linear layer `y = x·Wᵀ + b` with its weights quantized to 8 bits (see the module notes).
#[derive(Clone)]
pub struct Int8Linear {
    n: usize,
    k: usize,
    /// `K` rounded up to 4.
    kp: usize,
    /// `Wq` in panels of [`NR`] channels: panel `p`, group `g` of 4 `k` at `(p·kp/4 + g)·128`,
    /// channel `c` of the panel at `+ 4c`.
    panels: Vec<u8>,
    /// Per channel, padded to whole panels with zeros: `s_j`, `Σ_k Wq[j,k]`, `b_j`.
    scale: Vec<f32>,
    colsum: Vec<f32>,
    bias: Vec<f32>,
}

impl std::fmt::Debug for Int8Linear {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Int8Linear")
            .field("n", &self.n)
            .field("k", &self.k)
            .finish()
    }
}

/// Per-channel symmetric quantization of one weight row: `(Wq, s)`.
fn quantize_weight_row(row: &[f32]) -> (Vec<i8>, f32) {
    let max = row.iter().fold(0f32, |m, v| m.max(v.abs()));
    let s = if max > 0.0 { max / 127.0 } else { 1.0 };
    let q = row
        .iter()
        .map(|&v| (v / s).round_ties_even().clamp(-127.0, 127.0) as i8)
        .collect();
    (q, s)
}

impl Int8Linear {
    /// The layer of a candle `Linear` (f32 weights on the CPU), quantized; `None` when this CPU
    /// has no 8-bit kernel.
    pub fn new(layer: &candle_nn::Linear) -> Result<Option<Self>> {
        if !available() {
            return Ok(None);
        }
        let (n, k) = layer.weight().dims2()?;
        let w = layer
            .weight()
            .to_dtype(candle_core::DType::F32)?
            .flatten_all()?
            .to_vec1::<f32>()?;
        let b = match layer.bias() {
            Some(b) => Some(b.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()?),
            None => None,
        };
        if b.as_ref().is_some_and(|b| b.len() != n) {
            candle_core::bail!(
                "int8 linear: bias of {} values for {n} outputs",
                b.map_or(0, |b| b.len())
            );
        }
        Ok(Some(Self::from_weights(&w, n, k, b.as_deref())))
    }

    /// From `w` `(N, K)` row-major and an optional bias of `N` values (any CPU: only
    /// [`Int8Linear::forward`] needs the kernel).
    pub fn from_weights(w: &[f32], n: usize, k: usize, bias: Option<&[f32]>) -> Self {
        assert_eq!(w.len(), n * k, "int8 linear: {} weights for {n}×{k}", w.len());
        let kp = k.div_ceil(4) * 4;
        let npad = n.div_ceil(NR) * NR;
        let mut panels = vec![0u8; npad * kp];
        let (mut scale, mut colsum, mut b) = (vec![0f32; npad], vec![0f32; npad], vec![0f32; npad]);
        for j in 0..n {
            let (q, s) = quantize_weight_row(&w[j * k..(j + 1) * k]);
            scale[j] = s;
            colsum[j] = q.iter().map(|&v| v as i32).sum::<i32>() as f32;
            b[j] = bias.map_or(0.0, |bv| bv[j]);
            let (p, c) = (j / NR, j % NR);
            for (kk, &v) in q.iter().enumerate() {
                panels[(p * kp / 4 + kk / 4) * 4 * NR + c * 4 + kk % 4] = v as u8;
            }
        }
        Self {
            n,
            k,
            kp,
            panels,
            scale,
            colsum,
            bias: b,
        }
    }

    /// Output width `N`.
    pub fn n(&self) -> usize {
        self.n
    }

    /// Input width `K`.
    pub fn k(&self) -> usize {
        self.k
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.panels.len() + 4 * (self.scale.len() + self.colsum.len() + self.bias.len())
    }

    /// `act(xs·Wᵀ + b)` over the last dim of an f32 CPU tensor, any leading dims.
    pub fn forward(&self, xs: &Tensor, act: Act) -> Result<Tensor> {
        if !available() {
            candle_core::bail!("int8 linear: this CPU has no AVX-512 VNNI");
        }
        let dims = xs.dims();
        let Some((&k, lead)) = dims.split_last() else {
            candle_core::bail!("int8 linear: a scalar input");
        };
        if k != self.k {
            candle_core::bail!("int8 linear: input width {k}, layer {}", self.k);
        }
        let rows: usize = lead.iter().product();
        let xs = xs.to_dtype(candle_core::DType::F32)?.contiguous()?;
        let mut out = vec![0f32; rows * self.n];
        {
            let _t = crate::profile::span("matmul (int8)");
            let (storage, layout) = xs.storage_and_layout();
            let x = fused::storage_slice(&storage, layout, "int8 linear input")?;
            self.forward_slice(x, rows, &mut out);
        }
        if act != Act::None {
            let _t = crate::profile::span("bias + activation");
            fused::act_in_place(&mut out, act);
        }
        let mut out_dims = lead.to_vec();
        out_dims.push(self.n);
        Tensor::from_vec(out, out_dims, xs.device())
    }

    /// `out (rows, N) = x (rows, K)·Wᵀ + b`, both row-major. Panics if the CPU lacks the
    /// kernel or a slice is short.
    pub fn forward_slice(&self, x: &[f32], rows: usize, out: &mut [f32]) {
        assert!(available(), "int8 linear: this CPU has no AVX-512 VNNI");
        assert!(
            x.len() >= rows * self.k && out.len() >= rows * self.n,
            "int8 linear: short slices"
        );
        if rows == 0 || self.n == 0 {
            return;
        }
        if self.k == 0 {
            // No inputs: every output is its bias.
            out[..rows * self.n]
                .chunks_mut(self.n)
                .for_each(|row| row.copy_from_slice(&self.bias[..self.n]));
            return;
        }
        let q = QuantizedRows::new(x, rows, self.k, self.kp);
        let threads = rayon::current_num_threads().max(1);
        let panels = self.n.div_ceil(NR);
        let want = 4 * threads;
        let nc = NR * panels.div_ceil(want).clamp(1, NC / NR);
        let col_blocks = self.n.div_ceil(nc);
        let row_panels = rows.div_ceil(MR);
        let row_blocks = want.div_ceil(col_blocks).min(row_panels).max(1);
        let mc = MR * row_panels.div_ceil(row_blocks);
        let row_blocks = rows.div_ceil(mc);
        let dst = OutPtr(out.as_mut_ptr());
        let task = |t: usize| {
            let dst = &dst;
            let (r0, c0) = ((t % row_blocks) * mc, (t / row_blocks) * nc);
            let (r1, c1) = ((r0 + mc).min(rows), (c0 + nc).min(self.n));
            for i0 in (r0 / MR..r1.div_ceil(MR)).step_by(MC / MR) {
                let i1 = (i0 + MC / MR).min(r1.div_ceil(MR));
                for p in c0 / NR..c1.div_ceil(NR) {
                    for i in i0..i1 {
                        // SAFETY: tile (rows i·MR.., channels p·NR..) of `out` belongs to this
                        // task alone; `q` holds whole tiles of rows, the panels whole panels.
                        unsafe { self.tile(&q, i * MR, p, dst.0, rows) };
                    }
                }
            }
        };
        let tasks = row_blocks * col_blocks;
        if tasks == 1 || threads == 1 {
            (0..tasks).for_each(task);
        } else {
            (0..tasks).into_par_iter().for_each(task);
        }
    }

    /// One 12 × 32 tile: rows `row..`, panel `p`, written into `out` (`rows × N`), partial
    /// tiles through a scratch tile.
    ///
    /// # Safety
    /// No other thread may touch the tile's part of `out`, which holds `rows × N` values.
    unsafe fn tile(&self, q: &QuantizedRows, row: usize, p: usize, out: *mut f32, rows: usize) {
        let (h, w) = (MR.min(rows - row), NR.min(self.n - p * NR));
        let c0 = p * NR;
        let epi = Epi {
            scale: &self.scale[c0..c0 + NR],
            colsum: &self.colsum[c0..c0 + NR],
            bias: &self.bias[c0..c0 + NR],
            row_scale: &q.scale[row..row + MR],
            row_zero: &q.zero[row..row + MR],
        };
        let a = q.data[row * self.kp..].as_ptr();
        let b = self.panels[p * self.kp * NR..].as_ptr();
        let g = self.kp / 4;
        if h == MR && w == NR {
            x86::tile_vnni(g, a, self.kp, b, out.add(row * self.n + c0), self.n, &epi);
        } else {
            let mut tmp = [0f32; MR * NR];
            x86::tile_vnni(g, a, self.kp, b, tmp.as_mut_ptr(), NR, &epi);
            for r in 0..h {
                std::ptr::copy_nonoverlapping(tmp[r * NR..].as_ptr(), out.add((row + r) * self.n + c0), w);
            }
        }
    }
}

/// The output pointer shared by the tasks; each writes only its own tiles.
struct OutPtr(*mut f32);
// SAFETY: tasks write disjoint tiles of one live buffer.
unsafe impl Sync for OutPtr {}
unsafe impl Send for OutPtr {}

/// Per-tile dequantization: the panel's channel scales, weight sums and bias, the tile's row
/// scales and zero points.
struct Epi<'a> {
    scale: &'a [f32],
    colsum: &'a [f32],
    bias: &'a [f32],
    row_scale: &'a [f32],
    row_zero: &'a [f32],
}

/// `Xq`: rows quantized to u8 (row-major, `kp` bytes each, rows padded to whole tiles with
/// zeros), with each row's scale `t_i` and zero point `z_i`.
struct QuantizedRows {
    data: Vec<u8>,
    scale: Vec<f32>,
    zero: Vec<f32>,
}

impl QuantizedRows {
    fn new(x: &[f32], rows: usize, k: usize, kp: usize) -> Self {
        let padded = rows.div_ceil(MR) * MR;
        let mut data = vec![0u8; padded * kp];
        let (mut scale, mut zero) = (vec![0f32; padded], vec![0f32; padded]);
        data.par_chunks_mut(kp)
            .zip(scale.par_iter_mut().zip(zero.par_iter_mut()))
            .take(rows)
            .enumerate()
            .with_min_len(8)
            .for_each(|(i, (dst, (s, z)))| {
                let (t, zp) = quantize_row(&x[i * k..(i + 1) * k], &mut dst[..k]);
                (*s, *z) = (t, zp as f32);
            });
        Self { data, scale, zero }
    }
}

/// Quantizes `row` into `dst`; returns `(t, z)`.
fn quantize_row(row: &[f32], dst: &mut [u8]) -> (f32, i32) {
    // SAFETY: `available()` (checked by every caller) includes AVX-512F.
    let (t, zp) = unsafe { x86::row_params(row) };
    let inv = 1.0 / t;
    // SAFETY: as above; `dst` is as long as `row`.
    let done = unsafe { x86::quantize(row, inv, zp, dst) };
    for (d, &v) in dst[done..].iter_mut().zip(&row[done..]) {
        *d = ((v * inv).round_ties_even() as i32 + zp).clamp(0, 255) as u8;
    }
    (t, zp)
}

/// Scale and zero point from a row's range (see the module notes).
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
fn params_from_range(lo: f32, hi: f32) -> (f32, i32) {
    let t = if hi > lo { (hi - lo) / 255.0 } else { 1.0 };
    let zp = (-lo / t).round_ties_even().clamp(0.0, 255.0) as i32;
    (t, zp)
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{params_from_range, Epi, MR};
    use std::arch::x86_64::*;

    /// Scale and zero point of one activation row: its range including 0.
    ///
    /// # Safety
    /// The CPU has AVX-512F.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn row_params(row: &[f32]) -> (f32, i32) {
        let (mut lo, mut hi) = (_mm512_setzero_ps(), _mm512_setzero_ps());
        let mut chunks = row.chunks_exact(16);
        for c in &mut chunks {
            let v = _mm512_loadu_ps(c.as_ptr());
            lo = _mm512_min_ps(lo, v);
            hi = _mm512_max_ps(hi, v);
        }
        let (mut l, mut h) = (_mm512_reduce_min_ps(lo), _mm512_reduce_max_ps(hi));
        for &v in chunks.remainder() {
            (l, h) = (l.min(v), h.max(v));
        }
        params_from_range(l, h)
    }

    /// `dst = clamp(round(row·inv) + zp, 0, 255)` (round half to even: the default MXCSR mode)
    /// for whole vectors of 16; returns how many were done.
    ///
    /// # Safety
    /// The CPU has AVX-512F; `dst` is at least as long as `row`.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn quantize(row: &[f32], inv: f32, zp: i32, dst: &mut [u8]) -> usize {
        let (s, z) = (_mm512_set1_ps(inv), _mm512_set1_epi32(zp));
        let (lo, hi) = (_mm512_setzero_si512(), _mm512_set1_epi32(255));
        let whole = row.len() / 16 * 16;
        for i in (0..whole).step_by(16) {
            let q = _mm512_cvtps_epi32(_mm512_mul_ps(_mm512_loadu_ps(row.as_ptr().add(i)), s));
            let q = _mm512_min_epi32(_mm512_max_epi32(_mm512_add_epi32(q, z), lo), hi);
            _mm_storeu_si128(dst.as_mut_ptr().add(i) as *mut __m128i, _mm512_cvtepi32_epi8(q));
        }
        whole
    }

    /// `out[MR×NR]` (row stride `ldo`) = dequantized `Xq[MR×4g] · Wq-panel`: 24 i32
    /// accumulators, per group of 4 `k` two loads of the panel and 12 broadcasts of 4 bytes of
    /// `Xq` (row stride `lda`).
    ///
    /// # Safety
    /// `a` covers `MR` rows of `4g` bytes, `b` `g·128` bytes, `out` the tile; the CPU has
    /// AVX-512F and VNNI.
    #[target_feature(enable = "avx512f,avx512vnni")]
    pub(super) unsafe fn tile_vnni(
        g: usize,
        a: *const u8,
        lda: usize,
        b: *const u8,
        out: *mut f32,
        ldo: usize,
        e: &Epi,
    ) {
        let mut acc = [[_mm512_setzero_si512(); 2]; MR];
        for grp in 0..g {
            let b0 = _mm512_loadu_si512(b.add(grp * 128) as *const _);
            let b1 = _mm512_loadu_si512(b.add(grp * 128 + 64) as *const _);
            for (r, row) in acc.iter_mut().enumerate() {
                let av = _mm512_set1_epi32((a.add(r * lda + 4 * grp) as *const i32).read_unaligned());
                row[0] = _mm512_dpbusd_epi32(row[0], av, b0);
                row[1] = _mm512_dpbusd_epi32(row[1], av, b1);
            }
        }
        let half = |s: &[f32], h: usize| _mm512_loadu_ps(s[16 * h..].as_ptr());
        let (sw, cs, bias) = (
            [half(e.scale, 0), half(e.scale, 1)],
            [half(e.colsum, 0), half(e.colsum, 1)],
            [half(e.bias, 0), half(e.bias, 1)],
        );
        for (r, row) in acc.iter().enumerate() {
            let (t, z) = (_mm512_set1_ps(e.row_scale[r]), _mm512_set1_ps(e.row_zero[r]));
            for h in 0..2 {
                // t·s·(Σ − z·colsum) + b
                let v = _mm512_fnmadd_ps(z, cs[h], _mm512_cvtepi32_ps(row[h]));
                let v = _mm512_fmadd_ps(_mm512_mul_ps(t, sw[h]), v, bias[h]);
                _mm512_storeu_ps(out.add(r * ldo + 16 * h), v);
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod x86 {
    use super::Epi;

    pub(super) unsafe fn row_params(_: &[f32]) -> (f32, i32) {
        unreachable!("the int8 kernel is x86-64 only; `available()` is false here");
    }

    pub(super) unsafe fn quantize(_: &[f32], _: f32, _: i32, _: &mut [u8]) -> usize {
        unreachable!("the int8 kernel is x86-64 only; `available()` is false here");
    }

    pub(super) unsafe fn tile_vnni(_: usize, _: *const u8, _: usize, _: *const u8, _: *mut f32, _: usize, _: &Epi) {
        unreachable!("the int8 kernel is x86-64 only; `available()` is false here");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::testing::hashed_value as val;

    /// The scheme of the module notes from its definitions (scales and rounding in f32 as
    /// defined, integer dot products, dequantization in f64), independently of the kernel's
    /// layout; also the size of the terms the kernel cancels in f32, for the tolerance.
    fn reference(x: &[f32], rows: usize, w: &[f32], n: usize, k: usize, bias: &[f32]) -> Vec<(f64, f64)> {
        let mut out = vec![(0f64, 0f64); rows * n];
        for j in 0..n {
            let wr = &w[j * k..(j + 1) * k];
            let max = wr.iter().fold(0f32, |m, &v| m.max(v.abs()));
            let s = if max > 0.0 { max / 127.0 } else { 1.0 };
            let wq: Vec<i64> = wr.iter().map(|&v| (v / s).round_ties_even() as i64).collect();
            for i in 0..rows {
                let xr = &x[i * k..(i + 1) * k];
                let lo = xr.iter().fold(0f32, |m, &v| m.min(v));
                let hi = xr.iter().fold(0f32, |m, &v| m.max(v));
                let t = if hi > lo { (hi - lo) / 255.0 } else { 1.0 };
                let z = (-lo / t).round_ties_even().clamp(0.0, 255.0) as i64;
                let xq: Vec<i64> = xr
                    .iter()
                    .map(|&v| ((v * (1.0 / t)).round_ties_even() as i64 + z).clamp(0, 255))
                    .collect();
                let dot: i64 = xq.iter().zip(&wq).map(|(a, b)| (a - z) * b).sum();
                let terms: i64 = xq.iter().zip(&wq).map(|(a, b)| (a * b).abs() + (z * b).abs()).sum();
                let ts = t as f64 * s as f64;
                out[i * n + j] = (ts * dot as f64 + bias[j] as f64, ts * terms as f64);
            }
        }
        out
    }

    #[test]
    fn matches_the_scheme_computed_from_its_definition() {
        if !available() {
            eprintln!("no AVX-512 VNNI on this CPU: the int8 kernel is not tested here");
            return;
        }
        for &(rows, k, n) in &[
            (1, 1, 1),
            (5, 7, 33),
            (13, 64, 32),
            (25, 130, 70),
            (200, 384, 300),
            (37, 1030, 64),
        ] {
            let x: Vec<f32> = (0..rows * k).map(|i| val(i, 1) * 3.0 + 0.5).collect();
            let w: Vec<f32> = (0..n * k).map(|i| val(i, 2) * 0.1).collect();
            let bias: Vec<f32> = (0..n).map(|i| val(i, 3)).collect();
            let layer = Int8Linear::from_weights(&w, n, k, Some(&bias));
            let mut out = vec![f32::NAN; rows * n];
            layer.forward_slice(&x, rows, &mut out);
            let want = reference(&x, rows, &w, n, k, &bias);
            for (i, (&g, &(r, terms))) in out.iter().zip(&want).enumerate() {
                let tol = 1e-6 * terms + 1e-6 * (1.0 + r.abs());
                assert!((g as f64 - r).abs() <= tol, "{rows}x{k}x{n} at {i}: {g} vs {r}");
            }
        }
    }

    #[test]
    fn is_close_to_the_f32_product_and_exact_on_representable_values() {
        if !available() {
            return;
        }
        let (rows, k, n) = (64, 256, 96);
        // Values on the quantization grids: rows span [−1, 1.5] in steps of 2.5/255 with 0 on
        // the grid (z = 102), weights are multiples of max/127: the product is exact.
        let step = 2.5f32 / 255.0;
        let x: Vec<f32> = (0..rows * k)
            .map(|i| match i % k {
                0 => -102.0 * step,
                1 => 153.0 * step,
                _ => ((i * 37 % 256) as f32 - 102.0).clamp(-102.0, 153.0) * step,
            })
            .collect();
        let w: Vec<f32> = (0..n * k)
            .map(|i| {
                if i % k == 0 {
                    0.127
                } else {
                    ((i * 11 % 255) as f32 - 127.0) * 0.001
                }
            })
            .collect();
        let layer = Int8Linear::from_weights(&w, n, k, None);
        let mut out = vec![0f32; rows * n];
        layer.forward_slice(&x, rows, &mut out);
        for i in 0..rows {
            for j in 0..n {
                let exact: f64 = (0..k).map(|p| x[i * k + p] as f64 * w[j * k + p] as f64).sum();
                let got = out[i * n + j] as f64;
                assert!(
                    (got - exact).abs() <= 1e-4 * (1.0 + exact.abs()),
                    "({i},{j}): {got} vs {exact}"
                );
            }
        }
    }

    #[test]
    fn one_thread_and_many_give_the_same_bits() {
        if !available() {
            return;
        }
        let (rows, k, n) = (300, 200, 500);
        let x: Vec<f32> = (0..rows * k).map(|i| val(i, 4)).collect();
        let w: Vec<f32> = (0..n * k).map(|i| val(i, 5)).collect();
        let layer = Int8Linear::from_weights(&w, n, k, None);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            let mut out = vec![0f32; rows * n];
            pool.install(|| layer.forward_slice(&x, rows, &mut out));
            out
        };
        assert_eq!(run(1), run(3));
    }
}
