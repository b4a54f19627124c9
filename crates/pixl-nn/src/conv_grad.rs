//! Differentiable 2D convolutions for training on the CPU: [`conv2d`] (PyTorch `nn.Conv2d`, groups
//! 1, dilation 1) and [`conv_transpose_k`] (`nn.ConvTranspose2d(cin, cout, k, stride=k)`, the
//! non-overlapping upsampling of DPT's reassemble stage), each one candle custom op with its own
//! backward pass.
//!
//! Contract, with `x (B, Cin, H, W)` channels-first and zeros outside the image:
//! - [`conv2d`]: weight `(Cout, Cin, kh, kw)`, bias `(Cout)`, one stride `s` and one padding `p`
//!   for both axes; `y[b,o,i,j] = bias[o] + Σ_{c,u,v} w[o,c,u,v]·x[b,c,s·i+u−p,s·j+v−p]`, output
//!   `(B, Cout, ⌊(H+2p−kh)/s⌋+1, ⌊(W+2p−kw)/s⌋+1)`;
//! - [`conv_transpose_k`]: weight `(Cin, Cout, k, k)`, bias `(Cout)`;
//!   `y[b,o,k·i+u,k·j+v] = bias[o] + Σ_c x[b,c,i,j]·w[c,o,u,v]`, output `(B, Cout, k·H, k·W)`.
//!
//! Both are differentiable in every argument through candle's autograd; a gradient is computed
//! only for the arguments that track one (`track_op()`: an input image that is not a `Var` gets
//! none), and the returned gradients are constants (no second-order gradients). Nothing is kept
//! for the backward pass beyond what the autograd graph holds anyway: the op's arguments (the
//! contiguous copies where an argument was strided) and its output.
//!
//! On the CPU with f32 or f64 operands of one dtype (any strides: they are made contiguous) the
//! work is GEMMs (the `gemm` crate), except for narrow f32 layers (below), over tiles of about 256
//! output pixels, tiles in parallel on rayon's pool with single-threaded GEMMs (a GEMM parallel
//! over the pool when there are fewer tiles than threads), accumulating in the operands' type:
//! - forward: per tile of one image, an im2col matrix `(Cin·kh·kw, t)` (rows `(c, u, v)`, so the
//!   weight is read as `(Cout, Cin·kh·kw)` as it is) times the weight, written in place into the
//!   channels-first output over the bias. 1×1 stride-1 convolutions read the input directly;
//! - weight gradient: `gw (Cout, kh·kw·Cin) = Σ_tiles gy_tile (Cout, t) · cols_tile (t, kh·kw·Cin)`
//!   with a pixel-major, channels-last im2col (the layout the GEMM runs fastest on), each worker
//!   summing its tiles into its own accumulator, the accumulators added and reordered to
//!   `(Cout, Cin, kh, kw)` at the end. At stride 1 the im2col matrix is not built: a tile's input
//!   rows are copied channels-last with their zero padding once, and each kernel row's im2col
//!   rows are an overlapping strided view of that copy (see `wgrad_rows`);
//! - input gradient: at stride 1 (`p < k`) the forward kernel again, on `gy` with the weight
//!   rotated by 180° and its channel axes swapped, padding `k−1−p`; otherwise (stride > 1,
//!   including the `k×k`-stride-`k` patchify convolutions) `cols = wᵀ · gy_tile` then col2im
//!   (a scatter-add of `cols` into the input planes), workers owning disjoint channel blocks;
//! - bias gradient: `Σ_{b,i,j} gy`;
//! - [`conv_transpose_k`] is that col2im kernel over the bias (a pure scatter, the patches do not
//!   overlap); its input gradient is the forward convolution of `gy` with stride `k`, its weight
//!   gradient the weight-gradient kernel with the roles of input and output gradient swapped.
//!
//! Narrow f32 layers take direct kernels instead, on x86-64 CPUs with AVX2 and FMA or with
//! AVX-512F (register tiles written with `std::arch` intrinsics for both, chosen at run time):
//! passes with at most 64 outputs per pixel over at most 1024 taps `(c, u, v)`, 1×1 forward
//! passes with at most 128 input channels (the direct kernels do not block the sum over them),
//! weight gradients whose output channels fill at least half of their vector lanes (or with at
//! most 64 taps), and strided input gradients whose column matrix has at most 2¹⁴ values per
//! image (`examples/bench_conv_grad`, `tiny` group, 2 threads: 1.35× less kernel time in all,
//! 2–6× on the smallest layers; the largest are 1.3–1.9× faster alone, less in a training step,
//! where first touches of fresh output pages take much of their time).
//! - forward pass, and the stride-1 input gradient (the same convolution of `gy`, flipped weight):
//!   at stride 1 on outputs of at least 64 pixels, vectors of output positions: input rows are
//!   read in `Wp = W + 2p` wide zero-padded planes (the image itself when unpadded), each of 4
//!   output channels' vectors summing `w·x` over the taps at shifted offsets (the `kw − 1`
//!   positions past each output row are computed and dropped), stored straight into the output
//!   when none is dropped; otherwise (strides above 1, small images) vectors of output channels:
//!   each pixel's `Cout` values sum the input value broadcast times the weight's row of the tap,
//!   then are transposed into the output;
//! - weight gradient: vectors of output channels too, `gwᵀ[tap] += x[tap][pixel]·gy[pixel]` over
//!   a unit's pixels (its output gradient copied pixel-major) in registers, then added into one
//!   accumulator per worker;
//! - input gradient at strides above 1: each output pixel's columns `Σ_o gy[o]·w[o]` (vectors over
//!   the taps), then added into the input planes.
//!
//! A direct pass splits into units of output rows of one image, or of several whole small images;
//! units run on rayon's pool when the pass has at least 2²¹ multiply-adds (two units per thread at
//! least), else on the calling thread; scratch is a per-thread buffer kept from call to call, and
//! outputs are written once without being zeroed first (except the strided input gradient's, whose
//! sums overlap). [`set_direct_kernels`] turns the direct kernels off process-wide, for comparing.
//!
//! 3×3, stride-1, padding-1 f32 passes (the forward pass, and the input gradient, which is the
//! same convolution with the channel counts swapped) on images that
//! [suit](crate::winograd::suits) Winograd (64×64 pixels and up) with at least 64 channels in
//! and 32 out run through [`crate::winograd`] (F(4×4, 3×3): 1.4–2.5× faster here), which departs
//! from the direct sum by about 1e-5 of the output's scale (f32 rounding of a different
//! summation; the tests hold it within 1e-4 of an f64 reference). The weight gradient is always
//! the direct sum. A Winograd forward result is computed before the op is applied and handed to
//! it, one parallel copy of the output.
//!
//! Everything else (f16/bf16, mixed dtypes, CUDA/Metal) falls back to candle's own
//! `conv2d` / `conv_transpose2d` plus a broadcast bias add ([`conv2d_candle`],
//! [`conv_transpose_k_candle`]), whose backward candle provides.
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp2, CustomOp3, DType, Layout, Result, Shape, Tensor, WithDType};
use rayon::prelude::*;

use crate::conv3x3::Epilogue;
use crate::fused::{gemm_parallelism, Act};
use crate::winograd::{self, WinogradWeight};

/// Output pixels per im2col tile of the forward pass.
const FWD_TILE: usize = 256;
/// Output pixels per tile of the weight gradient (the GEMMs' inner dimension) for `cout` output
/// channels: 256, up to 1024 below 32 channels (`examples/bench_conv_grad`: 256 is best or within
/// 5% from 32 channels up; at 6 channels 1024 is 1.2× faster than 256).
fn wgrad_tile(cout: usize) -> usize {
    (256 * 32 / cout.max(1)).clamp(256, 1024)
}
/// Output pixels per tile of the col2im pass.
const COL2IM_TILE: usize = 256;
/// Smallest row count (`channels · kh · kw`) of a col2im worker's GEMM, when channels allow.
const COL2IM_MIN_ROWS: usize = 64;

/// Differentiable `nn.Conv2d` (groups 1, dilation 1): `x (B, Cin, H, W)`, `w (Cout, Cin, kh, kw)`,
/// `b (Cout)`, one `stride` and `padding` for both axes. See the module docs.
pub fn conv2d(x: &Tensor, w: &Tensor, b: Option<&Tensor>, stride: usize, padding: usize) -> Result<Tensor> {
    let g = conv_geom(x.shape(), w.shape(), b.map(Tensor::shape), stride, padding)?;
    if !fast_path(x, w, b) {
        return conv2d_candle(x, w, b, stride, padding);
    }
    let x = x.contiguous()?;
    let w = w.contiguous()?;
    let b = b.map(Tensor::contiguous).transpose()?;
    let op = Conv2dOp::new(stride, padding);
    if x.dtype() == DType::F32 && winograd_fits(&g, g.cin, g.cout) {
        let bias = b.as_ref().map(Tensor::to_vec1::<f32>).transpose()?;
        let epi = Epilogue {
            bias: bias.as_deref(),
            residual: None,
            act: Act::None,
        };
        let wt = WinogradWeight::new(&w)?;
        let y = winograd::conv3x3_winograd(&x, &wt, false, &epi, winograd::block_tiles(g.cin, g.cout))?;
        op.set_precomputed(y)?;
    }
    match &b {
        Some(b) => x.apply_op3(&w, b, op),
        None => x.apply_op2(&w, op),
    }
}

/// Differentiable `nn.ConvTranspose2d(cin, cout, k, stride=k)` (no padding, so the `k×k` output
/// patches do not overlap): `x (B, Cin, H, W)`, `w (Cin, Cout, k, k)`, `b (Cout)` →
/// `(B, Cout, k·H, k·W)`. See the module docs.
pub fn conv_transpose_k(x: &Tensor, w: &Tensor, b: Option<&Tensor>) -> Result<Tensor> {
    transpose_geom(x.shape(), w.shape(), b.map(Tensor::shape))?;
    if !fast_path(x, w, b) {
        return conv_transpose_k_candle(x, w, b);
    }
    let x = x.contiguous()?;
    let w = w.contiguous()?;
    match b {
        Some(b) => x.apply_op3(&w, &b.contiguous()?, ConvTransposeOp),
        None => x.apply_op2(&w, ConvTransposeOp),
    }
}

/// candle's `conv2d` plus a broadcast bias add: the fallback and the reference.
pub fn conv2d_candle(x: &Tensor, w: &Tensor, b: Option<&Tensor>, stride: usize, padding: usize) -> Result<Tensor> {
    let y = x.conv2d(w, padding, stride, 1, 1)?;
    add_bias(y, b)
}

/// candle's `conv_transpose2d` (stride `k`, no padding) plus a broadcast bias add: the fallback
/// and the reference.
pub fn conv_transpose_k_candle(x: &Tensor, w: &Tensor, b: Option<&Tensor>) -> Result<Tensor> {
    let k = w.dim(2)?;
    let y = x.conv_transpose2d(w, 0, 0, k, 1)?;
    add_bias(y, b)
}

fn add_bias(y: Tensor, b: Option<&Tensor>) -> Result<Tensor> {
    match b {
        Some(b) => y.broadcast_add(&b.reshape((1, b.elem_count(), 1, 1))?),
        None => Ok(y),
    }
}

/// CPU, and f32 or f64 throughout.
fn fast_path(x: &Tensor, w: &Tensor, b: Option<&Tensor>) -> bool {
    let dt = x.dtype();
    matches!(dt, DType::F32 | DType::F64)
        && x.device().is_cpu()
        && w.device().is_cpu()
        && w.dtype() == dt
        && b.is_none_or(|b| b.device().is_cpu() && b.dtype() == dt)
}

/// Whether a pass of the convolution `g` that maps `cin` to `cout` channels (the forward pass,
/// or the input gradient with the two swapped) goes through [`crate::winograd`] (f32 is checked
/// by the caller): 3×3, stride 1, padding 1, an image that [suits](winograd::suits) it, and at
/// least 64 channels in and 32 out (`examples/bench_conv_grad`: 1.4–2.5× faster than im2col
/// from 64 channels in, no faster or slower below).
fn winograd_fits(g: &Geom, cin: usize, cout: usize) -> bool {
    (g.kh, g.kw, g.s, g.ph, g.pw) == (3, 3, 1, 1, 1) && winograd::suits(1, g.h, g.w) && cin >= 64 && cout >= 32
}

/// The shape of one convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Geom {
    b: usize,
    cin: usize,
    h: usize,
    w: usize,
    cout: usize,
    kh: usize,
    kw: usize,
    s: usize,
    ph: usize,
    pw: usize,
    ho: usize,
    wo: usize,
}

impl Geom {
    fn new(
        b: usize,
        cin: usize,
        (h, w): (usize, usize),
        cout: usize,
        (kh, kw): (usize, usize),
        s: usize,
        (ph, pw): (usize, usize),
    ) -> Result<Self> {
        if s == 0 {
            candle_core::bail!("conv2d: stride 0");
        }
        if cin == 0 || cout == 0 || kh == 0 || kw == 0 {
            candle_core::bail!("conv2d: empty kernel ({cout}, {cin}, {kh}, {kw})");
        }
        if h == 0 || w == 0 {
            candle_core::bail!("conv2d: empty {h}x{w} input");
        }
        if h + 2 * ph < kh || w + 2 * pw < kw {
            candle_core::bail!("conv2d: {kh}x{kw} kernel larger than the {h}x{w} input padded by ({ph}, {pw})");
        }
        let ho = (h + 2 * ph - kh) / s + 1;
        let wo = (w + 2 * pw - kw) / s + 1;
        Ok(Self {
            b,
            cin,
            h,
            w,
            cout,
            kh,
            kw,
            s,
            ph,
            pw,
            ho,
            wo,
        })
    }

    fn taps(&self) -> usize {
        self.kh * self.kw
    }

    /// Rows of the im2col matrix, `Cin·kh·kw`.
    fn krows(&self) -> usize {
        self.cin * self.taps()
    }

    fn in_plane(&self) -> usize {
        self.h * self.w
    }

    fn out_plane(&self) -> usize {
        self.ho * self.wo
    }

    /// A 1×1, stride-1, unpadded convolution: im2col is the input itself.
    fn pointwise(&self) -> bool {
        (self.kh, self.kw, self.s, self.ph, self.pw) == (1, 1, 1, 0, 0)
    }

    fn out_dims(&self) -> [usize; 4] {
        [self.b, self.cout, self.ho, self.wo]
    }

    /// Multiply-adds of one pass (the forward pass, or either gradient).
    fn macs(&self) -> usize {
        self.b * self.cout * self.krows() * self.out_plane()
    }
}

/// The geometry of `conv2d(x, w, b, stride, padding)`, checking that the shapes agree.
fn conv_geom(x: &Shape, w: &Shape, b: Option<&Shape>, stride: usize, padding: usize) -> Result<Geom> {
    let (bsz, cin, h, wd) = x.dims4()?;
    let (cout, wcin, kh, kw) = w.dims4()?;
    if wcin != cin {
        candle_core::bail!("conv2d: weight {w:?} does not match input {x:?} ({cin} channels)");
    }
    if let Some(b) = b {
        if b.dims() != [cout] {
            candle_core::bail!("conv2d: bias {b:?} does not match {cout} output channels");
        }
    }
    Geom::new(bsz, cin, (h, wd), cout, (kh, kw), stride, (padding, padding))
}

/// The geometry of `conv_transpose_k(x, w, b)` as the convolution it transposes: input
/// `(B, Cout, k·H, k·W)`, weight `w` read as `(Cin, Cout, k, k)`, stride `k`, output `x`'s shape.
fn transpose_geom(x: &Shape, w: &Shape, b: Option<&Shape>) -> Result<Geom> {
    let (bsz, cin, h, wd) = x.dims4()?;
    let (wcin, cout, k, k2) = w.dims4()?;
    if wcin != cin || k != k2 {
        candle_core::bail!("conv transpose: weight {w:?} does not match input {x:?} (expected ({cin}, Cout, k, k))");
    }
    if let Some(b) = b {
        if b.dims() != [cout] {
            candle_core::bail!("conv transpose: bias {b:?} does not match {cout} output channels");
        }
    }
    Geom::new(bsz, cout, (k * h, k * wd), cin, (k, k), k, (0, 0))
}

