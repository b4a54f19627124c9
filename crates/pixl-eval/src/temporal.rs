//! Flicker of a clip (for relit video; see the crate README).
//!
//! Both scores work on luminance `Y = 0.2126 R + 0.7152 G + 0.0722 B` of the stored values, in
//! logarithms with an offset [`FLICKER_EPS`] so that near-black pixels do not dominate, per pixel
//! over time, averaged over the pixels:
//! - [`temporal_noise`]`(clip)`: `mean_p std_t log(Y_t(p) + ε)` — how much a clip's own pixels
//!   change from frame to frame (sensor or render noise, exposure changes, moving things).
//! - [`added_flicker`]`(relit, source)`: `mean_p std_t log((Y'_t(p) + ε) / (Y_t(p) + ε))` — how
//!   much the relit clip changes **relative to its source**: 0 when every relit frame is the
//!   source frame times one fixed per-pixel factor, however the source itself changes.
//!
//! A relit clip that flickers no more than its source has `added_flicker(relit, source) ≤
//! temporal_noise(source)` (relit video's acceptance uses a factor 1.1).
use pixl_core::Image;

/// The offset of the logarithms (about 2.5/255).
pub const FLICKER_EPS: f64 = 0.01;

fn luminance(img: &Image, i: usize) -> f64 {
    let p = &img.data[i * img.channels..];
    if img.channels >= 3 {
        0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64
    } else {
        p[0] as f64
    }
}

/// `mean_p std_t f_t(p)` for `f` over `n` frames of `pixels` pixels (population std).
fn mean_std(n: usize, pixels: usize, f: impl Fn(usize, usize) -> f64) -> f64 {
    if n < 2 || pixels == 0 {
        return 0.0;
    }
    let total: f64 = (0..pixels)
        .map(|p| {
            let (mut s, mut s2) = (0.0, 0.0);
            for t in 0..n {
                let v = f(t, p);
                s += v;
                s2 += v * v;
            }
            let mean = s / n as f64;
            (s2 / n as f64 - mean * mean).max(0.0).sqrt()
        })
        .sum();
    total / pixels as f64
}

fn pixels(clip: &[Image]) -> Option<usize> {
    let first = clip.first()?;
    clip.iter()
        .all(|f| (f.width, f.height) == (first.width, first.height))
        .then_some(first.width * first.height)
}

/// A clip's own frame-to-frame change (see the module docs); `None` for frames of different sizes.
pub fn temporal_noise(clip: &[Image]) -> Option<f64> {
    let px = pixels(clip)?;
    Some(mean_std(clip.len(), px, |t, p| {
        (luminance(&clip[t], p) + FLICKER_EPS).ln()
    }))
}

/// The relit clip's change relative to its source (see the module docs); `None` when the clips'
/// lengths or frame sizes differ.
pub fn added_flicker(relit: &[Image], source: &[Image]) -> Option<f64> {
    let px = pixels(relit)?;
    if relit.len() != source.len() || pixels(source)? != px {
        return None;
    }
    Some(mean_std(relit.len(), px, |t, p| {
        ((luminance(&relit[t], p) + FLICKER_EPS) / (luminance(&source[t], p) + FLICKER_EPS)).ln()
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grey(w: usize, h: usize, v: impl Fn(usize, usize) -> f32) -> Image {
        Image::from_fn(w, h, 3, |x, y, _| v(x, y))
    }

    #[test]
    fn a_fixed_per_pixel_factor_adds_no_flicker_and_a_frame_gain_adds_its_log_std() {
        // A source whose exposure changes: 0.3, 0.5, 0.4 (grey, so Y is the value).
        let levels = [0.3f32, 0.5, 0.4];
        let source: Vec<Image> = levels
            .iter()
            .map(|l| grey(4, 3, |x, _| l * (1.0 + x as f32 * 0.1)))
            .collect();
        // By hand: std over t of ln(l_t·k + ε) for each pixel, averaged.
        let by_hand = |vals: &[f64]| {
            let m = vals.iter().sum::<f64>() / vals.len() as f64;
            (vals.iter().map(|v| (v - m).powi(2)).sum::<f64>() / vals.len() as f64).sqrt()
        };
        let expected: f64 = (0..12)
            .map(|p| {
                let k = 1.0 + (p % 4) as f64 * 0.1;
                by_hand(&levels.map(|l| ((l as f64 * k) + FLICKER_EPS).ln()))
            })
            .sum::<f64>()
            / 12.0;
        let noise = temporal_noise(&source).unwrap();
        assert!((noise - expected).abs() < 1e-6, "{noise} vs {expected}");
        // relit = source (no relighting): 0.
        assert!(added_flicker(&source, &source).unwrap() < 1e-12);
        // relit = source + constant offset chosen so the ratio is fixed: (Y+ε)·2 - ε.
        let doubled: Vec<Image> = source
            .iter()
            .map(|f| f.map(|v| (v + FLICKER_EPS as f32) * 2.0 - FLICKER_EPS as f32))
            .collect();
        assert!(added_flicker(&doubled, &source).unwrap() < 1e-6);
        // A per-frame gain on (Y+ε): its log's std.
        let gains = [1.0f32, 1.2, 0.9];
        let flick: Vec<Image> = source
            .iter()
            .zip(gains)
            .map(|(f, g)| f.map(|v| (v + FLICKER_EPS as f32) * g - FLICKER_EPS as f32))
            .collect();
        let want = by_hand(&gains.map(|g| (g as f64).ln()));
        let got = added_flicker(&flick, &source).unwrap();
        assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        assert!(added_flicker(&flick[..2], &source).is_none());
    }
}
