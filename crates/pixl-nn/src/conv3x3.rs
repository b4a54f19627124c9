//! 3×3 convolution (padding 1, stride 1 or 2) for inference on the CPU (the relighting network's
//! DPT head, DA3's DPT head, Marigold's VAE), and [`Conv3x3`], the layer that uses it.
//!
//! The output pixels of each image are cut into tiles of [`tile_pixels`] pixels. Tiles run in parallel on rayon's pool; each
//! worker unrolls its tile straight from the channels-first input into an im2col matrix `(9·C,
//! t)` (rows `(c, ky, kx)`, so the weights are PyTorch's `(O, C, 3, 3)` read as `(O, 9·C)` with
//! no reordering), an optional ReLU of the input applied on the way, multiplies it by the weights
//! with one single-threaded GEMM that writes the `(O, t)` result in place into the channels-first
//! output, and applies the bias, a skip connection and the activation to that cache-hot block.
//! No padded copy of the input, no result buffer, no copy back. When an image has fewer tiles
//! than there are threads, the tiles run one after another with the GEMM itself parallel.
//!
//! Same operation as `candle_nn::Conv2d` (which the head uses on other devices): weight
//! `(O, C, 3, 3)`, `out[o, y, x] = b[o] + Σ_{c,ky,kx} w[o, c, ky, kx]·in[c, s·y + ky − 1,
//! s·x + kx − 1]` (zero outside), output `(B, O, ⌊(H − 1)/s⌋ + 1, ⌊(W − 1)/s⌋ + 1)`.
use crate::fused::{self, bias_act_channels, bias_residual_channels, Act, Vector};
use crate::winograd::{self, WinogradWeight};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use rayon::prelude::*;

/// Output pixels per tile for `cin` input channels. 256 measured fastest on the heads' shapes
/// (`examples/bench_conv3x3`: 64 to 1024 input channels, against 128, 227–455 and 1024 pixels).
pub fn tile_pixels(_cin: usize) -> usize {
    256
}

/// f32 values of im2col scratch one worker thread holds during a convolution with `cin` input
/// channels and `out_px` output pixels per image (allocated per call, freed on return).
pub fn scratch_floats(cin: usize, out_px: usize) -> usize {
    tile_pixels(cin).min(out_px.max(1)) * 9 * cin
}

/// Weights in im2col order: `(O, 9·C)`, columns `(c, ky, kx)` (PyTorch's layout, flattened).
#[derive(Clone, Debug)]
pub struct Im2colWeight {
    matrix: Tensor,
    cin: usize,
}

impl Im2colWeight {
    pub fn new(weight: &Tensor) -> Result<Self> {
        let (o, c, kh, kw) = weight.dims4()?;
        if (kh, kw) != (3, 3) {
            candle_core::bail!("3x3 convolution given a {kh}x{kw} kernel");
        }
        let matrix = weight.contiguous()?.reshape((o, 9 * c))?;
        Ok(Self { matrix, cin: c })
    }
}

/// What happens to each output value `v` of channel `o` at flat index `i` of its plane.
pub struct Epilogue<'a> {
    pub bias: Option<&'a [f32]>,
    /// Added after the bias, same shape as the output.
    pub residual: Option<&'a [f32]>,
    pub act: Act,
}

impl Epilogue<'_> {
    /// Errors unless the bias has `o` values and the skip connection `out_len`.
    pub fn check(&self, o: usize, out_len: usize) -> Result<()> {
        if let Some(r) = self.residual {
            if r.len() != out_len {
                candle_core::bail!("residual of {} values for an output of {out_len}", r.len());
            }
        }
        if let Some(bias) = self.bias {
            if bias.len() != o {
                candle_core::bail!("bias of {} values for {o} output channels", bias.len());
            }
        }
        Ok(())
    }
}

/// `(B, C, H, W)` f32 CPU tensor → `(B, O, H', W')`, tiles of [`tile_pixels`] output pixels.
pub fn conv3x3(xs: &Tensor, w: &Im2colWeight, stride: usize, epi: &Epilogue) -> Result<Tensor> {
    conv3x3_tiled(xs, w, stride, false, epi, tile_pixels(w.cin))
}

