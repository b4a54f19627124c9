//! The resamplers the estimators' official code uses (DA3, Marigold), each reproducing its
//! reference implementation's arithmetic:
//!
//! - [`cv2_resize_u8`]: OpenCV `cv2.resize` on 8-bit interleaved images with `INTER_CUBIC` or
//!   `INTER_AREA`, as opencv-python 5.1.0 computes them on x86-64, the official preprocessing's
//!   resizer (`utils/io/input_processor.py`). That build routes 8-bit `INTER_CUBIC` through its
//!   Intel IPP HAL, which works in floating point (not OpenCV's own 11-bit fixed point): taps
//!   A = −0.75 at `(o + 0.5)·in/out − 0.5`, border replicated, rows then columns, rounded half
//!   to even. `INTER_AREA` is OpenCV's exact pixel-area weights in f32; for integer ratios the
//!   block mean, rounded half *up* for 2×2 blocks and half to even otherwise.
//!   Checked byte for byte against `cv2.resize` (`fixtures/da3/resize.safetensors`); on random
//!   images about one `INTER_CUBIC` value in 10⁵ still differs by one level — values within a
//!   few f32 ulps of a rounding tie, where IPP's internal summation order decides.
//! - [`bicubic_scale`]: PyTorch `F.interpolate(mode="bicubic", scale_factor=s,
//!   align_corners=False, antialias=False)`, used for the ViT position embedding: the source
//!   coordinate is `(o + 0.5) / s − 0.5` with the *given* scale factor (not the size ratio),
//!   A = −0.75, taps clamped to the border.
//! - [`bilinear_align_corners`]: PyTorch `F.interpolate(mode="bilinear", align_corners=True)`,
//!   the DPT head's upsampling, and [`bilinear_half_pixel`] (`align_corners=False`), used to
//!   bring the outputs back to the photo's size; parallel over channels.
//! - [`bilinear_antialias`]: PyTorch `F.interpolate(mode="bilinear", antialias=True)` (Marigold's
//!   input resize): a triangle filter widened by the scale factor when shrinking, taps where
//!   the filter is non-zero, weights normalised to sum 1 (ATen's `_upsample_bilinear2d_aa`).
use candle_core::{CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// cv2 interpolation flags used by the DA3 preprocessing.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Cv2Filter {
    /// `cv2.INTER_CUBIC` (used when enlarging).
    Cubic,
    /// `cv2.INTER_AREA` (used when shrinking).
    Area,
}

/// `cv2.resize(src, (dw, dh), interpolation)` of an interleaved 8-bit image with `cn` channels,
/// `src.len() == sw * sh * cn`. Sizes must be positive (checked by the caller).
pub fn cv2_resize_u8(src: &[u8], sw: usize, sh: usize, cn: usize, dw: usize, dh: usize, filter: Cv2Filter) -> Vec<u8> {
    debug_assert_eq!(src.len(), sw * sh * cn);
    if sw == dw && sh == dh {
        return src.to_vec();
    }
    // OpenCV: inv_scale = dsize / ssize (double), scale = 1 / inv_scale.
    let scale_x = 1.0 / (dw as f64 / sw as f64);
    let scale_y = 1.0 / (dh as f64 / sh as f64);
    match filter {
        Cv2Filter::Cubic => resize_cubic(src, sw, sh, cn, dw, dh),
        Cv2Filter::Area if scale_x >= 1.0 && scale_y >= 1.0 => {
            let (ix, iy) = (scale_x.round(), scale_y.round());
            if (scale_x - ix).abs() < f64::EPSILON && (scale_y - iy).abs() < f64::EPSILON {
                resize_area_fast(src, sw, sh, cn, dw, dh, ix as usize, iy as usize)
            } else {
                resize_area(src, sw, sh, cn, dw, dh, scale_x, scale_y)
            }
        }
        // INTER_AREA when enlarging is a bilinear variant in OpenCV; the DA3 preprocessing never
        // asks for it (it picks INTER_CUBIC whenever a side grows).
        Cv2Filter::Area => resize_cubic(src, sw, sh, cn, dw, dh),
    }
}

