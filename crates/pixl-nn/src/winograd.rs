//! 3×3, stride-1, padding-1 convolution by Winograd's minimal filtering F(4×4, 3×3) (Lavin &
//! Gray, "Fast Algorithms for Convolutional Neural Networks", 2016), for f32 inference on the CPU.
//!
//! Contract: the same operation as [`crate::conv3x3::conv3x3`] with stride 1 — weight `(O, C, 3,
//! 3)` in PyTorch's layout, channels-first `(B, C, H, W)` input, output `(B, O, H, W)`, an
//! optional ReLU of the input, then the bias, a skip connection and the activation of an
//! [`Epilogue`] — with a different rounding: each 4×4 output tile is `Aᵀ[(G g Gᵀ) ⊙ (Bᵀ d B)]A`
//! over the 6×6 input patch `d`, which multiplies 4× fewer times than the direct sum and
//! departs from it by 4e-6 – 1.7e-5 of the largest output value at 9 to 256 input channels
//! (`examples/bench_conv3x3`, against the im2col path; the tests hold it within 1e-5 of the
//! output's scale against an f64 direct convolution).
//!
//! Layout: the weights are transformed once ([`WinogradWeight`], 36 matrices `U[ξ]` of `(O, C)`).
//! Output tiles are grouped 16 to a group along a tile row (one vector lane per tile), groups
//! into blocks; per block a worker transforms the input into `V[ξ]` `(C, n)`, runs one GEMM
//! `M[ξ] = U[ξ]·V[ξ]` per ξ of the 36, and transforms `M` back straight into the output planes
//! with the epilogue applied. The transforms are written over 16-lane arrays and compiled for
//! AVX-512 or AVX2 where the CPU has them.
use crate::conv3x3::{input_dims, run_units, Epilogue, OutPtr};
use crate::fused::{self, Act};
use candle_core::{Result, Tensor};
use rayon::prelude::*;

/// Tiles per group: one per vector lane.
const LANES: usize = 16;
/// Output pixels per tile side (the "4" of F(4×4, 3×3)); the input patch is 6×6.
const M_OUT: usize = 4;
const PATCH: usize = 6;
const XI: usize = PATCH * PATCH;

/// The 36 transformed weight matrices `U[ξ] = (G g Gᵀ)[ξ]`, `ξ = 6·row + col`, each `(O, C)`,
/// stored output channel by output channel: `U[ξ][o][c]` at `(o·36 + ξ)·C + c`.
#[derive(Clone, Debug)]
pub struct WinogradWeight {
    u: Vec<f32>,
    cin: usize,
    cout: usize,
}

/// `G·(a0, a1, a2)` for the 6×3 `G` of F(4, 3) (interpolation points 0, ±1, ±2 and ∞).
#[inline(always)]
fn g_col(a0: f32, a1: f32, a2: f32) -> [f32; PATCH] {
    let (p, q) = (a0 + a2, a0 / 4.0 + a2);
    [
        a0 / 4.0,
        -(p + a1) / 6.0,
        -(p - a1) / 6.0,
        (q / 6.0) + a1 / 12.0,
        (q / 6.0) - a1 / 12.0,
        a2,
    ]
}

/// `G g Gᵀ` of one 3×3 kernel `g` (row-major), `ξ = 6·row + col`.
fn transform_kernel(g: &[f32]) -> [f32; XI] {
    // G·g: down each kernel column.
    let cols: [[f32; PATCH]; 3] = std::array::from_fn(|kx| g_col(g[kx], g[3 + kx], g[6 + kx]));
    let mut u = [0f32; XI];
    for r in 0..PATCH {
        let row = g_col(cols[0][r], cols[1][r], cols[2][r]);
        u[PATCH * r..PATCH * (r + 1)].copy_from_slice(&row);
    }
    u
}

