//! Image metrics of paper §4.1: per-channel least-squares scale correction, PSNR and SSIM.
//!
//! Inputs are [`Image`]s with the same width, height and channel count (normally 3-channel sRGB
//! in [0, 1], compared at native target resolution). All sums are accumulated in `f64`. Every
//! function returns [`MetricError`] on mismatched or unusable inputs instead of panicking.
use pixl_core::Image;

/// Why a metric could not be computed.
#[derive(Debug, thiserror::Error)]
pub enum MetricError {
    #[error("prediction is {pw}x{ph}x{pc} but the ground truth is {gw}x{gh}x{gc}; metrics need equal sizes")]
    Shape {
        pw: usize,
        ph: usize,
        pc: usize,
        gw: usize,
        gh: usize,
        gc: usize,
    },
    #[error("image is empty ({width}x{height}x{channels})")]
    Empty {
        width: usize,
        height: usize,
        channels: usize,
    },
    #[error("SSIM needs images of at least {win}x{win} pixels (valid filtering), got {width}x{height}")]
    TooSmall { width: usize, height: usize, win: usize },
    #[error("{which} contains non-finite values (NaN/Inf); metrics are undefined")]
    NonFinite { which: &'static str },
    #[error("the light-response score needs one relit image per render and at least two lightings, got {relit} relit images and {renders} renders")]
    Lightings { relit: usize, renders: usize },
    #[error("the patch-grid score needs an image whose sides are multiples of the period (>= 2), got {width}x{height} and period {period}")]
    Grid { width: usize, height: usize, period: usize },
    #[error("the renders are the same under every lighting: there is no change of light to respond to")]
    NoLightChange,
}

/// `img` (called `which` in errors) has `reference`'s size, holds values and they are finite.
pub(crate) fn check_image(img: &Image, which: &'static str, reference: &Image) -> Result<(), MetricError> {
    if (img.width, img.height, img.channels) != (reference.width, reference.height, reference.channels) {
        return Err(MetricError::Shape {
            pw: img.width,
            ph: img.height,
            pc: img.channels,
            gw: reference.width,
            gh: reference.height,
            gc: reference.channels,
        });
    }
    if img.data.is_empty() {
        return Err(MetricError::Empty {
            width: img.width,
            height: img.height,
            channels: img.channels,
        });
    }
    if img.data.iter().any(|v| !v.is_finite()) {
        return Err(MetricError::NonFinite { which });
    }
    Ok(())
}

fn check_pair(pred: &Image, gt: &Image) -> Result<(), MetricError> {
    check_image(pred, "prediction", gt)?;
    check_image(gt, "ground truth", gt)
}

/// Per-image, per-channel least-squares scale correction (paper §4.1, after Kocsis et al. 2024):
/// for each channel `c`, `s_c = Σ gt_c·pred_c / Σ pred_c²` (the `s` minimising `Σ (s·pred_c − gt_c)²`;
/// `s_c = 0` when `Σ pred_c² = 0`), then `pred_c ← clip(s_c·pred_c, 0, 1)`.
/// Sums run over every pixel of the channel, in `f64`.
pub fn scale_correct(pred: &Image, gt: &Image) -> Result<Image, MetricError> {
    check_pair(pred, gt)?;
    let ch = pred.channels;
    let mut num = vec![0f64; ch];
    let mut den = vec![0f64; ch];
    for (p, g) in pred.data.chunks_exact(ch).zip(gt.data.chunks_exact(ch)) {
        for c in 0..ch {
            num[c] += g[c] as f64 * p[c] as f64;
            den[c] += p[c] as f64 * p[c] as f64;
        }
    }
    let scale: Vec<f64> = num
        .iter()
        .zip(&den)
        .map(|(&n, &d)| if d > 0.0 { n / d } else { 0.0 })
        .collect();
    let mut out = pred.clone();
    for px in out.data.chunks_exact_mut(ch) {
        for c in 0..ch {
            px[c] = (scale[c] * px[c] as f64).clamp(0.0, 1.0) as f32;
        }
    }
    Ok(out)
}

/// Mean squared error over all pixels and channels, in `f64`.
pub fn mse(pred: &Image, gt: &Image) -> Result<f64, MetricError> {
    check_pair(pred, gt)?;
    let sum: f64 = pred
        .data
        .iter()
        .zip(&gt.data)
        .map(|(&p, &g)| (p as f64 - g as f64).powi(2))
        .sum();
    Ok(sum / pred.data.len() as f64)
}

/// PSNR with data range 1: `10·log10(1 / MSE)`, MSE over all pixels and channels.
/// Identical images give `f64::INFINITY` (reported as "inf" in tables and JSON).
pub fn psnr(pred: &Image, gt: &Image) -> Result<f64, MetricError> {
    let m = mse(pred, gt)?;
    Ok(if m == 0.0 { f64::INFINITY } else { -10.0 * m.log10() })
}

/// SSIM window side (Wang et al. 2004).
pub const SSIM_WIN: usize = 11;
/// SSIM Gaussian window standard deviation.
pub const SSIM_SIGMA: f64 = 1.5;
/// SSIM stabilising constants `C1 = (K1·L)²`, `C2 = (K2·L)²` with `L = 1`.
pub const SSIM_K1: f64 = 0.01;
pub const SSIM_K2: f64 = 0.03;

/// The normalised 1-D Gaussian of the SSIM window: `g_i ∝ exp(−(i−5)²/(2·1.5²))`, `Σ g = 1`, so
/// the 2-D window `w_ij = g_i·g_j` is the normalised 11×11 Gaussian (MATLAB `fspecial('gaussian', 11, 1.5)`).
pub fn ssim_gaussian_1d() -> [f64; SSIM_WIN] {
    let mut g = [0f64; SSIM_WIN];
    let r = (SSIM_WIN / 2) as f64;
    for (i, v) in g.iter_mut().enumerate() {
        let d = i as f64 - r;
        *v = (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = g.iter().sum();
    g.iter_mut().for_each(|v| *v /= s);
    g
}

/// SSIM (Wang, Bovik, Sheikh, Simoncelli 2004) with the paper's standard settings: 11×11 Gaussian
/// window σ = 1.5 (normalised), K1 = 0.01, K2 = 0.03, data range L = 1, no covariance
/// (N/(N−1)) correction. For each channel the local statistics `μx, μy, σx², σy², σxy` are
/// Gaussian-weighted moments, the SSIM map is
/// `((2μxμy + C1)(2σxy + C2)) / ((μx² + μy² + C1)(σx² + σy² + C2))`,
/// and the channel score is the mean of the map; the result is the mean over channels.
///
/// Borders: **"valid" filtering** — the map is computed only where the whole window lies inside
/// the image, an `(H−10)×(W−10)` map, as in Wang's original MATLAB `ssim_index.m`
/// (`filter2(window, img, 'valid')`) and `pytorch_msssim`. (skimage's default pads by reflection
/// and then crops, so its numbers differ slightly.) Images smaller than 11×11 are an error.
/// Filtering is separable (rows, then columns), accumulated in `f64`.
pub fn ssim(pred: &Image, gt: &Image) -> Result<f64, MetricError> {
    check_pair(pred, gt)?;
    let (w, h, ch) = (pred.width, pred.height, pred.channels);
    if w < SSIM_WIN || h < SSIM_WIN {
        return Err(MetricError::TooSmall {
            width: w,
            height: h,
            win: SSIM_WIN,
        });
    }
    let g = ssim_gaussian_1d();
    let c1 = (SSIM_K1 * 1.0).powi(2);
    let c2 = (SSIM_K2 * 1.0).powi(2);
    let (ow, oh) = (w - SSIM_WIN + 1, h - SSIM_WIN + 1);
    let mut total = 0f64;
    for c in 0..ch {
        let x: Vec<f64> = pred.data.iter().skip(c).step_by(ch).map(|&v| v as f64).collect();
        let y: Vec<f64> = gt.data.iter().skip(c).step_by(ch).map(|&v| v as f64).collect();
        let xx: Vec<f64> = x.iter().map(|v| v * v).collect();
        let yy: Vec<f64> = y.iter().map(|v| v * v).collect();
        let xy: Vec<f64> = x.iter().zip(&y).map(|(a, b)| a * b).collect();
        let [mx, my, sxx, syy, sxy] = [&x, &y, &xx, &yy, &xy].map(|s| filter_valid(s, w, h, &g));
        let mut sum = 0f64;
        for i in 0..ow * oh {
            let (ux, uy) = (mx[i], my[i]);
            let vx = sxx[i] - ux * ux;
            let vy = syy[i] - uy * uy;
            let cxy = sxy[i] - ux * uy;
            sum += ((2.0 * ux * uy + c1) * (2.0 * cxy + c2)) / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
        }
        total += sum / (ow * oh) as f64;
    }
    Ok(total / ch as f64)
}

/// Separable "valid" correlation of a `w×h` plane with `g ⊗ g`: output `(w−k+1)×(h−k+1)`, row-major.
fn filter_valid(src: &[f64], w: usize, h: usize, g: &[f64]) -> Vec<f64> {
    let k = g.len();
    let ow = w - k + 1;
    let oh = h - k + 1;
    // Horizontal pass: h rows × ow columns.
    let mut rows = vec![0f64; h * ow];
    for y in 0..h {
        let line = &src[y * w..(y + 1) * w];
        for x in 0..ow {
            rows[y * ow + x] = line[x..x + k].iter().zip(g).map(|(a, b)| a * b).sum();
        }
    }
    // Vertical pass: accumulate k shifted rows.
    let mut out = vec![0f64; oh * ow];
    for y in 0..oh {
        let dst = &mut out[y * ow..(y + 1) * ow];
        for (j, &gj) in g.iter().enumerate() {
            let srow = &rows[(y + j) * ow..(y + j + 1) * ow];
            for (d, s) in dst.iter_mut().zip(srow) {
                *d += gj * s;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_core::Rng;

    fn random_image(w: usize, h: usize, seed: u64) -> Image {
        let mut rng = Rng::new(seed);
        let data = (0..w * h * 3).map(|_| rng.f32()).collect();
        Image::from_vec(w, h, 3, data).unwrap()
    }

    #[test]
    fn identical_images_psnr_inf_ssim_one() {
        let a = random_image(32, 24, 1);
        assert_eq!(psnr(&a, &a).unwrap(), f64::INFINITY);
        let s = ssim(&a, &a).unwrap();
        assert!((s - 1.0).abs() < 1e-12, "ssim {s}");
    }

    #[test]
    fn constant_offset_psnr() {
        // gt in [0, 0.8] so gt + δ stays inside [0, 1]; the offset is measured in f32 as stored.
        for &delta in &[0.1f32, 0.01, 0.003] {
            let gt = random_image(20, 16, 2).map(|v| 0.8 * v);
            let pred = gt.map(|v| v + delta);
            let expect = -20.0 * (delta as f64).log10();
            let got = psnr(&pred, &gt).unwrap();
            assert!((got - expect).abs() < 1e-3, "delta {delta}: psnr {got} vs {expect}");
        }
    }

    #[test]
    fn scale_correction_recovers_exact_scaling() {
        let gt = random_image(16, 16, 3);
        let pred = gt.map(|v| v / 2.0);
        let fixed = scale_correct(&pred, &gt).unwrap();
        assert_eq!(psnr(&fixed, &gt).unwrap(), f64::INFINITY);
        assert!(psnr(&pred, &gt).unwrap().is_finite());
    }

    #[test]
    fn scale_correction_per_channel_and_clipped() {
        // Channel 0 is 1/4 of gt, channel 1 is 2x gt, channel 2 all zero: s = 4, 0.5, 0.
        let gt = Image::from_fn(4, 4, 3, |x, y, _| 0.1 + 0.05 * (x + y) as f32);
        let pred = Image::from_fn(4, 4, 3, |x, y, c| {
            let g = gt.get(x, y, c);
            [g / 4.0, 2.0 * g, 0.0][c]
        });
        let fixed = scale_correct(&pred, &gt).unwrap();
        for y in 0..4 {
            for x in 0..4 {
                assert!((fixed.get(x, y, 0) - gt.get(x, y, 0)).abs() < 1e-6);
                assert!((fixed.get(x, y, 1) - gt.get(x, y, 1)).abs() < 1e-6);
                assert_eq!(fixed.get(x, y, 2), 0.0);
            }
        }
        // A scale that pushes values above 1 is clipped: least squares of pred = [0.1, 0.5] vs
        // gt = [1, 1] gives s = 0.6/0.26, so 0.5·s > 1 → 1.
        let gt = Image::from_vec(2, 1, 1, vec![1.0, 1.0]).unwrap();
        let pred = Image::from_vec(2, 1, 1, vec![0.1, 0.5]).unwrap();
        let fixed = scale_correct(&pred, &gt).unwrap();
        let s = 0.6f64 / 0.26;
        assert!((fixed.data[0] as f64 - 0.1 * s).abs() < 1e-6);
        assert_eq!(fixed.data[1], 1.0);
    }

    #[test]
    fn ssim_is_symmetric() {
        let a = random_image(40, 30, 4);
        let b = random_image(40, 30, 5);
        let ab = ssim(&a, &b).unwrap();
        let ba = ssim(&b, &a).unwrap();
        assert!((ab - ba).abs() < 1e-12, "{ab} vs {ba}");
        assert!(ab < 0.5, "unrelated noise images should score low, got {ab}");
    }

    /// SSIM written the most direct way: 2-D window from its definition, direct loops, f64.
    #[allow(clippy::needless_range_loop)] // index loops are the point of a naive reference
    fn naive_ssim(a: &Image, b: &Image) -> f64 {
        let (w, h, ch) = (a.width, a.height, a.channels);
        let mut win = [[0f64; 11]; 11];
        let mut s = 0.0;
        for (i, row) in win.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                let (di, dj) = (i as f64 - 5.0, j as f64 - 5.0);
                *v = (-(di * di + dj * dj) / (2.0 * 1.5 * 1.5)).exp();
                s += *v;
            }
        }
        let (c1, c2) = (0.0001, 0.0009);
        let mut total = 0.0;
        for c in 0..ch {
            let mut sum = 0.0;
            let mut n = 0usize;
            for y0 in 0..=h - 11 {
                for x0 in 0..=w - 11 {
                    let (mut mx, mut my, mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for i in 0..11 {
                        for j in 0..11 {
                            let wt = win[i][j] / s;
                            let x = a.get(x0 + j, y0 + i, c) as f64;
                            let y = b.get(x0 + j, y0 + i, c) as f64;
                            mx += wt * x;
                            my += wt * y;
                        }
                    }
                    for i in 0..11 {
                        for j in 0..11 {
                            let wt = win[i][j] / s;
                            let x = a.get(x0 + j, y0 + i, c) as f64 - mx;
                            let y = b.get(x0 + j, y0 + i, c) as f64 - my;
                            sxx += wt * x * x;
                            syy += wt * y * y;
                            sxy += wt * x * y;
                        }
                    }
                    sum += (2.0 * mx * my + c1) * (2.0 * sxy + c2) / ((mx * mx + my * my + c1) * (sxx + syy + c2));
                    n += 1;
                }
            }
            total += sum / n as f64;
        }
        total / ch as f64
    }

    #[test]
    fn ssim_matches_naive_reference() {
        for seed in 0..3 {
            let a = random_image(64, 64, 10 + seed);
            // A correlated second image so the score is not near 0.
            let noise = random_image(64, 64, 20 + seed);
            let data = a.data.iter().zip(&noise.data).map(|(x, n)| 0.7 * x + 0.3 * n).collect();
            let b = Image::from_vec(64, 64, 3, data).unwrap();
            let fast = ssim(&a, &b).unwrap();
            let slow = naive_ssim(&a, &b);
            assert!((fast - slow).abs() < 1e-6, "seed {seed}: {fast} vs naive {slow}");
            assert!(fast > 0.2 && fast < 0.99, "seed {seed}: implausible SSIM {fast}");
        }
        // Non-square, and a non-multiple-of-anything size.
        let a = random_image(23, 37, 7);
        let b = random_image(23, 37, 8);
        assert!((ssim(&a, &b).unwrap() - naive_ssim(&a, &b)).abs() < 1e-6);
    }

    /// Flat image x = μ against y = μ + n, n ~ N(0, σ²) i.i.d.: locally σx = σxy = 0 and the
    /// luminance term is 1 − O(σ²Σw²/μ²) ≈ 1, so SSIM = C2 / (V + C2) with V the Gaussian-weighted
    /// local variance of n. V = nᵀMn with M = diag(w) − wwᵀ: E[V] = σ²(1 − Σw²),
    /// Var[V] = 2σ⁴ tr(M²) = 2σ⁴(Σw² − 2Σw³ + (Σw²)²). To second order,
    /// E[C2/(V+C2)] ≈ C2/D̄ · (1 + Var[V]/D̄²) with D̄ = E[V] + C2; higher orders and sampling error are well under 2 %.
    #[test]
    fn ssim_against_gaussian_noise_matches_closed_form() {
        let g = ssim_gaussian_1d();
        let w2: Vec<f64> = g.iter().flat_map(|a| g.iter().map(move |b| a * b)).collect();
        let s2: f64 = w2.iter().map(|w| w * w).sum();
        let s3: f64 = w2.iter().map(|w| w * w * w).sum();
        let c2 = 0.0009;
        for &sigma in &[0.02f64, 0.05, 0.1] {
            let var = sigma * sigma;
            let ev = var * (1.0 - s2);
            let vv = 2.0 * var * var * (s2 - 2.0 * s3 + s2 * s2);
            let d = ev + c2;
            let expect = c2 / d * (1.0 + vv / (d * d));
            let mut rng = Rng::new(99);
            let (w, h) = (160, 160);
            let x = Image::from_fn(w, h, 3, |_, _, _| 0.5);
            let data = x
                .data
                .iter()
                .map(|&v| v + (sigma * rng.normal() as f64) as f32)
                .collect();
            let y = Image::from_vec(w, h, 3, data).unwrap();
            let got = ssim(&x, &y).unwrap();
            let first_order = c2 / d;
            assert!(
                got >= 0.98 * first_order,
                "sigma {sigma}: {got} below Jensen bound {first_order}"
            );
            assert!(
                (got - expect).abs() < 0.02 * expect,
                "sigma {sigma}: SSIM {got}, closed form {expect}"
            );
        }
    }

    #[test]
    fn errors_not_panics() {
        let a = random_image(16, 16, 1);
        let b = random_image(16, 15, 1);
        assert!(matches!(psnr(&a, &b), Err(MetricError::Shape { .. })));
        let small = random_image(10, 40, 1);
        assert!(matches!(ssim(&small, &small), Err(MetricError::TooSmall { .. })));
        let mut nan = a.clone();
        nan.data[5] = f32::NAN;
        assert!(matches!(psnr(&nan, &a), Err(MetricError::NonFinite { .. })));
        assert!(ssim(&a, &nan).is_err());
    }
}