/// Keys' cubic kernel, A = −0.75, at distance `t ≥ 0`.
fn keys_cubic(t: f64) -> f64 {
    const A: f64 = -0.75;
    if t <= 1.0 {
        ((A + 2.0) * t - (A + 3.0)) * t * t + 1.0
    } else {
        ((A * t - 5.0 * A) * t + 8.0 * A) * t - 4.0 * A
    }
}

/// Per output sample: the first source index (`floor(x) − 1`, unclamped) and the four weights,
/// computed in f64 and stored as f32.
fn cubic_taps(n_in: usize, n_out: usize) -> Vec<(isize, [f32; 4])> {
    let scale = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|d| {
            let x = (d as f64 + 0.5) * scale - 0.5;
            let s = x.floor();
            let t = x - s;
            let w = [
                keys_cubic(t + 1.0),
                keys_cubic(t),
                keys_cubic(1.0 - t),
                keys_cubic(2.0 - t),
            ];
            (s as isize - 1, w.map(|v| v as f32))
        })
        .collect()
}

/// 8-bit `INTER_CUBIC` (the IPP path): rows, then columns, in f32.
fn resize_cubic(src: &[u8], sw: usize, sh: usize, cn: usize, dw: usize, dh: usize) -> Vec<u8> {
    let xt = cubic_taps(sw, dw);
    let yt = cubic_taps(sh, dh);
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    let row_len = dw * cn;
    let mut hbuf = vec![0f32; sh * row_len];
    hbuf.par_chunks_mut(row_len).enumerate().for_each(|(y, out)| {
        let row = &src[y * sw * cn..(y + 1) * sw * cn];
        for (dx, (x0, w)) in xt.iter().enumerate() {
            let idx: [usize; 4] = std::array::from_fn(|j| clamp(x0 + j as isize, sw) * cn);
            for c in 0..cn {
                // Left to right: ((p0·w0 + p1·w1) + p2·w2) + p3·w3.
                out[dx * cn + c] = idx
                    .iter()
                    .zip(w)
                    .fold(0f32, |acc, (&i, &wj)| acc + row[i + c] as f32 * wj);
            }
        }
    });
    let mut dst = vec![0u8; dh * row_len];
    dst.par_chunks_mut(row_len)
        .zip(yt.par_iter())
        .for_each(|(out, (y0, b))| {
            let rows: [&[f32]; 4] = std::array::from_fn(|k| {
                let y = clamp(y0 + k as isize, sh);
                &hbuf[y * row_len..(y + 1) * row_len]
            });
            for (x, o) in out.iter_mut().enumerate() {
                let v = rows.iter().zip(b).fold(0f32, |acc, (r, &bk)| acc + r[x] * bk);
                *o = v.round_ties_even().clamp(0.0, 255.0) as u8;
            }
        });
    dst
}

/// One weight of OpenCV's area table: output index, source index, weight.
struct AreaTap {
    d: usize,
    s: usize,
    alpha: f32,
}

/// OpenCV `computeResizeAreaTab`: the pixel-area weights in f64, stored as f32.
fn area_taps(n_in: usize, n_out: usize, scale: f64) -> Vec<AreaTap> {
    let mut tab = Vec::with_capacity(n_in * 2);
    for d in 0..n_out {
        let fs1 = d as f64 * scale;
        let fs2 = fs1 + scale;
        let cell = scale.min(n_in as f64 - fs1);
        let mut s2 = fs2.floor() as isize;
        let s1 = (fs1.ceil() as isize).min(s2.min(n_in as isize - 1));
        s2 = s2.min(n_in as isize - 1);
        if s1 as f64 - fs1 > 1e-3 {
            tab.push(AreaTap {
                d,
                s: (s1 - 1) as usize,
                alpha: ((s1 as f64 - fs1) / cell) as f32,
            });
        }
        for s in s1..s2 {
            tab.push(AreaTap {
                d,
                s: s as usize,
                alpha: (1.0 / cell) as f32,
            });
        }
        if fs2 - s2 as f64 > 1e-3 {
            tab.push(AreaTap {
                d,
                s: s2 as usize,
                alpha: ((fs2 - s2 as f64).min(1.0).min(cell) / cell) as f32,
            });
        }
    }
    tab
}