impl WinogradWeight {
    pub fn new(weight: &Tensor) -> Result<Self> {
        let (o, c, kh, kw) = weight.dims4()?;
        if (kh, kw) != (3, 3) {
            candle_core::bail!("Winograd 3x3 convolution given a {kh}x{kw} kernel");
        }
        let weight = weight.to_dtype(candle_core::DType::F32)?.contiguous()?;
        let (storage, layout) = weight.storage_and_layout();
        let w = fused::storage_slice(&storage, layout, "Winograd weight transform")?;
        let mut u = vec![0f32; XI * o * c];
        if c > 0 {
            u.par_chunks_mut(XI * c).enumerate().for_each(|(oc, uo)| {
                for ic in 0..c {
                    let t = transform_kernel(&w[(oc * c + ic) * 9..][..9]);
                    for (xi, v) in t.iter().enumerate() {
                        uo[xi * c + ic] = *v;
                    }
                }
            });
        }
        Ok(Self { u, cin: c, cout: o })
    }

    pub fn cin(&self) -> usize {
        self.cin
    }

    pub fn cout(&self) -> usize {
        self.cout
    }
}

/// Whether an `h × w` stride-1 output is better done this way than by im2col tiles: measured
/// faster from 64×64 up (`examples/bench_conv3x3`: 1.7–2.2× at 64² to 512², 64 to 256
/// channels), slower at 32² and below, where a block of 16-tile groups leaves threads idle.
pub fn suits(stride: usize, h: usize, w: usize) -> bool {
    stride == 1 && w >= 32 && h * w >= 64 * 64
}

/// Tiles per block for `cin` → `cout` channels (fewer when the image has too few tiles to give
/// every thread two blocks): 128, or 256 from 384 channels in and out together, measured best
/// (`examples/bench_conv3x3` with `WINOGRAD_BLOCKS`: 16 to 512 tiles).
pub fn block_tiles(cin: usize, cout: usize) -> usize {
    if cin + cout < 384 {
        128
    } else {
        256
    }
}

/// f32 scratch one worker holds for `cin` → `cout` channels: a block's transformed input and
/// products.
pub fn scratch_floats(cin: usize, cout: usize) -> usize {
    XI * (cin + cout) * block_tiles(cin, cout)
}

type Lanes = [f32; LANES];

/// `Bᵀ` of F(4, 3) applied to six values (a column or a row of the patch).
#[inline(always)]
fn bt(d: [f32; PATCH]) -> [f32; PATCH] {
    let [d0, d1, d2, d3, d4, d5] = d;
    [
        4.0 * d0 - 5.0 * d2 + d4,
        -4.0 * d1 - 4.0 * d2 + d3 + d4,
        4.0 * d1 - 4.0 * d2 - d3 + d4,
        -2.0 * d1 - d2 + 2.0 * d3 + d4,
        2.0 * d1 - d2 - 2.0 * d3 + d4,
        4.0 * d1 - 5.0 * d3 + d5,
    ]
}

/// `Aᵀ` of F(4, 3) applied to six values.
#[inline(always)]
fn at(m: [f32; PATCH]) -> [f32; M_OUT] {
    let [m0, m1, m2, m3, m4, m5] = m;
    let (s12, d12, s34, d34) = (m1 + m2, m1 - m2, m3 + m4, m3 - m4);
    [m0 + s12 + s34, d12 + 2.0 * d34, s12 + 4.0 * s34, d12 + 8.0 * d34 + m5]
}

/// Geometry of one image's convolution.
#[derive(Clone, Copy)]
struct Geom {
    c: usize,
    o: usize,
    h: usize,
    w: usize,
    /// Groups of 16 tiles per tile row.
    gr: usize,
}

/// Width of a group's input rows: 16 tiles of 4 plus the 2-pixel halo, padded.
const ROW: usize = LANES * M_OUT + 8;

