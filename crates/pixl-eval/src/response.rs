//! The light-response score: how much of the change that new lights make to a scene shows up in
//! the relit images. It needs no ground truth, so it works on any photo: the path-traced renders
//! of the photo's coarse scene under the same lightings say which way each pixel should move.
//!
//! For `K ≥ 2` lightings with relit images `O_k` and renders `R_k` (sRGB-encoded in [0, 1], all of
//! one size), per pixel `p` the log-luminance `ℓ(I)_p = ln(Y(I)_p + ε)`, with `Y` the Rec. 709
//! luminance of the linearised pixel and `ε = 10⁻³`. Over every pair `i < j` and every pixel:
//!
//! - `a = ℓ(O_j) − ℓ(O_i)` (what the relit images did), `b = ℓ(R_j) − ℓ(R_i)` (what the light did);
//! - **gain** `= Σ a·b / Σ b²`: the least-squares slope of `a` on `b` through the origin — the
//!   fraction of the renders' change reproduced (1: all of it, 0: none; negative: the wrong way;
//!   noise in `a` that is unrelated to `b` does not move it in expectation);
//! - **correlation**: Pearson's r between `a` and `b` (direction alone, whatever the amplitude);
//!   0 when the relit images do not change at all.
//!
//! Identical relit images score gain 0 and correlation 0; relit images equal to the renders score
//! 1 and 1. Sums are accumulated in f64.
use crate::metrics::{check_image, MetricError};
use pixl_core::image::srgb_to_linear;
use pixl_core::Image;

/// Added to the luminance before the logarithm, so black pixels stay finite.
pub const EPS: f64 = 1e-3;

/// The light-response score of a set of relit images (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LightResponse {
    /// Σ a·b / Σ b²: the fraction of the renders' log-luminance change that the relit images show.
    pub gain: f64,
    /// Pearson's r between the two changes (0 when the relit images do not change).
    pub correlation: f64,
    /// Lighting pairs compared (K·(K − 1) / 2).
    pub pairs: usize,
    /// Pixels per pair.
    pub pixels: usize,
}

/// Per-pixel `ln(Y + ε)` of an sRGB-encoded image (1 or 3 channels).
fn log_luminance(img: &Image) -> Vec<f64> {
    let lin = |v: f32| srgb_to_linear(v.clamp(0.0, 1.0)) as f64;
    img.data
        .chunks_exact(img.channels)
        .map(|px| {
            let y = if px.len() >= 3 {
                0.2126 * lin(px[0]) + 0.7152 * lin(px[1]) + 0.0722 * lin(px[2])
            } else {
                lin(px[0])
            };
            (y + EPS).ln()
        })
        .collect()
}

/// The light-response score of `relit[k]` against `renders[k]`, `k = 0..K` (see the module docs).
///
/// Errors: fewer than two lightings, counts or sizes that differ, empty or non-finite images, or
/// renders that are the same under every lighting (no change to respond to).
pub fn light_response(relit: &[&Image], renders: &[&Image]) -> Result<LightResponse, MetricError> {
    let mut sums = ResponseSums::default();
    sums.add(relit, renders)?;
    sums.finish()
}

/// The sums behind [`light_response`], pooled over several sets of lightings (e.g. every
/// evaluation pair of a data set, each a source relit to its own and to another lighting): the
/// pooled score weighs every pixel of every pair alike.
#[derive(Clone, Debug, Default)]
pub struct ResponseSums {
    n: f64,
    sa: f64,
    sb: f64,
    sab: f64,
    saa: f64,
    sbb: f64,
    pairs: usize,
    pixels: usize,
}

impl ResponseSums {
    /// Adds the lighting pairs of one scene's `relit[k]` / `renders[k]` (same checks as
    /// [`light_response`], except that an unchanging set is only an error at [`finish`](Self::finish)).
    pub fn add(&mut self, relit: &[&Image], renders: &[&Image]) -> Result<(), MetricError> {
        if relit.len() != renders.len() || relit.len() < 2 {
            return Err(MetricError::Lightings {
                relit: relit.len(),
                renders: renders.len(),
            });
        }
        let first = renders[0];
        for (which, img) in relit
            .iter()
            .map(|i| ("relit image", *i))
            .chain(renders.iter().map(|i| ("render", *i)))
        {
            check_image(img, which, first)?;
        }
        let lo: Vec<Vec<f64>> = relit.iter().map(|i| log_luminance(i)).collect();
        let lr: Vec<Vec<f64>> = renders.iter().map(|i| log_luminance(i)).collect();
        let k = relit.len();
        for i in 0..k {
            for j in i + 1..k {
                for p in 0..lo[i].len() {
                    let a = lo[j][p] - lo[i][p];
                    let b = lr[j][p] - lr[i][p];
                    self.n += 1.0;
                    self.sa += a;
                    self.sb += b;
                    self.sab += a * b;
                    self.saa += a * a;
                    self.sbb += b * b;
                }
            }
        }
        self.pairs += k * (k - 1) / 2;
        self.pixels = first.num_pixels();
        Ok(())
    }