#[allow(clippy::too_many_arguments)]
fn resize_area(
    src: &[u8],
    sw: usize,
    sh: usize,
    cn: usize,
    dw: usize,
    dh: usize,
    scale_x: f64,
    scale_y: f64,
) -> Vec<u8> {
    let xt = area_taps(sw, dw, scale_x);
    let yt = area_taps(sh, dh, scale_y);
    let row_len = dw * cn;
    let mut dst = vec![0u8; dh * row_len];
    dst.par_chunks_mut(row_len).enumerate().for_each(|(dy, out)| {
        let mut sum = vec![0f32; row_len];
        let mut buf = vec![0f32; row_len];
        for ty in yt.iter().filter(|t| t.d == dy) {
            let row = &src[ty.s * sw * cn..(ty.s + 1) * sw * cn];
            buf.iter_mut().for_each(|v| *v = 0.0);
            for tx in &xt {
                for c in 0..cn {
                    let i = tx.d * cn + c;
                    buf[i] += row[tx.s * cn + c] as f32 * tx.alpha;
                }
            }
            for (s, b) in sum.iter_mut().zip(&buf) {
                *s += ty.alpha * b;
            }
        }
        for (o, s) in out.iter_mut().zip(&sum) {
            *o = s.round_ties_even().clamp(0.0, 255.0) as u8;
        }
    });
    dst
}

/// Integer-ratio `INTER_AREA`: the mean of each `ix × iy` block, `(sum + 2) >> 2` for 2×2
/// blocks, `sum · (1/area)` in f32 rounded half to even otherwise.
#[allow(clippy::too_many_arguments)]
fn resize_area_fast(
    src: &[u8],
    sw: usize,
    sh: usize,
    cn: usize,
    dw: usize,
    dh: usize,
    ix: usize,
    iy: usize,
) -> Vec<u8> {
    let row_len = dw * cn;
    let area = ix * iy;
    let scale = 1.0f32 / area as f32;
    let mut dst = vec![0u8; dh * row_len];
    dst.par_chunks_mut(row_len).enumerate().for_each(|(dy, out)| {
        for (dxe, o) in out.iter_mut().enumerate() {
            let (dx, c) = (dxe / cn, dxe % cn);
            let mut sum = 0u32;
            for sy in dy * iy..(dy * iy + iy).min(sh) {
                for sx in dx * ix..(dx * ix + ix).min(sw) {
                    sum += src[(sy * sw + sx) * cn + c] as u32;
                }
            }
            *o = if area == 4 && ix == 2 {
                ((sum + 2) >> 2) as u8
            } else {
                (sum as f32 * scale).round_ties_even().clamp(0.0, 255.0) as u8
            };
        }
    });
    dst
}

