//! An albedo texture with the errors of an intrinsic estimator, for `pixl synth --coarse
//! --coarse-albedo estimated`: the inference setting's reconstruction is textured with what an
//! estimator such as Marigold-IID would return for the source photo, not with the perfect
//! `DiffCol` pass and not with the photo itself.
//!
//! From the source render's passes, in linear values, per pixel and channel `c`:
//!
//! `A = clamp(g_c · box_r(DiffCol) · (S / median S)^α, 0, 1)`, `S` the luminance of the diffuse
//! light `DiffDir + DiffInd`,
//!
//! so a share `α` of the source's shading and shadows stays in the albedo (in log space
//! exactly `α·log(S / median S)`), fine texture is lost to a `(2r + 1)²` box blur, and each
//! channel's scale is off by `g_c` (a tint). [`EstimatorErrors::draw`] picks `α ∈ [0.1, 0.4]`,
//! `r ∈ {0, 1, 2}` and `g_c ∈ [0.88, 1.12]` from a seeded stream; the texture is returned in sRGB
//! as `coarse_scene_textured` takes it.
use pixl_core::{Image, Rng};

/// How wrong the estimated albedo is (see the module notes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EstimatorErrors {
    /// Share of the source's shading left in the albedo (log space).
    pub shading_leak: f32,
    /// Box-blur radius in pixels.
    pub blur_radius: usize,
    /// Per-channel scale.
    pub gain: [f32; 3],
}

impl EstimatorErrors {
    /// No error: the texture is `DiffCol` itself.
    pub const NONE: EstimatorErrors = EstimatorErrors {
        shading_leak: 0.0,
        blur_radius: 0,
        gain: [1.0; 3],
    };

    pub fn draw(rng: &mut Rng) -> Self {
        EstimatorErrors {
            shading_leak: rng.uniform(0.1, 0.4),
            blur_radius: rng.below(3),
            gain: [
                rng.uniform(0.88, 1.12),
                rng.uniform(0.88, 1.12),
                rng.uniform(0.88, 1.12),
            ],
        }
    }
}

/// `(2r + 1)²` box mean of each channel, the window clipped at the borders.
fn box_blur(img: &Image, r: usize) -> Image {
    if r == 0 {
        return img.clone();
    }
    let (w, h) = (img.width, img.height);
    Image::from_fn(w, h, img.channels, |x, y, c| {
        let (x0, x1, y0, y1) = (
            x.saturating_sub(r),
            (x + r).min(w - 1),
            y.saturating_sub(r),
            (y + r).min(h - 1),
        );
        let mut sum = 0.0;
        for yy in y0..=y1 {
            for xx in x0..=x1 {
                sum += img.get(xx, yy, c);
            }
        }
        sum / ((x1 - x0 + 1) * (y1 - y0 + 1)) as f32
    })
}

