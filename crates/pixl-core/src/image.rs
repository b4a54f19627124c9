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

/// Reinhard tonemap with auto-exposure (key 0.18 on the log-average luminance), then sRGB
/// encoding: how linear HDR renders are shown (paper §4.2, "Reinhard auto-exposure").
pub fn tonemap_reinhard(img: &Image) -> Image {
    let ch = img.channels;
    let lum = |px: &[f32]| {
        if ch >= 3 {
            0.2126 * px[0] + 0.7152 * px[1] + 0.0722 * px[2]
        } else {
            px[0]
        }
    };
    let n = img.num_pixels().max(1) as f64;
    let log_avg = (img
        .data
        .chunks_exact(ch)
        .map(|px| (1e-4 + lum(px).max(0.0) as f64).ln())
        .sum::<f64>()
        / n)
        .exp();
    let scale = (0.18 / log_avg.max(1e-8)) as f32;
    img.map(|v| {
        let v = v.max(0.0) * scale;
        linear_to_srgb(v / (1.0 + v))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