/// PyTorch bicubic interpolation of a contiguous `(C, h, w)` f32 array by the scale factors
/// `(sy, sx)`, output `(C, floor(h·sy), floor(w·sx))`: source coordinate `(o + 0.5) / s − 0.5`
/// computed in f32 (PyTorch's `opmath` for f32), A = −0.75, indices clamped to the border.
pub fn bicubic_scale(src: &[f32], c: usize, h: usize, w: usize, sy: f64, sx: f64) -> (Vec<f32>, usize, usize) {
    let oh = (h as f64 * sy).floor() as usize;
    let ow = (w as f64 * sx).floor() as usize;
    let taps = |n_in: usize, n_out: usize, s: f64| -> Vec<([usize; 4], [f32; 4])> {
        let inv = (1.0 / s) as f32;
        (0..n_out)
            .map(|o| {
                let real = inv * (o as f32 + 0.5) - 0.5;
                let i = real.floor();
                let t = real - i;
                let idx = std::array::from_fn(|j| (i as isize - 1 + j as isize).clamp(0, n_in as isize - 1) as usize);
                (idx, torch_cubic_coeffs(t))
            })
            .collect()
    };
    let yt = taps(h, oh, sy);
    let xt = taps(w, ow, sx);
    let mut out = vec![0f32; c * oh * ow];
    out.par_chunks_mut(oh * ow).enumerate().for_each(|(ch, dst)| {
        let plane = &src[ch * h * w..(ch + 1) * h * w];
        for (oy, (iy, wy)) in yt.iter().enumerate() {
            for (ox, (ix, wx)) in xt.iter().enumerate() {
                let mut acc = 0f32;
                for (r, wyr) in iy.iter().zip(wy) {
                    let row = &plane[r * w..(r + 1) * w];
                    let v = row[ix[0]] * wx[0] + row[ix[1]] * wx[1] + row[ix[2]] * wx[2] + row[ix[3]] * wx[3];
                    acc += v * wyr;
                }
                dst[oy * ow + ox] = acc;
            }
        }
    });
    (out, oh, ow)
}

/// PyTorch `get_cubic_upsample_coefficients` (A = −0.75).
fn torch_cubic_coeffs(t: f32) -> [f32; 4] {
    const A: f32 = -0.75;
    let cc1 = |x: f32| ((A + 2.0) * x - (A + 3.0)) * x * x + 1.0;
    let cc2 = |x: f32| ((A * x - 5.0 * A) * x + 8.0 * A) * x - 4.0 * A;
    [cc2(t + 1.0), cc1(t), cc1(1.0 - t), cc2(2.0 - t)]
}

/// `F.interpolate(xs, size=(h, w), mode="bilinear", align_corners=True)` for an f32
/// `(B, C, H, W)` tensor: source coordinate `o · (H − 1)/(h − 1)`.
pub fn bilinear_align_corners(xs: &Tensor, h: usize, w: usize) -> Result<Tensor> {
    bilinear(xs, h, w, true)
}

/// `F.interpolate(xs, size=(h, w), mode="bilinear", align_corners=False)`: source coordinate
/// `(o + 0.5) · H/h − 0.5`, clamped below at 0; no antialiasing.
pub fn bilinear_half_pixel(xs: &Tensor, h: usize, w: usize) -> Result<Tensor> {
    bilinear(xs, h, w, false)
}

/// Parallel f32 kernel on the CPU (weights in f32 as PyTorch's `opmath`); elsewhere candle's
/// `upsample_bilinear2d`, which implements the same formulas.
fn bilinear(xs: &Tensor, h: usize, w: usize, align_corners: bool) -> Result<Tensor> {
    let _t = pixl_nn::profile::span("bilinear resize");
    let (_, _, ih, iw) = xs.dims4()?;
    if ih == h && iw == w {
        return Ok(xs.clone());
    }
    if ih == 0 || iw == 0 || h == 0 || w == 0 {
        candle_core::bail!("bilinear resize from {ih}x{iw} to {h}x{w}: sizes must be positive");
    }
    if !xs.device().is_cpu() || xs.dtype() != candle_core::DType::F32 {
        return xs.upsample_bilinear2d(h, w, align_corners);
    }
    xs.contiguous()?.apply_op1_no_bwd(&Bilinear { h, w, align_corners })
}

struct Bilinear {
    h: usize,
    w: usize,
    align_corners: bool,
}

