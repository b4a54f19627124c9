//! Resampling an [`Image`] to another size, any channel count, values as they are (no
//! clamping, no colour conversion).
//!
//! - [`crop_resize`] / [`resize`]: a separable tent filter whose radius is the minification
//!   factor (at least one pixel), weights normalised to sum 1: shrinking averages every input
//!   pixel under the footprint (no aliasing), enlarging interpolates linearly between pixel
//!   centres (half-pixel centres, edges clamped). [`crop_resize`] reads a [`CropRect`] of the
//!   image; the filter may reach pixels just outside the rectangle, as a resize of the whole
//!   image followed by a crop would. The training crops (`pixl-train`) use it.
//! - [`area_resize_to_chw`] / [`area_resize`]: the exact area average (box filter): each output
//!   pixel is the mean of the input over its footprint, fractional pixels weighted by overlap.
//!   Planar output for tensors; how a photo and its `C_T` reach the network's working size
//!   (`pixl_model::fullres`). At the same size it is the input, copied.
//!
//! The two differ on purpose: the box is the integral of the image over the footprint (right for
//! a photo seen by a smaller sensor), the tent smooths across footprints (softer, but no blocky
//! steps when enlarging).
use crate::error::{CoreError, Result};
use crate::image::Image;

/// A rectangle in the pixels of an image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CropRect {
    pub x: usize,
    pub y: usize,
    pub width: usize,
    pub height: usize,
}

impl CropRect {
    /// The whole of a `width × height` image.
    pub fn whole(width: usize, height: usize) -> Self {
        Self {
            x: 0,
            y: 0,
            width,
            height,
        }
    }
}

/// Refuses empty sizes and an image whose data does not match its size.
fn check(what: &str, img: &Image, ow: usize, oh: usize) -> Result<()> {
    let (w, h, ch) = (img.width, img.height, img.channels);
    if w == 0 || h == 0 || ow == 0 || oh == 0 || img.data.len() != w * h * ch {
        return Err(CoreError::Invalid(format!(
            "{what} from {w}x{h}x{ch} ({} samples) to {ow}x{oh}: sizes must be positive and consistent",
            img.data.len()
        )));
    }
    Ok(())
}

/// Tent-filter weights mapping `n_in` source samples (starting at `offset`) onto `n_out`: for
/// every output sample, `(first source index, weights)`. The filter widens with the minification
/// factor, so downsampling averages (no aliasing) and upsampling interpolates linearly.
fn tent_weights(offset: usize, n_in: usize, n_out: usize, limit: usize) -> Vec<(usize, Vec<f32>)> {
    let scale = n_in as f64 / n_out as f64;
    let support = scale.max(1.0);
    (0..n_out)
        .map(|o| {
            let center = offset as f64 + (o as f64 + 0.5) * scale - 0.5;
            let lo = (center - support).floor().max(0.0) as usize;
            let hi = ((center + support).ceil() as usize).min(limit - 1);
            let mut ws: Vec<f32> = (lo..=hi)
                .map(|x| (1.0 - (x as f64 - center).abs() / support).max(0.0) as f32)
                .collect();
            let sum: f32 = ws.iter().sum();
            if sum > 0.0 {
                ws.iter_mut().for_each(|w| *w /= sum);
            } else {
                // centre falls exactly between clamped edges: take the nearest sample
                ws.iter_mut().for_each(|w| *w = 0.0);
                let nearest = (center.round().max(lo as f64) as usize).min(hi) - lo;
                ws[nearest] = 1.0;
            }
            (lo, ws)
        })
        .collect()
}

/// Crops `rect` out of `img` and resizes it to `ow × oh` (separable tent filter, see the module
/// notes). Errors on empty sizes or a rectangle not inside the image.
pub fn crop_resize(img: &Image, rect: CropRect, ow: usize, oh: usize) -> Result<Image> {
    check("tent resize", img, ow, oh)?;
    let inside = rect.x + rect.width <= img.width && rect.y + rect.height <= img.height;
    if rect.width == 0 || rect.height == 0 || !inside {
        return Err(CoreError::Invalid(format!(
            "crop {}x{} at ({}, {}) is empty or not inside the {}x{} image",
            rect.width, rect.height, rect.x, rect.y, img.width, img.height
        )));
    }
    let ch = img.channels;
    let wx = tent_weights(rect.x, rect.width, ow, img.width);
    let wy = tent_weights(rect.y, rect.height, oh, img.height);
    // horizontal pass over the rows the vertical pass will need
    let (row_lo, row_hi) = (
        wy.iter().map(|(lo, _)| *lo).min().unwrap_or(0),
        wy.iter().map(|(lo, w)| lo + w.len()).max().unwrap_or(0),
    );
    let mut tmp = vec![0.0f32; (row_hi - row_lo) * ow * ch];
    for y in row_lo..row_hi {
        for (o, (lo, ws)) in wx.iter().enumerate() {
            let dst = &mut tmp[((y - row_lo) * ow + o) * ch..][..ch];
            for (k, w) in ws.iter().enumerate() {
                let src = &img.data[(y * img.width + lo + k) * ch..][..ch];
                for c in 0..ch {
                    dst[c] += w * src[c];
                }
            }
        }
    }
    let mut out = Image::new(ow, oh, ch);
    for (oy, (lo, ws)) in wy.iter().enumerate() {
        for x in 0..ow {
            let dst = &mut out.data[(oy * ow + x) * ch..][..ch];
            for (k, w) in ws.iter().enumerate() {
                let src = &tmp[((lo + k - row_lo) * ow + x) * ch..][..ch];
                for c in 0..ch {
                    dst[c] += w * src[c];
                }
            }
        }
    }
    Ok(out)
}

