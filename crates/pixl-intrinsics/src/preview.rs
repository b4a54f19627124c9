//! Contact sheets of a C_T for a person to look at (8-bit sRGB PNG content).
//!
//! Display mapping, one rule for every panel so they can be compared:
//! - albedo A: clipped to [0, 1], sRGB-encoded;
//! - shading S, residual R and the recomposition A⊙S+R share one white point `w` and are shown
//!   as `sRGB(clip(v / w, 0, 1))`. `w = 1` when S and R already lie in [0, 1] (a rescaled C_T, as
//!   `pixl compose` writes by default); otherwise `w = max(p98(S), p98(R), ε)`, exactly compose's
//!   τ (App. B), so an HDR (`--no-rescale`) C_T looks like its rescaled version. Sharing `w`
//!   keeps the diffuse-to-specular balance visible.
//!
//! Panels are separated by a 4-pixel mid-grey gutter.
use crate::compose::{percentile, RESCALE_PERCENTILE, TAU_EPS};
use crate::ct::Ct;
use crate::error::Result;
use pixl_core::image::linear_to_srgb;
use pixl_core::Image;

/// Width of the gutter between panels, in pixels.
pub const GUTTER: usize = 4;
const GUTTER_GREY: f32 = 0.5;

/// The white point `w` of S, R and A⊙S+R (see the module docs).
pub fn white_point(ct: &Ct) -> f32 {
    let in_unit = |img: &Image| img.data.iter().all(|v| (0.0..=1.0).contains(v));
    if in_unit(&ct.shading) && in_unit(&ct.residual) {
        return 1.0;
    }
    let finite = |img: &Image| img.data.iter().copied().filter(|v| v.is_finite()).collect::<Vec<f32>>();
    let s = percentile(&mut finite(&ct.shading), RESCALE_PERCENTILE);
    let r = percentile(&mut finite(&ct.residual), RESCALE_PERCENTILE);
    s.max(r).max(TAU_EPS)
}

/// Display panels `[A, S, R, A⊙S+R]` with white point `white`.
pub fn panels(ct: &Ct, white: f32) -> [Image; 4] {
    let inv = 1.0 / white.max(TAU_EPS);
    let show = |img: &Image| img.map(|v| linear_to_srgb((v * inv).clamp(0.0, 1.0)));
    [
        ct.albedo.map(|v| linear_to_srgb(v.clamp(0.0, 1.0))),
        show(&ct.shading),
        show(&ct.residual),
        show(&ct.recompose()),
    ]
}

fn gutter(height: usize) -> Image {
    Image::from_fn(GUTTER, height, 3, |_, _, _| GUTTER_GREY)
}

/// Images side by side with gutters.
fn row(images: &[&Image]) -> Result<Image> {
    let g = gutter(images.first().map_or(1, |i| i.height));
    let mut parts: Vec<&Image> = Vec::with_capacity(images.len() * 2);
    for (k, img) in images.iter().enumerate() {
        if k > 0 {
            parts.push(&g);
        }
        parts.push(img);
    }
    Ok(Image::hstack(&parts)?)
}

/// Rows stacked vertically with gutters (all rows one width).
fn column(rows: &[Image]) -> Result<Image> {
    let Some(first) = rows.first() else {
        return Err(crate::IntrinsicsError::Invalid("contact sheet of no rows".into()));
    };
    let w = first.width;
    let mut data = Vec::new();
    for (k, r) in rows.iter().enumerate() {
        if r.width != w || r.channels != 3 {
            return Err(crate::IntrinsicsError::Invalid(
                "contact sheet rows differ in width".into(),
            ));
        }
        if k > 0 {
            data.extend(std::iter::repeat_n(GUTTER_GREY, w * GUTTER * 3));
        }
        data.extend_from_slice(&r.data);
    }
    let h = data.len() / (w * 3);
    Ok(Image::from_vec(w, h, 3, data)?)
}

/// `A | S | R | A⊙S+R`, one row.
pub fn preview_sheet(ct: &Ct) -> Result<Image> {
    let p = panels(ct, white_point(ct));
    row(&[&p[0], &p[1], &p[2], &p[3]])
}

/// One row `A | S | R | A⊙S+R` per C_T, all with the white point of the first (the clean input).
pub fn contact_sheet(cts: &[Ct]) -> Result<Image> {
    let Some(first) = cts.first() else {
        return Err(crate::IntrinsicsError::Invalid("contact sheet of no C_T".into()));
    };
    let white = white_point(first);
    let rows = cts
        .iter()
        .map(|ct| {
            let p = panels(ct, white);
            row(&[&p[0], &p[1], &p[2], &p[3]])
        })
        .collect::<Result<Vec<_>>>()?;
    column(&rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_and_mapping() {
        let a = Image::from_fn(3, 2, 3, |_, _, _| 0.5);
        let s = Image::from_fn(3, 2, 3, |x, _, _| x as f32 * 2.0);
        let r = Image::from_fn(3, 2, 3, |_, _, _| 1.0);
        let ct = Ct::new(a, s, r).unwrap();
        // HDR values: the white point is compose's τ, here p98(S) (R = 1 is smaller).
        let mut all: Vec<f32> = ct.shading.data.clone();
        let want = percentile(&mut all, 98.0);
        assert_eq!(white_point(&ct), want.max(1.0));
        let sheet = preview_sheet(&ct).unwrap();
        assert_eq!((sheet.width, sheet.height), (4 * 3 + 3 * GUTTER, 2));
        // Albedo panel: sRGB(0.5).
        assert!((sheet.get(0, 0, 0) - linear_to_srgb(0.5)).abs() < 1e-6);
        // First gutter.
        assert_eq!(sheet.get(3, 1, 2), GUTTER_GREY);
        let two = contact_sheet(&[ct.clone(), ct]).unwrap();
        assert_eq!((two.width, two.height), (sheet.width, 2 * 2 + GUTTER));
    }
}
