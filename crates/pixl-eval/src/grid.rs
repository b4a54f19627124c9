//! The patch-grid score: how strongly an image repeats with the network's patch period — the
//! "8-px grid" a ViT-based predictor can print on flat regions. No ground truth needed.
//!
//! The image (sRGB values, all channels averaged) is averaged over rows into a profile along `x`
//! and over columns into a profile along `y`; a grid of period `p` lines up across rows and
//! columns and survives that averaging, while texture and noise mostly cancel. For each profile
//! of length `N` (a multiple of `p`), its discrete Fourier transform `F` is taken at the grid's
//! harmonics (after removing the profile's least-squares line) `k = m·N/p`, `m = 1 … ⌊p/2⌋`; each harmonic's RMS (`√2|F(k)|/N`, or `|F(k)|/N` at
//! the Nyquist bin) counts only as far as it exceeds the median RMS of the six bins around it
//! (`k ± 1, 2, 3`: smooth content has a smooth spectrum). The **amplitude** is the root of the
//! sum of the squared excesses over the harmonics of both profiles: by Parseval, the RMS of the
//! periodic pattern (an added square wave of ±a scores ≈ a, tested), in sRGB units (1/255 ≈ 0.0039).
use crate::metrics::MetricError;
use pixl_core::Image;

/// The patch-grid amplitude of `img` for period `period` (see the module docs).
///
/// Errors: an empty image, a period below 2, or sides that are not multiples of the period.
pub fn patch_grid_amplitude(img: &Image, period: usize) -> Result<f64, MetricError> {
    let (w, h, ch) = (img.width, img.height, img.channels);
    if w == 0 || h == 0 || ch == 0 || period < 2 || w % period != 0 || h % period != 0 {
        return Err(MetricError::Grid {
            width: w,
            height: h,
            period,
        });
    }
    let mut px = vec![0f64; w];
    let mut py = vec![0f64; h];
    for (y, row_mean) in py.iter_mut().enumerate() {
        for (x, col_mean) in px.iter_mut().enumerate() {
            let v: f64 = (0..ch).map(|c| img.get(x, y, c) as f64).sum::<f64>() / ch as f64;
            *col_mean += v / h as f64;
            *row_mean += v / w as f64;
        }
    }
    Ok((harmonic_excess(&px, period) + harmonic_excess(&py, period)).sqrt())
}

/// Σ over the harmonics of period `p` of the squared excess RMS of `s` (module docs), after
/// removing its least-squares line (a gradient's wrap-around jump would leak into every bin).
fn harmonic_excess(s: &[f64], p: usize) -> f64 {
    let n = s.len();
    let tm = (n as f64 - 1.0) / 2.0;
    let mean = s.iter().sum::<f64>() / n as f64;
    let (sxy, sxx) = s.iter().enumerate().fold((0.0, 0.0), |(a, b), (t, v)| {
        let dt = t as f64 - tm;
        (a + dt * (v - mean), b + dt * dt)
    });
    let slope = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let s: Vec<f64> = s
        .iter()
        .enumerate()
        .map(|(t, v)| v - mean - slope * (t as f64 - tm))
        .collect();
    let amp = |k: usize| {
        let (mut re, mut im) = (0f64, 0f64);
        for (t, v) in s.iter().enumerate() {
            let a = -2.0 * std::f64::consts::PI * (k * t % n) as f64 / n as f64;
            re += v * a.cos();
            im += v * a.sin();
        }
        // RMS of the real sinusoid at bin k (the Nyquist bin holds it whole, not split)
        let scale = if 2 * k == n { 1.0 } else { std::f64::consts::SQRT_2 };
        scale * (re * re + im * im).sqrt() / n as f64
    };
    let mut sum = 0.0;
    for m in 1..=p / 2 {
        let k = m * n / p;
        // Neighbouring bins, folded into 1 … n/2 (the spectrum of a real signal is symmetric).
        let mut around: Vec<f64> = [-3i64, -2, -1, 1, 2, 3]
            .iter()
            .map(|d| {
                let j = (k as i64 + d).rem_euclid(n as i64) as usize;
                amp(j.min(n - j))
            })
            .collect();
        around.sort_by(f64::total_cmp);
        let floor = 0.5 * (around[2] + around[3]);
        sum += (amp(k) - floor).max(0.0).powi(2);
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat image and a smooth gradient score (about) 0; a square wave of period 8 and
    /// amplitude ±a added along x scores about its RMS a (on a gradient), one along both axes
    /// about a·√2; a period the image does not repeat with is not detected.
    #[test]
    fn detects_a_grid_and_ignores_smooth_content() {
        let flat = Image::from_fn(64, 48, 3, |_, _, _| 0.4);
        assert!(patch_grid_amplitude(&flat, 8).unwrap() < 1e-9);
        let ramp = Image::from_fn(64, 48, 3, |x, y, _| 0.2 + 0.004 * x as f32 + 0.002 * y as f32);
        assert!(patch_grid_amplitude(&ramp, 8).unwrap() < 2e-3);
        let a = 0.02f32;
        let sq = |t: usize| if t % 8 < 4 { a } else { -a };
        let grid_x = Image::from_fn(64, 48, 3, |x, y, _| 0.2 + 0.004 * x as f32 + 0.002 * y as f32 + sq(x));
        let gx = patch_grid_amplitude(&grid_x, 8).unwrap();
        assert!((gx - a as f64).abs() < 0.15 * a as f64, "square wave along x: {gx}");
        let grid_xy = Image::from_fn(64, 48, 3, |x, y, _| 0.4 + sq(x) + sq(y));
        let gxy = patch_grid_amplitude(&grid_xy, 8).unwrap();
        assert!(
            (gxy - (2.0f64).sqrt() * a as f64).abs() < 0.2 * a as f64,
            "both axes: {gxy}"
        );
        let other = Image::from_fn(64, 48, 3, |x, _, _| {
            0.4 + 0.02 * (2.0 * std::f32::consts::PI * x as f32 / 6.4).sin()
        });
        assert!(patch_grid_amplitude(&other, 8).unwrap() < 5e-3);
    }

    #[test]
    fn sides_must_be_multiples_of_the_period() {
        let img = Image::from_fn(30, 16, 3, |_, _, _| 0.5);
        assert!(patch_grid_amplitude(&img, 8).is_err());
        assert!(patch_grid_amplitude(&img, 1).is_err());
    }
}