/// The output pointer shared by the workers; each writes only its own tiles' pixels.
#[derive(Clone, Copy)]
pub(crate) struct OutPtr(pub(crate) *mut f32);
// SAFETY: workers write disjoint index sets (distinct tiles) of one live allocation.
unsafe impl Send for OutPtr {}
unsafe impl Sync for OutPtr {}

/// Geometry of one image's convolution.
#[derive(Clone, Copy)]
struct Geom {
    c: usize,
    h: usize,
    w: usize,
    stride: usize,
    wo: usize,
}

/// Unrolls output pixels `p0 .. p0 + t` (flat, row-major over `(H', W')`) of one image `img`
/// `(C, H, W)` into `cols` `(9·C, t)`: row `(c, ky, kx)` holds `in[c, s·y + ky − 1, s·x + kx − 1]`
/// (0 outside the image), ReLU'd when `relu`.
fn im2col(img: &[f32], g: Geom, p0: usize, t: usize, relu: bool, cols: &mut [f32]) {
    let Geom { c, h, w, stride, wo } = g;
    for ch in 0..c {
        let plane = &img[ch * h * w..(ch + 1) * h * w];
        for ky in 0..3 {
            for kx in 0..3 {
                let row = &mut cols[((ch * 3 + ky) * 3 + kx) * t..][..t];
                let mut j = 0;
                while j < t {
                    let (oy, ox) = ((p0 + j) / wo, (p0 + j) % wo);
                    let n = (wo - ox).min(t - j);
                    let seg = &mut row[j..j + n];
                    j += n;
                    let iy = oy * stride + ky;
                    if iy == 0 || iy > h {
                        seg.fill(0.0);
                        continue;
                    }
                    let line = &plane[(iy - 1) * w..iy * w];
                    if stride == 1 {
                        // Input column of seg[i] is ox + i + kx − 1: valid for lo ≤ i < hi.
                        let first = ox + kx; // input column + 1
                        let lo = 1usize.saturating_sub(first).min(n);
                        let hi = (w + 1).saturating_sub(first).min(n);
                        seg[..lo].fill(0.0);
                        if lo < hi {
                            let src = &line[first + lo - 1..first + hi - 1];
                            if relu {
                                for (d, &v) in seg[lo..hi].iter_mut().zip(src) {
                                    *d = v.max(0.0);
                                }
                            } else {
                                seg[lo..hi].copy_from_slice(src);
                            }
                        }
                        seg[hi.max(lo)..].fill(0.0);
                    } else {
                        for (i, d) in seg.iter_mut().enumerate() {
                            let ix = (ox + i) * stride + kx;
                            let v = if ix == 0 || ix > w { 0.0 } else { line[ix - 1] };
                            *d = if relu { v.max(0.0) } else { v };
                        }
                    }
                }
            }
        }
    }
}

/// `(B, C, H, W)` of a 3×3 convolution's input: errors unless it has `cin` channels and pixels.
pub(crate) fn input_dims(xs: &Tensor, cin: usize) -> Result<(usize, usize, usize, usize)> {
    let (b, c, h, w) = xs.dims4()?;
    if c != cin {
        candle_core::bail!("3x3 convolution expects {cin} input channels, got {c}");
    }
    if h == 0 || w == 0 {
        candle_core::bail!("3x3 convolution of an empty {h}x{w} input");
    }
    Ok((b, c, h, w))
}

/// Runs `run(unit, scratch, parallelism)` for the units `0 .. n` of a convolution (tiles or
/// blocks), each worker with its own `scratch_len` floats of scratch: in parallel on rayon's pool
/// with single-threaded GEMMs, or, with fewer units than threads, one after another with the
/// GEMM itself parallel.
pub(crate) fn run_units(n: usize, scratch_len: usize, run: impl Fn(usize, &mut [f32], gemm::Parallelism) + Sync) {
    let threads = rayon::current_num_threads().max(1);
    if n < threads {
        let mut scratch = vec![0f32; scratch_len];
        for unit in 0..n {
            run(unit, &mut scratch, fused::gemm_parallelism());
        }
    } else {
        let tasks = (4 * threads).min(n);
        let per_task = n.div_ceil(tasks);
        (0..tasks).into_par_iter().for_each(|task| {
            let mut scratch = vec![0f32; scratch_len];
            for unit in task * per_task..((task + 1) * per_task).min(n) {
                run(unit, &mut scratch, gemm::Parallelism::None);
            }
        });
    }
}

