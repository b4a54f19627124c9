//! The photo's depth (paper §3.4): read from a file the user gives, or estimated by a
//! [`DepthEstimator`] plugged in by the caller ([`crate::estimators::Da3Depth`] runs Depth
//! Anything 3); either way it ends as **metric z-depth at the photo's size**, 0 where missing.
//!
//! - **Kinds** ([`DepthKind`]): `metric` (metres, as stored); `relative` (depth up to an unknown
//!   affine map: its smallest and largest valid values map linearly to `NEAR,FAR`); `disparity`
//!   (inverse depth up to an affine map: largest → NEAR, smallest → FAR, linear in 1/depth).
//!   Without a range they use [`DEFAULT_DEPTH_RANGE`]. In every kind 0, negative and non-finite
//!   values are missing depth ([`to_metric`]).
//! - A map of another size than the photo is resampled bilinearly to it over valid samples only:
//!   a pixel whose valid neighbours carry less than half of the weight stays missing
//!   ([`resize_depth`]).
use crate::error::{PipelineError, Result};
use pixl_core::Image;
use pixl_render::depth::DepthMap;
use std::path::Path;

/// Near and far depth (m) that relative depth and disparity map to without a range.
pub const DEFAULT_DEPTH_RANGE: (f32, f32) = (1.0, 10.0);

/// What the values of a depth map are.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DepthKind {
    /// Z-depth in metres.
    Metric,
    /// Depth up to an unknown scale and shift (larger is farther; e.g. da3-mono).
    Relative,
    /// Inverse depth up to an unknown scale and shift (larger is nearer; e.g. Depth Anything 2).
    Disparity,
}

impl DepthKind {
    /// `metric`, `relative` or `disparity`.
    pub fn parse(s: &str) -> Option<DepthKind> {
        match s {
            "metric" => Some(DepthKind::Metric),
            "relative" => Some(DepthKind::Relative),
            "disparity" => Some(DepthKind::Disparity),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            DepthKind::Metric => "metric",
            DepthKind::Relative => "relative",
            DepthKind::Disparity => "disparity",
        }
    }
}

/// Parses `NEAR,FAR` (metres, 0 < NEAR < FAR).
pub fn parse_range(s: &str) -> Result<(f32, f32)> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let nums: Option<Vec<f32>> = parts.iter().map(|p| p.parse::<f32>().ok()).collect();
    match nums.as_deref() {
        Some(&[near, far]) if near.is_finite() && far.is_finite() && 0.0 < near && near < far => Ok((near, far)),
        _ => Err(PipelineError::input(format!(
            "--depth-range {s:?}: expected NEAR,FAR in metres with 0 < NEAR < FAR, e.g. 0.5,8"
        ))),
    }
}

/// Maps relative depth or disparity to metres in `[near, far]` (see the module docs); missing
/// values (≤ 0, non-finite) become 0. `Metric` only zeroes the missing values.
pub fn to_metric(map: &mut DepthMap, kind: DepthKind, (near, far): (f32, f32)) {
    let valid = |v: f32| v.is_finite() && v > 0.0;
    if kind == DepthKind::Metric {
        map.data.iter_mut().filter(|v| !valid(**v)).for_each(|v| *v = 0.0);
        return;
    }
    let (lo, hi) = map
        .data
        .iter()
        .copied()
        .filter(|v| valid(*v))
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if lo > hi {
        map.data.iter_mut().for_each(|v| *v = 0.0);
        return;
    }
    let (lo, hi) = (lo as f64, hi as f64);
    let (near, far) = (near as f64, far as f64);
    // A constant map: everything at the middle of the range.
    let t_of = |v: f64| if hi > lo { (v - lo) / (hi - lo) } else { 0.5 };
    for v in map.data.iter_mut() {
        if !valid(*v) {
            *v = 0.0;
            continue;
        }
        let t = t_of(*v as f64);
        *v = match kind {
            DepthKind::Relative => near + t * (far - near),
            // Largest disparity = nearest.
            _ => 1.0 / (1.0 / far + t * (1.0 / near - 1.0 / far)),
        } as f32;
    }
}

