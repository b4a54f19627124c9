//! Camera-space normal maps as files: what `pixl estimate normals` writes and
//! `pixl reconstruct --normals` reads, the `normals` argument of [`super::depth::depth_to_mesh`].
//!
//! The frame is [`super::depth`]'s camera space: **X right, Y up, Z towards the camera** (a wall
//! facing the camera is `(0, 0, 1)`); R, G, B hold X, Y, Z.
//! - **OpenEXR**: the values themselves, in [−1, 1] (written as f32; read from the first three
//!   channels).
//! - **PNG / JPEG**: `n/2 + 1/2` per channel, so (0, 0, 1) is (128, 128, 255) in 8 bits; written
//!   as 16-bit PNG. Reading maps each value `v` back to `2v − 1`.
//!
//! Reading keeps the values as stored (a mesh built from them renormalises each vertex's normal);
//! it refuses a map with fewer than 3 channels or with non-finite values, naming the file.
use crate::reconstruct::depth::{DepthError, Result};
use pixl_core::Image;
use std::path::Path;

/// Whether a normal map at `path` stores `n/2 + 1/2` (PNG, JPEG) rather than `n` (EXR).
fn is_encoded(path: &Path) -> bool {
    pixl_core::io::extension(path) != "exr"
}

/// Reads a camera-space normal map (see the module docs): 3 channels, values `n` in about
/// [−1, 1].
pub fn read_normal_map(path: &Path) -> Result<Image> {
    let img = pixl_core::io::read_image(path)?;
    if img.channels < 3 {
        return Err(DepthError::Format {
            path: path.to_owned(),
            reason: format!(
                "a normal map needs 3 channels (X, Y, Z as R, G, B), found {}",
                img.channels
            ),
        });
    }
    pixl_core::io::ensure_finite(path, &img)?;
    let rgb = img.select_channels(0..3);
    Ok(if is_encoded(path) {
        rgb.map(|v| 2.0 * v - 1.0)
    } else {
        rgb
    })
}

/// Writes a 3-channel camera-space normal map (values in [−1, 1]) as EXR or 16-bit PNG (see the
/// module docs), atomically; another extension, channel count or a non-finite value is an error.
pub fn write_normal_map(path: &Path, normals: &Image) -> Result<()> {
    if normals.channels != 3 {
        return Err(DepthError::Invalid(format!(
            "{}: a normal map has 3 channels, this one {}",
            path.display(),
            normals.channels
        )));
    }
    pixl_core::io::ensure_finite(path, normals)?;
    match pixl_core::io::extension(path).as_str() {
        "exr" => pixl_core::io::write_image(path, normals)?,
        "png" => pixl_core::io::write_png(path, &normals.map(|v| v * 0.5 + 0.5), pixl_core::io::PngDepth::Sixteen)?,
        _ => {
            return Err(pixl_core::CoreError::UnknownExtension {
                path: path.to_owned(),
                expected: "exr, png",
            }
            .into())
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map() -> Image {
        // Unit normals over a hemisphere facing the camera, plus the axes.
        Image::from_fn(5, 4, 3, |x, y, c| {
            let (u, v) = (x as f32 / 4.0 - 0.5, 0.5 - y as f32 / 3.0);
            let z = (1.0 - u * u - v * v).sqrt();
            [u, v, z][c]
        })
    }

    #[test]
    fn exr_keeps_the_values_and_png_stores_half_plus_a_half() {
        let dir = tempfile::tempdir().unwrap();
        let n = map();
        let exr = dir.path().join("n.exr");
        write_normal_map(&exr, &n).unwrap();
        assert_eq!(read_normal_map(&exr).unwrap().data, n.data);
        let png = dir.path().join("n.png");
        write_normal_map(&png, &n).unwrap();
        // The raw file: (x/2 + 1/2) in 16 bits; +Z is 65535 in blue, 0 in X and Y is 32768.
        let raw = pixl_core::io::read_image(&png).unwrap();
        for (r, v) in raw.data.iter().zip(&n.data) {
            assert!((r - (v * 0.5 + 0.5)).abs() <= 0.5 / 65535.0 + 1e-7, "{r} vs {v}");
        }
        let back = read_normal_map(&png).unwrap();
        let worst = back
            .data
            .iter()
            .zip(&n.data)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst <= 1.0 / 65535.0 + 1e-6, "{worst}");
    }

    #[test]
    fn bad_maps_are_refused_with_the_file_named() {
        let dir = tempfile::tempdir().unwrap();
        let grey = dir.path().join("grey.png");
        pixl_core::io::write_png(&grey, &Image::new(4, 4, 1), pixl_core::io::PngDepth::Eight).unwrap();
        let e = read_normal_map(&grey).unwrap_err().to_string();
        assert!(e.contains("grey.png") && e.contains("3 channels"), "{e}");
        let mut n = map();
        n.data[7] = f32::NAN;
        let e = write_normal_map(&dir.path().join("nan.exr"), &n)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nan.exr") && e.contains("non-finite"), "{e}");
        let e = write_normal_map(&dir.path().join("n.tif"), &map())
            .unwrap_err()
            .to_string();
        assert!(e.contains("n.tif"), "{e}");
    }
}