/// [`conv3x3`] with an optional ReLU of the input (`input_relu`: `conv(relu(x))`) and tiles of
/// `tile_px` output pixels (at least one).
pub fn conv3x3_tiled(
    xs: &Tensor,
    w: &Im2colWeight,
    stride: usize,
    input_relu: bool,
    epi: &Epilogue,
    tile_px: usize,
) -> Result<Tensor> {
    let _t = crate::profile::span("conv 3x3");
    let (b, c, h, wd) = input_dims(xs, w.cin)?;
    if !(stride == 1 || stride == 2) {
        candle_core::bail!("3x3 convolution: stride {stride} (1 or 2 supported)");
    }
    let o = w.matrix.dim(0)?;
    let (ho, wo) = ((h - 1) / stride + 1, (wd - 1) / stride + 1);
    let plane = ho * wo;
    let mut out = vec![0f32; b * o * plane];
    epi.check(o, out.len())?;
    if out.is_empty() {
        return Tensor::from_vec(out, (b, o, ho, wo), xs.device());
    }
    let xs = xs.contiguous()?;
    let (storage, layout) = xs.storage_and_layout();
    let src = fused::storage_slice(&storage, layout, "3x3 convolution")?;
    let (w_storage, w_layout) = w.matrix.storage_and_layout();
    let weights = fused::storage_slice(&w_storage, w_layout, "3x3 convolution")?;
    let k = 9 * c;
    let g = Geom {
        c,
        h,
        w: wd,
        stride,
        wo,
    };
    let tile = tile_px.clamp(1, plane);
    let per_image = plane.div_ceil(tile);
    let tiles = b * per_image;
    let dst = OutPtr(out.as_mut_ptr());
    // One tile: im2col, GEMM into the output, epilogue on the block just written.
    let run = |ti: usize, cols: &mut [f32], par: gemm::Parallelism| {
        let (bi, p0) = (ti / per_image, (ti % per_image) * tile);
        let t = tile.min(plane - p0);
        let cols = &mut cols[..k * t];
        im2col(&src[bi * c * h * wd..(bi + 1) * c * h * wd], g, p0, t, input_relu, cols);
        let base = bi * o * plane + p0;
        // SAFETY: dst (o × t, row stride `plane`) lies inside `out` at `base` (p0 + t ≤ plane), and
        // no other tile writes these indices; lhs (o × k, row stride k) is `weights`; rhs
        // (k × t, row stride t) is `cols`.
        unsafe {
            let d = dst;
            gemm::gemm(
                o,
                t,
                k,
                d.0.add(base),
                1,
                plane as isize,
                false,
                weights.as_ptr(),
                1,
                k as isize,
                cols.as_ptr(),
                1,
                t as isize,
                0.0f32,
                1.0f32,
                false,
                false,
                false,
                par,
            );
        }
        if epi.bias.is_none() && epi.residual.is_none() && epi.act == Act::None {
            return;
        }
        for oc in 0..o {
            let at = base + oc * plane;
            // SAFETY: the t values at `at` are this tile's output of channel oc (see above).
            let seg = unsafe { std::slice::from_raw_parts_mut(dst.0.add(at), t) };
            let bias = epi.bias.map_or(0.0, |bv| bv[oc]);
            match epi.residual {
                Some(skip) => {
                    for (d, &s) in seg.iter_mut().zip(&skip[at..at + t]) {
                        *d = epi.act.apply(*d + bias + s);
                    }
                }
                None => {
                    for d in seg.iter_mut() {
                        *d = epi.act.apply(*d + bias);
                    }
                }
            }
        }
    };
    run_units(tiles, k * tile, run);
    drop(storage);
    Tensor::from_vec(out, (b, o, ho, wo), xs.device())
}

