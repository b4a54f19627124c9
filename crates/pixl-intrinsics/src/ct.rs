//! The target intrinsics C_T = [A; S; R] (paper §3.1, eq. 1: `I = A ⊙ S + R`) and its file.
//!
//! In memory a [`Ct`] is three 3-channel [`Image`]s of one size (HWC, linear values):
//! albedo A (in [0, 1] when composed), diffuse shading S (≥ 0; in [0, 1] after the p98
//! rescale of App. B), non-diffuse residual R (same). As a tensor it is planar `9 × H × W`,
//! channel order `A.R, A.G, A.B, S.R, S.G, S.B, R.R, R.G, R.B` ([`Ct::to_chw`]).
//!
//! On disk it is one OpenEXR with the nine channels `albedo.R/G/B`, `shading.R/G/B`,
//! `residual.R/G/B`, written as f32 (atomically); f16 and u32 files are accepted on read. Reading
//! refuses missing channels (listing them), oversized headers (pixl-core's guard) and NaN/Inf
//! (with the count and first location).
use crate::error::{IntrinsicsError, Result};
use pixl_core::exrio::{read_exr_channels, write_exr_channels, ExrChannels};
use pixl_core::{CoreError, Image};
use std::path::Path;

/// The three intrinsic groups, in C_T order, as named in the file.
pub const GROUPS: [&str; 3] = ["albedo", "shading", "residual"];
/// Colour channel suffixes.
pub const RGB: [&str; 3] = ["R", "G", "B"];

/// Target intrinsics: albedo, diffuse shading and non-diffuse residual, each 3-channel, one size.
#[derive(Clone, Debug, PartialEq)]
pub struct Ct {
    pub albedo: Image,
    pub shading: Image,
    pub residual: Image,
}

impl Ct {
    /// Checks that the three images are RGB and share one non-empty size.
    pub fn new(albedo: Image, shading: Image, residual: Image) -> Result<Ct> {
        let (w, h) = (albedo.width, albedo.height);
        if w == 0 || h == 0 {
            return Err(IntrinsicsError::InvalidCt(format!("empty image ({w}x{h})")));
        }
        for (name, img) in GROUPS.iter().zip([&albedo, &shading, &residual]) {
            if img.channels != 3 {
                return Err(IntrinsicsError::InvalidCt(format!(
                    "{name} has {} channels, expected 3",
                    img.channels
                )));
            }
            if img.width != w || img.height != h {
                return Err(IntrinsicsError::InvalidCt(format!(
                    "{name} is {}x{}, but albedo is {w}x{h}",
                    img.width, img.height
                )));
            }
        }
        Ok(Ct {
            albedo,
            shading,
            residual,
        })
    }

    pub fn width(&self) -> usize {
        self.albedo.width
    }

    pub fn height(&self) -> usize {
        self.albedo.height
    }

    /// The three images in C_T order.
    pub fn groups(&self) -> [&Image; 3] {
        [&self.albedo, &self.shading, &self.residual]
    }

    /// Planar `9 × H × W`: `A.R, A.G, A.B, S.R, S.G, S.B, R.R, R.G, R.B`.
    pub fn to_chw(&self) -> Vec<f32> {
        let mut out = Vec::with_capacity(9 * self.width() * self.height());
        for img in self.groups() {
            out.extend_from_slice(&img.to_chw());
        }
        out
    }

    /// Planar `9 × oh × ow` as [`Ct::to_chw`], each group area-averaged to `ow × oh`
    /// ([`pixl_core::resample::area_resize_to_chw`]; at the C_T's own size, the plain copy).
    pub fn to_chw_at(&self, ow: usize, oh: usize) -> Result<Vec<f32>> {
        let mut out = Vec::with_capacity(9 * ow * oh);
        for img in self.groups() {
            out.extend(pixl_core::resample::area_resize_to_chw(img, ow, oh)?);
        }
        Ok(out)
    }

    /// Inverse of [`Ct::to_chw`].
    pub fn from_chw(width: usize, height: usize, chw: &[f32]) -> Result<Ct> {
        let n = width * height * 3;
        if chw.len() != 3 * n {
            return Err(IntrinsicsError::InvalidCt(format!(
                "planar buffer has {} samples, expected 9x{height}x{width} = {}",
                chw.len(),
                3 * n
            )));
        }
        let img = |g: usize| Image::from_chw(width, height, 3, &chw[g * n..(g + 1) * n]);
        Ct::new(img(0)?, img(1)?, img(2)?)
    }

    /// The recomposed image `A ⊙ S + R` (linear, same scale as S and R).
    pub fn recompose(&self) -> Image {
        let data = self
            .albedo
            .data
            .iter()
            .zip(&self.shading.data)
            .zip(&self.residual.data)
            .map(|((a, s), r)| a * s + r)
            .collect();
        Image {
            data,
            ..self.albedo.clone()
        }
    }
}

