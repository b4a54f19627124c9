//! The photograph, read once: [`Photo::open`] decodes the file (PNG, JPEG or EXR) a single time
//! and reads the focal length from its EXIF header ([`crate::exif`]); every stage after it —
//! depth estimation, the mesh's texture, the network — takes the decoded image.
//!
//! The image is RGB with values as stored, clamped to `[0, 1]` (with a warning when any were
//! outside; non-finite values are refused): PNG/JPEG hold sRGB-encoded values, an EXR linear ones
//! ([`Photo::linear`]). The network takes the values as stored (the paper's `I_S`); the depth
//! estimator and the mesh's texture take them sRGB-encoded ([`Photo::srgb`]).
use crate::error::{PipelineError, Result};
use crate::exif::{photo_focal, Focal};
use pixl_core::Image;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug)]
pub struct Photo {
    /// Where it was read from (`None` for an image handed over in memory).
    pub path: Option<PathBuf>,
    /// RGB, values as stored in `[0, 1]`.
    pub image: Image,
    /// Whether the values are linear (an EXR) rather than sRGB-encoded.
    pub linear: bool,
    /// The focal length the photo is processed with.
    pub focal: Focal,
}

impl Photo {
    /// Reads and decodes `path` once; the focal length is `focal_px`, else the vertical
    /// `fov_deg`, else EXIF, else the default field of view ([`crate::exif::photo_focal`]).
    pub fn open(path: &Path, focal_px: Option<f64>, fov_deg: Option<f64>) -> Result<Photo> {
        let img =
            pixl_core::io::read_rgb_finite(path).map_err(|e| PipelineError::from(e).context("reading the photo"))?;
        let outside = img.data.iter().filter(|v| !(0.0..=1.0).contains(*v)).count();
        if outside > 0 {
            tracing::warn!(
                "{}: {outside} values outside [0, 1] clamped (the network expects I_S in [0, 1])",
                path.display()
            );
        }
        let image = img.map(|v| v.clamp(0.0, 1.0));
        let linear = pixl_core::io::extension(path) == "exr";
        let focal = photo_focal(path, image.width, image.height, focal_px, fov_deg)?;
        Ok(Photo {
            path: Some(path.to_owned()),
            image,
            linear,
            focal,
        })
    }

    /// A photo already in memory (RGB, sRGB-encoded values in `[0, 1]`) with its focal length.
    pub fn from_image(image: Image, focal: Focal) -> Photo {
        Photo {
            path: None,
            image,
            linear: false,
            focal,
        }
    }

    /// The image sRGB-encoded (as the estimators and the mesh's texture take it).
    pub fn srgb(&self) -> std::borrow::Cow<'_, Image> {
        if self.linear {
            std::borrow::Cow::Owned(self.image.map(pixl_core::image::linear_to_srgb))
        } else {
            std::borrow::Cow::Borrowed(&self.image)
        }
    }

    pub fn size(&self) -> (usize, usize) {
        (self.image.width, self.image.height)
    }

    /// The path for messages (`the photo` for one in memory).
    pub fn name(&self) -> String {
        self.path
            .as_ref()
            .map(|p| p.display().to_string())
            .unwrap_or_else(|| "the photo".into())
    }
}
