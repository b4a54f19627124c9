//! DA3's official input preprocessing (`utils/io/input_processor.py`, method
//! `upper_bound_resize`, the API default), reproduced exactly:
//!
//! 1. the photo as 8-bit RGB (`PIL.Image.convert("RGB")`: grey replicated, alpha dropped); our
//!    [`Image`] holds `v/255` for 8-bit files, so `round(v·255)` gives back the file's bytes;
//! 2. longest side → `process_res` (default 504): `scale = res / longest`, each side
//!    `max(1, round(side·scale))` with Python's round-half-to-even, `cv2.INTER_CUBIC` when
//!    `scale > 1`, `cv2.INTER_AREA` otherwise; skipped when the longest side already equals
//!    `process_res`;
//! 3. each side to the *nearest* multiple of 14 (ties upward) by a second `cv2.resize` — not a
//!    crop — with `INTER_CUBIC` if either side grows, else `INTER_AREA`;
//! 4. `ToTensor` (`byte / 255` in f32) and ImageNet `Normalize` (`(x − mean) / std` in f32).
//!
//! Output: a `(1, 3, H, W)` f32 tensor, `H`, `W` multiples of 14, plus the sizes along the way.
use super::resize::{cv2_resize_u8, Cv2Filter};
use crate::error::EstimateError;
use candle_core::{Device, Tensor};
use pixl_core::Image;

/// `InputProcessor.PATCH_SIZE`.
pub const PATCH: usize = 14;
/// `InputProcessor.NORMALIZE` mean.
pub const MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// `InputProcessor.NORMALIZE` std.
pub const STD: [f32; 3] = [0.229, 0.224, 0.225];
/// The official API's default `process_res`.
pub const DEFAULT_PROCESS_RES: usize = 504;

/// The sizes of the two resizes, all `(width, height)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ProcessPlan {
    pub photo: (usize, usize),
    /// After the longest-side resize.
    pub bounded: (usize, usize),
    /// The network input, multiples of 14.
    pub processed: (usize, usize),
}

/// Python's `round(x)` (half to even) for the non-negative products of step 2.
fn py_round(x: f64) -> usize {
    x.round_ties_even().max(0.0) as usize
}

/// `_make_divisible_by_resize`'s `nearest_multiple`: ties go up.
fn nearest_multiple(x: usize, p: usize) -> usize {
    let down = (x / p) * p;
    let up = down + p;
    if up - x <= x - down {
        up
    } else {
        down
    }
}

impl ProcessPlan {
    /// The official sizes for a `width × height` photo. Errors when the photo is empty or so
    /// elongated that a side rounds below one patch (the official code would fail there too).
    pub fn new(width: usize, height: usize, process_res: usize) -> Result<Self, EstimateError> {
        if width == 0 || height == 0 {
            return Err(EstimateError::Input(format!("photo is empty ({width}x{height})")));
        }
        if process_res < PATCH {
            return Err(EstimateError::Input(format!(
                "process_res {process_res} is below the patch size {PATCH}"
            )));
        }
        let longest = width.max(height);
        let bounded = if longest == process_res {
            (width, height)
        } else {
            let scale = process_res as f64 / longest as f64;
            (
                py_round(width as f64 * scale).max(1),
                py_round(height as f64 * scale).max(1),
            )
        };
        let processed = (
            nearest_multiple(bounded.0, PATCH).max(1),
            nearest_multiple(bounded.1, PATCH).max(1),
        );
        if !processed.0.is_multiple_of(PATCH) || !processed.1.is_multiple_of(PATCH) {
            return Err(EstimateError::Input(format!(
                "photo {width}x{height} is too elongated for process_res {process_res}: its short side \
                 becomes {} px, under half a {PATCH}-px patch",
                bounded.0.min(bounded.1)
            )));
        }
        Ok(Self {
            photo: (width, height),
            bounded,
            processed,
        })
    }