/// Reads a C_T file (see the module docs for the format and the checks).
pub fn read_ct(path: &Path) -> Result<Ct> {
    let chans = read_exr_channels(path)?;
    let names: Vec<String> = GROUPS
        .iter()
        .flat_map(|g| RGB.iter().map(move |c| format!("{g}.{c}")))
        .collect();
    let missing: Vec<&str> = names
        .iter()
        .filter(|n| chans.get(n).is_none())
        .map(|s| s.as_str())
        .collect();
    if !missing.is_empty() {
        let found: Vec<&str> = chans.names().collect();
        return Err(IntrinsicsError::MissingCtChannels {
            path: path.display().to_string(),
            missing: missing.join(", "),
            found: if found.is_empty() {
                "none".into()
            } else {
                found.join(", ")
            },
        });
    }
    let (w, h) = (chans.width, chans.height);
    // First non-finite sample in file order (group, then row-major pixel, then channel).
    let mut count = 0usize;
    let mut first: Option<(usize, usize, String)> = None;
    let mut images = Vec::with_capacity(3);
    for (g, group) in GROUPS.iter().enumerate() {
        let mut img = Image::new(w, h, 3);
        for (c, name) in names[g * 3..g * 3 + 3].iter().enumerate() {
            let plane = chans.get(name).unwrap_or(&[]);
            for (p, &v) in plane.iter().enumerate() {
                img.data[p * 3 + c] = v;
            }
        }
        if let Some((n, x, y, c)) = img.find_non_finite() {
            count += n;
            if first.is_none() {
                first = Some((x, y, format!("{group}.{}", RGB[c])));
            }
        }
        images.push(img);
    }
    if let Some((x, y, channel)) = first {
        return Err(CoreError::NonFinite {
            path: path.to_owned(),
            count,
            x,
            y,
            channel,
        }
        .into());
    }
    let residual = images.pop().unwrap_or_else(|| Image::new(w, h, 3));
    let shading = images.pop().unwrap_or_else(|| Image::new(w, h, 3));
    let albedo = images.pop().unwrap_or_else(|| Image::new(w, h, 3));
    Ct::new(albedo, shading, residual)
}

/// The nine named planes of a C_T, as written to its file.
pub fn ct_to_exr_channels(ct: &Ct) -> Result<ExrChannels> {
    let mut chans = ExrChannels::new(ct.width(), ct.height());
    for (group, img) in GROUPS.iter().zip(ct.groups()) {
        for (c, suffix) in RGB.iter().enumerate() {
            chans.push(
                format!("{group}.{suffix}"),
                img.data.iter().skip(c).step_by(3).copied().collect(),
            )?;
        }
    }
    Ok(chans)
}

/// Writes a C_T file: f32 samples, atomically (a failed write leaves nothing behind).
pub fn write_ct(path: &Path, ct: &Ct) -> Result<()> {
    write_exr_channels(path, &ct_to_exr_channels(ct)?)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(w: usize, h: usize) -> Ct {
        let a = Image::from_fn(w, h, 3, |x, y, c| ((x + 2 * y + c) % 7) as f32 / 7.0);
        let s = Image::from_fn(w, h, 3, |x, y, c| (x * y + c) as f32 * 0.25);
        let r = Image::from_fn(w, h, 3, |x, _, c| (x as f32 - c as f32) * 0.01);
        Ct::new(a, s, r).unwrap()
    }

    #[test]
    fn chw_layout_and_roundtrip() {
        let ct = sample(4, 3);
        let chw = ct.to_chw();
        let n = 12;
        // channel 4 = shading.G, pixel (x=2, y=1)
        assert_eq!(chw[4 * n + 4 + 2], ct.shading.get(2, 1, 1));
        assert_eq!(chw[8 * n + 3 * 4 - 1], ct.residual.get(3, 2, 2));
        assert_eq!(Ct::from_chw(4, 3, &chw).unwrap(), ct);
        assert!(Ct::from_chw(4, 3, &chw[1..]).is_err());
    }

    #[test]
    fn recompose_is_a_times_s_plus_r() {
        let ct = sample(3, 2);
        let i = ct.recompose();
        for (k, v) in i.data.iter().enumerate() {
            let want = ct.albedo.data[k] as f64 * ct.shading.data[k] as f64 + ct.residual.data[k] as f64;
            assert!((*v as f64 - want).abs() < 1e-6);
        }
    }

    #[test]
    fn new_checks_sizes_and_channels() {
        let ct = sample(3, 2);
        assert!(Ct::new(ct.albedo.clone(), Image::new(3, 3, 3), ct.residual.clone()).is_err());
        assert!(Ct::new(ct.albedo.clone(), ct.shading.clone(), Image::new(3, 2, 4)).is_err());
    }

    #[test]
    fn file_roundtrip_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("ct.exr");
        let ct = sample(5, 4);
        write_ct(&p, &ct).unwrap();
        assert_eq!(read_ct(&p).unwrap(), ct);

        // Missing channels are listed.
        let mut chans = ct_to_exr_channels(&ct).unwrap();
        chans.channels.retain(|(n, _)| n != "shading.G" && n != "residual.B");
        let q = dir.path().join("partial.exr");
        write_exr_channels(&q, &chans).unwrap();
        let e = read_ct(&q).unwrap_err().to_string();
        assert!(
            e.contains("shading.G") && e.contains("residual.B") && e.contains("partial.exr"),
            "{e}"
        );

        // NaN/Inf: count and first location.
        let mut bad = ct.clone();
        bad.shading.set(2, 1, 2, f32::NAN);
        bad.residual.set(0, 0, 0, f32::INFINITY);
        let q = dir.path().join("nan.exr");
        write_ct(&q, &bad).unwrap();
        let e = read_ct(&q).unwrap_err().to_string();
        assert!(
            e.contains("2 non-finite") && e.contains("x=2, y=1") && e.contains("shading.B"),
            "{e}"
        );
    }
}