    /// The score of everything added. `pixels` is that of the last set added.
    pub fn finish(&self) -> Result<LightResponse, MetricError> {
        if self.sbb == 0.0 {
            return Err(MetricError::NoLightChange);
        }
        let (n, sa, sb) = (self.n, self.sa, self.sb);
        let gain = self.sab / self.sbb;
        let cov = self.sab - sa * sb / n;
        let var_a = (self.saa - sa * sa / n).max(0.0);
        let var_b = (self.sbb - sb * sb / n).max(0.0);
        let correlation = if var_a > 0.0 && var_b > 0.0 {
            (cov / (var_a * var_b).sqrt()).clamp(-1.0, 1.0)
        } else {
            0.0
        };
        Ok(LightResponse {
            gain,
            correlation,
            pairs: self.pairs,
            pixels: self.pixels,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Five lightings of a 12×9 scene: smooth, different per lighting and per channel.
    fn renders() -> Vec<Image> {
        (0..5)
            .map(|k| {
                Image::from_fn(12, 9, 3, |x, y, c| {
                    let t = 0.15
                        + 0.7
                            * ((x as f32 * (0.3 + 0.1 * k as f32) + y as f32 * 0.2 * c as f32 + k as f32).sin() * 0.5
                                + 0.5);
                    t.clamp(0.0, 1.0)
                })
            })
            .collect()
    }

    fn refs(v: &[Image]) -> Vec<&Image> {
        v.iter().collect()
    }

    /// The score computed naively, in f64, straight from the definition.
    fn naive(relit: &[Image], renders: &[Image]) -> (f64, f64) {
        let l = |img: &Image, x: usize, y: usize| -> f64 {
            let lin = |c| srgb_to_linear(img.get(x, y, c)) as f64;
            (0.2126 * lin(0) + 0.7152 * lin(1) + 0.0722 * lin(2) + 1e-3).ln()
        };
        let mut pts = Vec::new();
        for i in 0..relit.len() {
            for j in i + 1..relit.len() {
                for y in 0..relit[0].height {
                    for x in 0..relit[0].width {
                        pts.push((
                            l(&relit[j], x, y) - l(&relit[i], x, y),
                            l(&renders[j], x, y) - l(&renders[i], x, y),
                        ));
                    }
                }
            }
        }
        let n = pts.len() as f64;
        let gain = pts.iter().map(|(a, b)| a * b).sum::<f64>() / pts.iter().map(|(_, b)| b * b).sum::<f64>();
        let (ma, mb) = (
            pts.iter().map(|p| p.0).sum::<f64>() / n,
            pts.iter().map(|p| p.1).sum::<f64>() / n,
        );
        let cov: f64 = pts.iter().map(|(a, b)| (a - ma) * (b - mb)).sum();
        let va: f64 = pts.iter().map(|(a, _)| (a - ma).powi(2)).sum();
        let vb: f64 = pts.iter().map(|(_, b)| (b - mb).powi(2)).sum();
        (gain, cov / (va * vb).sqrt())
    }

    /// Pooling two sets of two lightings equals the score of the side-by-side images (the
    /// same pixel pairs), computed naively.
    #[test]
    fn pooled_sets_equal_the_stitched_images() {
        let r = renders();
        let o: Vec<Image> = r
            .iter()
            .enumerate()
            .map(|(k, i)| i.map(|v| (v * (0.6 + 0.1 * k as f32)).min(1.0)))
            .collect();
        let stitch = |a: &Image, b: &Image| {
            Image::from_fn(a.width + b.width, a.height, 3, |x, y, c| {
                if x < a.width {
                    a.get(x, y, c)
                } else {
                    b.get(x - a.width, y, c)
                }
            })
        };
        let mut sums = ResponseSums::default();
        sums.add(&[&o[0], &o[1]], &[&r[0], &r[1]]).unwrap();
        sums.add(&[&o[2], &o[3]], &[&r[2], &r[3]]).unwrap();
        let pooled = sums.finish().unwrap();
        let (so, sr) = (
            [stitch(&o[0], &o[2]), stitch(&o[1], &o[3])],
            [stitch(&r[0], &r[2]), stitch(&r[1], &r[3])],
        );
        let (gain, corr) = naive(&so, &sr);
        assert!((pooled.gain - gain).abs() < 1e-9 && (pooled.correlation - corr).abs() < 1e-9);
        assert_eq!(pooled.pairs, 2);
    }

    #[test]
    fn identical_outputs_score_zero() {
        let r = renders();
        let same = vec![r[2].clone(); r.len()];
        let s = light_response(&refs(&same), &refs(&r)).unwrap();
        assert_eq!((s.gain, s.correlation), (0.0, 0.0));
        assert_eq!((s.pairs, s.pixels), (10, 108));
    }

    #[test]
    fn outputs_equal_to_the_renders_score_one() {
        let r = renders();
        let s = light_response(&refs(&r), &refs(&r)).unwrap();
        assert!(
            (s.gain - 1.0).abs() < 1e-12 && (s.correlation - 1.0).abs() < 1e-12,
            "{s:?}"
        );
    }

    #[test]
    fn half_the_change_scores_half_and_the_reverse_scores_minus_one() {
        let r = renders();
        // Relit luminance moving half as far in log space: scale each linear pixel of a fixed base
        // by sqrt of the render's luminance ratio (grey images, so Y is the channel value).
        let grey: Vec<Image> = r
            .iter()
            .map(|img| Image::from_fn(img.width, img.height, 3, |x, y, _| img.get(x, y, 1)))
            .collect();
        let half: Vec<Image> = grey
            .iter()
            .map(|img| {
                img.map(|v| {
                    let lin = (srgb_to_linear(v) as f64 + EPS).sqrt() - EPS;
                    pixl_core::image::linear_to_srgb(lin.max(0.0) as f32)
                })
            })
            .collect();
        let s = light_response(&refs(&half), &refs(&grey)).unwrap();
        let (g, c) = naive(&half, &grey);
        assert!(
            (s.gain - g).abs() < 1e-9 && (s.correlation - c).abs() < 1e-9,
            "{s:?} vs {g} {c}"
        );
        assert!((s.gain - 0.5).abs() < 0.02, "gain {}", s.gain);
        assert!(s.correlation > 0.99);
        // The same images in the opposite lighting order: the change runs backwards.
        let rev: Vec<Image> = grey.iter().rev().cloned().collect();
        let s = light_response(&refs(&rev), &refs(&grey)).unwrap();
        let (g, c) = naive(&rev, &grey);
        assert!((s.gain - g).abs() < 1e-9 && (s.correlation - c).abs() < 1e-9);
        assert!(s.correlation < 0.0 && s.gain < 0.0);
    }

    #[test]
    fn any_outputs_match_the_naive_definition() {
        let r = renders();
        let relit: Vec<Image> = (0..r.len())
            .map(|k| Image::from_fn(12, 9, 3, |x, y, c| ((x * 7 + y * 3 + c + k * 5) % 11) as f32 / 10.0))
            .collect();
        let s = light_response(&refs(&relit), &refs(&r)).unwrap();
        let (g, c) = naive(&relit, &r);
        assert!(
            (s.gain - g).abs() < 1e-9 && (s.correlation - c).abs() < 1e-9,
            "{s:?} vs {g} {c}"
        );
    }

    #[test]
    fn bad_inputs_are_errors() {
        let r = renders();
        assert!(matches!(
            light_response(&refs(&r[..1]), &refs(&r[..1])),
            Err(MetricError::Lightings { .. })
        ));
        assert!(matches!(
            light_response(&refs(&r[..3]), &refs(&r[..2])),
            Err(MetricError::Lightings { .. })
        ));
        let small = Image::new(4, 4, 3);
        let mut mixed = refs(&r[..2]);
        mixed[1] = &small;
        assert!(matches!(
            light_response(&mixed, &refs(&r[..2])),
            Err(MetricError::Shape { .. })
        ));
        let same = vec![r[0].clone(); 3];
        assert!(matches!(
            light_response(&refs(&r[..3]), &refs(&same)),
            Err(MetricError::NoLightChange)
        ));
        let mut nan = r[1].clone();
        nan.data[5] = f32::NAN;
        assert!(matches!(
            light_response(&[&r[0], &nan], &refs(&r[..2])),
            Err(MetricError::NonFinite { .. })
        ));
    }
}
