//! f32 linear layers for CPU inference with their weights packed once for an AVX-512 kernel, and
//! the bias, the activation and a (layer-scaled) residual add applied to each output tile while
//! it is still in registers or in L1.
//!
//! Contract of [`PackedLinear::forward_slice`]: `x` `(rows, K)` and `out` `(rows, N)` row-major
//! f32; per output `out[i, j] = r[i, j] + γ[j]·act(Σ_k x[i, k]·W[j, k] + b[j])`, where the
//! residual `r` and the scale `γ` are optional ([`Epilogue`]; without `r` the output is
//! `act(…)`, without `γ` the scale is 1) and `W` `(N, K)`, `b` `(N)` are PyTorch's `Linear`
//! weights. The sum runs over `k` in order in f32 (one fused multiply-add per term); the
//! activations are [`Act::apply`]'s (GELU through the vectorised [`crate::fastmath`] `erf`).
//!
//! Why: `gemm::gemm` packs the weights again on every call and reached 180–260 GFLOP/s on the
//! ViT-L shapes on 2 AVX-512 cores (this kernel: 250–290, `examples/bench_packed`); the bias,
//! GELU and LayerScale residual were then three more passes over 16 MB outputs. Here `W` is
//! packed at load time in panels of [`NR`] = 32 output channels, `k`-major (32 consecutive
//! floats per `k`, 64-byte aligned), the rows of `x` per call in tiles of 12 rows, `k`-major
//! (rows 4 KiB apart, read in turn, would alias in L1), and a 12 × 32 tile of outputs is held
//! in 24 zmm registers over the whole `K`: per `k`, two loads of the panel and 12 broadcasts,
//! with software prefetches ahead on both streams. Tasks are column blocks (split by rows when
//! there are few) on rayon's pool; a task walks blocks of rows small enough to stay in L2 while
//! each panel of weights is reused across them.
//!
//! The same tile kernel serves the fused attention ([`crate::attention::attention_qkv_rows`])
//! through `pack_tiles` and `tile_product` (crate-internal).
//!
//! [`available`] says whether this CPU runs it (AVX-512F); elsewhere callers keep their f32 path.
use crate::fused::Act;
use rayon::prelude::*;

/// Output channels per panel (two 16-lane vectors).
pub const NR: usize = 32;
/// Rows per register tile.
const MR: usize = 12;
/// Bytes of `x` a task keeps in L2 while it walks a panel: sets its block of rows.
const ROW_BLOCK_BYTES: usize = 512 * 1024;
/// Most output channels per task.
const NC: usize = 256;

/// Whether this CPU runs the packed kernel (AVX-512F), detected once.
pub fn available() -> bool {
    static AVX512: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *AVX512.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            is_x86_feature_detected!("avx512f")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// What happens to each tile after the products (see the module contract).
#[derive(Clone, Copy, Debug)]
pub struct Epilogue<'a> {
    pub act: Act,
    /// `(rows, N)` row-major, added last.
    pub residual: Option<&'a [f32]>,
    /// `γ`, `N` values, scaling the activated output before the residual add.
    pub scale: Option<&'a [f32]>,
}

impl Epilogue<'_> {
    /// `act(v)` alone.
    pub fn act(act: Act) -> Epilogue<'static> {
        Epilogue {
            act,
            residual: None,
            scale: None,
        }
    }

    /// Output `j`'s final value from `v = Σ + b` and its residual value `r`.
    #[inline]
    fn finish(&self, v: f32, j: usize, r: f32) -> f32 {
        let y = self.act.apply(v);
        match (self.residual.is_some(), self.scale) {
            (false, _) => y,
            (true, Some(g)) => r + y * g[j],
            (true, None) => r + y,
        }
    }
}

/// 64 bytes of weights: the panels' unit of storage, so that every panel row is aligned.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Line([f32; 16]);

/// A linear layer `y = x·Wᵀ + b` with `W` packed for the kernel (see the module notes).
#[derive(Clone)]
pub struct PackedLinear {
    n: usize,
    k: usize,
    /// Panel `p`, input `kk`, channel `c` at float `(p·K + kk)·NR + c`; channels past `N` are 0.
    panels: Vec<Line>,
    /// `N` rounded up to whole panels, zeros past `N`.
    bias: Vec<f32>,
    has_bias: bool,
}

