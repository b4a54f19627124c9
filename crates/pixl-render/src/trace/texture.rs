//! Image textures: bilinear lookups with repeat wrapping, UV `v = 0` at the image's top row.
//! PNG/JPEG colour textures are sRGB-decoded to linear; EXR is linear as stored; scalar
//! textures (roughness, metallic) read their first channel as-is (Blender's "Non-Color"), data
//! textures (normal maps) their RGB as-is.
use crate::error::Result;
use crate::math::V3;
use pixl_core::Image;
use std::path::Path;

#[derive(Clone, Debug)]
pub struct Texture {
    img: Image,
}

impl Texture {
    /// A colour texture (RGB, linear).
    pub fn load_color(path: &Path) -> Result<Self> {
        let img = pixl_core::io::read_image(path)?;
        Ok(Self::color(&img, pixl_core::io::extension(path) != "exr"))
    }

    /// A colour texture from an image in memory: sRGB-decoded when `srgb`, grey repeated to RGB.
    pub fn color(img: &Image, srgb: bool) -> Self {
        let ch = img.channels;
        let rgb = Image::from_fn(img.width, img.height, 3, |x, y, c| {
            let v = img.get(x, y, if ch >= 3 { c } else { 0 });
            if srgb {
                pixl_core::image::srgb_to_linear(v)
            } else {
                v
            }
        });
        Texture { img: rgb }
    }

    /// An RGB data texture (as stored, no colour decoding; grey images repeat their channel).
    pub fn load_data(path: &Path) -> Result<Self> {
        Ok(Self::data(&pixl_core::io::read_image(path)?))
    }

    /// [`Texture::load_data`] of an image in memory.
    pub fn data(img: &Image) -> Self {
        let ch = img.channels;
        let rgb = Image::from_fn(img.width, img.height, 3, |x, y, c| {
            img.get(x, y, if ch >= 3 { c } else { 0 })
        });
        Texture { img: rgb }
    }

    /// A scalar texture (first channel, as stored).
    pub fn load_scalar(path: &Path) -> Result<Self> {
        Ok(Self::scalar(&pixl_core::io::read_image(path)?))
    }

    /// [`Texture::load_scalar`] of an image in memory.
    pub fn scalar(img: &Image) -> Self {
        Texture {
            img: img.select_channels(0..1),
        }
    }

    pub fn from_image(img: Image) -> Self {
        Texture { img }
    }

    pub fn width(&self) -> usize {
        self.img.width
    }
    pub fn height(&self) -> usize {
        self.img.height
    }
    pub fn image(&self) -> &Image {
        &self.img
    }

    /// Texel `(x, y)` (wrapped) as RGB.
    #[inline]
    pub fn texel(&self, x: isize, y: isize) -> V3 {
        let (w, h) = (self.img.width as isize, self.img.height as isize);
        let xi = x.rem_euclid(w) as usize;
        let yi = y.clamp(0, h - 1) as usize;
        let i = (yi * self.img.width + xi) * self.img.channels;
        let d = &self.img.data;
        if self.img.channels >= 3 {
            V3::new(d[i], d[i + 1], d[i + 2])
        } else {
            V3::splat(d[i])
        }
    }

    /// Bilinear lookup at `(u, v)`; `u` wraps, `v` clamps.
    pub fn sample(&self, u: f32, v: f32) -> V3 {
        let x = u * self.img.width as f32 - 0.5;
        let y = v * self.img.height as f32 - 0.5;
        if !(x.is_finite() && y.is_finite()) {
            return self.texel(0, 0);
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as isize, y0 as isize);
        let a = self.texel(x0, y0) * (1.0 - fx) + self.texel(x0 + 1, y0) * fx;
        let b = self.texel(x0, y0 + 1) * (1.0 - fx) + self.texel(x0 + 1, y0 + 1) * fx;
        a * (1.0 - fy) + b * fy
    }
}