/// Bilinear resampling of a depth map to `w` × `h` (pixel centres aligned), over valid samples
/// only: a pixel whose valid neighbours carry less than half the weight is missing (0).
pub fn resize_depth(src: &DepthMap, w: usize, h: usize) -> Result<DepthMap> {
    if (src.width, src.height) == (w, h) {
        return Ok(src.clone());
    }
    let axis = |dst: usize, n: usize, i: usize| -> (usize, usize, f64) {
        let s = ((i as f64 + 0.5) * n as f64 / dst as f64 - 0.5).clamp(0.0, (n - 1) as f64);
        let i0 = s.floor() as usize;
        (i0, (i0 + 1).min(n - 1), s - i0 as f64)
    };
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        let (y0, y1, fy) = axis(h, src.height, y);
        for x in 0..w {
            let (x0, x1, fx) = axis(w, src.width, x);
            let taps = [
                (x0, y0, (1.0 - fx) * (1.0 - fy)),
                (x1, y0, fx * (1.0 - fy)),
                (x0, y1, (1.0 - fx) * fy),
                (x1, y1, fx * fy),
            ];
            let (mut sum, mut wsum) = (0.0f64, 0.0f64);
            for (sx, sy, wt) in taps {
                let d = src.get(sx, sy);
                if d.is_finite() && d > 0.0 {
                    sum += wt * d as f64;
                    wsum += wt;
                }
            }
            if wsum >= 0.5 {
                out[y * w + x] = (sum / wsum) as f32;
            }
        }
    }
    Ok(DepthMap::new(w, h, out)?)
}

/// How to read a depth file.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthFile {
    pub kind: DepthKind,
    /// `NEAR,FAR` for relative depth and disparity ([`DEFAULT_DEPTH_RANGE`] when `None`).
    pub range: Option<(f32, f32)>,
    /// Metres per unit of 16-bit PNG and uint16 `.npy` depth.
    pub scale: f32,
}

impl Default for DepthFile {
    fn default() -> Self {
        DepthFile {
            kind: DepthKind::Metric,
            range: None,
            scale: pixl_render::depth::DEFAULT_DEPTH_SCALE,
        }
    }
}

/// Reads a depth file (EXR, 16-bit PNG, `.npy`), refuses non-finite values, converts its kind to
/// metres and resamples it to `size` (the photo's), with a warning for each assumption made.
pub fn read_depth_file(path: &Path, how: &DepthFile, size: (usize, usize)) -> Result<DepthMap> {
    let mut map = pixl_render::depth::read_depth(path, how.scale)?;
    if let Some(i) = map.data.iter().position(|d| !d.is_finite()) {
        let count = map.data.iter().filter(|d| !d.is_finite()).count();
        return Err(PipelineError::input(format!(
            "{}: {count} non-finite depth values (NaN/Inf), first at x={}, y={}; mark missing depth as 0 instead",
            path.display(),
            i % map.width,
            i / map.width
        )));
    }
    if how.kind == DepthKind::Metric {
        if how.range.is_some() {
            tracing::warn!("--depth-range is ignored for metric depth");
        }
    } else {
        let r = how.range.unwrap_or_else(|| {
            let (near, far) = DEFAULT_DEPTH_RANGE;
            tracing::warn!(
                "{}: {:?} depth without --depth-range: mapping it to {near}-{far} m (the default); \
pass --depth-range NEAR,FAR for the scene's real scale",
                path.display(),
                how.kind
            );
            DEFAULT_DEPTH_RANGE
        });
        to_metric(&mut map, how.kind, r);
    }
    if (map.width, map.height) != size {
        tracing::warn!(
            "{}: the depth map is {}x{} but the photo is {}x{}; resampling it bilinearly to the photo",
            path.display(),
            map.width,
            map.height,
            size.0,
            size.1
        );
        map = resize_depth(&map, size.0, size.1)?;
    }
    Ok(map)
}

/// What a [`DepthEstimator`] returns.
#[derive(Clone, Debug)]
pub struct EstimatedDepth {
    /// At the photo's size; sky and other missing depth are 0.
    pub depth: DepthMap,
    pub kind: DepthKind,
    /// Fraction of the pixels the estimator saw as sky (left to the scene's world).
    pub sky_fraction: f64,
}