impl std::fmt::Debug for PackedLinear {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PackedLinear")
            .field("n", &self.n)
            .field("k", &self.k)
            .finish()
    }
}

impl PackedLinear {
    /// From `w` `(N, K)` row-major and an optional bias of `N` values (any CPU: only the
    /// forward needs the kernel). Errors when the lengths do not fit.
    pub fn from_weights(w: &[f32], n: usize, k: usize, bias: Option<&[f32]>) -> Result<Self, String> {
        if w.len() != n * k {
            return Err(format!("packed linear: {} weights for {n}×{k}", w.len()));
        }
        if let Some(b) = bias.filter(|b| b.len() != n) {
            return Err(format!("packed linear: bias of {} values for {n} outputs", b.len()));
        }
        let panels_n = n.div_ceil(NR);
        let mut panels = vec![Line([0.0; 16]); panels_n * k * NR / 16];
        {
            let flat = Self::floats_mut(&mut panels);
            for (j, row) in w.chunks_exact(k.max(1)).enumerate().take(n) {
                let (p, c) = (j / NR, j % NR);
                for (kk, &v) in row.iter().enumerate() {
                    flat[(p * k + kk) * NR + c] = v;
                }
            }
        }
        let mut b = vec![0f32; panels_n * NR];
        if let Some(bias) = bias {
            b[..n].copy_from_slice(bias);
        }
        Ok(Self {
            n,
            k,
            panels,
            bias: b,
            has_bias: bias.is_some(),
        })
    }

    fn floats(panels: &[Line]) -> &[f32] {
        // SAFETY: `Line` is 16 f32 with no padding (repr(C), size 64, align 64).
        unsafe { std::slice::from_raw_parts(panels.as_ptr() as *const f32, panels.len() * 16) }
    }

    fn floats_mut(panels: &mut [Line]) -> &mut [f32] {
        // SAFETY: as in `floats`.
        unsafe { std::slice::from_raw_parts_mut(panels.as_mut_ptr() as *mut f32, panels.len() * 16) }
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
        self.panels.len() * 64 + 4 * self.bias.len()
    }

    /// The weights back as `(N, K)` row-major, and the bias if the layer has one.
    pub fn to_dense(&self) -> (Vec<f32>, Option<Vec<f32>>) {
        let (n, k) = (self.n, self.k);
        let flat = Self::floats(&self.panels);
        let mut w = vec![0f32; n * k];
        for (j, row) in w.chunks_exact_mut(k.max(1)).enumerate().take(n) {
            let (p, c) = (j / NR, j % NR);
            for (kk, v) in row.iter_mut().enumerate() {
                *v = flat[(p * k + kk) * NR + c];
            }
        }
        (w, self.has_bias.then(|| self.bias[..n].to_vec()))
    }

    /// `out (rows, N)` from `x (rows, K)` as the module contract says. Panics if the CPU lacks
    /// the kernel or a slice does not fit.
    pub fn forward_slice(&self, x: &[f32], rows: usize, out: &mut [f32], epi: &Epilogue) {
        assert!(out.len() >= rows * self.n, "packed linear: short slices");
        // SAFETY: `out` holds `rows × N` values.
        unsafe { self.forward_raw(x, rows, out.as_mut_ptr(), epi) }
    }

    /// [`Self::forward_slice`] into a new vector (every value written once, never zeroed first).
    pub fn forward_vec(&self, x: &[f32], rows: usize, epi: &Epilogue) -> Vec<f32> {
        let len = rows * self.n;
        let mut out = Vec::<f32>::with_capacity(len);
        // SAFETY: the capacity holds `rows × N` values, and the kernel writes every one of them
        // (whole tiles in place, partial ones value by value) before `set_len` exposes them.
        unsafe {
            self.forward_raw(x, rows, out.as_mut_ptr(), epi);
            out.set_len(len);
        }
        out
    }

    /// # Safety
    /// `out` is valid for writes of `rows × N` values, which nobody else reads or writes
    /// meanwhile.
    unsafe fn forward_raw(&self, x: &[f32], rows: usize, out: *mut f32, epi: &Epilogue) {
        assert!(available(), "packed linear: this CPU has no AVX-512F");
        let (n, k) = (self.n, self.k);
        assert!(x.len() >= rows * k, "packed linear: short slices");
        assert!(
            epi.residual.is_none_or(|r| r.len() >= rows * n) && epi.scale.is_none_or(|g| g.len() >= n),
            "packed linear: residual or scale too short"
        );
        if rows == 0 || n == 0 {
            return;
        }
        let row_tiles = rows.div_ceil(MR);
        PACKED_ROWS.with_borrow_mut(|xp| {
            pack_rows(x, rows, k, xp);
            self.run(xp, rows, out, epi, row_tiles);
        });
    }

