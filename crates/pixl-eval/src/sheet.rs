//! The contact sheet of `pixl eval --sheet`: the images of the first pairs evaluated
//! ([`crate::EvalOptions::sheet_pairs`]), one row per pair, the panels of a row side by side in
//! the order of [`sheet_columns`]:
//!
//! `source | C_T albedo | C_T shading | C_T residual | <each method's prediction> | target`
//!
//! - The three C_T columns are there only when some method reads C_T (otherwise C_T is never
//!   loaded). Each map is shown clipped to [0, 1] and sRGB-encoded, as `pixl intrinsics preview`
//!   shows a rescaled C_T ([`ct_panels`]).
//! - A prediction is shown as it was scored: after the per-channel scale correction when that is
//!   on, the raw prediction otherwise.
//! - Every panel of a row has the pair's size (the evaluation refuses pairs whose images differ).
//!   Rows of different sizes (a set mixing image sizes) are stacked as they are, a narrower row
//!   padded on the right with mid-grey ([`PAD_GREY`]); nothing is resampled.
//! - No text is drawn on the image: the column order is written into `results.json`
//!   (`sheet_columns`) and `results.md` instead.
use crate::error::{EvalError, Result};
use pixl_core::image::linear_to_srgb;
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;

/// The value that pads rows narrower than the widest one.
pub const PAD_GREY: f32 = 0.5;

/// The kept images of one evaluated pair, in the order of [`sheet_columns`].
#[derive(Clone, PartialEq)]
pub struct SheetRow {
    pub scene: String,
    /// File names of the pair's source and target images.
    pub source: String,
    pub target: String,
    pub panels: Vec<Image>,
}

impl std::fmt::Debug for SheetRow {
    // The pixels would drown everything else; their sizes are what a reader wants.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let sizes: Vec<String> = self
            .panels
            .iter()
            .map(|p| format!("{}x{}x{}", p.width, p.height, p.channels))
            .collect();
        f.debug_struct("SheetRow")
            .field("scene", &self.scene)
            .field("source", &self.source)
            .field("target", &self.target)
            .field("panels", &sizes)
            .finish()
    }
}

/// The column names of a sheet: `source`, the three C_T maps when `with_ct`, one column per
/// method (its row label), `target`.
pub fn sheet_columns<'a>(methods: impl IntoIterator<Item = &'a str>, with_ct: bool) -> Vec<String> {
    let mut cols = vec!["source".to_string()];
    if with_ct {
        cols.extend(["C_T albedo", "C_T shading", "C_T residual"].map(String::from));
    }
    cols.extend(methods.into_iter().map(String::from));
    cols.push("target".into());
    cols
}

/// C_T's albedo, shading and residual for display: `sRGB(clip(v, 0, 1))` (NaN shows as 0).
pub fn ct_panels(ct: &Ct) -> [Image; 3] {
    let show = |img: &Image| {
        img.map(|v| {
            if v.is_nan() {
                0.0
            } else {
                linear_to_srgb(v.clamp(0.0, 1.0))
            }
        })
    };
    [show(&ct.albedo), show(&ct.shading), show(&ct.residual)]
}

/// The contact sheet of `rows` (see the module docs): each row's panels side by side, the rows
/// top to bottom. Errors on no rows, a row without panels, or panels of a row that differ in
/// height or channels.
pub fn contact_sheet(rows: &[SheetRow]) -> Result<Image> {
    if rows.is_empty() {
        return Err(EvalError::Empty("no pair kept for the contact sheet".into()));
    }
    let mut strips = Vec::with_capacity(rows.len());
    for row in rows {
        let panels: Vec<&Image> = row.panels.iter().collect();
        let strip = Image::hstack(&panels).map_err(|e| EvalError::Pair {
            scene: row.scene.clone(),
            source_name: row.source.clone(),
            target: row.target.clone(),
            reason: format!("contact sheet: {e}"),
        })?;
        strips.push(strip);
    }
    let strips: Vec<&Image> = strips.iter().collect();
    Ok(Image::vstack(&strips, PAD_GREY)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(w: usize, h: usize, n: usize, base: f32) -> SheetRow {
        SheetRow {
            scene: "s".into(),
            source: "a.png".into(),
            target: "b.png".into(),
            panels: (0..n)
                .map(|k| Image::from_fn(w, h, 3, |x, y, c| base + (k * 1000 + y * 100 + x * 3 + c) as f32))
                .collect(),
        }
    }

    #[test]
    fn columns_in_order() {
        assert_eq!(
            sheet_columns(["Ours", "Identity (source)"], true),
            [
                "source",
                "C_T albedo",
                "C_T shading",
                "C_T residual",
                "Ours",
                "Identity (source)",
                "target"
            ]
        );
        assert_eq!(
            sheet_columns(["Identity (source)"], false),
            ["source", "Identity (source)", "target"]
        );
    }

    /// Rows of different sizes: each keeps its pixels at its place, the narrower one is padded.
    #[test]
    fn rows_of_different_sizes_are_padded_not_resampled() {
        let (a, b) = (row(4, 3, 3, 0.0), row(2, 5, 3, 0.5));
        let sheet = contact_sheet(&[a.clone(), b.clone()]).unwrap();
        assert_eq!((sheet.width, sheet.height, sheet.channels), (12, 8, 3));
        for (k, p) in a.panels.iter().enumerate() {
            assert_eq!(sheet.get(4 * k + 3, 2, 1), p.get(3, 2, 1));
        }
        for (k, p) in b.panels.iter().enumerate() {
            assert_eq!(sheet.get(2 * k + 1, 3 + 4, 2), p.get(1, 4, 2));
        }
        assert_eq!(sheet.get(6, 3, 0), PAD_GREY);
        assert_eq!(sheet.get(11, 7, 2), PAD_GREY);
    }

    #[test]
    fn bad_rows_are_errors() {
        assert!(contact_sheet(&[]).is_err());
        let mut r = row(4, 3, 2, 0.0);
        r.panels[1] = Image::new(4, 2, 3);
        let e = contact_sheet(&[r]).unwrap_err().to_string();
        assert!(e.contains("a.png") && e.contains("contact sheet"), "{e}");
    }

    #[test]
    fn ct_panels_clip_and_encode() {
        let a = Image::from_fn(2, 1, 3, |x, _, _| [0.25, 1.5][x]);
        let s = Image::from_fn(2, 1, 3, |x, _, _| [-0.5, f32::NAN][x]);
        let r = Image::from_fn(2, 1, 3, |_, _, _| 0.0);
        let [pa, ps, pr] = ct_panels(&Ct {
            albedo: a,
            shading: s,
            residual: r,
        });
        // 0.25 linear is 0.537 in sRGB (1.055·0.25^(1/2.4) − 0.055).
        assert!((pa.get(0, 0, 0) - 0.5370987).abs() < 1e-5);
        assert!((pa.get(1, 0, 0) - 1.0).abs() < 1e-6);
        assert_eq!((ps.get(0, 0, 1), ps.get(1, 0, 1)), (0.0, 0.0));
        assert_eq!(pr.get(1, 0, 2), 0.0);
    }
}