/// `Conv2d(cin, cout, 3, stride, padding=1)` with the bias, an optional skip connection and an
/// activation applied in the same pass (on the CPU in f32: [`crate::winograd`] where it
/// [suits](crate::winograd::suits) the shape, [`conv3x3`] otherwise; candle's `Conv2d` followed
/// by the fused ops elsewhere).
#[derive(Clone, Debug)]
pub struct Conv3x3 {
    conv: Conv2d,
    im2col: Im2colWeight,
    /// The Winograd-transformed weights of a stride-1 convolution, made on first CPU use.
    winograd: std::sync::Arc<std::sync::OnceLock<WinogradWeight>>,
    stride: usize,
    bias: Option<Vector>,
}

impl Conv3x3 {
    pub fn new(cin: usize, cout: usize, stride: usize, bias: bool, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get((cout, cin, 3, 3), "weight")?;
        let bias = if bias {
            Some(Vector::new(vb.get(cout, "bias")?)?)
        } else {
            None
        };
        Self::from_parts(weight, bias, stride)
    }

    pub fn from_parts(weight: Tensor, bias: Option<Vector>, stride: usize) -> Result<Self> {
        let cfg = Conv2dConfig {
            padding: 1,
            stride,
            ..Default::default()
        };
        Ok(Self {
            im2col: Im2colWeight::new(&weight)?,
            winograd: Default::default(),
            conv: Conv2d::new(weight, None, cfg),
            stride,
            bias,
        })
    }

    /// `act((conv(xs) + b) + residual)`.
    pub fn apply(&self, xs: &Tensor, residual: Option<&Tensor>, act: Act) -> Result<Tensor> {
        self.apply_relu_input(xs, false, residual, act)
    }

    /// `act((conv(relu(xs) if input_relu else xs) + b) + residual)`: on the CPU in f32 the ReLU
    /// is applied as the kernels read the input and the skip connection is read in place (no
    /// extra pass or copy).
    pub fn apply_relu_input(
        &self,
        xs: &Tensor,
        input_relu: bool,
        residual: Option<&Tensor>,
        act: Act,
    ) -> Result<Tensor> {
        if fused::cpu_f32(xs) && residual.is_none_or(fused::cpu_f32) {
            let residual = residual.map(Tensor::contiguous).transpose()?;
            let guard = residual.as_ref().map(|r| r.storage_and_layout());
            let skip = match &guard {
                Some((storage, layout)) => Some(fused::storage_slice(storage, layout, "3x3 convolution residual")?),
                None => None,
            };
            let epi = Epilogue {
                bias: self.bias.as_ref().map(Vector::values),
                residual: skip,
                act,
            };
            let (_, _, h, w) = xs.dims4()?;
            if winograd::suits(self.stride, h, w) {
                let wt = match self.winograd.get() {
                    Some(wt) => wt,
                    None => {
                        let wt = WinogradWeight::new(self.conv.weight())?;
                        self.winograd.get_or_init(|| wt)
                    }
                };
                let tiles = winograd::block_tiles(wt.cin(), wt.cout());
                return winograd::conv3x3_winograd(xs, wt, input_relu, &epi, tiles);
            }
            let tile = tile_pixels(self.im2col.cin);
            return conv3x3_tiled(xs, &self.im2col, self.stride, input_relu, &epi, tile);
        }
        let xs = if input_relu { xs.relu()? } else { xs.clone() };
        let ys = self.conv.forward(&xs)?;
        match (&self.bias, residual) {
            (Some(b), Some(r)) => bias_residual_channels(&ys, b, r, act),
            (Some(b), None) => bias_act_channels(&ys, b, act),
            (None, Some(r)) => fused::add_act(&ys, r, act),
            (None, None) if act == Act::Relu => fused::relu(&ys),
            (None, None) => Ok(ys),
        }
    }

    pub fn forward(&self, xs: &Tensor, act: Act) -> Result<Tensor> {
        self.apply(xs, None, act)
    }

