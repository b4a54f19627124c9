//! The photo's surface normals for the reconstruction (paper §3.4's coarse scene): the mesh's
//! shading normals taken from a normal map instead of from its own faces, so that the renderer
//! shades the detail a monocular depth map smooths away. The map is read from a file the user
//! gives ([`read_normals`]; formats: `pixl_render::normals`) or estimated by a
//! [`NormalsEstimator`] plugged in by the caller ([`estimate_normals`];
//! [`crate::estimators::MarigoldNormalsEstimator`] runs Marigold Normals), and goes to
//! [`crate::reconstruct::Maps::normals`].
//!
//! **Frame.** The reconstructed scene is the camera's space (`pixl_render::depth`: camera at the
//! origin looking down −Z, +X image right, +Y image up, so +Z points at the camera), and the mesh
//! is placed there unchanged, so a map for it holds camera-space unit normals with X right, Y up
//! and Z towards the camera. Marigold's normals are in its camera frame, x right, y up, z towards
//! the viewer (`pixl_estimate::marigold::normals`): the same axes. [`scene_from_marigold`] is
//! therefore the identity on the axes and only renormalises (each vertex's normal is renormalised
//! again when the mesh is built).
//!
//! **Resolution.** The map reaches the renderer as per-vertex normals, interpolated across each
//! triangle. Marigold works at 768 px on the long side by default, and the default triangle
//! budget keeps about 1000 samples on a 3:2 photo's long side, so sampling the map at the
//! vertices keeps what the estimator resolves.
use crate::error::{PipelineError, Result};
use crate::observe::{Observer, Stage};
use crate::photo::Photo;
use crate::reconstruct::check_map;
use pixl_core::Image;
use std::path::Path;

/// An estimator of a photo's surface normals, plugged in by the caller (`pixl reconstruct
/// --normals marigold` plugs in [`crate::estimators::MarigoldNormalsEstimator`]).
pub trait NormalsEstimator: Send + Sync {
    /// A short name for messages ("Marigold Normals (marigold-normals)").
    fn name(&self) -> String;
    /// Unit normals of `photo` (RGB, sRGB-encoded values in `[0, 1]`) at its size, 3 channels,
    /// in the scene's camera frame (module docs). Progress goes to `observer` as
    /// [`Stage::Normals`] (the caller begins and ends the stage).
    fn estimate(&self, photo: &Image, observer: &dyn Observer) -> Result<Image>;
}

/// Marigold's camera-frame normals (x right, y up, z towards the viewer) in the scene's camera
/// frame (X right, Y up, Z towards the camera): the same axes, each pixel scaled to unit length
/// (a zero vector stays zero).
pub fn scene_from_marigold(normals: &Image) -> Image {
    let mut out = normals.select_channels(0..3);
    for n in out.data.chunks_exact_mut(3) {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len > 0.0 && len.is_finite() {
            n.iter_mut().for_each(|v| *v /= len);
        }
    }
    out
}

/// The normals of `photo` from `estimator`, checked (the photo's size, 3 channels, finite),
/// with the stage's begin and end said to `observer`.
pub fn estimate_normals(estimator: &dyn NormalsEstimator, photo: &Photo, observer: &dyn Observer) -> Result<Image> {
    let name = estimator.name();
    observer.begin(Stage::Normals, 0);
    let n = estimator.estimate(&photo.srgb(), observer);
    observer.end(Stage::Normals);
    let n = n.map_err(|e| e.context(format!("estimating the photo's normals with {name}")))?;
    if n.channels != 3 {
        return Err(PipelineError::input(format!(
            "{name} returned a {}-channel normal map; normals have 3",
            n.channels
        )));
    }
    check_map("normal", &name, &n, photo.size())?;
    Ok(n)
}

/// A camera-space normal map file (EXR in [−1, 1], or PNG/JPEG storing `n/2 + 1/2`) for a photo
/// of `size`, checked like every material map.
pub fn read_normals(path: &Path, size: (usize, usize)) -> Result<Image> {
    let n = pixl_render::normals::read_normal_map(path)?;
    check_map("normal", &path.display().to_string(), &n, size)?;
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marigold_axes_are_the_scenes_and_pixels_become_unit() {
        let m = Image::from_fn(3, 1, 3, |x, _, c| {
            [[0.0, 0.0, 2.0], [0.3, -0.4, 0.0], [0.0, 0.0, 0.0]][x][c]
        });
        let s = scene_from_marigold(&m);
        assert_eq!(s.data, vec![0.0, 0.0, 1.0, 0.6, -0.8, 0.0, 0.0, 0.0, 0.0]);
    }
}
