//! What happens to the network's output: the sky rule, metric scaling, and the resize back to
//! the photo.
//!
//! - [`apply_sky_rule`]: the official `DepthAnything3Net._process_mono_sky_estimation`, at the
//!   processed resolution: pixels with sky ≥ [`SKY_THRESHOLD`] (0.3) take the 0.99 quantile
//!   (linear interpolation, as `torch.quantile`) of the depth of the other pixels; nothing
//!   changes unless both sets hold more than 10 pixels. Above 100 000 non-sky pixels the
//!   official code estimates the quantile from 100 000 pixels drawn at random (with
//!   replacement); here the quantile is computed over all of them, which is what that sample
//!   estimates, and deterministic.
//! - [`metric_scale`]: README of DA3METRIC-LARGE, `metric_depth = focal · net_output / 300` with
//!   `focal = (fx + fy) / 2` in pixels of the *processed* image: the official `_resize_ixt`
//!   scales `fx` by `W/W₀` and `fy` by `H/H₀`.
//! - Back to the photo's size: bilinear, `align_corners=False` (PyTorch's
//!   `F.interpolate` default); the official API returns the processed resolution and leaves
//!   this step to the caller.
use crate::error::EstimateError;

/// Sky score at or above which a pixel is sky (`compute_sky_mask(threshold=0.3)`).
pub const SKY_THRESHOLD: f32 = 0.3;
/// The metric model's canonical focal length in pixels.
pub const METRIC_FOCAL: f64 = 300.0;
/// Fewest pixels of each kind for the sky rule to run (`sum() <= 10` skips it).
const MIN_PIXELS: usize = 10;

/// The official sky rule on one processed depth map (row-major, same length as `sky`).
/// Returns the depth given to sky pixels, or `None` when the rule did not apply.
pub fn apply_sky_rule(depth: &mut [f32], sky: &[f32]) -> Result<Option<f32>, EstimateError> {
    if depth.len() != sky.len() {
        return Err(EstimateError::Input(format!(
            "sky rule: depth has {} pixels, sky {}",
            depth.len(),
            sky.len()
        )));
    }
    let mut ground: Vec<f32> = depth
        .iter()
        .zip(sky)
        .filter(|(_, &s)| s < SKY_THRESHOLD)
        .map(|(&d, _)| d)
        .collect();
    let n_sky = depth.len() - ground.len();
    if ground.len() <= MIN_PIXELS || n_sky <= MIN_PIXELS {
        return Ok(None);
    }
    let q = quantile_linear(&mut ground, 0.99);
    for (d, &s) in depth.iter_mut().zip(sky) {
        if s >= SKY_THRESHOLD || s.is_nan() {
            *d = q;
        }
    }
    Ok(Some(q))
}

/// `torch.quantile(values, q)` with linear interpolation (sorts `values`; NaN sorts last).
pub fn quantile_linear(values: &mut [f32], q: f64) -> f32 {
    values.sort_unstable_by(|a, b| a.total_cmp(b));
    let n = values.len();
    if n == 0 {
        return f32::NAN;
    }
    let rank = q * (n - 1) as f64;
    let lo = rank.floor() as usize;
    let hi = (rank.ceil() as usize).min(n - 1);
    let t = (rank - lo as f64) as f32;
    let (a, b) = (values[lo], values[hi]);
    // torch.lerp's two-sided form.
    if t < 0.5 {
        a + t * (b - a)
    } else {
        b - (b - a) * (1.0 - t)
    }
}

/// The factor that turns the metric model's output into metres: `focal_processed / 300`, with
/// the photo's focal length `focal_px_at_photo` (pixels, fx = fy) carried to the processed size
/// as the official `_resize_ixt` does.
pub fn metric_scale(focal_px_at_photo: f64, photo: (usize, usize), processed: (usize, usize)) -> f64 {
    let fx = focal_px_at_photo * processed.0 as f64 / photo.0 as f64;
    let fy = focal_px_at_photo * processed.1 as f64 / photo.1 as f64;
    (fx + fy) / 2.0 / METRIC_FOCAL
}
