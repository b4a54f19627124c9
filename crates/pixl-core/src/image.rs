//! [`Image`]: `height × width × channels` interleaved `f32` samples (row-major, HWC).
//!
//! The value convention is the caller's: PNG/JPEG load as sRGB-encoded values in [0, 1], EXR
//! loads as stored (linear HDR). Conversions are explicit ([`srgb_to_linear`], [`linear_to_srgb`]).

#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    /// `data[(y * width + x) * channels + c]`
    pub data: Vec<f32>,
}

impl Image {
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        Self {
            width,
            height,
            channels,
            data: vec![0.0; width * height * channels],
        }
    }

    pub fn from_vec(width: usize, height: usize, channels: usize, data: Vec<f32>) -> crate::Result<Self> {
        if data.len() != width * height * channels {
            return Err(crate::CoreError::Invalid(format!(
                "image buffer has {} samples, expected {width}x{height}x{channels} = {}",
                data.len(),
                width * height * channels
            )));
        }
        Ok(Self {
            width,
            height,
            channels,
            data,
        })
    }

    /// Builds an image from a per-pixel function `f(x, y, c)`.
    pub fn from_fn(width: usize, height: usize, channels: usize, f: impl Fn(usize, usize, usize) -> f32) -> Self {
        let mut data = Vec::with_capacity(width * height * channels);
        for y in 0..height {
            for x in 0..width {
                for c in 0..channels {
                    data.push(f(x, y, c));
                }
            }
        }
        Self {
            width,
            height,
            channels,
            data,
        }
    }

    #[inline]
    pub fn idx(&self, x: usize, y: usize, c: usize) -> usize {
        (y * self.width + x) * self.channels + c
    }

    #[inline]
    pub fn get(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[self.idx(x, y, c)]
    }

    #[inline]
    pub fn set(&mut self, x: usize, y: usize, c: usize, v: f32) {
        let i = self.idx(x, y, c);
        self.data[i] = v;
    }

    pub fn num_pixels(&self) -> usize {
        self.width * self.height
    }

    /// Planar copy (`channels × height × width`, CHW), the layout tensors use.
    pub fn to_chw(&self) -> Vec<f32> {
        let (w, h, ch) = (self.width, self.height, self.channels);
        let mut out = vec![0.0; w * h * ch];
        for (p, px) in self.data.chunks_exact(ch).enumerate() {
            for (c, v) in px.iter().enumerate() {
                out[c * w * h + p] = *v;
            }
        }
        out
    }

    /// Inverse of [`Image::to_chw`].
    pub fn from_chw(width: usize, height: usize, channels: usize, chw: &[f32]) -> crate::Result<Self> {
        if chw.len() != width * height * channels {
            return Err(crate::CoreError::Invalid(format!(
                "planar buffer has {} samples, expected {}",
                chw.len(),
                width * height * channels
            )));
        }
        let mut img = Image::new(width, height, channels);
        let n = width * height;
        for c in 0..channels {
            for p in 0..n {
                img.data[p * channels + c] = chw[c * n + p];
            }
        }
        Ok(img)
    }

    /// Channels `range` of this image as a new image (e.g. `0..3` for RGB of RGBA).
    pub fn select_channels(&self, range: std::ops::Range<usize>) -> Image {
        let ch = range.len();
        let mut data = Vec::with_capacity(self.num_pixels() * ch);
        for px in self.data.chunks_exact(self.channels) {
            data.extend_from_slice(&px[range.clone()]);
        }
        Image {
            width: self.width,
            height: self.height,
            channels: ch,
            data,
        }
    }

    /// First non-finite sample as `(count, x, y, c)`, or `None` if all are finite.
    pub fn find_non_finite(&self) -> Option<(usize, usize, usize, usize)> {
        let mut first = None;
        let mut count = 0;
        for (i, v) in self.data.iter().enumerate() {
            if !v.is_finite() {
                count += 1;
                if first.is_none() {
                    let p = i / self.channels;
                    first = Some((p % self.width, p / self.width, i % self.channels));
                }
            }
        }
        first.map(|(x, y, c)| (count, x, y, c))
    }

    pub fn map(&self, f: impl Fn(f32) -> f32) -> Image {
        Image {
            data: self.data.iter().map(|&v| f(v)).collect(),
            ..self.clone()
        }
    }

    /// Horizontal concatenation of images of equal height and channel count.
    pub fn hstack(images: &[&Image]) -> crate::Result<Image> {
        let Some(first) = images.first() else {
            return Err(crate::CoreError::Invalid("hstack of no images".into()));
        };
        let (h, ch) = (first.height, first.channels);
        if images.iter().any(|i| i.height != h || i.channels != ch) {
            return Err(crate::CoreError::Invalid(
                "hstack: images differ in height or channels".into(),
            ));
        }
        let w: usize = images.iter().map(|i| i.width).sum();
        let mut out = Image::new(w, h, ch);
        for y in 0..h {
            let mut x0 = 0;
            for img in images {
                let src = &img.data[y * img.width * ch..(y + 1) * img.width * ch];
                let dst = (y * w + x0) * ch;
                out.data[dst..dst + src.len()].copy_from_slice(src);
                x0 += img.width;
            }
        }
        Ok(out)
    }

    /// Vertical concatenation of images of equal channel count, top to bottom. Images narrower
    /// than the widest are padded on the right with `fill` (every channel).
    pub fn vstack(images: &[&Image], fill: f32) -> crate::Result<Image> {
        let Some(first) = images.first() else {
            return Err(crate::CoreError::Invalid("vstack of no images".into()));
        };
        let ch = first.channels;
        if images.iter().any(|i| i.channels != ch) {
            return Err(crate::CoreError::Invalid("vstack: images differ in channels".into()));
        }
        let w = images.iter().map(|i| i.width).max().unwrap_or(0);
        let h: usize = images.iter().map(|i| i.height).sum();
        let mut out = Image {
            width: w,
            height: h,
            channels: ch,
            data: vec![fill; w * h * ch],
        };
        let mut y0 = 0;
        for img in images {
            let row = img.width * ch;
            for y in 0..img.height {
                let dst = (y0 + y) * w * ch;
                out.data[dst..dst + row].copy_from_slice(&img.data[y * row..(y + 1) * row]);
            }
            y0 += img.height;
        }
        Ok(out)
    }
}