/// Source index pair and weight of each output sample (PyTorch `area_pixel_compute_scale` /
/// `area_pixel_compute_source_index`, linear mode).
fn linear_taps(n_in: usize, n_out: usize, align_corners: bool) -> Vec<(usize, usize, f32)> {
    let scale = if align_corners {
        if n_out > 1 {
            (n_in - 1) as f32 / (n_out - 1) as f32
        } else {
            0.0
        }
    } else {
        n_in as f32 / n_out as f32
    };
    (0..n_out)
        .map(|o| {
            let src = if align_corners {
                scale * o as f32
            } else {
                (scale * (o as f32 + 0.5) - 0.5).max(0.0)
            };
            let i0 = (src.floor() as usize).min(n_in - 1);
            let i1 = (i0 + 1).min(n_in - 1);
            (i0, i1, (src - i0 as f32).clamp(0.0, 1.0))
        })
        .collect()
}

impl CustomOp1 for Bilinear {
    fn name(&self) -> &'static str {
        "da3-bilinear"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        let (b, c, ih, iw) = layout.shape().dims4()?;
        let src = match storage {
            CpuStorage::F32(v) => v,
            _ => candle_core::bail!("da3 bilinear resize: expected f32"),
        };
        let src = match layout.contiguous_offsets() {
            Some((start, end)) => &src[start..end],
            None => candle_core::bail!("da3 bilinear resize: expected a contiguous input"),
        };
        let (h, w) = (self.h, self.w);
        let yt = linear_taps(ih, h, self.align_corners);
        let xt = linear_taps(iw, w, self.align_corners);
        let mut out = vec![0f32; b * c * h * w];
        // One task per output row (of every plane), so a single large plane is parallel too.
        out.par_chunks_mut(w).enumerate().for_each(|(r, row)| {
            let (p, oy) = (r / h, r % h);
            let plane = &src[p * ih * iw..(p + 1) * ih * iw];
            let (y0, y1, fy) = yt[oy];
            let (r0, r1) = (&plane[y0 * iw..(y0 + 1) * iw], &plane[y1 * iw..(y1 + 1) * iw]);
            for (o, &(x0, x1, fx)) in row.iter_mut().zip(&xt) {
                let top = r0[x0] * (1.0 - fx) + r0[x1] * fx;
                let bot = r1[x0] * (1.0 - fx) + r1[x1] * fx;
                *o = top * (1.0 - fy) + bot * fy;
            }
        });
        Ok((CpuStorage::F32(out), Shape::from((b, c, h, w))))
    }
}

/// Taps of PyTorch's antialiased linear resampling along one axis: for each output sample, the
/// first source index and the normalised weights (ATen `_compute_index_ranges_weights`,
/// `aa_filter` = triangle, support `max(scale, 1)`).
fn aa_taps(n_in: usize, n_out: usize) -> Vec<(usize, Vec<f32>)> {
    let scale = n_in as f32 / n_out as f32;
    let support = if scale >= 1.0 { scale } else { 1.0 };
    let invscale = if scale >= 1.0 { 1.0 / scale } else { 1.0 };
    (0..n_out)
        .map(|i| {
            let center = scale * (i as f32 + 0.5);
            // int64_t truncation toward zero, then clamped to the image.
            let xmin = ((center - support + 0.5) as i64).max(0) as usize;
            let xmax = ((center + support + 0.5) as i64).clamp(0, n_in as i64) as usize;
            let mut w: Vec<f32> = (xmin..xmax.max(xmin))
                .map(|j| {
                    let x = (j as f32 - center + 0.5) * invscale;
                    (1.0 - x.abs()).max(0.0)
                })
                .collect();
            let total: f32 = w.iter().sum();
            if total != 0.0 {
                w.iter_mut().for_each(|v| *v /= total);
            }
            (xmin, w)
        })
        .collect()
}