/// The whole of `img` resized to `ow × oh` by the tent filter ([`crop_resize`]).
pub fn resize(img: &Image, ow: usize, oh: usize) -> Result<Image> {
    crop_resize(img, CropRect::whole(img.width, img.height), ow, oh)
}

/// Box-filter weights from `n_in` samples to `n_out`: for each output `o`, the input samples
/// overlapping `[o·n_in/n_out, (o+1)·n_in/n_out)` and their overlap fractions (summing to 1).
fn area_weights(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f32)>> {
    let scale = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|o| {
            let (a, b) = (o as f64 * scale, (o + 1) as f64 * scale);
            let first = (a.floor() as usize).min(n_in - 1);
            let last = ((b.ceil() as usize).max(first + 1)).min(n_in);
            (first..last)
                .filter_map(|i| {
                    let overlap = b.min(i as f64 + 1.0) - a.max(i as f64);
                    (overlap > 0.0).then_some((i, (overlap / (b - a)) as f32))
                })
                .collect()
        })
        .collect()
}

/// Area-average resampling of `img` (interleaved, any channel count) to `ow × oh`, returned
/// planar (`channels × oh × ow`, the layout tensors use). At the same size it is the planar
/// copy of the input. Errors on empty sizes.
pub fn area_resize_to_chw(img: &Image, ow: usize, oh: usize) -> Result<Vec<f32>> {
    check("area resize", img, ow, oh)?;
    let (w, h, ch) = (img.width, img.height, img.channels);
    if (ow, oh) == (w, h) {
        return Ok(img.to_chw());
    }
    let wx = area_weights(w, ow);
    let wy = area_weights(h, oh);
    // Horizontal pass into planar rows `(c, y, ox)`, then vertical.
    let mut rows = vec![0f32; ch * h * ow];
    for y in 0..h {
        let line = &img.data[y * w * ch..(y + 1) * w * ch];
        for (ox, taps) in wx.iter().enumerate() {
            for c in 0..ch {
                let s: f32 = taps.iter().map(|&(x, t)| t * line[x * ch + c]).sum();
                rows[(c * h + y) * ow + ox] = s;
            }
        }
    }
    let mut out = vec![0f32; ch * oh * ow];
    for c in 0..ch {
        for (oy, taps) in wy.iter().enumerate() {
            let dst = &mut out[(c * oh + oy) * ow..(c * oh + oy + 1) * ow];
            for &(y, t) in taps {
                let src = &rows[(c * h + y) * ow..(c * h + y + 1) * ow];
                for (d, s) in dst.iter_mut().zip(src) {
                    *d += t * s;
                }
            }
        }
    }
    Ok(out)
}

/// [`area_resize_to_chw`] with the result interleaved, as an [`Image`].
pub fn area_resize(img: &Image, ow: usize, oh: usize) -> Result<Image> {
    Image::from_chw(ow, oh, img.channels, &area_resize_to_chw(img, ow, oh)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn area_weights_sum_to_one_and_cover_the_input_once() {
        for (n_in, n_out) in [(10, 3), (3, 10), (7, 7), (4000, 1024), (1, 5), (5, 1)] {
            let w = area_weights(n_in, n_out);
            let mut cover = vec![0f64; n_in];
            for taps in &w {
                let s: f64 = taps.iter().map(|t| t.1 as f64).sum();
                assert!((s - 1.0).abs() < 1e-5, "{n_in}->{n_out}: {s}");
                for &(i, t) in taps {
                    cover[i] += t as f64 * n_in as f64 / n_out as f64;
                }
            }
            // Every input sample contributes its whole area exactly once.
            assert!(
                cover.iter().all(|c| (c - 1.0).abs() < 1e-4),
                "{n_in}->{n_out}: {cover:?}"
            );
        }
    }

    #[test]
    fn tent_weights_sum_to_one() {
        for (offset, n_in, n_out, limit) in [(0, 10, 3, 10), (2, 3, 10, 8), (0, 7, 7, 7), (5, 20, 6, 40)] {
            for (lo, ws) in tent_weights(offset, n_in, n_out, limit) {
                let s: f64 = ws.iter().map(|&w| w as f64).sum();
                assert!((s - 1.0).abs() < 1e-5, "{n_in}->{n_out}: {s}");
                assert!(lo + ws.len() <= limit);
            }
        }
    }
}