    /// Filter of the longest-side resize (`None`: skipped).
    pub fn first_filter(&self) -> Option<Cv2Filter> {
        let longest = self.photo.0.max(self.photo.1);
        if self.bounded == self.photo {
            None
        } else if self.bounded.0.max(self.bounded.1) > longest {
            Some(Cv2Filter::Cubic)
        } else {
            Some(Cv2Filter::Area)
        }
    }

    /// Filter of the multiple-of-14 resize (`None`: skipped).
    pub fn second_filter(&self) -> Option<Cv2Filter> {
        let ((w, h), (nw, nh)) = (self.bounded, self.processed);
        if (w, h) == (nw, nh) {
            None
        } else if nw > w || nh > h {
            Some(Cv2Filter::Cubic)
        } else {
            Some(Cv2Filter::Area)
        }
    }
}

/// The photo as interleaved 8-bit RGB: `round(clamp(v, 0, 1)·255)`; 1 channel is replicated,
/// the second of 2 and the fourth of 4 (alpha) dropped. Errors on other channel counts and on
/// non-finite values.
pub fn to_rgb8(photo: &Image) -> Result<Vec<u8>, EstimateError> {
    let ch = photo.channels;
    if !matches!(ch, 1..=4) || photo.data.len() != photo.width * photo.height * ch {
        return Err(EstimateError::Input(format!(
            "photo has {ch} channels ({} samples for {}x{}); expected grey, grey+alpha, RGB or RGBA",
            photo.data.len(),
            photo.width,
            photo.height
        )));
    }
    if let Some((count, x, y, c)) = photo.find_non_finite() {
        return Err(EstimateError::Input(format!(
            "photo has {count} non-finite values; first at x={x}, y={y}, channel {c}"
        )));
    }
    let q = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    let mut out = Vec::with_capacity(photo.width * photo.height * 3);
    for px in photo.data.chunks_exact(ch) {
        if ch >= 3 {
            out.extend([q(px[0]), q(px[1]), q(px[2])]);
        } else {
            let g = q(px[0]);
            out.extend([g, g, g]);
        }
    }
    Ok(out)
}

/// Steps 2–3 on interleaved 8-bit RGB: the processed image's bytes.
pub fn resize_rgb8(rgb: &[u8], plan: &ProcessPlan) -> Vec<u8> {
    let (w0, h0) = plan.photo;
    let (w1, h1) = plan.bounded;
    let (w2, h2) = plan.processed;
    let first = match plan.first_filter() {
        Some(f) => cv2_resize_u8(rgb, w0, h0, 3, w1, h1, f),
        None => rgb.to_vec(),
    };
    match plan.second_filter() {
        Some(f) => cv2_resize_u8(&first, w1, h1, 3, w2, h2, f),
        None => first,
    }
}

/// Step 4: `(3, H, W)` planar normalised f32.
pub fn normalize_rgb8(rgb: &[u8], width: usize, height: usize) -> Vec<f32> {
    let n = width * height;
    let mut out = vec![0f32; 3 * n];
    for (p, px) in rgb.chunks_exact(3).enumerate() {
        for c in 0..3 {
            out[c * n + p] = (px[c] as f32 / 255.0 - MEAN[c]) / STD[c];
        }
    }
    out
}

/// The whole preprocessing: `(1, 3, H, W)` f32 on `device`, and the plan.
pub fn preprocess(photo: &Image, process_res: usize, device: &Device) -> Result<(Tensor, ProcessPlan), EstimateError> {
    let plan = ProcessPlan::new(photo.width, photo.height, process_res)?;
    let rgb = to_rgb8(photo)?;
    let resized = resize_rgb8(&rgb, &plan);
    let (w, h) = plan.processed;
    let chw = normalize_rgb8(&resized, w, h);
    Ok((Tensor::from_vec(chw, (1, 3, h, w), device)?, plan))
}