/// `F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)` of a
/// planar f32 image `(c, ih, iw)`: columns first, then rows (ATen's order), parallel over planes.
pub fn bilinear_antialias(src: &[f32], c: usize, ih: usize, iw: usize, h: usize, w: usize) -> Vec<f32> {
    assert_eq!(src.len(), c * ih * iw, "bilinear_antialias: buffer size");
    if ih == 0 || iw == 0 || h == 0 || w == 0 {
        return vec![0.0; c * h * w];
    }
    let tx = aa_taps(iw, w);
    let ty = aa_taps(ih, h);
    let mut out = vec![0.0f32; c * h * w];
    out.par_chunks_mut(h * w).enumerate().for_each(|(ch, dst)| {
        let plane = &src[ch * ih * iw..(ch + 1) * ih * iw];
        let mut mid = vec![0.0f32; ih * w];
        for y in 0..ih {
            let row = &plane[y * iw..(y + 1) * iw];
            for (x, (x0, wx)) in tx.iter().enumerate() {
                mid[y * w + x] = wx.iter().enumerate().map(|(k, wk)| row[x0 + k] * wk).sum();
            }
        }
        for (y, (y0, wy)) in ty.iter().enumerate() {
            for x in 0..w {
                dst[y * w + x] = wy.iter().enumerate().map(|(k, wk)| mid[(y0 + k) * w + x] * wk).sum();
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Both bilinear modes against candle's own `upsample_bilinear2d` (same formulas, computed
    /// in f64 there), up and down, several planes.
    #[test]
    fn bilinear_matches_candle_kernel() {
        let xs = Tensor::randn(0f32, 1.0, (2, 3, 11, 17), &Device::Cpu).unwrap();
        for (h, w) in [(23, 40), (5, 9), (11, 17), (1, 4)] {
            for ac in [true, false] {
                let ours = if ac {
                    bilinear_align_corners(&xs, h, w)
                } else {
                    bilinear_half_pixel(&xs, h, w)
                }
                .unwrap();
                let theirs = xs.upsample_bilinear2d(h, w, ac).unwrap();
                let err = (ours - theirs)
                    .unwrap()
                    .abs()
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .max(0)
                    .unwrap();
                let err = err.to_scalar::<f32>().unwrap();
                assert!(err < 1e-5, "{h}x{w} align_corners={ac}: {err}");
            }
        }
    }

    /// cv2 size-preserving resizes copy; a 1-pixel image upscales to a constant.
    #[test]
    fn cv2_resize_trivial_cases() {
        let src: Vec<u8> = (0..2 * 3 * 3).map(|v| v as u8 * 10).collect();
        assert_eq!(cv2_resize_u8(&src, 3, 2, 3, 3, 2, Cv2Filter::Cubic), src);
        let one = [7u8, 8, 9];
        let up = cv2_resize_u8(&one, 1, 1, 3, 4, 3, Cv2Filter::Cubic);
        assert!(up.chunks(3).all(|p| p == one));
    }

    #[test]
    fn antialias_halving_is_a_tent_average_and_upscaling_is_plain_bilinear() {
        // 4 -> 2: scale 2, support 2; output 0 centred at 1.0 sees pixels 0..=2 with triangle
        // weights (0.75, 0.75, 0.25) normalised; by hand: (0.75·1 + 0.75·2 + 0.25·3) / 1.75.
        let out = bilinear_antialias(&[1.0, 2.0, 3.0, 4.0], 1, 1, 4, 1, 2);
        assert!((out[0] - 3.0 / 1.75).abs() < 1e-6, "{out:?}");
        assert!((out[1] - (0.25 * 2.0 + 0.75 * 3.0 + 0.75 * 4.0) / 1.75).abs() < 1e-6);
        // Enlarging: the same as align_corners=False bilinear, border clamped.
        let up = bilinear_antialias(&[0.0, 1.0], 1, 1, 2, 1, 4);
        let want = [0.0, 0.25, 0.75, 1.0];
        for (a, b) in up.iter().zip(want) {
            assert!((a - b).abs() < 1e-6, "{up:?}");
        }
    }
}