/// The float types of the CPU kernels (the `gemm` crate's real types), with the passes for
/// them: GEMMs, and for f32 the direct kernels where they fit.
trait Float: WithDType {
    /// The forward convolution (see [`conv_forward`]).
    fn forward(x: &[Self], w: &[Self], bias: Option<&[Self]>, g: &Geom) -> Vec<Self> {
        conv_forward(x, w, bias, g)
    }

    /// The weight gradient (see [`conv_weight_grad`]).
    fn weight_grad(x: &[Self], gy: &[Self], g: &Geom) -> Vec<Self> {
        conv_weight_grad(x, gy, g)
    }

    /// The input gradient (see [`conv_input_grad`]).
    fn input_grad(gy: &[Self], w: &[Self], g: &Geom) -> Result<Vec<Self>> {
        conv_input_grad(gy, w, g)
    }
}

impl Float for f64 {}

impl Float for f32 {
    fn forward(x: &[f32], w: &[f32], bias: Option<&[f32]>, g: &Geom) -> Vec<f32> {
        match Isa::detect() {
            Some(isa) if direct_fwd_fits(g) => direct_forward(x, w, bias, g, isa),
            _ => conv_forward(x, w, bias, g),
        }
    }

    fn weight_grad(x: &[f32], gy: &[f32], g: &Geom) -> Vec<f32> {
        match Isa::detect() {
            Some(isa) if direct_wgrad_fits(g, isa) => direct_weight_grad(x, gy, g, isa),
            _ => conv_weight_grad(x, gy, g),
        }
    }

    fn input_grad(gy: &[f32], w: &[f32], g: &Geom) -> Result<Vec<f32>> {
        let Some(isa) = Isa::detect() else {
            return conv_input_grad(gy, w, g);
        };
        match back_geom(g)? {
            Some(back) if direct_fwd_fits(&back) => {
                let flipped = flip_weight(w, g.cout, g.cin, g.kh, g.kw);
                Ok(direct_forward(gy, &flipped, None, &back, isa))
            }
            None if direct_fits(g.cout, g.krows()) && g.out_plane() * g.krows() <= COL2IM_DIRECT_MAX => {
                Ok(direct_col2im(gy, w, g, isa))
            }
            _ => conv_input_grad(gy, w, g),
        }
    }
}

/// The values of a contiguous CPU storage of type `T`.
fn data<'a, T: Float>(s: &'a CpuStorage, l: &Layout, what: &str) -> Result<&'a [T]> {
    let all = s.as_slice::<T>()?;
    match l.contiguous_offsets() {
        Some((a, b)) if b <= all.len() => Ok(&all[a..b]),
        _ => candle_core::bail!("conv2d kernel: {what} must be contiguous"),
    }
}

/// A pointer into an output shared by workers that write disjoint parts of it.
#[derive(Clone, Copy)]
struct SyncPtr<T>(*mut T);
// SAFETY: used only for outputs whose workers write disjoint index sets of one live allocation.
unsafe impl<T: Send> Send for SyncPtr<T> {}
unsafe impl<T: Send> Sync for SyncPtr<T> {}

impl<T> SyncPtr<T> {
    fn get(self) -> *mut T {
        self.0
    }
}

/// Runs `run(unit, scratch, parallelism)` for units `0 .. n`, each worker with `scratch_len`
/// values of scratch: in parallel with single-threaded GEMMs, or one after another with the GEMM
/// parallel when there are fewer units than threads.
fn run_units<T: Float>(n: usize, scratch_len: usize, run: impl Fn(usize, &mut [T], gemm::Parallelism) + Sync) {
    let threads = rayon::current_num_threads().max(1);
    if n < threads {
        let mut scratch = vec![T::zero(); scratch_len];
        for unit in 0..n {
            run(unit, &mut scratch, gemm_parallelism());
        }
        return;
    }
    let tasks = (4 * threads).min(n);
    let per_task = n.div_ceil(tasks);
    (0..tasks).into_par_iter().for_each(|task| {
        let mut scratch = vec![T::zero(); scratch_len];
        for unit in task * per_task..((task + 1) * per_task).min(n) {
            run(unit, &mut scratch, gemm::Parallelism::None);
        }
    });
}

/// For the outputs `o0 .. o0 + n` of one row and the kernel offset `k`: the range `lo..hi` of `i`
/// whose input index `(o0 + i)·s + k − pad` lies in `0..len`.
#[inline]
fn valid_span(o0: usize, n: usize, s: usize, k: usize, pad: usize, len: usize) -> (usize, usize) {
    let first = o0 * s + k; // input index + pad at i = 0
    let lo = pad.saturating_sub(first).div_ceil(s).min(n);
    let hi = (len + pad).saturating_sub(first).div_ceil(s).min(n);
    (lo, hi.max(lo))
}