    /// The tasks over the packed rows `xp` ([`pack_rows`]).
    ///
    /// # Safety
    /// As [`Self::forward_raw`].
    unsafe fn run(&self, xp: &[f32], rows: usize, out: *mut f32, epi: &Epilogue, row_tiles: usize) {
        let (n, k) = (self.n, self.k);
        let threads = rayon::current_num_threads().max(1);
        let panels = n.div_ceil(NR);
        let want = 4 * threads;
        let nc = NR * panels.div_ceil(want).clamp(1, NC / NR);
        let col_blocks = n.div_ceil(nc);
        let row_blocks = want.div_ceil(col_blocks).min(row_tiles).max(1);
        let mc = MR * row_tiles.div_ceil(row_blocks);
        let row_blocks = rows.div_ceil(mc);
        // Tiles of rows per L2 block.
        let block_tiles = (ROW_BLOCK_BYTES / (4 * k.max(1) * MR)).max(1);
        let dst = OutPtr(out);
        let task = |t: usize| {
            let dst = &dst;
            let (r0, c0) = ((t % row_blocks) * mc, (t / row_blocks) * nc);
            let (r1, c1) = ((r0 + mc).min(rows), (c0 + nc).min(n));
            let (t0, t1) = (r0 / MR, r1.div_ceil(MR));
            for i0 in (t0..t1).step_by(block_tiles) {
                let i1 = (i0 + block_tiles).min(t1);
                for p in c0 / NR..c1.div_ceil(NR) {
                    for i in i0..i1 {
                        // SAFETY: tile (rows i·MR.., panel p) of `out` belongs to this task
                        // alone; `xp` holds whole tiles of rows, the panels whole panels.
                        unsafe { self.tile(xp, i, p, dst.0, rows, epi) };
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

    /// The tile of row tile `i`, panel `p`, over the whole `K`; a partial tile (at the last rows
    /// or channels) through a scratch tile and a scalar epilogue.
    ///
    /// # Safety
    /// No other thread may touch the tile's part of `out`, which holds `rows × N` values; `xp`
    /// holds row tile `i`; the CPU has AVX-512F.
    unsafe fn tile(&self, xp: &[f32], i: usize, p: usize, out: *mut f32, rows: usize, epi: &Epilogue) {
        let (n, k) = (self.n, self.k);
        let (row, c0) = (i * MR, p * NR);
        let (h, w) = (MR.min(rows - row), NR.min(n - c0));
        let b = Self::floats(&self.panels)[p * k * NR..].as_ptr();
        let a = xp[i * k * MR..].as_ptr();
        let bias = self.bias[c0..].as_ptr();
        if h == MR && w == NR {
            let tail = Tail {
                bias,
                res: epi.residual.map(|r| r[row * n + c0..].as_ptr()),
                scale: epi.scale.map(|g| g[c0..].as_ptr()),
                act: epi.act,
            };
            x86::tile(k, a, b, out.add(row * n + c0), n, &tail);
            return;
        }
        let mut tmp = [0f32; MR * NR];
        let tail = Tail {
            bias,
            res: None,
            scale: None,
            act: Act::None,
        };
        x86::tile(k, a, b, tmp.as_mut_ptr(), NR, &tail);
        for r in 0..h {
            for c in 0..w {
                let o = (row + r) * n + c0 + c;
                let res = epi.residual.map_or(0.0, |rv| rv[o]);
                *out.add(o) = epi.finish(tmp[r * NR + c], c0 + c, res);
            }
        }
    }
}

thread_local! {
    /// The calling thread's packed copy of the rows ([`pack_rows`]), kept between calls so that
    /// its pages are not faulted in again.
    static PACKED_ROWS: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// `x (rows, K)` into tiles of [`MR`] rows, `k`-major: row `r` of tile `i`, input `kk` at
/// `(i·K + kk)·MR + r`; rows past `rows` are 0. Parallel over tiles.
fn pack_rows(x: &[f32], rows: usize, k: usize, xp: &mut Vec<f32>) {
    let tiles = rows.div_ceil(MR);
    xp.resize(tiles * k * MR, 0.0);
    xp[..tiles * k * MR]
        .par_chunks_mut((k * MR).max(1))
        .enumerate()
        .for_each(|(i, dst)| {
            let h = MR.min(rows - i * MR);
            pack_tiles(&x[i * MR * k..], h, k, k, 1.0, dst);
        });
}

/// `rows` rows of `x` (row stride `ld`, their first `k` values) times `scale` into
/// `⌈rows / MR⌉` tiles of [`pack_rows`]' layout in `dst`, rows past `rows` 0. Each tile goes
/// through a small buffer of 16 inputs per row (rows a multiple of 4 KiB apart alias in L1
/// when read in turn).
pub(crate) fn pack_tiles(x: &[f32], rows: usize, k: usize, ld: usize, scale: f32, dst: &mut [f32]) {
    const KB: usize = 16;
    for (i, tile) in dst
        .chunks_exact_mut((k * MR).max(1))
        .take(rows.div_ceil(MR))
        .enumerate()
    {
        let h = MR.min(rows - i * MR);
        let mut buf = [[0f32; KB]; MR];
        for k0 in (0..k).step_by(KB) {
            let kn = KB.min(k - k0);
            for (r, line) in buf.iter_mut().enumerate().take(h) {
                let src = &x[(i * MR + r) * ld + k0..][..kn];
                line[..kn].iter_mut().zip(src).for_each(|(d, &v)| *d = v * scale);
            }
            for (j, d) in tile[k0 * MR..(k0 + kn) * MR].chunks_exact_mut(MR).enumerate() {
                for (r, v) in d.iter_mut().enumerate() {
                    *v = buf[r][j];
                }
            }
        }
    }
}

/// Rows of tiles ([`MR`]) of the kernel.
pub(crate) const TILE_ROWS: usize = MR;

/// Scratch of 64-byte aligned floats for panels built on the fly (the kernel's aligned loads).
#[derive(Default)]
pub(crate) struct AlignedScratch(Vec<Line>);

impl AlignedScratch {
    /// The first `len` floats, grown (zeroed) as needed; contents are whatever was left.
    pub(crate) fn floats_mut(&mut self, len: usize) -> &mut [f32] {
        let lines = len.div_ceil(16);
        if self.0.len() < lines {
            self.0.resize(lines, Line([0.0; 16]));
        }
        &mut PackedLinear::floats_mut(&mut self.0)[..len]
    }
}

/// `out[MR×NR]` (row stride `ldo`) `= a · b`: `a` a packed row tile of `k` inputs
/// ([`pack_tiles`]), `b` a panel of `k·NR` floats, 64-byte aligned ([`AlignedScratch`]).
///
/// # Safety
/// The pointers cover what is said; nobody else touches the tile of `out`; the CPU has
/// AVX-512F ([`available`]).
pub(crate) unsafe fn tile_product(k: usize, a: *const f32, b: *const f32, out: *mut f32, ldo: usize) {
    static ZERO: [f32; NR] = [0.0; NR];
    let tail = Tail {
        bias: ZERO.as_ptr(),
        res: None,
        scale: None,
        act: Act::None,
    };
    x86::tile(k, a, b, out, ldo, &tail);
}

/// Prefetch distances, in inputs `k`, of the packed rows (L1) and of the panel (L2 → L1):
/// measured on the ViT-L shapes (`examples/bench_packed`), 0 and 0 ran 10–25 % slower.
const PREFETCH_A: usize = 32;
const PREFETCH_B: usize = 16;

/// The epilogue's pointers for one tile: the panel's bias (and scale), the tile's residual.
pub(crate) struct Tail {
    bias: *const f32,
    res: Option<*const f32>,
    scale: Option<*const f32>,
    act: Act,
}

/// The output pointer shared by the tasks; each writes only its own tiles.
struct OutPtr(*mut f32);
// SAFETY: tasks write disjoint tiles of one live buffer.
unsafe impl Sync for OutPtr {}
unsafe impl Send for OutPtr {}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Act, Tail, MR, NR, PREFETCH_A, PREFETCH_B};
    use std::arch::x86_64::*;

    /// `out[MR×NR]` (row stride `ldo`) `= a · b + bias`, `a` a packed row tile (`K·MR` floats,
    /// [`super::pack_rows`]), `b` a panel (`K·NR` floats, 64-byte aligned); 24 accumulators
    /// over the whole `K`, per `k` two loads of the panel and 12 broadcasts; then the
    /// activation, and `res + scale ⊙ ·` (row stride `ldo`) when `res` is given.
    ///
    /// # Safety
    /// The pointers cover what is said above, the tail's `bias` and `scale` `NR` floats, `out`
    /// and `res` the tile; the CPU has AVX-512F.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn tile(k: usize, a: *const f32, b: *const f32, out: *mut f32, ldo: usize, t: &Tail) {
        let mut acc = [[_mm512_setzero_ps(); 2]; MR];
        for kk in 0..k {
            // Prefetches past the end are harmless hints (never faults).
            _mm_prefetch::<_MM_HINT_T0>(a.wrapping_add((kk + PREFETCH_A) * MR) as *const i8);
            _mm_prefetch::<_MM_HINT_T0>(b.wrapping_add((kk + PREFETCH_B) * NR) as *const i8);
            _mm_prefetch::<_MM_HINT_T0>(b.wrapping_add((kk + PREFETCH_B) * NR + 16) as *const i8);
            let b0 = _mm512_load_ps(b.add(kk * NR));
            let b1 = _mm512_load_ps(b.add(kk * NR + 16));
            for (r, row) in acc.iter_mut().enumerate() {
                let av = _mm512_set1_ps(*a.add(kk * MR + r));
                row[0] = _mm512_fmadd_ps(av, b0, row[0]);
                row[1] = _mm512_fmadd_ps(av, b1, row[1]);
            }
        }
        let (res, scale, act) = (t.res, t.scale, t.act);
        let bv = [_mm512_loadu_ps(t.bias), _mm512_loadu_ps(t.bias.add(16))];
        let one = _mm512_set1_ps(1.0);
        let gv = scale.map_or([one, one], |g| [_mm512_loadu_ps(g), _mm512_loadu_ps(g.add(16))]);
        if act == Act::None {
            for (r, row) in acc.iter().enumerate() {
                for h in 0..2 {
                    let v = _mm512_add_ps(row[h], bv[h]);
                    let v = match res {
                        Some(rp) => {
                            let rv = _mm512_loadu_ps(rp.add(r * ldo + 16 * h));
                            if scale.is_some() {
                                _mm512_add_ps(rv, _mm512_mul_ps(v, gv[h]))
                            } else {
                                _mm512_add_ps(rv, v)
                            }
                        }
                        None => v,
                    };
                    _mm512_storeu_ps(out.add(r * ldo + 16 * h), v);
                }
            }
            return;
        }
        for (r, row) in acc.iter().enumerate() {
            for h in 0..2 {
                _mm512_storeu_ps(out.add(r * ldo + 16 * h), _mm512_add_ps(row[h], bv[h]));
            }
            let line = std::slice::from_raw_parts_mut(out.add(r * ldo), NR);
            match act {
                Act::Gelu => crate::fastmath::gelu_generic(line),
                _ => line.iter_mut().for_each(|v| *v = act.apply(*v)),
            }
            if let Some(rp) = res {
                for (h, &g) in gv.iter().enumerate() {
                    let o = out.add(r * ldo + 16 * h);
                    let rv = _mm512_loadu_ps(rp.add(r * ldo + 16 * h));
                    let y = _mm512_loadu_ps(o);
                    let y = if scale.is_some() { _mm512_mul_ps(y, g) } else { y };
                    _mm512_storeu_ps(o, _mm512_add_ps(rv, y));
                }
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod x86 {
    use super::Tail;

    pub(super) unsafe fn tile(_: usize, _: *const f32, _: *const f32, _: *mut f32, _: usize, _: &Tail) {
        unreachable!("the packed kernel is x86-64 only; `available()` is false here");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::testing::hashed_value as val;

    /// The contract computed in f64 from its definition, independently of the layouts.
    #[allow(clippy::too_many_arguments)]
    fn reference(
        x: &[f32],
        rows: usize,
        w: &[f32],
        n: usize,
        k: usize,
        bias: Option<&[f32]>,
        act: Act,
        residual: Option<&[f32]>,
        scale: Option<&[f32]>,
    ) -> Vec<f64> {
        let mut out = vec![0f64; rows * n];
        for i in 0..rows {
            for j in 0..n {
                let mut v: f64 = (0..k).map(|p| x[i * k + p] as f64 * w[j * k + p] as f64).sum();
                v += bias.map_or(0.0, |b| b[j] as f64);
                let y = match act {
                    Act::None => v,
                    Act::Relu => v.max(0.0),
                    Act::Gelu => 0.5 * v * (1.0 + candle_core::cpu::erf::erf_f64(v / std::f64::consts::SQRT_2)),
                    Act::Silu => v / (1.0 + (-v).exp()),
                };
                out[i * n + j] = match residual {
                    Some(r) => r[i * n + j] as f64 + y * scale.map_or(1.0, |g| g[j] as f64),
                    None => y,
                };
            }
        }
        out
    }

    #[test]
    fn matches_f64_with_every_epilogue_and_partial_tiles() {
        if !available() {
            eprintln!("no AVX-512F on this CPU: the packed kernel is not tested here");
            return;
        }
        for &(rows, k, n) in &[
            (1, 1, 1),
            (5, 7, 33),
            (12, 64, 32),
            (25, 130, 70),
            (200, 384, 300),
            (37, 1030, 64),
        ] {
            let x: Vec<f32> = (0..rows * k).map(|i| val(i, 1)).collect();
            let w: Vec<f32> = (0..n * k).map(|i| val(i, 2) * 0.3).collect();
            let bias: Vec<f32> = (0..n).map(|i| val(i, 3)).collect();
            let res: Vec<f32> = (0..rows * n).map(|i| val(i, 4) * 2.0).collect();
            let gamma: Vec<f32> = (0..n).map(|i| val(i, 5)).collect();
            let cases: [(bool, Act, bool, bool); 6] = [
                (true, Act::None, false, false),
                (false, Act::None, false, false),
                (true, Act::Gelu, false, false),
                (true, Act::Relu, true, false),
                (true, Act::None, true, true),
                (false, Act::Gelu, true, true),
            ];
            for (with_bias, act, with_res, with_scale) in cases {
                let b = with_bias.then_some(bias.as_slice());
                let layer = PackedLinear::from_weights(&w, n, k, b).unwrap();
                let epi = Epilogue {
                    act,
                    residual: with_res.then_some(res.as_slice()),
                    scale: with_scale.then_some(gamma.as_slice()),
                };
                let mut out = vec![f32::NAN; rows * n];
                layer.forward_slice(&x, rows, &mut out, &epi);
                let want = reference(&x, rows, &w, n, k, b, act, epi.residual, epi.scale);
                // f32 sums of k terms of size ≤ 0.3, then GELU's erf (3e-7 absolute).
                let tol = 1e-6 * (k as f64).sqrt() * 4.0 + 1e-6;
                for (i, (&g, &r)) in out.iter().zip(&want).enumerate() {
                    assert!(
                        (g as f64 - r).abs() <= tol * (1.0 + r.abs()),
                        "{rows}x{k}x{n} {act:?} bias {with_bias} residual {with_res} scale {with_scale} at {i}: {g} vs {r}"
                    );
                }
            }
        }
    }

    #[test]
    fn unpacks_to_the_weights_and_checks_lengths() {
        let (n, k) = (45, 19);
        let w: Vec<f32> = (0..n * k).map(|i| val(i, 6)).collect();
        let b: Vec<f32> = (0..n).map(|i| val(i, 7)).collect();
        let layer = PackedLinear::from_weights(&w, n, k, Some(&b)).unwrap();
        assert_eq!(layer.to_dense(), (w.clone(), Some(b.clone())));
        assert_eq!(PackedLinear::from_weights(&w, n, k, None).unwrap().to_dense().1, None);
        assert!(PackedLinear::from_weights(&w[1..], n, k, None).is_err());
        assert!(PackedLinear::from_weights(&w, n, k, Some(&b[1..])).is_err());
    }

    #[test]
    fn one_thread_and_many_give_the_same_bits() {
        if !available() {
            return;
        }
        let (rows, k, n) = (300, 200, 500);
        let x: Vec<f32> = (0..rows * k).map(|i| val(i, 8)).collect();
        let w: Vec<f32> = (0..n * k).map(|i| val(i, 9)).collect();
        let layer = PackedLinear::from_weights(&w, n, k, None).unwrap();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("pool");
            let mut out = vec![0f32; rows * n];
            pool.install(|| layer.forward_slice(&x, rows, &mut out, &Epilogue::act(Act::Gelu)));
            out
        };
        assert_eq!(run(1), run(3));
    }
}