impl EstimatedDepth {
    /// Metric z-depth at `size`: relative depth mapped to [`DEFAULT_DEPTH_RANGE`], resampled.
    pub fn to_metric(&self, size: (usize, usize)) -> Result<DepthMap> {
        let mut map = self.depth.clone();
        to_metric(&mut map, self.kind, DEFAULT_DEPTH_RANGE);
        resize_depth(&map, size.0, size.1)
    }
}

/// A monocular depth estimator, plugged in by the caller (`pixl relight`, `pixl reconstruct`
/// and `pixl studio` plug in [`crate::estimators::Da3Depth`]).
pub trait DepthEstimator: Send + Sync {
    /// A short name for messages and the studio's banner ("Depth Anything 3 (metric)").
    fn name(&self) -> String;
    /// Depth of `photo` (RGB, sRGB-encoded values in `[0, 1]`), whose focal length is
    /// `focal_px` pixels at its size.
    fn estimate(&self, photo: &Image, focal_px: f64) -> Result<EstimatedDepth>;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_and_disparity_map_to_the_range() {
        let mut m = DepthMap::new(4, 1, vec![2.0, 4.0, 6.0, 0.0]).unwrap();
        to_metric(&mut m, DepthKind::Relative, (1.0, 5.0));
        assert_eq!(m.data, vec![1.0, 3.0, 5.0, 0.0]);
        // Disparity: 6 (largest) → near 1 m, 2 → far 5 m, 4 → halfway in 1/d: 1/(0.2 + 0.4) m.
        let mut m = DepthMap::new(4, 1, vec![2.0, 4.0, 6.0, -1.0]).unwrap();
        to_metric(&mut m, DepthKind::Disparity, (1.0, 5.0));
        let want = [5.0, 1.0 / 0.6, 1.0, 0.0];
        for (a, b) in m.data.iter().zip(want) {
            assert!((*a as f64 - b).abs() < 1e-6, "{:?}", m.data);
        }
        let mut m = DepthMap::new(2, 1, vec![7.0, 7.0]).unwrap();
        to_metric(&mut m, DepthKind::Relative, (2.0, 4.0));
        assert_eq!(m.data, vec![3.0, 3.0]);
        let mut m = DepthMap::new(3, 1, vec![2.0, -1.0, 0.5]).unwrap();
        to_metric(&mut m, DepthKind::Metric, (2.0, 4.0));
        assert_eq!(m.data, vec![2.0, 0.0, 0.5]);
        assert_eq!(parse_range(" 0.5, 8").unwrap(), (0.5, 8.0));
        for bad in ["8,0.5", "0,1", "1", "a,b", "1,2,3", "1,inf"] {
            assert!(parse_range(bad).is_err(), "{bad}");
        }
        for k in [DepthKind::Metric, DepthKind::Relative, DepthKind::Disparity] {
            assert_eq!(DepthKind::parse(k.name()), Some(k));
        }
    }

    /// Against a naive bilinear interpolation of a linear ramp (exact for bilinear), and the
    /// missing-sample rule.
    #[test]
    fn resize_is_bilinear_over_valid_samples() {
        let (sw, sh) = (4usize, 3usize);
        let f = |x: f64, y: f64| 1.0 + 0.5 * x + 0.25 * y;
        let src = DepthMap::new(
            sw,
            sh,
            (0..sw * sh)
                .map(|i| f((i % sw) as f64, (i / sw) as f64) as f32)
                .collect(),
        )
        .unwrap();
        let (w, h) = (7usize, 5usize);
        let out = resize_depth(&src, w, h).unwrap();
        for y in 0..h {
            for x in 0..w {
                let sx = ((x as f64 + 0.5) * sw as f64 / w as f64 - 0.5).clamp(0.0, (sw - 1) as f64);
                let sy = ((y as f64 + 0.5) * sh as f64 / h as f64 - 0.5).clamp(0.0, (sh - 1) as f64);
                assert!((out.get(x, y) as f64 - f(sx, sy)).abs() < 1e-5, "({x},{y})");
            }
        }
        // 2x1 → 4x1 with the right sample missing: x=0,1 see mostly the left sample; x=2,3 mostly
        // the missing one and stay missing.
        let src = DepthMap::new(2, 1, vec![3.0, 0.0]).unwrap();
        let out = resize_depth(&src, 4, 1).unwrap();
        assert_eq!(out.data, vec![3.0, 3.0, 0.0, 0.0]);
    }
}