/// sRGB electro-optical transfer (IEC 61966-2-1), encoded → linear.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// Inverse of [`srgb_to_linear`]; input clamped to [0, 1].
pub fn linear_to_srgb(v: f32) -> f32 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.0031308 {
        v * 12.92
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// Rec. 709 luminance of one pixel's first three channels, or its single channel.
fn pixel_luminance(px: &[f32], channels: usize) -> f32 {
    if channels >= 3 {
        0.2126 * px[0] + 0.7152 * px[1] + 0.0722 * px[2]
    } else {
        px[0]
    }
}

/// The exposure that maps the log-average luminance (Rec. 709 weights on the first three
/// channels, or the single channel; `10⁻⁴` added before the logarithm) to the key 0.18: the
/// auto-exposure of [`tonemap_reinhard`] and [`tonemap_camera`].
pub fn auto_exposure(img: &Image) -> f32 {
    let ch = img.channels;
    let lum = |px: &[f32]| pixel_luminance(px, ch);
    let n = img.num_pixels().max(1) as f64;
    let log_avg = (img
        .data
        .chunks_exact(ch)
        .map(|px| (1e-4 + lum(px).max(0.0) as f64).ln())
        .sum::<f64>()
        / n)
        .exp();
    (0.18 / log_avg.max(1e-8)) as f32
}

/// Reinhard tonemap with auto-exposure (key 0.18 on the log-average luminance), then sRGB
/// encoding: how linear HDR renders are shown (paper §4.2, "Reinhard auto-exposure").
pub fn tonemap_reinhard(img: &Image) -> Image {
    let scale = auto_exposure(img);
    img.map(|v| {
        let v = v.max(0.0) * scale;
        linear_to_srgb(v / (1.0 + v))
    })
}

/// The filmic curve of [`tonemap_camera`]: Narkowicz's fit of the ACES reference rendering
/// transform, `x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14)`, clamped to [0, 1] — a toe that
/// deepens shadows and a shoulder that rolls highlights off (0.18 → 0.267, 1 → 0.80, 4 → 0.97).
pub fn filmic(x: f32) -> f32 {
    let x = x.max(0.0);
    (x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0)
}

/// How a camera shows a linear HDR render: the exposure of [`tonemap_reinhard`] (key 0.18 on
/// the log-average luminance) lowered where needed so that the 99th-percentile luminance lands
/// at no more than 3 (a small bright region does not blow out the picture: 3 → 0.955), the
/// [`filmic`] curve per channel, sRGB encoding. Middle grey lands at sRGB 0.55 (Reinhard:
/// 0.43), blacks stay black and highlights roll off without a hard clip.
pub fn tonemap_camera(img: &Image) -> Image {
    let ch = img.channels;
    let mut lum: Vec<f32> = img
        .data
        .chunks_exact(ch.max(1))
        .map(|px| pixel_luminance(px, ch))
        .collect();
    let k = (lum.len() * 99 / 100).min(lum.len().saturating_sub(1));
    let p99 = if lum.is_empty() {
        0.0
    } else {
        *lum.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let mut scale = auto_exposure(img);
    if p99 > 0.0 && p99 * scale > 3.0 {
        scale = 3.0 / p99;
    }
    img.map(|v| linear_to_srgb(filmic(v * scale)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The camera tone curve against values worked out here in f64: the exposure puts the
    /// log-average luminance at 0.18, the curve is the stated rational function, and the result
    /// does not depend on the render's absolute scale.
    #[test]
    fn tonemap_camera_is_auto_exposed_filmic() {
        let img = Image::from_fn(4, 3, 3, |x, y, c| {
            // one bright highlight among mid-tones
            if (x, y) == (3, 2) {
                60.0
            } else {
                0.01 + (x * 3 + y) as f32 * 0.05 + c as f32 * 0.02
            }
        });
        let lum: Vec<f64> = img
            .data
            .chunks_exact(3)
            .map(|p| 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64)
            .collect();
        let log_avg = (lum.iter().map(|l| (l + 1e-4).ln()).sum::<f64>() / lum.len() as f64).exp();
        let mut sorted = lum.clone();
        sorted.sort_by(f64::total_cmp);
        let p99 = sorted[lum.len() * 99 / 100];
        let k = (0.18 / log_avg).min(3.0 / p99);
        assert!(
            3.0 / p99 < 0.18 / log_avg,
            "the test image must exercise the highlight cap"
        );
        let aces = |x: f64| (x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0);
        let srgb = |v: f64| {
            if v <= 0.0031308 {
                12.92 * v
            } else {
                1.055 * v.powf(1.0 / 2.4) - 0.055
            }
        };
        let out = tonemap_camera(&img);
        let brighter = tonemap_camera(&img.map(|v| v * 37.0));
        for (i, (&v, &o)) in img.data.iter().zip(&out.data).enumerate() {
            let want = srgb(aces(v as f64 * k));
            assert!((o as f64 - want).abs() < 2e-5, "{i}: {o} vs {want}");
            assert!((brighter.data[i] - o).abs() < 2e-5, "exposure must cancel the scale");
        }
        assert!((filmic(0.18) - 0.2669).abs() < 1e-3 && (filmic(1.0) - 0.8038).abs() < 1e-3);
        assert_eq!(filmic(1e9), 1.0);
        assert_eq!(filmic(-1.0), 0.0);
    }

    /// Rows keep their pixels where they land; a narrower one is padded with `fill`.
    #[test]
    fn vstack_pads_narrow_rows() {
        let a = Image::from_fn(3, 2, 3, |x, y, c| (x + 10 * y + 100 * c) as f32);
        let b = Image::from_fn(2, 1, 3, |x, _, c| -((x + 1 + 100 * c) as f32));
        let v = Image::vstack(&[&a, &b], 0.5).unwrap();
        assert_eq!((v.width, v.height, v.channels), (3, 3, 3));
        for c in 0..3 {
            for x in 0..3 {
                for y in 0..2 {
                    assert_eq!(v.get(x, y, c), a.get(x, y, c));
                }
            }
            assert_eq!(v.get(0, 2, c), b.get(0, 0, c));
            assert_eq!(v.get(1, 2, c), b.get(1, 0, c));
            assert_eq!(v.get(2, 2, c), 0.5);
        }
        assert!(Image::vstack(&[], 0.0).is_err());
        assert!(Image::vstack(&[&a, &Image::new(3, 1, 1)], 0.0).is_err());
    }

    #[test]
    fn chw_roundtrip() {
        let img = Image::from_fn(3, 2, 4, |x, y, c| (x * 100 + y * 10 + c) as f32);
        let chw = img.to_chw();
        // channel 2, row 1, column 2 of a 3-wide, 2-high plane: 2·(3·2) + 1·3 + 2
        assert_eq!(chw[2 * 6 + 3 + 2], img.get(2, 1, 2));
        assert_eq!(Image::from_chw(3, 2, 4, &chw).unwrap(), img);
    }

    #[test]
    fn srgb_inverse() {
        for i in 0..=100 {
            let v = i as f32 / 100.0;
            assert!((linear_to_srgb(srgb_to_linear(v)) - v).abs() < 1e-6);
        }
    }

    #[test]
    fn non_finite_located() {
        let mut img = Image::new(4, 3, 3);
        img.set(2, 1, 1, f32::NAN);
        img.set(3, 2, 0, f32::INFINITY);
        assert_eq!(img.find_non_finite(), Some((2, 2, 1, 1)));
    }
}