/// The estimated albedo in linear values from `diffcol` and the diffuse light `diffuse`
/// (`DiffDir + DiffInd`), both RGB of one size; `None` if they differ in shape.
pub fn estimated_albedo_linear(diffcol: &Image, diffuse: &Image, e: &EstimatorErrors) -> Option<Image> {
    if (diffcol.width, diffcol.height, diffcol.channels) != (diffuse.width, diffuse.height, 3) || diffcol.channels != 3
    {
        return None;
    }
    let (w, h) = (diffcol.width, diffcol.height);
    let lum = |x: usize, y: usize| {
        0.2126 * diffuse.get(x, y, 0) + 0.7152 * diffuse.get(x, y, 1) + 0.0722 * diffuse.get(x, y, 2)
    };
    let mut lums: Vec<f32> = (0..w * h).map(|i| lum(i % w, i / w)).filter(|v| *v > 0.0).collect();
    let median = if lums.is_empty() {
        1.0
    } else {
        let mid = lums.len() / 2;
        *lums.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    // Unlit pixels (S = 0) keep a dark but finite factor: a floor at 1 % of the median.
    let floor = median * 0.01;
    let blurred = box_blur(diffcol, e.blur_radius);
    Some(Image::from_fn(w, h, 3, |x, y, c| {
        let s = (lum(x, y).max(floor) / median).powf(e.shading_leak);
        (e.gain[c] * blurred.get(x, y, c) * s).clamp(0.0, 1.0)
    }))
}

/// [`estimated_albedo_linear`] in sRGB, from a render's `DiffCol`, `DiffDir` and `DiffInd`.
pub fn estimated_albedo_srgb(
    diffcol: &Image,
    diff_dir: &Image,
    diff_ind: &Image,
    e: &EstimatorErrors,
) -> Option<Image> {
    if (diff_dir.width, diff_dir.height, diff_dir.channels) != (diff_ind.width, diff_ind.height, diff_ind.channels) {
        return None;
    }
    let diffuse = Image::from_fn(diff_dir.width, diff_dir.height, diff_dir.channels, |x, y, c| {
        diff_dir.get(x, y, c) + diff_ind.get(x, y, c)
    });
    estimated_albedo_linear(diffcol, &diffuse, e).map(|a| a.map(pixl_core::image::linear_to_srgb))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: usize, h: usize, f: impl Fn(usize, usize, usize) -> f32) -> Image {
        Image::from_fn(w, h, 3, f)
    }

    #[test]
    fn without_errors_it_is_diffcol() {
        let diffcol = img(5, 4, |x, y, c| 0.1 + 0.05 * (x + y + c) as f32);
        let diffuse = img(5, 4, |x, y, _| 0.2 + x as f32 * y as f32);
        let a = estimated_albedo_linear(&diffcol, &diffuse, &EstimatorErrors::NONE).unwrap();
        assert_eq!(a.data, diffcol.data);
    }

    #[test]
    fn the_shading_leak_is_exactly_alpha_in_log_space_and_the_gain_scales_channels() {
        // Grey shading (all channels equal): luminance = the value itself.
        let diffcol = img(6, 3, |_, _, c| [0.3, 0.4, 0.5][c]);
        let diffuse = img(6, 3, |x, _, _| [0.5, 1.0, 2.0, 4.0, 1.0, 1.0][x]);
        let e = EstimatorErrors {
            shading_leak: 0.25,
            blur_radius: 0,
            gain: [1.1, 1.0, 0.9],
        };
        let a = estimated_albedo_linear(&diffcol, &diffuse, &e).unwrap();
        // Median of the positive luminances {0.5, 1, 2, 4, 1, 1} × 3 rows is 1.
        for x in 0..6 {
            let s = [0.5f32, 1.0, 2.0, 4.0, 1.0, 1.0][x];
            for c in 0..3 {
                let want = e.gain[c] * diffcol.get(x, 1, c) * s.powf(0.25);
                assert!(
                    (a.get(x, 1, c) - want).abs() < 1e-6,
                    "({x},{c}): {} vs {want}",
                    a.get(x, 1, c)
                );
            }
        }
    }

    #[test]
    fn blur_averages_the_window_and_shapes_must_match() {
        let diffcol = img(3, 3, |x, y, _| if (x, y) == (1, 1) { 0.9 } else { 0.0 });
        let diffuse = img(3, 3, |_, _, _| 1.0);
        let e = EstimatorErrors {
            blur_radius: 1,
            ..EstimatorErrors::NONE
        };
        let a = estimated_albedo_linear(&diffcol, &diffuse, &e).unwrap();
        assert!((a.get(1, 1, 0) - 0.1).abs() < 1e-6); // 0.9 over 9 pixels
        assert!((a.get(0, 0, 0) - 0.225).abs() < 1e-6); // 0.9 over the 4 pixels of the corner
        assert!(estimated_albedo_linear(&diffcol, &img(2, 3, |_, _, _| 1.0), &e).is_none());
    }

    #[test]
    fn draws_stay_in_their_ranges_and_follow_the_seed() {
        let mut rng = Rng::new(3);
        let draws: Vec<EstimatorErrors> = (0..200).map(|_| EstimatorErrors::draw(&mut rng)).collect();
        assert!(draws.iter().all(|d| (0.1..=0.4).contains(&d.shading_leak)
            && d.blur_radius <= 2
            && d.gain.iter().all(|g| (0.88..=1.12).contains(g))));
        assert!((0..3).all(|r| draws.iter().any(|d| d.blur_radius == r)));
        assert_eq!(EstimatorErrors::draw(&mut Rng::new(3)), draws[0]);
    }
}