/// Transforms group `g` (flat over tile rows and groups per row) of channel-first image `img`
/// into `v[ξ·vs + l]` for `l` in the group's 16 lanes (`vs`: stride between ξ planes).
#[inline(always)]
fn input_group(img: &[f32], geo: Geom, ch: usize, g: usize, relu: bool, v: &mut [f32], vs: usize) {
    let Geom { h, w, gr, .. } = geo;
    let (ty, x0) = (g / gr, (g % gr) * LANES * M_OUT);
    let plane = &img[ch * h * w..(ch + 1) * h * w];
    // The 6 input rows of the tile row, columns x0 − 1 .. x0 + 65, zero outside the image,
    // transformed down the columns (Bᵀ d).
    let mut rows = [[0f32; ROW]; PATCH];
    let lo = x0.saturating_sub(1); // first input column read
    let hi = (x0 + LANES * M_OUT + 1).min(w); // one past the last
    let off = lo + 1 - x0; // where column `lo` lands in the row buffer
    for (r, row) in rows.iter_mut().enumerate() {
        let iy = (M_OUT * ty + r) as isize - 1;
        if iy < 0 || iy >= h as isize {
            continue;
        }
        if lo < hi {
            let src = &plane[iy as usize * w + lo..iy as usize * w + hi];
            let dst = &mut row[off..off + src.len()];
            if relu {
                for (d, s) in dst.iter_mut().zip(src) {
                    *d = s.max(0.0);
                }
            } else {
                dst.copy_from_slice(src);
            }
        }
    }
    let mut e = [[0f32; ROW]; PATCH];
    for q in 0..ROW {
        let t = bt([rows[0][q], rows[1][q], rows[2][q], rows[3][q], rows[4][q], rows[5][q]]);
        for r in 0..PATCH {
            e[r][q] = t[r];
        }
    }
    // Across each transformed row: lane l's six values are columns 4l .. 4l + 5.
    for (r, er) in e.iter().enumerate() {
        let mut x = [[0f32; LANES]; PATCH];
        for (k, xk) in x.iter_mut().enumerate() {
            for (l, xl) in xk.iter_mut().enumerate() {
                *xl = er[M_OUT * l + k];
            }
        }
        let mut y = [[0f32; LANES]; PATCH];
        for l in 0..LANES {
            let t = bt([x[0][l], x[1][l], x[2][l], x[3][l], x[4][l], x[5][l]]);
            for k in 0..PATCH {
                y[k][l] = t[k];
            }
        }
        for (k, yk) in y.iter().enumerate() {
            v[(PATCH * r + k) * vs..][..LANES].copy_from_slice(yk);
        }
    }
}

/// Transforms the products `m[ξ·ms + l]` of group `g`, output channel `oc`, back to the 4×4
/// tiles and writes them (bias, skip and activation applied) into `out` (the image's `(O, H, W)`
/// planes, through a raw pointer shared by the workers).
///
/// # Safety
/// `out` points at the image's `O·H·W` output values, and no other thread writes this group's
/// pixels of channel `oc`.
#[allow(clippy::too_many_arguments, clippy::needless_range_loop)]
#[inline(always)]
unsafe fn output_group(
    m: &[f32],
    ms: usize,
    geo: Geom,
    oc: usize,
    g: usize,
    epi: &Epilogue,
    skip: Option<&[f32]>,
    out: *mut f32,
) {
    let Geom { h, w, gr, .. } = geo;
    let (ty, x0) = (g / gr, (g % gr) * LANES * M_OUT);
    let lane = |xi: usize| -> Lanes {
        let mut a = [0f32; LANES];
        a.copy_from_slice(&m[xi * ms..][..LANES]);
        a
    };
    // Aᵀ down the columns: t[i][k] for output row i, patch column k.
    let mut t = [[[0f32; LANES]; PATCH]; M_OUT];
    for k in 0..PATCH {
        let col = [
            lane(k),
            lane(PATCH + k),
            lane(2 * PATCH + k),
            lane(3 * PATCH + k),
            lane(4 * PATCH + k),
            lane(5 * PATCH + k),
        ];
        for l in 0..LANES {
            let r = at([col[0][l], col[1][l], col[2][l], col[3][l], col[4][l], col[5][l]]);
            for i in 0..M_OUT {
                t[i][k][l] = r[i];
            }
        }
    }
    let bias = epi.bias.map_or(0.0, |b| b[oc]);
    let width = (w - x0).min(LANES * M_OUT);
    for (i, ti) in t.iter().enumerate() {
        let oy = M_OUT * ty + i;
        if oy >= h {
            break;
        }
        // Aᵀ across: output column 4l + j of the group.
        let mut row = [0f32; LANES * M_OUT];
        for l in 0..LANES {
            let r = at([ti[0][l], ti[1][l], ti[2][l], ti[3][l], ti[4][l], ti[5][l]]);
            for j in 0..M_OUT {
                row[M_OUT * l + j] = r[j] + bias;
            }
        }
        let at = (oc * h + oy) * w + x0;
        let row = &mut row[..width];
        if let Some(s) = skip {
            for (d, &sv) in row.iter_mut().zip(&s[at..at + width]) {
                *d += sv;
            }
        }
        if epi.act != Act::None {
            for d in row.iter_mut() {
                *d = epi.act.apply(*d);
            }
        }
        // SAFETY: `at .. at + width` lies in this image's channel-oc row oy (x0 + width ≤ w),
        // written by this group only (caller's contract).
        std::ptr::copy_nonoverlapping(row.as_ptr(), out.add(at), width);
    }
}