/// Unrolls output pixels `p0 .. p0 + t` (row-major over `(Ho, Wo)`) of one image `img`
/// `(C, H, W)` into `cols` `(C·kh·kw, t)`: row `(c, u, v)` holds `img[c, s·i+u−ph, s·j+v−pw]`,
/// 0 outside the image. `C` is `img.len() / (H·W)`.
fn im2col<T: Float>(img: &[T], g: &Geom, p0: usize, t: usize, cols: &mut [T]) {
    for (c, plane) in img.chunks_exact(g.in_plane()).enumerate() {
        for u in 0..g.kh {
            for v in 0..g.kw {
                let row = &mut cols[((c * g.kh + u) * g.kw + v) * t..][..t];
                let mut j = 0;
                while j < t {
                    let (oy, ox) = ((p0 + j) / g.wo, (p0 + j) % g.wo);
                    let n = (g.wo - ox).min(t - j);
                    let seg = &mut row[j..j + n];
                    j += n;
                    let Some(iy) = (oy * g.s + u).checked_sub(g.ph).filter(|&r| r < g.h) else {
                        seg.fill(T::zero());
                        continue;
                    };
                    let line = &plane[iy * g.w..(iy + 1) * g.w];
                    let (lo, hi) = valid_span(ox, n, g.s, v, g.pw, g.w);
                    seg[..lo].fill(T::zero());
                    seg[hi..].fill(T::zero());
                    if lo < hi {
                        let start = (ox + lo) * g.s + v - g.pw;
                        if g.s == 1 {
                            seg[lo..hi].copy_from_slice(&line[start..start + hi - lo]);
                        } else {
                            for (d, x) in seg[lo..hi].iter_mut().zip(line[start..].iter().step_by(g.s)) {
                                *d = *x;
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The adjoint of [`im2col`]: adds `cols` `(C·kh·kw, t)` of output pixels `p0 .. p0 + t` into the
/// planes `out` `(C, H, W)` of one image.
fn col2im_add<T: Float>(cols: &[T], g: &Geom, p0: usize, t: usize, out: &mut [T]) {
    for (c, plane) in out.chunks_exact_mut(g.in_plane()).enumerate() {
        for u in 0..g.kh {
            for v in 0..g.kw {
                let row = &cols[((c * g.kh + u) * g.kw + v) * t..][..t];
                let mut j = 0;
                while j < t {
                    let (oy, ox) = ((p0 + j) / g.wo, (p0 + j) % g.wo);
                    let n = (g.wo - ox).min(t - j);
                    let seg = &row[j..j + n];
                    j += n;
                    let Some(iy) = (oy * g.s + u).checked_sub(g.ph).filter(|&r| r < g.h) else {
                        continue;
                    };
                    let line = &mut plane[iy * g.w..(iy + 1) * g.w];
                    let (lo, hi) = valid_span(ox, n, g.s, v, g.pw, g.w);
                    if lo < hi {
                        let start = (ox + lo) * g.s + v - g.pw;
                        if g.s == 1 {
                            for (d, x) in line[start..start + hi - lo].iter_mut().zip(&seg[lo..hi]) {
                                *d += *x;
                            }
                        } else {
                            for (d, x) in line[start..].iter_mut().step_by(g.s).zip(&seg[lo..hi]) {
                                *d += *x;
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The forward convolution: `x (B, Cin, H, W)`, `wt (Cout, Cin, kh, kw)`, `bias (Cout)` →
/// `(B, Cout, Ho, Wo)`, tiles of [`FWD_TILE`] output pixels.
fn conv_forward<T: Float>(x: &[T], wt: &[T], bias: Option<&[T]>, g: &Geom) -> Vec<T> {
    let (plane, hw, kr) = (g.out_plane(), g.in_plane(), g.krows());
    let mut out = vec![T::zero(); g.b * g.cout * plane];
    if out.is_empty() {
        return out;
    }
    let tile = FWD_TILE.min(plane);
    let per_image = plane.div_ceil(tile);
    let pointwise = g.pointwise();
    let dst = SyncPtr(out.as_mut_ptr());
    let one = T::from_f64(1.0);
    let run = |unit: usize, cols: &mut [T], par: gemm::Parallelism| {
        let (bi, p0) = (unit / per_image, (unit % per_image) * tile);
        let t = tile.min(plane - p0);
        let img = &x[bi * g.cin * hw..(bi + 1) * g.cin * hw];
        let (rhs, rhs_rs) = if pointwise {
            (img[p0..].as_ptr(), hw)
        } else {
            let cols = &mut cols[..kr * t];
            im2col(img, g, p0, t, cols);
            (cols.as_ptr(), t)
        };
        let base = bi * g.cout * plane + p0;
        if let Some(bias) = bias {
            for (o, &bo) in bias.iter().enumerate() {
                // SAFETY: the `t` values at `base + o·plane` are this tile's output of channel
                // `o` (p0 + t ≤ plane), inside `out` and written by no other tile.
                unsafe { std::slice::from_raw_parts_mut(dst.get().add(base + o * plane), t) }.fill(bo);
            }
        }
        // SAFETY: dst (Cout × t, row stride `plane`) is this tile's block of `out` (see above);
        // lhs (Cout × kr, row stride kr) is `wt`; rhs (kr × t) is `cols` (row stride t) or, for a
        // pointwise convolution, the image's pixels p0.. of each channel (row stride H·W).
        unsafe {
            gemm::gemm(
                g.cout,
                t,
                kr,
                dst.get().add(base),
                1,
                plane as isize,
                bias.is_some(),
                wt.as_ptr(),
                1,
                kr as isize,
                rhs,
                1,
                rhs_rs as isize,
                one,
                one,
                false,
                false,
                false,
                par,
            );
        }
    };
    run_units(g.b * per_image, if pointwise { 0 } else { kr * tile }, run);
    out
}

/// Unrolls output pixels `p0 .. p0 + t` of one image `img` `(C, H, W)` pixel-major: `cols`
/// `(t, kh·kw·C)`, row `j` holding `img[c, s·i+u−ph, s·j'+v−pw]` at column `(u·kw + v)·C + c`
/// (0 outside the image). The input rows the tile reads are first copied channels-last into
/// `band`, so each `(pixel, u)` is one run of `kw·C` contiguous values.
fn im2col_pixel_major<T: Float>(img: &[T], g: &Geom, p0: usize, t: usize, band: &mut Vec<T>, cols: &mut [T]) {
    let hw = g.in_plane();
    let c_n = img.len() / hw;
    let run = g.kw * c_n;
    let kr = g.kh * run;
    let (oy0, oy1) = (p0 / g.wo, (p0 + t - 1) / g.wo);
    let r0 = (oy0 * g.s).saturating_sub(g.ph).min(g.h);
    let r1 = (oy1 * g.s + g.kh).saturating_sub(g.ph).min(g.h).max(r0);
    band.clear();
    band.resize((r1 - r0) * g.w * c_n, T::zero());
    for (c, plane) in img.chunks_exact(hw).enumerate() {
        for (q, &v) in plane[r0 * g.w..r1 * g.w].iter().enumerate() {
            band[q * c_n + c] = v;
        }
    }
    for (j, row) in cols[..t * kr].chunks_exact_mut(kr).enumerate() {
        let (oy, ox) = ((p0 + j) / g.wo, (p0 + j) % g.wo);
        for (u, dst) in row.chunks_exact_mut(run).enumerate() {
            let Some(iy) = (oy * g.s + u).checked_sub(g.ph).filter(|&r| r < g.h) else {
                dst.fill(T::zero());
                continue;
            };
            let line = &band[(iy - r0) * g.w * c_n..(iy - r0 + 1) * g.w * c_n];
            let (lo, hi) = valid_span(0, g.kw, 1, ox * g.s, g.pw, g.w);
            dst[..lo * c_n].fill(T::zero());
            dst[hi * c_n..].fill(T::zero());
            if lo < hi {
                let ix0 = ox * g.s + lo - g.pw;
                dst[lo * c_n..hi * c_n].copy_from_slice(&line[ix0 * c_n..(ix0 + hi - lo) * c_n]);
            }
        }
    }
}

/// The weight gradient: `x (B, Cin, H, W)`, `gy (B, Cout, Ho, Wo)` → `(Cout, Cin, kh, kw)`,
/// accumulated as `(Cout, kh·kw·Cin)` (columns `(u, v, c)`, reordered at the end) over units of
/// about [`wgrad_tile`] output pixels: [`wgrad_rows`] at stride 1 (1×1 kernels, or outputs at
/// least 32 wide), [`im2col_pixel_major`] tiles otherwise (`examples/bench_conv_grad`: the
/// implicit form is 7–25% faster at 32 and 6 output channels on 256×256, the same at 64×64
/// and 32×32, 10% slower at 8×8).
fn conv_weight_grad<T: Float>(x: &[T], gy: &[T], g: &Geom) -> Vec<T> {
    let (plane, hw, kr) = (g.out_plane(), g.in_plane(), g.krows());
    let len = g.cout * kr;
    let target = wgrad_tile(g.cout);
    // The implicit form wastes `kw − 1` of every `Wp` columns: it is used where that is small.
    let acc = if g.s == 1 && (g.kw == 1 || g.wo >= 32) {
        let wp = g.w + 2 * g.pw;
        let per_image = g.ho.div_ceil(target.div_ceil(wp).max(1));
        let rows = g.ho.div_ceil(per_image);
        accumulate(len, g.b * per_image, |acc, unit, band, gpad, par| {
            let (bi, oy0) = (unit / per_image, (unit % per_image) * rows);
            let img = &x[bi * g.cin * hw..(bi + 1) * g.cin * hw];
            let grad = &gy[bi * g.cout * plane..(bi + 1) * g.cout * plane];
            wgrad_rows(img, grad, g, oy0, rows.min(g.ho - oy0), acc, band, gpad, par);
        })
    } else {
        let tile = target.min(plane);
        let per_image = plane.div_ceil(tile);
        let one = T::from_f64(1.0);
        accumulate(len, g.b * per_image, |acc, unit, band, cols, par| {
            let (bi, p0) = (unit / per_image, (unit % per_image) * tile);
            let t = tile.min(plane - p0);
            let img = &x[bi * g.cin * hw..(bi + 1) * g.cin * hw];
            cols.resize(kr * t, T::zero());
            im2col_pixel_major(img, g, p0, t, band, cols);
            let lhs = &gy[bi * g.cout * plane + p0..(bi + 1) * g.cout * plane];
            // SAFETY: dst (Cout × kr, row-major) is `acc` (len values); lhs (Cout × t, row
            // stride `plane`) starts at pixel p0 of image bi's gradient, p0 + t ≤ plane; rhs
            // (t × kr, row-major) is `cols`, filled for t rows.
            unsafe {
                gemm::gemm(
                    g.cout,
                    kr,
                    t,
                    acc.as_mut_ptr(),
                    1,
                    kr as isize,
                    true,
                    lhs.as_ptr(),
                    1,
                    plane as isize,
                    cols.as_ptr(),
                    1,
                    kr as isize,
                    one,
                    one,
                    false,
                    false,
                    false,
                    par,
                );
            }
        })
    };
    // (Cout, kh, kw, Cin) → (Cout, Cin, kh, kw).
    let taps = g.taps();
    let mut out = vec![T::zero(); len];
    for (o_row, a_row) in out.chunks_exact_mut(kr).zip(acc.chunks_exact(kr)) {
        for (tap, vals) in a_row.chunks_exact(g.cin).enumerate() {
            for (c, &v) in vals.iter().enumerate() {
                o_row[c * taps + tap] = v;
            }
        }
    }
    out
}

/// Runs `add(acc, unit, scratch_a, scratch_b, parallelism)` for units `0 .. n` and returns the
/// sum of the `len`-value accumulators: one accumulator per worker (at most one per thread),
/// added up at the end, or a single one with the GEMMs parallel when there are fewer units than
/// threads.
fn accumulate<T: Float>(
    len: usize,
    n: usize,
    add: impl Fn(&mut [T], usize, &mut Vec<T>, &mut Vec<T>, gemm::Parallelism) + Sync,
) -> Vec<T> {
    let threads = rayon::current_num_threads().max(1);
    if n < threads {
        let mut acc = vec![T::zero(); len];
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for unit in 0..n {
            add(&mut acc, unit, &mut a, &mut b, gemm_parallelism());
        }
        return acc;
    }
    let per_task = n.div_ceil(threads);
    let parts: Vec<Vec<T>> = (0..n.div_ceil(per_task))
        .into_par_iter()
        .map(|task| {
            let mut acc = vec![T::zero(); len];
            let (mut a, mut b) = (Vec::new(), Vec::new());
            for unit in task * per_task..((task + 1) * per_task).min(n) {
                add(&mut acc, unit, &mut a, &mut b, gemm::Parallelism::None);
            }
            acc
        })
        .collect();
    let mut parts = parts.into_iter();
    let mut total = parts.next().unwrap_or_else(|| vec![T::zero(); len]);
    for part in parts {
        for (a, p) in total.iter_mut().zip(part) {
            *a += p;
        }
    }
    total
}

/// The stride-1 weight gradient of output rows `oy0 .. oy0 + r` of one image (`img (C, H, W)`,
/// `grad (Cout, Ho, Wo)`), added to `acc (Cout, kh·kw·C)`, without an im2col matrix.
///
/// The input rows the tile reads are copied channels-last and zero-padded into `band`
/// (`r + kh − 1` rows of `Wp = W + 2·pw` pixels of `C` values), and the gradient rows into
/// `gpad` (`Cout × r·Wp`, zero past column `Wo` of each row). Then for each kernel row `u`, the
/// im2col rows `(pixel, (v, c))` of all the unit's pixels are one strided view of `band`: pixel
/// `q = row·Wp + ox` starts at `band[(u·Wp + q)·C]` and runs over `kw·C` contiguous values, so
/// consecutive pixels overlap (row stride `C`). One GEMM per `u`,
/// `acc[:, u·kw·C ..] += gpad (Cout × K) · view (K × kw·C)`, `K = (r − 1)·Wp + Wo`, where the
/// `kw − 1` padding columns between rows meet zeros of `gpad`.
#[allow(clippy::too_many_arguments)]
fn wgrad_rows<T: Float>(
    img: &[T],
    grad: &[T],
    g: &Geom,
    oy0: usize,
    r: usize,
    acc: &mut [T],
    band: &mut Vec<T>,
    gpad: &mut Vec<T>,
    par: gemm::Parallelism,
) {
    let (c_n, wp, kr) = (g.cin, g.w + 2 * g.pw, g.krows());
    let band_rows = r + g.kh - 1;
    band.clear();
    band.resize(band_rows * wp * c_n, T::zero());
    for (c, plane) in img.chunks_exact(g.in_plane()).enumerate() {
        for br in 0..band_rows {
            let Some(iy) = (oy0 + br).checked_sub(g.ph).filter(|&y| y < g.h) else {
                continue;
            };
            let dst = &mut band[(br * wp + g.pw) * c_n..(br * wp + g.pw + g.w) * c_n];
            for (d, &v) in dst.chunks_exact_mut(c_n).zip(&plane[iy * g.w..(iy + 1) * g.w]) {
                d[c] = v;
            }
        }
    }
    gpad.clear();
    gpad.resize(g.cout * r * wp, T::zero());
    for (co, dst) in gpad.chunks_exact_mut(r * wp).enumerate() {
        let src = &grad[(co * g.ho + oy0) * g.wo..(co * g.ho + oy0 + r) * g.wo];
        for (d, s) in dst.chunks_exact_mut(wp).zip(src.chunks_exact(g.wo)) {
            d[..g.wo].copy_from_slice(s);
        }
    }
    let k = (r - 1) * wp + g.wo;
    let one = T::from_f64(1.0);
    for u in 0..g.kh {
        // SAFETY: dst is columns u·kw·C .. (u + 1)·kw·C of `acc` (Cout × kr, row-major); lhs
        // (Cout × K, row stride r·Wp) lies in `gpad` (K ≤ r·Wp); rhs (K × kw·C, row stride C)
        // reads band[(u·Wp + q)·C + j] for q < K, j < kw·C, at most
        // ((u + r − 1)·Wp + Wo + kw − 1)·C − 1 = (u + r)·Wp·C − 1 < band.len(), as
        // Wo + kw − 1 = Wp at stride 1 and u < kh.
        unsafe {
            gemm::gemm(
                g.cout,
                g.kw * c_n,
                k,
                acc.as_mut_ptr().add(u * g.kw * c_n),
                1,
                kr as isize,
                true,
                gpad.as_ptr(),
                1,
                (r * wp) as isize,
                band.as_ptr().add(u * wp * c_n),
                1,
                c_n as isize,
                one,
                one,
                false,
                false,
                false,
                par,
            );
        }
    }
}

/// The transposed convolution by col2im: `gy (B, Cout, Ho, Wo)`, `wt (Cout, Cin, kh, kw)`,
/// `bias (Cin)` → `(B, Cin, H, W)`, `out[b,c] = bias[c] + Σ_{o,u,v,i,j} wt[o,c,u,v]·gy[b,o,i,j]`
/// over `s·i+u−ph, s·j+v−pw` landing on the pixel. Workers own blocks of input channels.
fn col2im_conv<T: Float>(gy: &[T], wt: &[T], bias: Option<&[T]>, g: &Geom) -> Vec<T> {
    let (plane, hw, kr, taps) = (g.out_plane(), g.in_plane(), g.krows(), g.taps());
    let mut out = vec![T::zero(); g.b * g.cin * hw];
    if out.is_empty() {
        return out;
    }
    let threads = rayon::current_num_threads().max(1);
    let blocks_per_image = (4 * threads).div_ceil(g.b.max(1));
    let cc = g
        .cin
        .div_ceil(blocks_per_image)
        .max(COL2IM_MIN_ROWS.div_ceil(taps))
        .min(g.cin);
    let mut tasks: Vec<(usize, usize, &mut [T])> = Vec::new();
    for (bi, img) in out.chunks_mut(g.cin * hw).enumerate() {
        for (k, part) in img.chunks_mut(cc * hw).enumerate() {
            tasks.push((bi, k * cc, part));
        }
    }
    let par = if tasks.len() < threads {
        gemm_parallelism()
    } else {
        gemm::Parallelism::None
    };
    let tile = COL2IM_TILE.min(plane);
    let one = T::from_f64(1.0);
    tasks.into_par_iter().for_each(|(bi, c0, part)| {
        let ch = part.len() / hw;
        if let Some(bias) = bias {
            for (p, &bv) in part.chunks_exact_mut(hw).zip(&bias[c0..c0 + ch]) {
                p.fill(bv);
            }
        }
        let rows = ch * taps;
        let mut cols = vec![T::zero(); rows * tile];
        let grad = &gy[bi * g.cout * plane..(bi + 1) * g.cout * plane];
        for p0 in (0..plane).step_by(tile) {
            let t = tile.min(plane - p0);
            let cols = &mut cols[..rows * t];
            // SAFETY: dst (rows × t, row-major) is `cols`; lhs (rows × Cout) is the weight's
            // columns c0·taps .. (c0 + ch)·taps read transposed (column stride kr, inside `wt`);
            // rhs (Cout × t, row stride `plane`) is pixels p0 .. p0 + t ≤ plane of `grad`.
            unsafe {
                gemm::gemm(
                    rows,
                    t,
                    g.cout,
                    cols.as_mut_ptr(),
                    1,
                    t as isize,
                    false,
                    wt[c0 * taps..].as_ptr(),
                    kr as isize,
                    1,
                    grad[p0..].as_ptr(),
                    1,
                    plane as isize,
                    one,
                    one,
                    false,
                    false,
                    false,
                    par,
                );
            }
            col2im_add(cols, g, p0, t, part);
        }
    });
    out
}

/// `(Cout, Cin, kh, kw)` → `(Cin, Cout, kh, kw)` rotated by 180°: the weight of the stride-1
/// input-gradient convolution.
fn flip_weight<T: Float>(wt: &[T], cout: usize, cin: usize, kh: usize, kw: usize) -> Vec<T> {
    let mut f = vec![T::zero(); wt.len()];
    for o in 0..cout {
        for c in 0..cin {
            for u in 0..kh {
                for v in 0..kw {
                    f[((c * cout + o) * kh + u) * kw + v] = wt[((o * cin + c) * kh + (kh - 1 - u)) * kw + (kw - 1 - v)];
                }
            }
        }
    }
    f
}

/// The input gradient of the convolution `g`: `gy (B, Cout, Ho, Wo)`, `wt (Cout, Cin, kh, kw)` →
/// `(B, Cin, H, W)`.
fn conv_input_grad<T: Float>(gy: &[T], wt: &[T], g: &Geom) -> Result<Vec<T>> {
    match back_geom(g)? {
        Some(back) => Ok(conv_forward(
            gy,
            &flip_weight(wt, g.cout, g.cin, g.kh, g.kw),
            None,
            &back,
        )),
        None => Ok(col2im_conv(gy, wt, None, g)),
    }
}

/// At stride 1 (`p < k`), the convolution whose forward pass with the [flipped](flip_weight)
/// weight is the input gradient of `g`: `gy (B, Cout, Ho, Wo)` → `(B, Cin, H, W)`, padding
/// `k − 1 − p`; `None` for the other convolutions (col2im).
fn back_geom(g: &Geom) -> Result<Option<Geom>> {
    if !(g.s == 1 && g.ph < g.kh && g.pw < g.kw) {
        return Ok(None);
    }
    let back = Geom::new(
        g.b,
        g.cout,
        (g.ho, g.wo),
        g.cin,
        (g.kh, g.kw),
        1,
        (g.kh - 1 - g.ph, g.kw - 1 - g.pw),
    )?;
    if (back.ho, back.wo) != (g.h, g.w) {
        candle_core::bail!(
            "conv2d input gradient: {}x{} from a {}x{} input",
            back.ho,
            back.wo,
            g.h,
            g.w
        );
    }
    Ok(Some(back))
}

// Direct kernels for narrow f32 layers (see the module docs).

/// Output channels per register block of the position-vector forward kernel.
const FWD_R: usize = 4;
/// Output positions (padded-width coordinates) per unit of the position-vector forward pass.
const FWD_UNIT_POSITIONS: usize = 2048;
/// Output pixels per unit of the channel-vector forward pass and of the weight gradient.
const PIX_UNIT: usize = 1024;
/// Input values a unit's copied rows hold at most (256 KiB, a quarter of a Zen 4 core's L2).
const BAND_VALUES: usize = 1 << 16;
/// Output pixels per block of the channel-vector input gradient.
const COL2IM_PIXELS: usize = 128;
/// Multiply-adds below which a direct pass runs on the calling thread (a rayon dispatch costs
/// 20–40 µs on the 2-core machine `examples/bench_conv_grad` was tuned on).
const PAR_MIN_MACS: usize = 2 << 20;

/// Whether f32 passes may take the direct kernels (see [`set_direct_kernels`]).
static DIRECT_KERNELS: AtomicBool = AtomicBool::new(true);

/// Lets f32 passes take the direct kernels for narrow layers (`true`, the default) or keeps
/// every pass on the GEMM path (`false`), process-wide: for comparing the two
/// (`examples/bench_conv_grad`).
pub fn set_direct_kernels(on: bool) {
    DIRECT_KERNELS.store(on, Ordering::Relaxed);
}

/// The vector instruction set the direct kernels are compiled for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Isa {
    /// AVX-512F: 16 f32 lanes.
    #[cfg(target_arch = "x86_64")]
    Avx512,
    /// AVX2 with FMA: 8 f32 lanes.
    #[cfg(target_arch = "x86_64")]
    Avx2,
}

impl Isa {
    /// The widest the CPU has, `None` without AVX2 and FMA (the direct kernels are then unused).
    fn detect() -> Option<Self> {
        if !DIRECT_KERNELS.load(Ordering::Relaxed) {
            return None;
        }
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Some(Self::Avx512);
            }
            if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                return Some(Self::Avx2);
            }
        }
        None
    }

    fn lanes(self) -> usize {
        match self {
            #[cfg(target_arch = "x86_64")]
            Self::Avx512 => 16,
            #[cfg(target_arch = "x86_64")]
            Self::Avx2 => 8,
        }
    }

    /// The register tile `(T, V)` of [`Isa::pv`] for rows of `nvec` vectors: at most 24
    /// accumulators of the 32 vector registers with AVX-512, 12 of 16 with AVX2. Rows are
    /// padded to a multiple of `V` vectors.
    fn pv_shape(self, nvec: usize) -> (usize, usize) {
        match (self.lanes(), nvec) {
            (_, 0 | 1) => (8, 1),
            (8, _) | (_, 2) => (6, 2),
            (_, 3) => (6, 3),
            _ => (4, 4),
        }
    }

    /// `n` values rounded up to whole register tiles of `V` vectors of [`Isa::pv_shape`].
    fn pv_width(self, n: usize) -> (usize, usize, usize) {
        let lanes = self.lanes();
        let (t, v) = self.pv_shape(n.div_ceil(lanes));
        (t, v, n.div_ceil(v * lanes) * v * lanes)
    }

    /// The position-vector forward kernel (`fwd_core` of the instruction set's module).
    ///
    /// # Safety
    /// As the kernel's; `self` must be supported by the CPU.
    #[allow(clippy::too_many_arguments)]
    unsafe fn fwd_core(
        self,
        inp: *const f32,
        offs: &[usize],
        wpack: &[f32],
        init: &[f32],
        n: usize,
        obuf: *mut f32,
        ld: usize,
    ) {
        // SAFETY: forwarded contract.
        unsafe {
            match self {
                #[cfg(target_arch = "x86_64")]
                Self::Avx512 => avx512::fwd_core(inp, offs, wpack, init, n, obuf, ld),
                #[cfg(target_arch = "x86_64")]
                Self::Avx2 => avx2::fwd_core(inp, offs, wpack, init, n, obuf, ld),
            }
        }
    }

    /// A channel-vector register tile (`pv` of the instruction set's module).
    ///
    /// # Safety
    /// As the kernel's; `self` must be supported by the CPU.
    #[allow(clippy::too_many_arguments)]
    unsafe fn pv(
        self,
        tv: (usize, usize),
        a: *const f32,
        base: &[usize],
        offs: &[usize],
        b: *const f32,
        bs: usize,
        out: *mut f32,
        os: usize,
    ) {
        // SAFETY: forwarded contract.
        unsafe {
            match self {
                #[cfg(target_arch = "x86_64")]
                Self::Avx512 => avx512::pv(tv, a, base, offs, b, bs, out, os),
                #[cfg(target_arch = "x86_64")]
                Self::Avx2 => avx2::pv(tv, a, base, offs, b, bs, out, os),
            }
        }
    }
}

/// Whether the direct kernels take a pass with `cout` outputs over `j` = `Cin·kh·kw` inputs
/// each (f32 on a CPU with AVX2 or AVX-512 is checked by the caller): narrow layers.
fn direct_fits(cout: usize, j: usize) -> bool {
    cout <= 64 && j <= 1024
}

/// Whether the weight gradient of `g` takes the direct kernel: a narrow layer whose output
/// channels fill at least half of the vector lanes they occupy, or with few taps (measured with
/// 6 output channels: 1.3× slower than the GEMMs over 288 taps, 1.6× faster over 16).
fn direct_wgrad_fits(g: &Geom, isa: Isa) -> bool {
    let (_, _, cp) = isa.pv_width(g.cout);
    direct_fits(g.cout, g.krows()) && (2 * g.cout >= cp || g.krows() <= 64)
}

/// Whether the forward pass of `g` takes the direct kernels: a narrow layer, and at most 128
/// input channels for a 1×1 kernel (the direct kernels do not block the sum over the input
/// channels; measured: 1.5× slower than the GEMMs at 256).
fn direct_fwd_fits(g: &Geom) -> bool {
    direct_fits(g.cout, g.krows()) && (g.taps() > 1 || g.cin <= 128)
}

/// Whether the input gradient of `g` at a stride above 1 takes the direct kernel: a narrow
/// layer whose per-image column matrix `(Ho·Wo, Cin·kh·kw)` has at most this many values (the
/// small model's strided layers have 2.3k–9.2k; measured at 256 × 512 the direct kernel only
/// matches the GEMMs, and its pixel-major scatter was 2× slower on 64×64 outputs).
const COL2IM_DIRECT_MAX: usize = 1 << 14;

/// The first `N` values of `s` (zeros past its end).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn arr<const N: usize>(s: &[usize]) -> [usize; N] {
    let mut a = [0; N];
    for (d, &v) in a.iter_mut().zip(s) {
        *d = v;
    }
    a
}

/// Generates the register tiles of the direct kernels for one vector instruction set: a module
/// `$m` of `#[target_feature($feat)]` functions on `$lanes`-lane vectors.
macro_rules! direct_kernels {
    ($m:ident, $feat:literal, $lanes:literal, $vmax:literal,
     $zero:ident, $splat:ident, $loadu:ident, $storeu:ident, $fmadd:ident) => {
        #[cfg(target_arch = "x86_64")]
        mod $m {
            use super::{arr, FWD_R};
            use std::arch::x86_64::*;

            const L: usize = $lanes;

            /// One position-vector tile: for `r < R` and `q < V·L`,
            /// `out[r·ld + q] = init[r] + Σ_j w[j][r]·inp[offs[j] + q]`.
            ///
            /// # Safety
            /// `inp + offs[j] + q` must be readable for every `j` and `q < V·L`, and
            /// `out + r·ld + q` writable for every `r < R`, `q < V·L`.
            #[inline]
            #[target_feature(enable = $feat)]
            unsafe fn fwd_tile<const R: usize, const V: usize>(
                inp: *const f32,
                offs: &[usize],
                w: &[f32],
                init: &[f32; R],
                out: *mut f32,
                ld: usize,
            ) {
                let mut acc = [[$zero(); V]; R];
                for (a, &b) in acc.iter_mut().zip(init) {
                    *a = [$splat(b); V];
                }
                for (&off, wj) in offs.iter().zip(w.chunks_exact(R)) {
                    let mut xs = [$zero(); V];
                    for (v, x) in xs.iter_mut().enumerate() {
                        // SAFETY: see the function's contract.
                        *x = unsafe { $loadu(inp.add(off + v * L)) };
                    }
                    for (a, &wv) in acc.iter_mut().zip(wj) {
                        let wv = $splat(wv);
                        for (s, &x) in a.iter_mut().zip(&xs) {
                            *s = $fmadd(x, wv, *s);
                        }
                    }
                }
                for (r, a) in acc.iter().enumerate() {
                    for (v, &s) in a.iter().enumerate() {
                        // SAFETY: see the function's contract.
                        unsafe { $storeu(out.add(r * ld + v * L), s) };
                    }
                }
            }

            /// The position-vector forward kernel over `n` positions: `obuf[co·ld + q] =
            /// init[co] + Σ_j w[co][j]·inp[offs[j] + q]` for every `co < init.len()` and
            /// `q < ⌈n/L⌉·L`, `wpack` holding the weight in blocks of [`FWD_R`] output
            /// channels, `[block][j][r]`, and `init.len()` a multiple of [`FWD_R`].
            ///
            /// # Safety
            /// `inp + offs[j] + q` must be readable for every `j` and `q < ⌈n/L⌉·L`, and
            /// `obuf + co·ld + q` writable for those `q` and every `co`.
            #[target_feature(enable = $feat)]
            pub(super) unsafe fn fwd_core(
                inp: *const f32,
                offs: &[usize],
                wpack: &[f32],
                init: &[f32],
                n: usize,
                obuf: *mut f32,
                ld: usize,
            ) {
                let block = offs.len() * FWD_R;
                if block == 0 {
                    return;
                }
                let mut q0 = 0;
                while q0 < n {
                    let nv = (n - q0).div_ceil(L).min($vmax);
                    for (cb, (w, b)) in wpack
                        .chunks_exact(block)
                        .zip(init.chunks_exact(FWD_R))
                        .enumerate()
                    {
                        let Ok(b) = <&[f32; FWD_R]>::try_from(b) else {
                            continue;
                        };
                        // SAFETY: within the caller's bounds (q0 + nv·L ≤ ⌈n/L⌉·L).
                        unsafe {
                            let (i, o) = (inp.add(q0), obuf.add(cb * FWD_R * ld + q0));
                            match nv {
                                1 => fwd_tile::<FWD_R, 1>(i, offs, w, b, o, ld),
                                2 => fwd_tile::<FWD_R, 2>(i, offs, w, b, o, ld),
                                3 => fwd_tile::<FWD_R, 3>(i, offs, w, b, o, ld),
                                _ => fwd_tile::<FWD_R, $vmax>(i, offs, w, b, o, ld),
                            }
                        }
                    }
                    q0 += nv * L;
                }
            }

            /// One channel-vector tile: for `t < T`, `v < V`,
            /// `out[t·os + v·L ..][..L] += Σ_k a[base[t] + offs[k]] · b[k·bs + v·L ..][..L]`.
            ///
            /// # Safety
            /// Every `a`, `b` and `out` position named above must be valid.
            #[inline]
            #[target_feature(enable = $feat)]
            unsafe fn pv_tile<const T: usize, const V: usize>(
                a: *const f32,
                base: &[usize; T],
                offs: &[usize],
                b: *const f32,
                bs: usize,
                out: *mut f32,
                os: usize,
            ) {
                let mut acc = [[$zero(); V]; T];
                for (t, at) in acc.iter_mut().enumerate() {
                    for (v, s) in at.iter_mut().enumerate() {
                        // SAFETY: see the function's contract.
                        *s = unsafe { $loadu(out.add(t * os + v * L)) };
                    }
                }
                let mut rows = [a; T];
                for (r, &o) in rows.iter_mut().zip(base) {
                    // SAFETY: see the function's contract.
                    *r = unsafe { a.add(o) };
                }
                for (k, &off) in offs.iter().enumerate() {
                    let mut bv = [$zero(); V];
                    for (v, x) in bv.iter_mut().enumerate() {
                        // SAFETY: see the function's contract.
                        *x = unsafe { $loadu(b.add(k * bs + v * L)) };
                    }
                    for (at, &r) in acc.iter_mut().zip(&rows) {
                        // SAFETY: see the function's contract.
                        let av = $splat(unsafe { *r.add(off) });
                        for (s, &x) in at.iter_mut().zip(&bv) {
                            *s = $fmadd(av, x, *s);
                        }
                    }
                }
                for (t, at) in acc.iter().enumerate() {
                    for (v, &s) in at.iter().enumerate() {
                        // SAFETY: see the function's contract.
                        unsafe { $storeu(out.add(t * os + v * L), s) };
                    }
                }
            }

            /// [`pv_tile`] with `tv = (T, V)` one of (8, 1), (6, 2), (6, 3), (4, 4) and the
            /// first `T` values of `base` (zeros past its end).
            ///
            /// # Safety
            /// As [`pv_tile`]'s.
            #[allow(clippy::too_many_arguments)]
            #[target_feature(enable = $feat)]
            pub(super) unsafe fn pv(
                tv: (usize, usize),
                a: *const f32,
                base: &[usize],
                offs: &[usize],
                b: *const f32,
                bs: usize,
                out: *mut f32,
                os: usize,
            ) {
                // SAFETY: forwarded contract.
                unsafe {
                    match tv {
                        (8, 1) => pv_tile::<8, 1>(a, &arr(base), offs, b, bs, out, os),
                        (6, 2) => pv_tile::<6, 2>(a, &arr(base), offs, b, bs, out, os),
                        (6, 3) => pv_tile::<6, 3>(a, &arr(base), offs, b, bs, out, os),
                        _ => pv_tile::<4, 4>(a, &arr(base), offs, b, bs, out, os),
                    }
                }
            }
        }
    };
}

direct_kernels!(
    avx512,
    "avx512f,fma",
    16,
    4,
    _mm512_setzero_ps,
    _mm512_set1_ps,
    _mm512_loadu_ps,
    _mm512_storeu_ps,
    _mm512_fmadd_ps
);
direct_kernels!(
    avx2,
    "avx2,fma",
    8,
    2,
    _mm256_setzero_ps,
    _mm256_set1_ps,
    _mm256_loadu_ps,
    _mm256_storeu_ps,
    _mm256_fmadd_ps
);

/// Copies input rows `r0 − ph .. r0 − ph + nb` of the image `img` starts with, `(Cin, H, W)`,
/// into `band`, zero-padded: `Cin` planes `bplane` apart of `nb` rows of `wp = W + 2·pw` values.
fn copy_band(img: &[f32], g: &Geom, r0: usize, nb: usize, (wp, bplane): (usize, usize), band: &mut [f32]) {
    let hw = g.in_plane();
    for (c, src) in img.chunks_exact(hw).take(g.cin).enumerate() {
        let plane = &mut band[c * bplane..c * bplane + nb * wp];
        for (br, dst) in plane.chunks_exact_mut(wp).enumerate() {
            match (r0 + br).checked_sub(g.ph).filter(|&iy| iy < g.h) {
                Some(iy) => {
                    dst[..g.pw].fill(0.0);
                    dst[g.pw..g.pw + g.w].copy_from_slice(&src[iy * g.w..(iy + 1) * g.w]);
                    dst[g.pw + g.w..].fill(0.0);
                }
                None => dst.fill(0.0),
            }
        }
    }
}

/// How a direct pass splits into units: bands of `rows` output rows of `images` consecutive
/// images (several images only when a band is a whole image).
#[derive(Clone, Copy, Debug)]
struct Units {
    rows: usize,
    images: usize,
    bands: usize,
    groups: usize,
}

/// One unit: `n` images from `bi`, output rows `oy0 .. oy0 + nr`.
#[derive(Clone, Copy, Debug)]
struct Unit {
    bi: usize,
    n: usize,
    oy0: usize,
    nr: usize,
}

impl Units {
    /// Units of about `target` values (`per_row` per output row of an image) whose input rows
    /// hold at most [`BAND_VALUES`], several whole images per unit when `stack` allows it; when
    /// the pass is parallel, at least two units per thread (so that a worker that wakes late
    /// still finds work).
    fn new(g: &Geom, per_row: usize, target: usize, parallel: bool, stack: bool) -> Self {
        let threads = rayon::current_num_threads();
        let in_row = g.cin * g.s * (g.w + 2 * g.pw);
        let mut bands = g.ho.div_ceil((target / per_row.max(1)).max(1));
        bands = bands.max((g.ho * in_row).div_ceil(BAND_VALUES));
        if parallel {
            bands = bands.max((2 * threads).div_ceil(g.b.max(1)));
        }
        let rows = g.ho.div_ceil(bands.min(g.ho));
        let bands = g.ho.div_ceil(rows);
        let mut images = 1;
        if stack && bands == 1 {
            images = (target / (g.ho * per_row).max(1)).min(BAND_VALUES / (g.ho * in_row).max(1));
            images = images.clamp(1, g.b.max(1));
            if parallel {
                images = images.min(g.b.div_ceil(2 * threads)).max(1);
            }
        }
        Self {
            rows,
            images,
            bands,
            groups: g.b.div_ceil(images),
        }
    }

    fn count(&self) -> usize {
        self.groups * self.bands
    }

    fn get(&self, g: &Geom, u: usize) -> Unit {
        let (bi, oy0) = ((u / self.bands) * self.images, (u % self.bands) * self.rows);
        Unit {
            bi,
            n: self.images.min(g.b - bi),
            oy0,
            nr: self.rows.min(g.ho - oy0),
        }
    }

    /// Output pixels of a unit, at most.
    fn pixels(&self, g: &Geom) -> usize {
        self.images * self.rows * g.wo
    }
}

/// Where a unit of the direct kernels reads its input: the images themselves (stride 1, no
/// padding), or a zero-padded copy of the unit's input rows, the images' rows one after the other
/// in each channel's plane (at strides above 1 the kernels' reads skip values, and a cold input
/// read in place that way is 2× slower than copied first).
#[derive(Clone, Copy, Debug)]
struct Source {
    /// The images are read in place.
    in_place: bool,
    /// Row length, plane length (between channels) and image stride of what is read.
    wp: usize,
    plane: usize,
    stride: usize,
    /// Scratch values for the copy (0 in place).
    len: usize,
}

impl Source {
    /// In place at stride 1 without padding, else a copy.
    fn new(g: &Geom, units: &Units) -> Self {
        if g.ph == 0 && g.pw == 0 && g.s == 1 {
            Self {
                in_place: true,
                wp: g.w,
                plane: g.in_plane(),
                stride: g.cin * g.in_plane(),
                len: 0,
            }
        } else {
            Self::copy(g, units)
        }
    }

    /// A copy.
    fn copy(g: &Geom, units: &Units) -> Self {
        let wp = g.w + 2 * g.pw;
        let stride = ((units.rows - 1) * g.s + g.kh) * wp;
        let plane = units.images * stride;
        Self {
            in_place: false,
            wp,
            plane,
            stride,
            len: g.cin * plane,
        }
    }

    /// The input of unit `u` of `x (B, Cin, H, W)`: a pointer to (padded) input row
    /// `oy0·s − ph` of its first image, copied into `band` when not in place.
    fn rows(&self, x: &[f32], g: &Geom, u: Unit, band: &mut [f32]) -> *const f32 {
        let img = g.cin * g.in_plane();
        if self.in_place {
            return x[u.bi * img + u.oy0 * g.s * g.w..].as_ptr();
        }
        for i in 0..u.n {
            let src = &x[(u.bi + i) * img..];
            let nb = (u.nr - 1) * g.s + g.kh;
            copy_band(
                src,
                g,
                u.oy0 * g.s,
                nb,
                (self.wp, self.plane),
                &mut band[i * self.stride..],
            );
        }
        band.as_ptr()
    }

    /// Offsets of the kernel taps `(c, u, v)`, in that order.
    fn taps(&self, g: &Geom) -> Vec<usize> {
        let mut offs = Vec::with_capacity(g.krows());
        for c in 0..g.cin {
            for u in 0..g.kh {
                for v in 0..g.kw {
                    offs.push(c * self.plane + u * self.wp + v);
                }
            }
        }
        offs
    }

    /// Offsets of the output pixels of unit `u` (image by image, row-major) from its first
    /// input row.
    fn pixels(&self, g: &Geom, u: Unit, out: &mut Vec<usize>) {
        out.clear();
        for i in 0..u.n {
            for r in 0..u.nr {
                let row = i * self.stride + r * g.s * self.wp;
                out.extend((0..g.wo).map(|ox| row + ox * g.s));
            }
        }
    }
}

/// `w (Cout, J)` transposed to `(J, cp)`, zero past `Cout`.
fn transpose_weight(w: &[f32], cout: usize, jn: usize, cp: usize) -> Vec<f32> {
    let mut wt = vec![0f32; jn * cp];
    for (co, row) in w.chunks_exact(jn).take(cout).enumerate() {
        for (j, &v) in row.iter().enumerate() {
            wt[j * cp + co] = v;
        }
    }
    wt
}

/// `bias` padded with zeros to `n` values.
fn padded_bias(bias: Option<&[f32]>, cout: usize, n: usize) -> Vec<f32> {
    let mut init = vec![0f32; n];
    if let Some(b) = bias {
        init[..cout].copy_from_slice(&b[..cout]);
    }
    init
}

/// How a direct forward pass computes its units.
enum FwdMode {
    /// Stride 1: vectors of output positions ([`Isa::fwd_core`]), units of one image. The
    /// input rows are read in `Wp = W + 2·pw` wide planes (the image itself when unpadded,
    /// else a zero-padded copy), output position `q = row·Wp + ox` reading
    /// `plane·c + u·Wp + v + q` (columns `ox ≥ Wo` are computed and dropped) into the output,
    /// or into a buffer of rows `ld` apart.
    Positions {
        /// `w` in blocks of [`FWD_R`] output channels, `[block][j][r]`, and the bias likewise.
        wpack: Vec<f32>,
        init: Vec<f32>,
        ld: usize,
        /// The copy used when reading in place could run past the input's end, and its taps.
        copy: Source,
        copy_offs: Vec<usize>,
    },
    /// Any stride: vectors of output channels ([`Isa::pv`]): each pixel's products summed
    /// over the taps into `cp` channels over the bias, then transposed into the output.
    Channels {
        /// `w` transposed, `(J, cp)`, and the bias padded to `cp`.
        wt: Vec<f32>,
        init: Vec<f32>,
        tv: (usize, usize),
        cp: usize,
    },
}

/// A direct forward pass (the forward convolution, or the stride-1 input gradient): the plan
/// shared by its units.
struct FwdPlan {
    g: Geom,
    isa: Isa,
    mode: FwdMode,
    units: Units,
    src: Source,
    offs: Vec<usize>,
    /// Scratch values per unit: the input copy (with slack), then the output buffer.
    in_len: usize,
    scratch: usize,
}

/// Whether the forward pass of `g` vectorises over output channels rather than positions:
/// strides above 1, and images too small for whole vectors of positions.
fn channel_vectors(g: &Geom) -> bool {
    g.s > 1 || g.out_plane() < 64
}

impl FwdPlan {
    /// The plan of vectors of output channels (`channels`; any stride) or of positions
    /// (stride 1).
    fn new(w: &[f32], bias: Option<&[f32]>, g: &Geom, isa: Isa, channels: bool) -> Self {
        let lanes = isa.lanes();
        let jn = g.krows();
        let parallel = direct_parallel(g.macs());
        if !channels && g.s == 1 {
            let wp = g.w + 2 * g.pw;
            let units = Units::new(g, wp, FWD_UNIT_POSITIONS, parallel, false);
            let cpad = g.cout.div_ceil(FWD_R) * FWD_R;
            let mut wpack = vec![0f32; cpad * jn];
            for (co, row) in w.chunks_exact(jn).take(g.cout).enumerate() {
                let (blk, r) = (co / FWD_R, co % FWD_R);
                for (j, &v) in row.iter().enumerate() {
                    wpack[(blk * jn + j) * FWD_R + r] = v;
                }
            }
            let ld = ((units.rows - 1) * wp + g.wo).div_ceil(lanes) * lanes;
            let (src, copy) = (Source::new(g, &units), Source::copy(g, &units));
            // The copy's last vector may read up to `lanes` values past it.
            let in_len = copy.len + lanes;
            return Self {
                g: *g,
                isa,
                offs: src.taps(g),
                mode: FwdMode::Positions {
                    wpack,
                    init: padded_bias(bias, g.cout, cpad),
                    ld,
                    copy_offs: copy.taps(g),
                    copy,
                },
                units,
                src,
                in_len,
                scratch: in_len + cpad * ld,
            };
        }
        let units = Units::new(g, g.wo, PIX_UNIT, parallel, true);
        let src = Source::new(g, &units);
        let (t, v, cp) = isa.pv_width(g.cout);
        let npix = units.pixels(g).div_ceil(t) * t;
        Self {
            g: *g,
            isa,
            offs: src.taps(g),
            mode: FwdMode::Channels {
                wt: transpose_weight(w, g.cout, jn, cp),
                init: padded_bias(bias, g.cout, cp),
                tv: (t, v),
                cp,
            },
            units,
            src,
            in_len: src.len,
            scratch: src.len + npix * cp,
        }
    }

    /// One unit of `x (B, Cin, H, W)`, written into `out (B, Cout, Ho, Wo)`.
    ///
    /// # Safety
    /// `self.isa` must be the CPU's; `out` must point to the `B·Cout·Ho·Wo` values of the
    /// output, of which the unit writes its own rows; `scratch` must hold `self.scratch`
    /// values and `pix` is scratch for pixel offsets.
    unsafe fn unit(&self, x: &[f32], unit: usize, scratch: &mut [f32], pix: &mut Vec<usize>, out: SyncPtr<f32>) {
        let g = &self.g;
        let u = self.units.get(g, unit);
        let (hw, plane) = (g.in_plane(), g.out_plane());
        let (band, obuf) = scratch.split_at_mut(self.in_len);
        let isa = self.isa;
        match &self.mode {
            FwdMode::Positions {
                wpack,
                init,
                ld,
                copy,
                copy_offs,
            } => {
                // Units of one image.
                let (bi, oy0, nr) = (u.bi, u.oy0, u.nr);
                let img = &x[bi * g.cin * hw..];
                let wp = g.w + 2 * g.pw;
                let n = (nr - 1) * wp + g.wo;
                let end = oy0 * g.w + n.div_ceil(isa.lanes()) * isa.lanes() + self.offs.last().copied().unwrap_or(0);
                let (inp, offs) = if self.src.in_place && end <= img.len() {
                    (img[oy0 * g.w..].as_ptr(), &self.offs)
                } else {
                    (copy.rows(x, g, u, band), copy_offs)
                };
                // Reads (all calls below): in place, they end before `img`'s end (checked); a
                // copy's end before c·plane + (kh − 1)·Wp + kw − 1 + ⌈n/L⌉·L ≤ cin·plane + L − 1
                // < in_len (as Wo + kw − 1 = Wp).
                let base = bi * g.cout * plane + oy0 * g.wo;
                // Without dropped columns (Wp = Wo), whole vectors of positions of the whole
                // blocks of FWD_R channels go straight into the output, the rest through `obuf`.
                let lanes = isa.lanes();
                let full = if wp == g.wo { g.cout / FWD_R } else { 0 };
                let direct = if full > 0 { n / lanes * lanes } else { 0 };
                let split = full * FWD_R * offs.len();
                let ((w_full, w_rest), (i_full, i_rest)) = (wpack.split_at(split), init.split_at(full * FWD_R));
                let ob = obuf.as_mut_ptr();
                // SAFETY: the first call writes positions oy0·Wo + q, q < direct ≤ n = nr·Wo,
                // of channels < full·FWD_R of image bi: this unit's own rows; the others write
                // `obuf` rows (cpad of them) of `ld` ≥ ⌈n/L⌉·L values.
                unsafe {
                    isa.fwd_core(inp, offs, w_full, i_full, direct, out.get().add(base), plane);
                    isa.fwd_core(inp.add(direct), offs, w_full, i_full, n - direct, ob, *ld);
                    isa.fwd_core(inp, offs, w_rest, i_rest, n, ob.add(full * FWD_R * ld), *ld);
                }
                for co in 0..g.cout {
                    // `obuf` holds positions `from ..` of the channel.
                    let from = if co < full * FWD_R { direct } else { 0 };
                    let src = &obuf[co * ld..(co + 1) * ld];
                    // Position q of the unit is output row q / Wp, column q % Wp.
                    let mut q = from;
                    while q < n {
                        let (r, ox) = (q / wp, q % wp);
                        let len = (g.wo - ox).min(n - q);
                        // SAFETY: row oy0 + r < Ho, columns ox .. ox + len ≤ Wo of channel co of
                        // image bi: this unit's.
                        unsafe {
                            let d = out.get().add(base + co * plane + r * g.wo + ox);
                            std::ptr::copy_nonoverlapping(src[q - from..].as_ptr(), d, len);
                        }
                        q = (r + 1) * wp;
                    }
                }
            }
            FwdMode::Channels { wt, init, tv, cp } => {
                let inp = self.src.rows(x, g, u, band);
                self.src.pixels(g, u, pix);
                let npix = pix.len();
                let (t, v) = *tv;
                let obuf = &mut obuf[..npix.div_ceil(t) * t * cp];
                for row in obuf.chunks_exact_mut(*cp) {
                    row.copy_from_slice(init);
                }
                for (pb, i0) in pix.chunks(t).zip((0..).step_by(t)) {
                    for cb in (0..*cp).step_by(v * isa.lanes()) {
                        // SAFETY: pixel p reads the input at pix[p] + offs[j], inside the
                        // images (in place: no padding) or the copied rows; padding pixels of
                        // the last block read at offs[j]. `wt` has J rows of cp values, `obuf`
                        // ⌈npix/T⌉·T rows of cp.
                        unsafe {
                            let o = obuf.as_mut_ptr().add(i0 * cp + cb);
                            isa.pv(*tv, inp, pb, &self.offs, wt[cb..].as_ptr(), *cp, o, *cp);
                        }
                    }
                }
                let per_image = u.nr * g.wo;
                for (i, rows) in obuf.chunks_exact(per_image * cp).take(u.n).enumerate() {
                    let base = (u.bi + i) * g.cout * plane + u.oy0 * g.wo;
                    for co in 0..g.cout {
                        // SAFETY: pixels oy0·Wo .. + nr·Wo of channel co of image bi + i: this
                        // unit's.
                        let dst =
                            unsafe { std::slice::from_raw_parts_mut(out.get().add(base + co * plane), per_image) };
                        for (d, row) in dst.iter_mut().zip(rows.chunks_exact(*cp)) {
                            *d = row[co];
                        }
                    }
                }
            }
        }
    }
}

/// The direct weight gradient: the plan shared by its units.
///
/// `gw[co][j] = Σ_pixels gy[co][pixel]·x[j][pixel]` for `j = (c, u, v)` by [`Isa::pv`],
/// accumulated transposed, `(J, cp)`: the unit's output gradient is copied pixel-major (`cp`
/// values per pixel, its vectors), and `x[j][pixel]` is broadcast from the input at
/// `taps[j] + pixel offset` (see [`Source`]).
struct WgradPlan {
    g: Geom,
    isa: Isa,
    units: Units,
    src: Source,
    /// Offsets of the `J` taps.
    taps: Vec<usize>,
    tv: (usize, usize),
    cp: usize,
    /// Scratch values per unit: the input copy, then the pixel-major gradient.
    scratch: usize,
}

impl WgradPlan {
    fn new(g: &Geom, isa: Isa) -> Self {
        let (t, v, cp) = isa.pv_width(g.cout);
        let units = Units::new(g, g.wo, PIX_UNIT, direct_parallel(g.macs()), true);
        let src = Source::new(g, &units);
        Self {
            g: *g,
            isa,
            units,
            taps: src.taps(g),
            src,
            tv: (t, v),
            cp,
            scratch: src.len + units.pixels(g) * cp,
        }
    }

    /// Length of a task's accumulator, `(J rounded up to T, cp)`.
    fn acc_len(&self) -> usize {
        self.g.krows().div_ceil(self.tv.0) * self.tv.0 * self.cp
    }

    /// Adds the products of unit `unit` into `acc`.
    ///
    /// # Safety
    /// `self.isa` must be the CPU's; `scratch` must hold `self.scratch` values (the gradient's
    /// channels past `Cout` are never written: they reach only accumulator columns that are
    /// dropped) and `pix` is scratch for pixel offsets.
    unsafe fn unit(
        &self,
        x: &[f32],
        gy: &[f32],
        unit: usize,
        scratch: &mut [f32],
        pix: &mut Vec<usize>,
        acc: &mut [f32],
    ) {
        let g = &self.g;
        let u = self.units.get(g, unit);
        let plane = g.out_plane();
        let (band, gt) = scratch.split_at_mut(self.src.len);
        let inp = self.src.rows(x, g, u, band);
        self.src.pixels(g, u, pix);
        let cp = self.cp;
        let per_image = u.nr * g.wo;
        for (i, gt) in gt.chunks_mut(per_image * cp).take(u.n).enumerate() {
            let grad = &gy[(u.bi + i) * g.cout * plane + u.oy0 * g.wo..];
            for co in 0..g.cout {
                for (d, &s) in gt[co..]
                    .iter_mut()
                    .step_by(cp)
                    .zip(&grad[co * plane..co * plane + per_image])
                {
                    *d = s;
                }
            }
        }
        let (t, v) = self.tv;
        let isa = self.isa;
        for (taps, j0) in self.taps.chunks(t).zip((0..).step_by(t)) {
            for cb in (0..cp).step_by(v * isa.lanes()) {
                // SAFETY: tap j of pixel p reads the input at taps[j] + pix[p], inside the
                // images (in place: no padding) or the copied rows; padding rows of the last
                // block read at pix[p]. `gt` holds pix.len() rows of cp values, `acc` J rounded
                // up to T rows.
                unsafe {
                    let o = acc.as_mut_ptr().add(j0 * cp + cb);
                    isa.pv((t, v), inp, taps, pix, gt[cb..].as_ptr(), cp, o, cp);
                }
            }
        }
    }
}

/// The direct input gradient at strides above 1, per image: blocks of output pixels, each
/// pixel's `cols[j] = Σ_co gy[co][pixel]·w[co][j]` by [`Isa::pv`] (the weight's rows padded to
/// `jp`), then added into the image's planes (the adjoint of reading `x` at the taps).
struct Col2imPlan {
    g: Geom,
    isa: Isa,
    /// `w` with rows padded to `jp` values.
    wp: Vec<f32>,
    jp: usize,
    tv: (usize, usize),
    /// Offsets of the output gradient's channels.
    offs: Vec<usize>,
    scratch: usize,
}

impl Col2imPlan {
    fn new(w: &[f32], g: &Geom, isa: Isa) -> Self {
        let jn = g.krows();
        let (t, v, jp) = isa.pv_width(jn);
        let mut wp = vec![0f32; g.cout * jp];
        for (dst, src) in wp.chunks_exact_mut(jp).zip(w.chunks_exact(jn)) {
            dst[..jn].copy_from_slice(src);
        }
        let block = COL2IM_PIXELS.div_ceil(t) * t;
        Self {
            g: *g,
            isa,
            wp,
            jp,
            tv: (t, v),
            offs: (0..g.cout).map(|co| co * g.out_plane()).collect(),
            scratch: block * jp,
        }
    }

    /// Image `bi`'s input gradient, added into `out` (its `(Cin, H, W)` planes).
    ///
    /// # Safety
    /// `self.isa` must be the CPU's; `scratch` must hold `self.scratch` values.
    unsafe fn image(&self, gy: &[f32], bi: usize, scratch: &mut [f32], out: &mut [f32]) {
        let g = &self.g;
        let plane = g.out_plane();
        let grad = &gy[bi * g.cout * plane..(bi + 1) * g.cout * plane];
        let (t, v) = self.tv;
        let jp = self.jp;
        let isa = self.isa;
        let block = scratch.len() / jp;
        let mut pixels = [0usize; 8];
        for p0 in (0..plane).step_by(block) {
            let n = block.min(plane - p0);
            let cols = &mut scratch[..n.div_ceil(t) * t * jp];
            cols.fill(0.0);
            for i0 in (0..n).step_by(t) {
                for (d, p) in pixels.iter_mut().zip(p0 + i0..p0 + n) {
                    *d = p;
                }
                let pb = &pixels[..t.min(n - i0)];
                for jb in (0..jp).step_by(v * isa.lanes()) {
                    // SAFETY: pixel p reads grad[co·plane + p], p < plane (padding pixels of
                    // the last block read pixel 0); `wp` holds Cout rows of jp values, `cols`
                    // ⌈n/T⌉·T rows of jp.
                    unsafe {
                        let o = cols.as_mut_ptr().add(i0 * jp + jb);
                        isa.pv((t, v), grad.as_ptr(), pb, &self.offs, self.wp[jb..].as_ptr(), jp, o, jp);
                    }
                }
            }
            col2im_pixels(cols, jp, g, p0, n, out);
        }
    }
}

/// Adds pixel-major columns (`ld` values for each of the output pixels `p0 .. p0 + n` of one
/// image, the first `C·kh·kw` in `(c, u, v)` order) into the image's planes `out (C, H, W)`
/// at the positions the forward pass reads them from.
fn col2im_pixels(cols: &[f32], ld: usize, g: &Geom, p0: usize, n: usize, out: &mut [f32]) {
    // A few channels at a time, so that the writes stay within a few planes.
    const CHANNELS: usize = 8;
    let (hw, taps) = (g.in_plane(), g.taps());
    for (cb, planes) in out.chunks_mut(CHANNELS * hw).take(g.cin.div_ceil(CHANNELS)).enumerate() {
        for (i, col) in cols.chunks_exact(ld).take(n).enumerate() {
            let (oy, ox) = ((p0 + i) / g.wo, (p0 + i) % g.wo);
            let vals = &col[cb * CHANNELS * taps..];
            for (plane, vals) in planes.chunks_exact_mut(hw).zip(vals.chunks_exact(taps)) {
                for (u, row) in vals.chunks_exact(g.kw).enumerate() {
                    let Some(iy) = (oy * g.s + u).checked_sub(g.ph).filter(|&y| y < g.h) else {
                        continue;
                    };
                    let line = &mut plane[iy * g.w..(iy + 1) * g.w];
                    for (v, &val) in row.iter().enumerate() {
                        if let Some(ix) = (ox * g.s + v).checked_sub(g.pw).filter(|&x| x < g.w) {
                            line[ix] += val;
                        }
                    }
                }
            }
        }
    }
}

thread_local! {
    /// Scratch of the direct kernels on this thread, kept from call to call.
    static SCRATCH: std::cell::Cell<(Vec<f32>, Vec<usize>)> = const { std::cell::Cell::new((Vec::new(), Vec::new())) };
}

/// Runs `f` on `len` values of this thread's scratch (whatever values earlier calls left: the
/// kernels write what they read, except padding whose results they drop) and its scratch of
/// offsets.
fn with_scratch<R>(len: usize, f: impl FnOnce(&mut [f32], &mut Vec<usize>) -> R) -> R {
    // Taken out of the cell, so that a nested call (a rayon task stolen meanwhile) has its own.
    let (mut buf, mut offs) = SCRATCH.with(std::cell::Cell::take);
    if buf.len() < len {
        buf.resize(len, 0.0);
    }
    let out = f(&mut buf[..len], &mut offs);
    SCRATCH.with(|s| s.set((buf, offs)));
    out
}

/// Whether a direct pass of `macs` multiply-adds runs in parallel (else on the calling thread).
fn direct_parallel(macs: usize) -> bool {
    macs >= PAR_MIN_MACS && rayon::current_num_threads() > 1
}

/// The direct forward convolution (also the stride-1 input gradient, on the flipped weight):
/// `x (B, Cin, H, W)`, `w (Cout, Cin, kh, kw)`, `bias (Cout)` → `(B, Cout, Ho, Wo)`.
fn direct_forward(x: &[f32], w: &[f32], bias: Option<&[f32]>, g: &Geom, isa: Isa) -> Vec<f32> {
    direct_forward_with(x, w, bias, g, isa, channel_vectors(g))
}

/// [`direct_forward`] with vectors of output channels (`channels`) or of positions (stride 1).
fn direct_forward_with(x: &[f32], w: &[f32], bias: Option<&[f32]>, g: &Geom, isa: Isa, channels: bool) -> Vec<f32> {
    let plan = FwdPlan::new(w, bias, g, isa, channels);
    let len = g.b * g.cout * g.out_plane();
    let mut out: Vec<f32> = Vec::with_capacity(len);
    let dst = SyncPtr(out.as_mut_ptr());
    let run = |unit: usize, scratch: &mut [f32], pix: &mut Vec<usize>| {
        // SAFETY: `isa` is the CPU's; each unit writes its own rows of `out`'s `len` values
        // (its capacity), all units together every value.
        unsafe { plan.unit(x, unit, scratch, pix, dst) }
    };
    if direct_parallel(plan.g.macs()) {
        (0..plan.units.count())
            .into_par_iter()
            .for_each(|u| with_scratch(plan.scratch, |s, p| run(u, s, p)));
    } else {
        with_scratch(plan.scratch, |s, p| (0..plan.units.count()).for_each(|u| run(u, s, p)));
    }
    // SAFETY: every one of the `len` values was written above.
    unsafe { out.set_len(len) };
    out
}

/// The direct weight gradient: `x (B, Cin, H, W)`, `gy (B, Cout, Ho, Wo)` → `(Cout, Cin, kh, kw)`.
fn direct_weight_grad(x: &[f32], gy: &[f32], g: &Geom, isa: Isa) -> Vec<f32> {
    let plan = WgradPlan::new(g, isa);
    let acc_len = plan.acc_len();
    let add = |mut acc: Vec<f32>, unit: usize| {
        // SAFETY: `isa` is the CPU's.
        with_scratch(plan.scratch, |s, p| unsafe { plan.unit(x, gy, unit, s, p, &mut acc) });
        acc
    };
    let total = if direct_parallel(plan.g.macs()) {
        // One task per unit (rayon folds them into one accumulator per thread it splits into).
        (0..plan.units.count())
            .into_par_iter()
            .fold(|| vec![0f32; acc_len], add)
            .reduce(
                || vec![0f32; acc_len],
                |mut a, b| {
                    a.iter_mut().zip(&b).for_each(|(a, &b)| *a += b);
                    a
                },
            )
    } else {
        (0..plan.units.count()).fold(vec![0f32; acc_len], add)
    };
    // (J, cp) → (Cout, J).
    let jn = g.krows();
    let mut out = vec![0f32; g.cout * jn];
    for (j, row) in total.chunks_exact(plan.cp).take(jn).enumerate() {
        for (co, &v) in row[..g.cout].iter().enumerate() {
            out[co * jn + j] = v;
        }
    }
    out
}

/// The direct input gradient at strides above 1: `gy (B, Cout, Ho, Wo)`,
/// `w (Cout, Cin, kh, kw)` → `(B, Cin, H, W)`, images in parallel.
fn direct_col2im(gy: &[f32], w: &[f32], g: &Geom, isa: Isa) -> Vec<f32> {
    let plan = Col2imPlan::new(w, g, isa);
    let img_len = g.cin * g.in_plane();
    let mut out = vec![0f32; g.b * img_len];
    let run = |bi: usize, img: &mut [f32], scratch: &mut [f32]| {
        // SAFETY: `isa` is the CPU's.
        unsafe { plan.image(gy, bi, scratch, img) }
    };
    if direct_parallel(plan.g.macs()) {
        out.par_chunks_mut(img_len)
            .enumerate()
            .for_each(|(bi, img)| with_scratch(plan.scratch, |s, _| run(bi, img, s)));
    } else {
        with_scratch(plan.scratch, |s, _| {
            for (bi, img) in out.chunks_exact_mut(img_len).enumerate() {
                run(bi, img, s);
            }
        });
    }
    out
}

/// The forward convolution op, `(x, w[, b]) → y` (the no-bias form is its [`CustomOp2`]).
#[derive(Debug)]
struct Conv2dOp {
    stride: usize,
    padding: usize,
    /// An output computed before the op was applied (the Winograd path), taken by the forward.
    precomputed: Mutex<Option<Tensor>>,
}

impl Conv2dOp {
    fn new(stride: usize, padding: usize) -> Self {
        Self {
            stride,
            padding,
            precomputed: Mutex::new(None),
        }
    }

    fn lock(&self) -> Result<std::sync::MutexGuard<'_, Option<Tensor>>> {
        match self.precomputed.lock() {
            Ok(guard) => Ok(guard),
            Err(_) => candle_core::bail!("conv2d: poisoned lock"),
        }
    }

    fn set_precomputed(&self, y: Tensor) -> Result<()> {
        *self.lock()? = Some(y);
        Ok(())
    }

    fn cpu_forward(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bias: Option<(&CpuStorage, &Layout)>,
    ) -> Result<(CpuStorage, Shape)> {
        let g = conv_geom(
            xl.shape(),
            wl.shape(),
            bias.map(|(_, l)| l.shape()),
            self.stride,
            self.padding,
        )?;
        let shape = Shape::from_dims(&g.out_dims());
        if let Some(y) = self.lock()?.take() {
            if y.dims() != shape.dims() || y.dtype() != DType::F32 || xs.dtype() != DType::F32 {
                candle_core::bail!("conv2d: precomputed output {:?} for {shape:?}", y.shape());
            }
            return Ok((CpuStorage::F32(parallel_copy(&y)?), shape));
        }
        let _t = crate::profile::span("conv2d (training)");
        fn run<T: Float>(
            xs: &CpuStorage,
            xl: &Layout,
            ws: &CpuStorage,
            wl: &Layout,
            bias: Option<(&CpuStorage, &Layout)>,
            g: &Geom,
        ) -> Result<CpuStorage> {
            let x = data::<T>(xs, xl, "input")?;
            let w = data::<T>(ws, wl, "weight")?;
            let b = bias.map(|(s, l)| data::<T>(s, l, "bias")).transpose()?;
            Ok(T::to_cpu_storage_owned(T::forward(x, w, b, g)))
        }
        let out = match xs.dtype() {
            DType::F32 => run::<f32>(xs, xl, ws, wl, bias, &g)?,
            DType::F64 => run::<f64>(xs, xl, ws, wl, bias, &g)?,
            dt => candle_core::bail!("conv2d kernel: unsupported dtype {dt:?}"),
        };
        Ok((out, shape))
    }

    /// Gradients of `x`, `w` and `b` (each only if it tracks one).
    fn grads(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: Option<&Tensor>,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let (_, _, h, wd) = x.dims4()?;
        let (_, _, kh, kw) = w.dims4()?;
        let grad_x = if x.track_op() {
            Some(input_grad(&grad, w, self.stride, self.padding, (h, wd))?)
        } else {
            None
        };
        let grad_w = if w.track_op() {
            let op = WeightGradOp {
                stride: self.stride,
                padding: self.padding,
                kh,
                kw,
            };
            Some(x.apply_op2_no_bwd(&grad, &op)?)
        } else {
            None
        };
        let grad_b = match b {
            Some(b) if b.track_op() => Some(bias_grad(&grad)?),
            _ => None,
        };
        Ok((grad_x, grad_w, grad_b))
    }
}

/// The values of a contiguous f32 CPU tensor, copied in parallel.
fn parallel_copy(y: &Tensor) -> Result<Vec<f32>> {
    const CHUNK: usize = 1 << 16;
    let (storage, layout) = y.storage_and_layout();
    let src = crate::fused::storage_slice(&storage, layout, "conv2d output")?;
    let mut out = vec![0f32; src.len()];
    out.par_chunks_mut(CHUNK)
        .zip(src.par_chunks(CHUNK))
        .for_each(|(d, s)| d.copy_from_slice(s));
    Ok(out)
}

/// `Σ_{b,i,j} grad[b, o, i, j]`, reducing the contiguous last dim first (candle's strided
/// multi-dim sum is much slower).
fn bias_grad(grad: &Tensor) -> Result<Tensor> {
    let _t = crate::profile::span("conv2d bias gradient");
    let (b, c, h, w) = grad.dims4()?;
    grad.reshape((b, c, h * w))?.sum(2)?.sum(0)
}

/// The input gradient of `conv2d` with `stride`, `padding` and an `(h, w)` input, from
/// `grad (B, Cout, Ho, Wo)` and `w (Cout, Cin, kh, kw)`.
fn input_grad(grad: &Tensor, w: &Tensor, stride: usize, padding: usize, (h, wd): (usize, usize)) -> Result<Tensor> {
    let (cout, cin, kh, kw) = w.dims4()?;
    let g = Geom::new(grad.dim(0)?, cin, (h, wd), cout, (kh, kw), stride, (padding, padding))?;
    if grad.dtype() == DType::F32 && winograd_fits(&g, cout, cin) {
        let flipped = flip_weight(&w.flatten_all()?.to_vec1::<f32>()?, cout, cin, kh, kw);
        let flipped = Tensor::from_vec(flipped, (cin, cout, kh, kw), w.device())?;
        let epi = Epilogue {
            bias: None,
            residual: None,
            act: Act::None,
        };
        let wt = WinogradWeight::new(&flipped)?;
        return winograd::conv3x3_winograd(grad, &wt, false, &epi, winograd::block_tiles(cout, cin));
    }
    let op = InputGradOp {
        stride,
        padding,
        h,
        w: wd,
    };
    grad.apply_op2_no_bwd(w, &op)
}

impl CustomOp3 for Conv2dOp {
    fn name(&self) -> &'static str {
        "pixl-conv2d"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.cpu_forward(s1, l1, s2, l2, Some((s3, l3)))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        self.grads(x, w, Some(b), grad)
    }
}

impl CustomOp2 for Conv2dOp {
    fn name(&self) -> &'static str {
        "pixl-conv2d-nobias"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        self.cpu_forward(s1, l1, s2, l2, None)
    }

    fn bwd(&self, x: &Tensor, w: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (gx, gw, _) = self.grads(x, w, None, grad)?;
        Ok((gx, gw))
    }
}

/// The input-gradient kernel, `(grad_y, w) → grad_x (B, Cin, h, w)`.
#[derive(Clone, Copy, Debug)]
struct InputGradOp {
    stride: usize,
    padding: usize,
    h: usize,
    w: usize,
}

impl CustomOp2 for InputGradOp {
    fn name(&self) -> &'static str {
        "pixl-conv2d-input-grad"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let _t = crate::profile::span("conv2d input gradient");
        let (b, cout, ho, wo) = l1.shape().dims4()?;
        let (wco, cin, kh, kw) = l2.shape().dims4()?;
        let g = Geom::new(
            b,
            cin,
            (self.h, self.w),
            wco,
            (kh, kw),
            self.stride,
            (self.padding, self.padding),
        )?;
        if (cout, ho, wo) != (wco, g.ho, g.wo) {
            candle_core::bail!(
                "conv2d input gradient: grad {:?} does not match weight {:?} and a {}x{} input",
                l1.shape(),
                l2.shape(),
                self.h,
                self.w
            );
        }
        fn run<T: Float>(s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout, g: &Geom) -> Result<CpuStorage> {
            let gy = data::<T>(s1, l1, "grad")?;
            let w = data::<T>(s2, l2, "weight")?;
            Ok(T::to_cpu_storage_owned(T::input_grad(gy, w, g)?))
        }
        let out = match s1.dtype() {
            DType::F32 => run::<f32>(s1, l1, s2, l2, &g)?,
            DType::F64 => run::<f64>(s1, l1, s2, l2, &g)?,
            dt => candle_core::bail!("conv2d input gradient: unsupported dtype {dt:?}"),
        };
        Ok((out, Shape::from_dims(&[b, cin, self.h, self.w])))
    }
}

/// The weight-gradient kernel, `(x, grad_y) → grad_w (Cout, Cin, kh, kw)`.
#[derive(Clone, Copy, Debug)]
struct WeightGradOp {
    stride: usize,
    padding: usize,
    kh: usize,
    kw: usize,
}

impl CustomOp2 for WeightGradOp {
    fn name(&self) -> &'static str {
        "pixl-conv2d-weight-grad"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        let _t = crate::profile::span("conv2d weight gradient");
        let (b, cin, h, w) = l1.shape().dims4()?;
        let (gb, cout, ho, wo) = l2.shape().dims4()?;
        let g = Geom::new(
            b,
            cin,
            (h, w),
            cout,
            (self.kh, self.kw),
            self.stride,
            (self.padding, self.padding),
        )?;
        if (gb, ho, wo) != (b, g.ho, g.wo) {
            candle_core::bail!(
                "conv2d weight gradient: grad {:?} does not match input {:?}",
                l2.shape(),
                l1.shape()
            );
        }
        fn run<T: Float>(s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout, g: &Geom) -> Result<CpuStorage> {
            let x = data::<T>(s1, l1, "input")?;
            let gy = data::<T>(s2, l2, "grad")?;
            Ok(T::to_cpu_storage_owned(T::weight_grad(x, gy, g)))
        }
        let out = match s1.dtype() {
            DType::F32 => run::<f32>(s1, l1, s2, l2, &g)?,
            DType::F64 => run::<f64>(s1, l1, s2, l2, &g)?,
            dt => candle_core::bail!("conv2d weight gradient: unsupported dtype {dt:?}"),
        };
        Ok((out, Shape::from_dims(&[cout, cin, self.kh, self.kw])))
    }
}

/// The transposed convolution op, `(x, w[, b]) → y` (the no-bias form is its [`CustomOp2`]).
#[derive(Clone, Copy, Debug)]
struct ConvTransposeOp;

impl ConvTransposeOp {
    fn cpu_forward(
        &self,
        xs: &CpuStorage,
        xl: &Layout,
        ws: &CpuStorage,
        wl: &Layout,
        bias: Option<(&CpuStorage, &Layout)>,
    ) -> Result<(CpuStorage, Shape)> {
        let _t = crate::profile::span("conv transpose (training)");
        let g = transpose_geom(xl.shape(), wl.shape(), bias.map(|(_, l)| l.shape()))?;
        fn run<T: Float>(
            xs: &CpuStorage,
            xl: &Layout,
            ws: &CpuStorage,
            wl: &Layout,
            bias: Option<(&CpuStorage, &Layout)>,
            g: &Geom,
        ) -> Result<CpuStorage> {
            let x = data::<T>(xs, xl, "input")?;
            let w = data::<T>(ws, wl, "weight")?;
            let b = bias.map(|(s, l)| data::<T>(s, l, "bias")).transpose()?;
            Ok(T::to_cpu_storage_owned(col2im_conv(x, w, b, g)))
        }
        let out = match xs.dtype() {
            DType::F32 => run::<f32>(xs, xl, ws, wl, bias, &g)?,
            DType::F64 => run::<f64>(xs, xl, ws, wl, bias, &g)?,
            dt => candle_core::bail!("conv transpose kernel: unsupported dtype {dt:?}"),
        };
        Ok((out, Shape::from_dims(&[g.b, g.cin, g.h, g.w])))
    }

    fn grads(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: Option<&Tensor>,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let grad = grad.contiguous()?;
        let k = w.dim(2)?;
        // y = conv2dᵀ(x) for the stride-k convolution whose weight is `w`: its input gradient is
        // that convolution of `grad`, its weight gradient the convolution's weight gradient with
        // `grad` as the input and `x` as the output gradient.
        let grad_x = if x.track_op() {
            Some(grad.apply_op2_no_bwd(w, &Conv2dOp::new(k, 0))?)
        } else {
            None
        };
        let grad_w = if w.track_op() {
            let op = WeightGradOp {
                stride: k,
                padding: 0,
                kh: k,
                kw: k,
            };
            Some(grad.apply_op2_no_bwd(x, &op)?)
        } else {
            None
        };
        let grad_b = match b {
            Some(b) if b.track_op() => Some(bias_grad(&grad)?),
            _ => None,
        };
        Ok((grad_x, grad_w, grad_b))
    }
}

impl CustomOp3 for ConvTransposeOp {
    fn name(&self) -> &'static str {
        "pixl-conv-transpose-k"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        self.cpu_forward(s1, l1, s2, l2, Some((s3, l3)))
    }

    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        self.grads(x, w, Some(b), grad)
    }
}

impl CustomOp2 for ConvTransposeOp {
    fn name(&self) -> &'static str {
        "pixl-conv-transpose-k-nobias"
    }

    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        self.cpu_forward(s1, l1, s2, l2, None)
    }

    fn bwd(&self, x: &Tensor, w: &Tensor, _res: &Tensor, grad: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let (gx, gw, _) = self.grads(x, w, None, grad)?;
        Ok((gx, gw))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{assert_gradients, uniform};
    use candle_core::{Device, Var};

    /// A convolution's shape in the tests: batch, channels, image, kernel, stride, padding.
    #[derive(Clone, Copy, Debug)]
    struct Case {
        b: usize,
        cin: usize,
        cout: usize,
        h: usize,
        w: usize,
        kh: usize,
        kw: usize,
        s: usize,
        p: usize,
    }

    const fn case(
        b: usize,
        cin: usize,
        cout: usize,
        (h, w): (usize, usize),
        (kh, kw): (usize, usize),
        s: usize,
        p: usize,
    ) -> Case {
        Case {
            b,
            cin,
            cout,
            h,
            w,
            kh,
            kw,
            s,
            p,
        }
    }

    impl Case {
        fn out(&self) -> (usize, usize) {
            (
                (self.h + 2 * self.p - self.kh) / self.s + 1,
                (self.w + 2 * self.p - self.kw) / self.s + 1,
            )
        }
    }

    /// Naive f64 convolution and its gradients for the loss `Σ y ⊙ r`:
    /// `(y, grad_x, grad_w, grad_b)`.
    fn naive_conv(c: &Case, x: &[f64], w: &[f64], bias: &[f64], r: &[f64]) -> [Vec<f64>; 4] {
        let (ho, wo) = c.out();
        let mut y = vec![0.0; c.b * c.cout * ho * wo];
        let mut gx = vec![0.0; x.len()];
        let mut gw = vec![0.0; w.len()];
        let mut gb = vec![0.0; c.cout];
        for b in 0..c.b {
            for o in 0..c.cout {
                for i in 0..ho {
                    for j in 0..wo {
                        let yi = ((b * c.cout + o) * ho + i) * wo + j;
                        let mut acc = bias[o];
                        for ci in 0..c.cin {
                            for u in 0..c.kh {
                                for v in 0..c.kw {
                                    let (iy, ix) = (
                                        (i * c.s + u) as isize - c.p as isize,
                                        (j * c.s + v) as isize - c.p as isize,
                                    );
                                    if iy < 0 || ix < 0 || iy >= c.h as isize || ix >= c.w as isize {
                                        continue;
                                    }
                                    let xi = ((b * c.cin + ci) * c.h + iy as usize) * c.w + ix as usize;
                                    let wi = ((o * c.cin + ci) * c.kh + u) * c.kw + v;
                                    acc += w[wi] * x[xi];
                                    gx[xi] += w[wi] * r[yi];
                                    gw[wi] += x[xi] * r[yi];
                                }
                            }
                        }
                        y[yi] = acc;
                        gb[o] += r[yi];
                    }
                }
            }
        }
        [y, gx, gw, gb]
    }

    /// Naive f64 `ConvTranspose2d(stride = k)` and its gradients for the loss `Σ y ⊙ r`, with
    /// `x (B, Cin, H, W)`, `w (Cin, Cout, k, k)`: `(y, grad_x, grad_w, grad_b)`.
    #[allow(clippy::too_many_arguments)]
    fn naive_transpose(
        (b_n, cin, cout, h, w_n, k): (usize, usize, usize, usize, usize, usize),
        x: &[f64],
        w: &[f64],
        bias: &[f64],
        r: &[f64],
    ) -> [Vec<f64>; 4] {
        let (ho, wo) = (k * h, k * w_n);
        let mut y = vec![0.0; b_n * cout * ho * wo];
        let mut gx = vec![0.0; x.len()];
        let mut gw = vec![0.0; w.len()];
        let mut gb = vec![0.0; cout];
        for b in 0..b_n {
            for o in 0..cout {
                for oy in 0..ho {
                    for ox in 0..wo {
                        let yi = ((b * cout + o) * ho + oy) * wo + ox;
                        let (i, u, j, v) = (oy / k, oy % k, ox / k, ox % k);
                        let mut acc = bias[o];
                        for c in 0..cin {
                            let xi = ((b * cin + c) * h + i) * w_n + j;
                            let wi = ((c * cout + o) * k + u) * k + v;
                            acc += x[xi] * w[wi];
                            gx[xi] += w[wi] * r[yi];
                            gw[wi] += x[xi] * r[yi];
                        }
                        y[yi] = acc;
                        gb[o] += r[yi];
                    }
                }
            }
        }
        [y, gx, gw, gb]
    }

    fn values(t: &Tensor) -> Vec<f64> {
        t.to_dtype(DType::F64)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1::<f64>())
            .expect("tensor values")
    }

    /// `max |got − want| / max |want|` (absolute when `want` is all zero).
    fn rel_err(got: &[f64], want: &[f64]) -> f64 {
        assert_eq!(got.len(), want.len());
        let scale = want.iter().fold(0f64, |m, v| m.max(v.abs())).max(1e-12);
        let err = got.iter().zip(want).fold(0f64, |m, (a, b)| m.max((a - b).abs()));
        err / scale
    }

    fn check(name: &str, got: Option<&Tensor>, want: &[f64], tol: f64) {
        let got = got.unwrap_or_else(|| panic!("{name}: no gradient"));
        let e = rel_err(&values(got), want);
        assert!(e <= tol, "{name}: relative error {e:e} > {tol:e}");
    }

    /// Forward and the three gradients of [`conv2d`] against [`naive_conv`], in f32 and f64, with
    /// and without a bias; `x` given non-contiguous (a transposed view).
    fn check_conv(c: Case, tol_f32: f64) {
        check_conv_with(c, tol_f32, &[DType::F32, DType::F64], &[true, false]);
    }

    fn check_conv_with(c: Case, tol_f32: f64, dtypes: &[DType], biases: &[bool]) {
        let dev = Device::Cpu;
        let (ho, wo) = c.out();
        let seed = (c.cin * 131 + c.cout * 17 + c.h * 7 + c.kh * 3 + c.s) as u64;
        // x is stored (B, Cin, W, H) and handed over transposed: a non-contiguous view.
        let xt = uniform((c.b, c.cin, c.w, c.h), -1.0, 1.0, seed, &dev).expect("x");
        let w = uniform((c.cout, c.cin, c.kh, c.kw), -0.5, 0.5, seed + 1, &dev).expect("w");
        let bias = uniform(c.cout, -0.5, 0.5, seed + 2, &dev).expect("b");
        let r = uniform((c.b, c.cout, ho, wo), -1.0, 1.0, seed + 3, &dev).expect("r");
        let x = xt.transpose(2, 3).expect("transpose");
        assert!(c.h == 1 || c.w == 1 || !x.is_contiguous());
        for &dt in dtypes {
            let tol = if dt == DType::F32 { tol_f32 } else { 1e-10 };
            for &with_bias in biases {
                let name = format!("{c:?} {dt:?} bias {with_bias}");
                let zero = vec![0.0; c.cout];
                let bias_v = if with_bias { values(&bias) } else { zero };
                let [y_ref, gx_ref, gw_ref, gb_ref] = naive_conv(&c, &values(&x), &values(&w), &bias_v, &values(&r));
                let xv = Var::from_tensor(&xt.to_dtype(dt).expect("cast")).expect("var");
                let wv = Var::from_tensor(&w.to_dtype(dt).expect("cast")).expect("var");
                let bv = Var::from_tensor(&bias.to_dtype(dt).expect("cast")).expect("var");
                let xs = xv.as_tensor().transpose(2, 3).expect("transpose");
                let y = conv2d(&xs, wv.as_tensor(), with_bias.then(|| bv.as_tensor()), c.s, c.p).expect("conv2d");
                assert_eq!(y.dims(), [c.b, c.cout, ho, wo], "{name}");
                assert_eq!(y.dtype(), dt);
                check(&format!("{name}: y"), Some(&y), &y_ref, tol);
                let loss = (&y * r.to_dtype(dt).expect("cast"))
                    .expect("mul")
                    .sum_all()
                    .expect("sum");
                let grads = loss.backward().expect("backward");
                let gx = grads.get(xv.as_tensor()).map(|g| g.transpose(2, 3).expect("transpose"));
                check(&format!("{name}: grad x"), gx.as_ref(), &gx_ref, tol);
                check(&format!("{name}: grad w"), grads.get(wv.as_tensor()), &gw_ref, tol);
                if with_bias {
                    check(&format!("{name}: grad b"), grads.get(bv.as_tensor()), &gb_ref, tol);
                } else {
                    assert!(grads.get(bv.as_tensor()).is_none());
                }
            }
        }
    }

    #[test]
    fn conv_3x3_matches_naive() {
        check_conv(case(2, 3, 5, (7, 9), (3, 3), 1, 1), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (3, 3), 2, 1), 1e-5);
        check_conv(case(2, 3, 5, (8, 6), (3, 3), 2, 1), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (3, 3), 1, 0), 1e-5);
        check_conv(case(1, 3, 5, (7, 9), (3, 3), 3, 2), 1e-5);
        check_conv(case(2, 3, 5, (1, 1), (3, 3), 1, 1), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (3, 2), 1, 1), 1e-5);
    }

    #[test]
    fn conv_1x1_2x2_4x4_match_naive() {
        check_conv(case(2, 3, 5, (7, 9), (1, 1), 1, 0), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (1, 1), 2, 0), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (1, 1), 1, 1), 1e-5);
        check_conv(case(2, 3, 5, (8, 6), (2, 2), 2, 0), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (2, 2), 2, 0), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (2, 2), 1, 1), 1e-5);
        check_conv(case(2, 3, 5, (8, 12), (4, 4), 4, 0), 1e-5);
        check_conv(case(2, 3, 5, (9, 7), (4, 4), 4, 0), 1e-5);
        check_conv(case(2, 3, 5, (7, 9), (4, 4), 2, 1), 1e-5);
    }

    /// Images of several tiles (tiles straddling output rows, several weight-gradient tiles,
    /// several col2im channel blocks).
    #[test]
    fn conv_multi_tile_matches_naive() {
        check_conv(case(2, 4, 6, (23, 25), (3, 3), 1, 1), 1e-5);
        check_conv(case(1, 40, 7, (33, 35), (3, 3), 2, 1), 1e-5);
        check_conv(case(2, 9, 12, (36, 40), (4, 4), 4, 0), 1e-5);
        check_conv(case(2, 20, 6, (30, 31), (1, 1), 1, 0), 1e-5);
        // 32 output channels: stride-1 weight-gradient units of 7, 7 and 6 rows.
        check_conv(case(1, 3, 32, (20, 40), (3, 3), 1, 1), 1e-5);
        check_conv(case(1, 3, 32, (22, 42), (3, 3), 1, 0), 1e-5);
        check_conv(case(2, 5, 32, (20, 40), (1, 1), 1, 0), 1e-5);
    }

    /// The Winograd path (3×3, stride 1, padding 1, 64×64, 64 channels in and out): forward and
    /// input gradient within Winograd's rounding.
    #[test]
    fn conv_winograd_path_matches_naive() {
        let c = case(1, 64, 64, (64, 64), (3, 3), 1, 1);
        let g = Geom::new(c.b, c.cin, (c.h, c.w), c.cout, (c.kh, c.kw), c.s, (c.p, c.p)).expect("geom");
        assert!(winograd_fits(&g, c.cin, c.cout) && winograd_fits(&g, c.cout, c.cin));
        check_conv_with(c, 1e-4, &[DType::F32], &[true]);
    }

    /// The instruction sets of the direct kernels this CPU has.
    fn isas() -> Vec<Isa> {
        let mut out = Vec::new();
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                out.push(Isa::Avx512);
            }
            if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                out.push(Isa::Avx2);
            }
        }
        out
    }

    /// The direct kernels against [`naive_conv`], for each instruction set the CPU has: the
    /// forward pass with vectors of output channels and (stride 1) of positions, the input
    /// gradient (the stride-1 forward pass on the flipped weight, both ways, or the
    /// channel-vector col2im) and the weight gradient.
    fn check_direct(c: Case) {
        let dev = Device::Cpu;
        let (ho, wo) = c.out();
        let seed = (c.cin * 31 + c.cout * 7 + c.h + c.kh * 5 + c.s * 3 + c.p) as u64;
        let vals = |t: Tensor| {
            t.to_dtype(DType::F32)
                .and_then(|t| t.flatten_all())
                .and_then(|t| t.to_vec1::<f32>())
                .expect("values")
        };
        let x = vals(uniform((c.b, c.cin, c.h, c.w), -1.0, 1.0, seed, &dev).expect("x"));
        let w = vals(uniform((c.cout, c.cin, c.kh, c.kw), -0.5, 0.5, seed + 1, &dev).expect("w"));
        let bias = vals(uniform(c.cout, -0.5, 0.5, seed + 2, &dev).expect("b"));
        let gy = vals(uniform((c.b, c.cout, ho, wo), -1.0, 1.0, seed + 3, &dev).expect("gy"));
        let f64s = |v: &[f32]| v.iter().map(|&v| f64::from(v)).collect::<Vec<_>>();
        let [y_ref, gx_ref, gw_ref, _] = naive_conv(&c, &f64s(&x), &f64s(&w), &f64s(&bias), &f64s(&gy));
        let g = Geom::new(c.b, c.cin, (c.h, c.w), c.cout, (c.kh, c.kw), c.s, (c.p, c.p)).expect("geom");
        let back = back_geom(&g).expect("back geom");
        let err = |got: &[f32], want: &[f64]| rel_err(&f64s(got), want);
        for isa in isas() {
            let name = format!("{c:?} {isa:?}");
            for channels in [true, false] {
                if !channels && c.s != 1 {
                    continue;
                }
                let y = direct_forward_with(&x, &w, Some(&bias), &g, isa, channels);
                let e = err(&y, &y_ref);
                assert!(e <= 1e-5, "{name} channels {channels}: y error {e:e}");
                if let Some(back) = back {
                    let flipped = flip_weight(&w, c.cout, c.cin, c.kh, c.kw);
                    let gx = direct_forward_with(&gy, &flipped, None, &back, isa, channels);
                    let e = err(&gx, &gx_ref);
                    assert!(e <= 1e-5, "{name} channels {channels}: grad x error {e:e}");
                }
            }
            if back.is_none() {
                let e = err(&direct_col2im(&gy, &w, &g, isa), &gx_ref);
                assert!(e <= 1e-5, "{name}: col2im grad x error {e:e}");
            }
            let e = err(&direct_weight_grad(&x, &gy, &g, isa), &gw_ref);
            assert!(e <= 1e-5, "{name}: grad w error {e:e}");
        }
    }

    /// The layers of the small model (batch 2) through the direct kernels.
    #[test]
    fn direct_kernels_match_naive_on_narrow_layers() {
        for c in [
            case(2, 16, 16, (96, 96), (3, 3), 1, 1),
            case(2, 32, 16, (48, 48), (3, 3), 1, 1),
            case(2, 32, 32, (24, 24), (3, 3), 1, 1),
            case(2, 32, 32, (12, 12), (3, 3), 1, 1),
            case(2, 32, 32, (6, 6), (3, 3), 1, 1),
            case(2, 32, 32, (3, 3), (3, 3), 1, 1),
            case(2, 16, 32, (24, 24), (3, 3), 1, 1),
            case(2, 64, 32, (6, 6), (3, 3), 1, 1),
            case(2, 64, 32, (3, 3), (3, 3), 1, 1),
            case(2, 64, 64, (6, 6), (3, 3), 2, 1),
            case(2, 16, 6, (96, 96), (1, 1), 1, 0),
            case(2, 32, 32, (48, 48), (1, 1), 1, 0),
            case(2, 32, 32, (6, 6), (1, 1), 1, 0),
            case(2, 64, 16, (6, 6), (1, 1), 1, 0),
            case(2, 9, 16, (96, 96), (4, 4), 4, 0),
            case(2, 16, 32, (24, 24), (2, 2), 2, 0),
            case(2, 64, 64, (6, 6), (2, 2), 2, 0),
            case(1, 3, 64, (96, 96), (16, 16), 16, 0),
        ] {
            check_direct(c);
        }
    }

    /// The direct kernels on odd shapes: channel counts off the register blocks, rectangular
    /// kernels and images, strides with padding, 1×1 convolutions with padding (col2im at
    /// stride 1) and unpadded ones whose last vector would run past the input, an empty batch.
    #[test]
    fn direct_kernels_match_naive_on_odd_shapes() {
        for c in [
            case(2, 3, 5, (7, 9), (3, 3), 1, 1),
            case(2, 3, 5, (7, 9), (3, 2), 1, 1),
            case(2, 3, 5, (9, 8), (2, 3), 2, 1),
            case(1, 5, 17, (11, 13), (3, 3), 3, 2),
            case(2, 3, 6, (13, 10), (1, 1), 1, 0),
            case(2, 3, 5, (7, 9), (1, 1), 1, 1),
            case(2, 4, 7, (23, 25), (3, 3), 1, 0),
            case(1, 3, 70, (9, 9), (3, 3), 1, 1),
            case(2, 20, 9, (40, 31), (1, 1), 1, 0),
            case(2, 5, 8, (13, 11), (1, 1), 1, 0),
            case(2, 3, 5, (1, 1), (3, 3), 1, 1),
            case(0, 3, 5, (7, 9), (3, 3), 1, 1),
        ] {
            check_direct(c);
        }
    }

    /// Gradients flow to the weight and bias only when the input does not track one.
    #[test]
    fn input_without_gradient() {
        let dev = Device::Cpu;
        for (s, k) in [(1, 3), (4, 4)] {
            let c = case(2, 3, 5, (8, 8), (k, k), s, if k == 3 { 1 } else { 0 });
            let (ho, wo) = c.out();
            let x = uniform((c.b, c.cin, c.h, c.w), -1.0, 1.0, 1, &dev).expect("x");
            let w = Var::from_tensor(&uniform((c.cout, c.cin, k, k), -0.5, 0.5, 2, &dev).expect("w")).expect("var");
            let b = Var::from_tensor(&uniform(c.cout, -0.5, 0.5, 3, &dev).expect("b")).expect("var");
            let r = uniform((c.b, c.cout, ho, wo), -1.0, 1.0, 4, &dev).expect("r");
            let y = conv2d(&x, w.as_tensor(), Some(b.as_tensor()), s, c.p).expect("conv2d");
            let grads = (&y * &r)
                .and_then(|t| t.sum_all())
                .and_then(|l| l.backward())
                .expect("backward");
            assert!(grads.get(&x).is_none());
            let [_, _, gw_ref, gb_ref] = naive_conv(
                &c,
                &values(&x),
                &values(w.as_tensor()),
                &values(b.as_tensor()),
                &values(&r),
            );
            check("grad w", grads.get(w.as_tensor()), &gw_ref, 1e-10);
            check("grad b", grads.get(b.as_tensor()), &gb_ref, 1e-10);
        }
    }

    /// Forward and gradients of [`conv_transpose_k`] against [`naive_transpose`].
    #[test]
    fn conv_transpose_matches_naive() {
        let dev = Device::Cpu;
        for (b_n, cin, cout, h, w_n, k) in [
            (2, 3, 5, 4, 5, 2),
            (2, 3, 5, 3, 4, 4),
            (1, 4, 3, 5, 3, 1),
            (2, 70, 9, 6, 7, 4),
        ] {
            let dims = (b_n, cin, cout, h, w_n, k);
            let xt = uniform((b_n, cin, w_n, h), -1.0, 1.0, 10, &dev).expect("x");
            let w = uniform((cin, cout, k, k), -0.5, 0.5, 11, &dev).expect("w");
            let bias = uniform(cout, -0.5, 0.5, 12, &dev).expect("b");
            let r = uniform((b_n, cout, k * h, k * w_n), -1.0, 1.0, 13, &dev).expect("r");
            for (dt, tol) in [(DType::F32, 1e-5), (DType::F64, 1e-10)] {
                for (with_bias, x_grad) in [(true, true), (false, true), (true, false)] {
                    let name = format!("{dims:?} {dt:?} bias {with_bias} x grad {x_grad}");
                    let x_src = xt.transpose(2, 3).expect("transpose");
                    let zero = vec![0.0; cout];
                    let bias_v = if with_bias { values(&bias) } else { zero };
                    let [y_ref, gx_ref, gw_ref, gb_ref] =
                        naive_transpose(dims, &values(&x_src), &values(&w), &bias_v, &values(&r));
                    let xv = Var::from_tensor(&xt.to_dtype(dt).expect("cast")).expect("var");
                    let x = if x_grad {
                        xv.as_tensor().transpose(2, 3).expect("transpose")
                    } else {
                        xv.as_tensor().detach().transpose(2, 3).expect("transpose")
                    };
                    let wv = Var::from_tensor(&w.to_dtype(dt).expect("cast")).expect("var");
                    let bv = Var::from_tensor(&bias.to_dtype(dt).expect("cast")).expect("var");
                    let y = conv_transpose_k(&x, wv.as_tensor(), with_bias.then(|| bv.as_tensor()))
                        .expect("conv transpose");
                    assert_eq!(y.dims(), [b_n, cout, k * h, k * w_n], "{name}");
                    check(&format!("{name}: y"), Some(&y), &y_ref, tol);
                    let loss = (&y * r.to_dtype(dt).expect("cast"))
                        .and_then(|t| t.sum_all())
                        .expect("loss");
                    let grads = loss.backward().expect("backward");
                    if x_grad {
                        let gx = grads.get(xv.as_tensor()).map(|g| g.transpose(2, 3).expect("transpose"));
                        check(&format!("{name}: grad x"), gx.as_ref(), &gx_ref, tol);
                    } else {
                        assert!(grads.get(xv.as_tensor()).is_none());
                    }
                    check(&format!("{name}: grad w"), grads.get(wv.as_tensor()), &gw_ref, tol);
                    if with_bias {
                        check(&format!("{name}: grad b"), grads.get(bv.as_tensor()), &gb_ref, tol);
                    }
                }
            }
        }
    }

    /// f64 finite differences through candle's autograd.
    #[test]
    fn finite_differences() {
        let dev = Device::Cpu;
        for (s, k, p) in [(1, 3, 1), (2, 3, 1), (2, 2, 0), (1, 1, 0)] {
            let x = uniform((2, 2, 5, 6), -1.0, 1.0, 20, &dev).expect("x");
            let w = uniform((3, 2, k, k), -0.5, 0.5, 21, &dev).expect("w");
            let b = uniform(3, -0.5, 0.5, 22, &dev).expect("b");
            let f = |t: &[Tensor]| conv2d(&t[0], &t[1], Some(&t[2]), s, p);
            assert_gradients(&format!("conv2d k{k} s{s} p{p}"), f, &[x, w, b], 1e-7).expect("gradients");
        }
        let x = uniform((2, 3, 3, 4), -1.0, 1.0, 23, &dev).expect("x");
        let w = uniform((3, 2, 2, 2), -0.5, 0.5, 24, &dev).expect("w");
        let b = uniform(2, -0.5, 0.5, 25, &dev).expect("b");
        let f = |t: &[Tensor]| conv_transpose_k(&t[0], &t[1], Some(&t[2]));
        assert_gradients("conv transpose k2", f, &[x, w, b], 1e-7).expect("gradients");
    }

    /// Same values and gradients as candle's own convolutions (the fallback).
    #[test]
    fn matches_candle() {
        let dev = Device::Cpu;
        let x = Var::from_tensor(&Tensor::randn(0f32, 1.0, (2, 6, 12, 10), &dev).expect("x")).expect("var");
        let w = Var::from_tensor(&Tensor::randn(0f32, 0.3, (4, 6, 3, 3), &dev).expect("w")).expect("var");
        let b = Var::from_tensor(&Tensor::randn(0f32, 0.3, 4, &dev).expect("b")).expect("var");
        for s in [1, 2] {
            let ours = conv2d(x.as_tensor(), w.as_tensor(), Some(b.as_tensor()), s, 1).expect("ours");
            let theirs = conv2d_candle(x.as_tensor(), w.as_tensor(), Some(b.as_tensor()), s, 1).expect("candle");
            let r = Tensor::randn(0f32, 1.0, ours.dims(), &dev).expect("r");
            let g1 = (&ours * &r)
                .and_then(|t| t.sum_all())
                .and_then(|l| l.backward())
                .expect("backward");
            let g2 = (&theirs * &r)
                .and_then(|t| t.sum_all())
                .and_then(|l| l.backward())
                .expect("backward");
            check("y", Some(&ours), &values(&theirs), 1e-5);
            for v in [&x, &w, &b] {
                let want = values(g2.get(v.as_tensor()).expect("candle gradient"));
                check(&format!("stride {s} gradient"), g1.get(v.as_tensor()), &want, 1e-5);
            }
        }
        let xt = Var::from_tensor(&Tensor::randn(0f32, 1.0, (2, 6, 5, 4), &dev).expect("x")).expect("var");
        let wt = Var::from_tensor(&Tensor::randn(0f32, 0.3, (6, 3, 2, 2), &dev).expect("w")).expect("var");
        let ours = conv_transpose_k(
            xt.as_tensor(),
            wt.as_tensor(),
            Some(b.as_tensor().narrow(0, 0, 3).expect("narrow").as_ref()),
        );
        let bias = b.as_tensor().narrow(0, 0, 3).expect("narrow");
        let ours = ours.expect("ours");
        let theirs = conv_transpose_k_candle(xt.as_tensor(), wt.as_tensor(), Some(&bias)).expect("candle");
        check("transpose y", Some(&ours), &values(&theirs), 1e-5);
    }

    /// Other dtypes take candle's path; mismatched shapes and dtypes are errors.
    #[test]
    fn fallback_and_errors() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (1, 2, 5, 5), &dev).expect("x");
        let w = Tensor::randn(0f32, 1.0, (3, 2, 3, 3), &dev).expect("w");
        let b = Tensor::randn(0f32, 1.0, 3, &dev).expect("b");
        let want = conv2d_candle(&x, &w, Some(&b), 1, 1).expect("candle");
        let half = |t: &Tensor| t.to_dtype(DType::BF16).expect("cast");
        if let Ok(got) = conv2d(&half(&x), &half(&w), Some(&half(&b)), 1, 1) {
            assert_eq!(got.dtype(), DType::BF16);
            assert!(rel_err(&values(&got), &values(&want)) < 3e-2);
        }
        assert!(conv2d(&x, &w.narrow(1, 0, 1).expect("narrow"), None, 1, 1).is_err());
        assert!(conv2d(&x, &w, Some(&b.narrow(0, 0, 2).expect("narrow")), 1, 1).is_err());
        assert!(conv2d(&x, &w, None, 0, 1).is_err());
        assert!(conv2d(&x, &w.to_dtype(DType::F64).expect("cast"), None, 1, 1).is_err());
        let big = Tensor::randn(0f32, 1.0, (3, 2, 9, 9), &dev).expect("w");
        assert!(conv2d(&x, &big, None, 1, 1).is_err());
        let wt = Tensor::randn(0f32, 1.0, (2, 3, 2, 3), &dev).expect("w");
        assert!(conv_transpose_k(&x, &wt, None).is_err());
    }
}