    /// `(conv(xs) + b) + residual`.
    pub fn forward_residual(&self, xs: &Tensor, residual: &Tensor) -> Result<Tensor> {
        self.apply(xs, Some(residual), Act::None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Module};

    /// The input ReLU applied on the way equals a ReLU pass first: im2col (stride 1 small and
    /// stride 2) and Winograd (stride 1, 64×70) shapes, with a bias, a skip connection and an
    /// output activation.
    #[test]
    fn input_relu_equals_a_relu_pass_first() {
        let dev = Device::Cpu;
        for (stride, h, w) in [(1usize, 9usize, 13usize), (2, 9, 13), (1, 64, 70)] {
            let (c, o) = (5, 7);
            let xs = Tensor::randn(0f32, 1.0, (2, c, h, w), &dev).unwrap();
            let wt = Tensor::randn(0f32, 0.3, (o, c, 3, 3), &dev).unwrap();
            let b = Vector::new(Tensor::randn(0f32, 0.3, o, &dev).unwrap()).unwrap();
            let conv = Conv3x3::from_parts(wt, Some(b), stride).unwrap();
            let (ho, wo) = ((h - 1) / stride + 1, (w - 1) / stride + 1);
            let res = Tensor::randn(0f32, 1.0, (2, o, ho, wo), &dev).unwrap();
            let want = conv.apply(&xs.relu().unwrap(), Some(&res), Act::Relu).unwrap();
            let got = conv.apply_relu_input(&xs, true, Some(&res), Act::Relu).unwrap();
            let err = crate::testing::max_abs_diff(&got, &want).unwrap();
            assert!(err < 1e-5, "stride {stride}, {h}x{w}: {err}");
        }
    }

    /// Against candle's conv2d, with bias, residual and ReLU, both strides, odd sizes.
    #[test]
    fn matches_candle_conv2d() {
        let dev = Device::Cpu;
        for (stride, (h, w)) in [
            (1, (9, 13)),
            (2, (9, 13)),
            (2, (8, 6)),
            (1, (1, 1)),
            (2, (1, 2)),
            (1, (2, 1)),
        ] {
            let xs = Tensor::randn(0f32, 1.0, (2, 5, h, w), &dev).unwrap();
            let wt = Tensor::randn(0f32, 1.0, (7, 5, 3, 3), &dev).unwrap();
            let bias = Tensor::randn(0f32, 1.0, 7, &dev).unwrap();
            let cfg = candle_nn::Conv2dConfig {
                padding: 1,
                stride,
                ..Default::default()
            };
            let want = candle_nn::Conv2d::new(wt.clone(), Some(bias.clone()), cfg)
                .forward(&xs)
                .unwrap();
            let skip = Tensor::randn(0f32, 1.0, want.dims(), &dev).unwrap();
            let want = (want + &skip).unwrap().relu().unwrap();
            let bv = bias.to_vec1::<f32>().unwrap();
            let sv = skip.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let epi = Epilogue {
                bias: Some(&bv),
                residual: Some(&sv),
                act: Act::Relu,
            };
            let im2col = Im2colWeight::new(&wt).unwrap();
            let got = conv3x3(&xs, &im2col, stride, &epi).unwrap();
            assert_eq!(got.dims(), want.dims());
            let max_abs = |a: &Tensor, b: &Tensor| crate::testing::max_abs_diff(a, b).unwrap();
            assert!(max_abs(&got, &want) < 1e-4, "stride {stride} {h}x{w}");
            // Tiles of one pixel, and tiles that straddle output rows, give the same values.
            for tile in [1, 7] {
                let tiled = conv3x3_tiled(&xs, &im2col, stride, false, &epi, tile).unwrap();
                assert!(max_abs(&got, &tiled) < 1e-5, "tile {tile}, stride {stride} {h}x{w}");
            }
            // A ReLU of the input on the way equals the convolution of the ReLU'd input.
            let want_relu = candle_nn::Conv2d::new(wt.clone(), Some(bias.clone()), cfg)
                .forward(&xs.relu().unwrap())
                .unwrap();
            let want_relu = (want_relu + &skip).unwrap().relu().unwrap();
            let got_relu = conv3x3_tiled(&xs, &im2col, stride, true, &epi, 5).unwrap();
            let empty = Tensor::zeros((1, 5, 0, 3), candle_core::DType::F32, &dev).unwrap();
            assert!(conv3x3(&empty, &im2col, stride, &epi).is_err());
            assert!(
                max_abs(&got_relu, &want_relu) < 1e-4,
                "input ReLU, stride {stride} {h}x{w}"
            );
        }
    }
}