/// What every block of one image's convolution shares.
struct Job<'a> {
    img: &'a [f32],
    geo: Geom,
    wt: &'a WinogradWeight,
    relu: bool,
    epi: &'a Epilogue<'a>,
    skip: Option<&'a [f32]>,
    /// The image's output planes.
    out: OutPtr,
}

/// One block: groups `g0 .. g0 + ng` of the job's image.
#[inline(always)]
fn block(job: &Job, g0: usize, ng: usize, scratch: &mut [f32], par: gemm::Parallelism) {
    let Job {
        img,
        geo,
        wt,
        relu,
        epi,
        skip,
        out,
    } = *job;
    let Geom { c, o, .. } = geo;
    let n = ng * LANES;
    let (v, m) = scratch.split_at_mut(XI * c * n);
    let m = &mut m[..XI * o * n];
    // V[ξ] is (C, n): element (ξ, ch, t) at (ξ·C + ch)·n + t.
    for ch in 0..c {
        for gi in 0..ng {
            input_group(img, geo, ch, g0 + gi, relu, &mut v[ch * n + gi * LANES..], c * n);
        }
    }
    for xi in 0..XI {
        // SAFETY: dst M[ξ] (o × n, row stride n), lhs U[ξ] (o × c, row stride 36·c), rhs V[ξ]
        // (c × n, row stride n), all inside their buffers.
        unsafe {
            gemm::gemm(
                o,
                n,
                c,
                m.as_mut_ptr().add(xi * o * n),
                1,
                n as isize,
                false,
                wt.u.as_ptr().add(xi * c),
                1,
                (XI * c) as isize,
                v.as_ptr().add(xi * c * n),
                1,
                n as isize,
                0.0f32,
                1.0f32,
                false,
                false,
                false,
                par,
            );
        }
    }
    for oc in 0..o {
        for gi in 0..ng {
            // SAFETY: groups of a block belong to this worker alone; `out` is this image's planes.
            unsafe {
                output_group(&m[oc * n + gi * LANES..], o * n, geo, oc, g0 + gi, epi, skip, out.0);
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn block_avx512(job: &Job, g0: usize, ng: usize, scratch: &mut [f32], par: gemm::Parallelism) {
    block(job, g0, ng, scratch, par)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn block_avx2(job: &Job, g0: usize, ng: usize, scratch: &mut [f32], par: gemm::Parallelism) {
    block(job, g0, ng, scratch, par)
}

/// [`block`] compiled for the widest vector unit the CPU has.
fn block_dispatch(job: &Job, g0: usize, ng: usize, scratch: &mut [f32], par: gemm::Parallelism) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { block_avx512(job, g0, ng, scratch, par) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { block_avx2(job, g0, ng, scratch, par) };
        }
    }
    block(job, g0, ng, scratch, par)
}

/// `act(conv(relu?(xs)) + b + residual)` for a stride-1 3×3 convolution, `(B, C, H, W)` f32 CPU
/// tensor → `(B, O, H, W)`, blocks of `block_tiles` tiles (rounded up to whole groups of 16).
pub fn conv3x3_winograd(
    xs: &Tensor,
    wt: &WinogradWeight,
    input_relu: bool,
    epi: &Epilogue,
    block_tiles: usize,
) -> Result<Tensor> {
    let _t = crate::profile::span("conv 3x3");
    let (b, c, h, w) = input_dims(xs, wt.cin)?;
    let o = wt.cout;
    let plane = h * w;
    let mut out = vec![0f32; b * o * plane];
    epi.check(o, out.len())?;
    if out.is_empty() {
        return Tensor::from_vec(out, (b, o, h, w), xs.device());
    }
    let xs = xs.contiguous()?;
    let (storage, layout) = xs.storage_and_layout();
    let src = fused::storage_slice(&storage, layout, "3x3 convolution")?;
    let th = h.div_ceil(M_OUT);
    let gr = w.div_ceil(M_OUT * LANES);
    let geo = Geom { c, o, h, w, gr };
    let groups = th * gr;
    let threads = rayon::current_num_threads().max(1);
    let per_block = block_tiles
        .div_ceil(LANES)
        .min((b * groups).div_ceil(2 * threads))
        .clamp(1, groups);
    let blocks_per_image = groups.div_ceil(per_block);
    let blocks = b * blocks_per_image;
    let scratch_len = XI * (c + o) * per_block * LANES;
    let dst = OutPtr(out.as_mut_ptr());
    let run = |bi: usize, scratch: &mut [f32], par: gemm::Parallelism| {
        let (img, blk) = (bi / blocks_per_image, bi % blocks_per_image);
        let g0 = blk * per_block;
        let ng = per_block.min(groups - g0);
        let d = dst;
        let job = Job {
            img: &src[img * c * plane..(img + 1) * c * plane],
            geo,
            wt,
            relu: input_relu,
            epi,
            skip: epi.residual.map(|r| &r[img * o * plane..(img + 1) * o * plane]),
            // SAFETY: image `img`'s output planes lie at this offset inside `out`.
            out: OutPtr(unsafe { d.0.add(img * o * plane) }),
        };
        block_dispatch(&job, g0, ng, scratch, par);
    };
    run_units(blocks, scratch_len, run);
    drop(storage);
    Tensor::from_vec(out, (b, o, h, w), xs.device())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Direct convolution in f64 (zero padding 1, stride 1), ReLU of the input optional.
    fn direct(x: &[f32], wt: &[f32], dims: (usize, usize, usize, usize), o: usize, relu: bool) -> Vec<f64> {
        let (b, c, h, w) = dims;
        let mut out = vec![0f64; b * o * h * w];
        for bi in 0..b {
            for oc in 0..o {
                for y in 0..h {
                    for xx in 0..w {
                        let mut s = 0f64;
                        for ic in 0..c {
                            for ky in 0..3 {
                                for kx in 0..3 {
                                    let (iy, ix) = (y as isize + ky as isize - 1, xx as isize + kx as isize - 1);
                                    if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                        continue;
                                    }
                                    let mut v = f64::from(x[((bi * c + ic) * h + iy as usize) * w + ix as usize]);
                                    if relu {
                                        v = v.max(0.0);
                                    }
                                    s += v * f64::from(wt[((oc * c + ic) * 3 + ky) * 3 + kx]);
                                }
                            }
                        }
                        out[((bi * o + oc) * h + y) * w + xx] = s;
                    }
                }
            }
        }
        out
    }

    /// Against an f64 direct convolution: sizes that are and are not multiples of the tile and
    /// of the 64-pixel group, one block and many, ReLU of the input, bias, skip and activation.
    #[test]
    fn matches_direct_convolution() {
        let dev = Device::Cpu;
        for (b, c, o, h, w, blk) in [
            (1, 3, 5, 4, 4, 16),
            (2, 5, 7, 9, 13, 16),
            (1, 8, 4, 1, 1, 16),
            (1, 6, 3, 17, 70, 16),
            (1, 6, 3, 17, 70, 1000),
            (1, 16, 16, 33, 129, 48),
        ] {
            let xs = Tensor::randn(0f32, 1.0, (b, c, h, w), &dev).unwrap();
            let wt = Tensor::randn(0f32, 0.3, (o, c, 3, 3), &dev).unwrap();
            let xv = xs.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let wv = wt.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let bias: Vec<f32> = (0..o).map(|i| 0.1 * i as f32 - 0.2).collect();
            let skip: Vec<f32> = (0..b * o * h * w)
                .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.5)
                .collect();
            let ww = WinogradWeight::new(&wt).unwrap();
            for relu in [false, true] {
                let want = direct(&xv, &wv, (b, c, h, w), o, relu);
                // Plain.
                let epi = Epilogue {
                    bias: None,
                    residual: None,
                    act: Act::None,
                };
                let got = conv3x3_winograd(&xs, &ww, relu, &epi, blk).unwrap();
                assert_eq!(got.dims(), &[b, o, h, w]);
                let got = got.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                let scale = want.iter().fold(0f64, |a, v| a.max(v.abs())).max(1.0);
                for (i, (g, e)) in got.iter().zip(&want).enumerate() {
                    assert!(
                        (f64::from(*g) - e).abs() < 1e-5 * scale,
                        "{b}x{c}x{h}x{w} relu {relu} at {i}: {g} vs {e}"
                    );
                }
                // Bias, skip and ReLU of the result.
                let epi = Epilogue {
                    bias: Some(&bias),
                    residual: Some(&skip),
                    act: Act::Relu,
                };
                let got = conv3x3_winograd(&xs, &ww, relu, &epi, blk).unwrap();
                let got = got.flatten_all().unwrap().to_vec1::<f32>().unwrap();
                for (i, g) in got.iter().enumerate() {
                    let oc = (i / (h * w)) % o;
                    let e = (want[i] + f64::from(bias[oc]) + f64::from(skip[i])).max(0.0);
                    assert!((f64::from(*g) - e).abs() < 1e-5 * scale, "epilogue at {i}: {g} vs {e}");
                }
            }
        }
    }

    /// `G g Gᵀ` of a kernel that is 1 at one tap picks out the interpolation points' products:
    /// the centre tap gives `u[ξ] = G[r][1]·G[c][1]`.
    #[test]
    fn kernel_transform_of_a_unit_tap() {
        let mut g = [0f32; 9];
        g[4] = 1.0;
        let u = transform_kernel(&g);
        let g1 = [0.0, -1.0 / 6.0, 1.0 / 6.0, 1.0 / 12.0, -1.0 / 12.0, 0.0];
        for r in 0..PATCH {
            for c in 0..PATCH {
                assert!((f64::from(u[PATCH * r + c]) - g1[r] * g1[c]).abs() < 1e-8);
            }
        }
    }

    #[test]
    fn rejects_bad_input() {
        let dev = Device::Cpu;
        let wt = Tensor::zeros((2, 3, 3, 3), candle_core::DType::F32, &dev).unwrap();
        let ww = WinogradWeight::new(&wt).unwrap();
        let epi = Epilogue {
            bias: None,
            residual: None,
            act: Act::None,
        };
        let wrong = Tensor::zeros((1, 4, 8, 8), candle_core::DType::F32, &dev).unwrap();
        assert!(conv3x3_winograd(&wrong, &ww, false, &epi, 16).is_err());
        let empty = Tensor::zeros((1, 3, 0, 8), candle_core::DType::F32, &dev).unwrap();
        assert!(conv3x3_winograd(&empty, &ww, false, &epi, 16).is_err());
        let k5 = Tensor::zeros((2, 3, 5, 5), candle_core::DType::F32, &dev).unwrap();
        assert!(WinogradWeight::new(&k5).is_err());
    }
}
