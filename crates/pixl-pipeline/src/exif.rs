//! The camera's focal length from a JPEG's EXIF block, and the focal length in pixels a photo is
//! processed with.
//!
//! # EXIF
//! Only what the focal length needs is read: the JPEG's segments up to the start of scan, the
//! first APP1 segment that starts with `Exif\0\0`, its TIFF header (either byte order), IFD0's
//! pointer to the Exif IFD (tag 0x8769), and there `FocalLengthIn35mmFilm` (0xA405, SHORT) and
//! `FocalLength` (0x920A, RATIONAL, reported only). Every offset is bounds-checked; a malformed
//! block gives `None`, never a panic. Other formats (PNG, EXR) have no focal length here.
//!
//! # Focal length in pixels ([`photo_focal`]), in this order
//! 1. `--focal PX`;
//! 2. `--fov DEG`: the **vertical** field of view, `f = (H/2) / tan(fov/2)` (the convention of
//!    `pixl reconstruct` and the scene camera);
//! 3. EXIF `FocalLengthIn35mmFilm` `f35` (mm): a 35 mm-equivalent focal length is the one that
//!    gives the same **diagonal** field of view on a 36 × 24 mm frame (diagonal 43.27 mm), so
//!    `f = f35 · √(W² + H²) / 43.27`. For a 3:2 photo this is `f35 / 36 · W_long`, the long-side
//!    rule; for 4:3 phone photos the diagonal rule gives a 4 % longer focal length than it.
//!    The value 0 means "unknown" in EXIF and is ignored;
//! 4. the default vertical field of view, [`DEFAULT_FOV_DEG`] (50°).
use crate::error::{PipelineError, Result};
use std::path::Path;

/// Vertical field of view assumed when neither a focal length, a field of view nor EXIF gives one.
pub const DEFAULT_FOV_DEG: f64 = 50.0;

/// What a JPEG's EXIF block says about the lens.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LensInfo {
    /// `FocalLengthIn35mmFilm`, mm (None if absent or 0).
    pub focal_35mm: Option<f64>,
    /// `FocalLength`, mm (the real focal length; needs the sensor size to be useful).
    pub focal_mm: Option<f64>,
}

/// Diagonal of the 36 × 24 mm frame, mm.
pub fn full_frame_diagonal_mm() -> f64 {
    36f64.hypot(24.0)
}

/// Most bytes read from a file when looking for its EXIF block (the block is at most 64 KiB and
/// comes right after the start of the file).
const HEAD_BYTES: u64 = 256 * 1024;

/// Reads the lens information of a JPEG file; `None` for other files or without EXIF.
pub fn read_lens_info(path: &Path) -> Option<LensInfo> {
    use std::io::Read;
    let f = std::fs::File::open(path).ok()?;
    let mut head = Vec::new();
    f.take(HEAD_BYTES).read_to_end(&mut head).ok()?;
    let tiff = jpeg_exif_block(&head)?;
    parse_tiff(tiff)
}

/// The TIFF payload of the first `Exif\0\0` APP1 segment of a JPEG byte stream.
pub fn jpeg_exif_block(bytes: &[u8]) -> Option<&[u8]> {
    if bytes.get(..2)? != [0xFF, 0xD8] {
        return None;
    }
    let mut pos = 2usize;
    loop {
        if *bytes.get(pos)? != 0xFF {
            return None;
        }
        // Fill bytes: any number of 0xFF before the marker code.
        while *bytes.get(pos + 1)? == 0xFF {
            pos += 1;
        }
        let marker = *bytes.get(pos + 1)?;
        pos += 2;
        match marker {
            // Start of scan / end of image: no more metadata segments.
            0xDA | 0xD9 => return None,
            // Markers without a length.
            0x01 | 0xD0..=0xD7 => continue,
            _ => {}
        }
        let len = u16::from_be_bytes([*bytes.get(pos)?, *bytes.get(pos + 1)?]) as usize;
        if len < 2 {
            return None;
        }
        let data = bytes.get(pos + 2..pos + len)?;
        if marker == 0xE1 && data.starts_with(b"Exif\0\0") {
            return Some(&data[6..]);
        }
        pos += len;
    }
}

struct Tiff<'a> {
    b: &'a [u8],
    little: bool,
}

impl Tiff<'_> {
    fn u16(&self, at: usize) -> Option<u16> {
        let s = self.b.get(at..at.checked_add(2)?)?;
        let a = [s[0], s[1]];
        Some(if self.little {
            u16::from_le_bytes(a)
        } else {
            u16::from_be_bytes(a)
        })
    }
    fn u32(&self, at: usize) -> Option<u32> {
        let s = self.b.get(at..at.checked_add(4)?)?;
        let a = [s[0], s[1], s[2], s[3]];
        Some(if self.little {
            u32::from_le_bytes(a)
        } else {
            u32::from_be_bytes(a)
        })
    }
    /// The entries of the IFD at `offset`: (tag, type, count, offset of the value field).
    fn entries(&self, offset: usize) -> Option<Vec<(u16, u16, u32, usize)>> {
        let n = self.u16(offset)? as usize;
        (0..n)
            .map(|i| {
                let e = offset + 2 + 12 * i;
                Some((self.u16(e)?, self.u16(e + 2)?, self.u32(e + 4)?, e + 8))
            })
            .collect()
    }
}

/// Reads the lens tags from a TIFF-structured EXIF payload.
pub fn parse_tiff(b: &[u8]) -> Option<LensInfo> {
    let little = match b.get(..2)? {
        b"II" => true,
        b"MM" => false,
        _ => return None,
    };
    let t = Tiff { b, little };
    if t.u16(2)? != 42 {
        return None;
    }
    let ifd0 = t.u32(4)? as usize;
    const SHORT: u16 = 3;
    const LONG: u16 = 4;
    const RATIONAL: u16 = 5;
    let exif_ifd = t
        .entries(ifd0)?
        .into_iter()
        .find(|&(tag, ty, _, _)| tag == 0x8769 && ty == LONG)
        .and_then(|(_, _, _, v)| t.u32(v))? as usize;
    let mut info = LensInfo::default();
    for (tag, ty, count, v) in t.entries(exif_ifd)? {
        match (tag, ty) {
            (0xA405, SHORT) if count >= 1 => {
                info.focal_35mm = t.u16(v).filter(|&f| f > 0).map(f64::from);
            }
            (0x920A, RATIONAL) if count >= 1 => {
                let at = t.u32(v)? as usize;
                let (num, den) = (t.u32(at), t.u32(at + 4));
                if let (Some(n), Some(d)) = (num, den) {
                    if n > 0 && d > 0 {
                        info.focal_mm = Some(n as f64 / d as f64);
                    }
                }
            }
            _ => {}
        }
    }
    Some(info)
}

/// Where a focal length came from.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FocalSource {
    /// `--focal`.
    Flag,
    /// `--fov` (vertical degrees).
    Fov(f64),
    /// EXIF `FocalLengthIn35mmFilm` (mm).
    Exif35mm(f64),
    /// The default vertical field of view (degrees).
    Default(f64),
}

impl std::fmt::Display for FocalSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            FocalSource::Flag => write!(f, "--focal"),
            FocalSource::Fov(d) => write!(f, "--fov {d}° (vertical)"),
            FocalSource::Exif35mm(mm) => write!(f, "EXIF 35 mm-equivalent focal length {mm} mm (diagonal rule)"),
            FocalSource::Default(d) => write!(f, "default vertical field of view {d}° (no --fov, --focal or EXIF)"),
        }
    }
}

/// A focal length in pixels at the photo's resolution.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Focal {
    pub px: f64,
    pub source: FocalSource,
}

impl Focal {
    /// Vertical field of view in degrees for an image `height` pixels tall.
    pub fn vfov_deg(&self, height: usize) -> f64 {
        (2.0 * (0.5 * height as f64 / self.px).atan()).to_degrees()
    }
}

/// The focal length a `width` × `height` photo at `photo` is processed with (see the module docs).
pub fn photo_focal(photo: &Path, width: usize, height: usize, focal: Option<f64>, fov: Option<f64>) -> Result<Focal> {
    if let Some(f) = focal {
        if !(f.is_finite() && f > 0.0) {
            return Err(PipelineError::input(format!(
                "--focal {f}: the focal length must be a positive number of pixels"
            )));
        }
        return Ok(Focal {
            px: f,
            source: FocalSource::Flag,
        });
    }
    let from_vfov = |deg: f64| 0.5 * height as f64 / (0.5 * deg.to_radians()).tan();
    if let Some(d) = fov {
        if !(d.is_finite() && d > 0.0 && d < 180.0) {
            return Err(PipelineError::input(format!(
                "--fov {d}: the vertical field of view must be in (0, 180) degrees"
            )));
        }
        return Ok(Focal {
            px: from_vfov(d),
            source: FocalSource::Fov(d),
        });
    }
    if let Some(f35) = read_lens_info(photo).and_then(|i| i.focal_35mm) {
        let diag = (width as f64).hypot(height as f64);
        return Ok(Focal {
            px: f35 * diag / full_frame_diagonal_mm(),
            source: FocalSource::Exif35mm(f35),
        });
    }
    let d = DEFAULT_FOV_DEG;
    Ok(Focal {
        px: from_vfov(d),
        source: FocalSource::Default(d),
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A TIFF/EXIF payload with IFD0 → Exif IFD holding FocalLength (RATIONAL) and
    /// FocalLengthIn35mmFilm (SHORT), in either byte order, built byte by byte.
    pub fn exif_payload(little: bool, f35: u16, focal: (u32, u32)) -> Vec<u8> {
        let w16 = |v: u16| if little { v.to_le_bytes() } else { v.to_be_bytes() };
        let w32 = |v: u32| if little { v.to_le_bytes() } else { v.to_be_bytes() };
        let mut b = Vec::new();
        b.extend_from_slice(if little { b"II" } else { b"MM" });
        b.extend_from_slice(&w16(42));
        b.extend_from_slice(&w32(8)); // IFD0 at 8
                                      // IFD0: 1 entry (ExifIFD pointer), next IFD 0. 8 + 2 + 12 + 4 = 26.
        b.extend_from_slice(&w16(1));
        b.extend_from_slice(&w16(0x8769));
        b.extend_from_slice(&w16(4));
        b.extend_from_slice(&w32(1));
        b.extend_from_slice(&w32(26));
        b.extend_from_slice(&w32(0));
        // Exif IFD at 26: 2 entries; 26 + 2 + 24 + 4 = 56 → the rational's value.
        b.extend_from_slice(&w16(2));
        b.extend_from_slice(&w16(0x920A));
        b.extend_from_slice(&w16(5));
        b.extend_from_slice(&w32(1));
        b.extend_from_slice(&w32(56));
        b.extend_from_slice(&w16(0xA405));
        b.extend_from_slice(&w16(3));
        b.extend_from_slice(&w32(1));
        b.extend_from_slice(&w16(f35));
        b.extend_from_slice(&[0, 0]);
        b.extend_from_slice(&w32(0));
        assert_eq!(b.len(), 56);
        b.extend_from_slice(&w32(focal.0));
        b.extend_from_slice(&w32(focal.1));
        b
    }

    /// A JPEG head: SOI, an APP0 (JFIF) segment, the APP1 Exif segment, then SOS.
    pub fn jpeg_head(payload: &[u8]) -> Vec<u8> {
        let mut j = vec![0xFF, 0xD8];
        j.extend_from_slice(&[0xFF, 0xE0, 0x00, 0x10]);
        j.extend_from_slice(b"JFIF\0\x01\x01\0\0\x01\0\x01\0\0");
        let len = (2 + 6 + payload.len()) as u16;
        j.extend_from_slice(&[0xFF, 0xE1]);
        j.extend_from_slice(&len.to_be_bytes());
        j.extend_from_slice(b"Exif\0\0");
        j.extend_from_slice(payload);
        j.extend_from_slice(&[0xFF, 0xDA, 0x00, 0x02]);
        j
    }

    #[test]
    fn reads_focal_lengths_in_both_byte_orders() {
        for little in [true, false] {
            let j = jpeg_head(&exif_payload(little, 26, (425, 100)));
            let info = parse_tiff(jpeg_exif_block(&j).unwrap()).unwrap();
            assert_eq!(info.focal_35mm, Some(26.0), "little={little}");
            assert_eq!(info.focal_mm, Some(4.25), "little={little}");
        }
        // 0 = unknown.
        let j = jpeg_head(&exif_payload(true, 0, (0, 1)));
        assert_eq!(parse_tiff(jpeg_exif_block(&j).unwrap()).unwrap(), LensInfo::default());
    }

    #[test]
    fn malformed_blocks_give_none_without_panicking() {
        let good = jpeg_head(&exif_payload(true, 26, (425, 100)));
        // Every truncation of the stream and of the payload.
        for n in 0..good.len() {
            let _ = jpeg_exif_block(&good[..n]).and_then(parse_tiff);
        }
        let p = exif_payload(false, 26, (425, 100));
        for n in 0..p.len() {
            let _ = parse_tiff(&p[..n]);
        }
        // Offsets pointing far outside.
        let mut bad = exif_payload(true, 26, (425, 100));
        bad[4..8].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(parse_tiff(&bad), None);
        assert_eq!(jpeg_exif_block(b"\x89PNG\r\n\x1a\n"), None);
        // A segment length of 0 or 1.
        assert_eq!(jpeg_exif_block(&[0xFF, 0xD8, 0xFF, 0xE1, 0x00, 0x01]), None);
    }

    #[test]
    fn focal_precedence_and_the_diagonal_rule() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("p.jpg");
        std::fs::write(&p, jpeg_head(&exif_payload(true, 36, (50, 1)))).unwrap();
        let (w, h) = (300usize, 200usize);
        // 3:2 photo, f35 = 36 mm: the diagonal rule equals the long-side rule, f = W.
        let f = photo_focal(&p, w, h, None, None).unwrap();
        assert_eq!(f.source, FocalSource::Exif35mm(36.0));
        assert!((f.px - 300.0).abs() < 1e-9, "{}", f.px);
        // 4:3 photo: f = 36 · 500 / 43.2666 = 415.99.
        let f = photo_focal(&p, 400, 300, None, None).unwrap();
        assert!((f.px - 36.0 * 500.0 / (36f64 * 36.0 + 24.0 * 24.0).sqrt()).abs() < 1e-9);
        // --fov wins over EXIF: 90° vertical → f = H/2.
        let f = photo_focal(&p, w, h, None, Some(90.0)).unwrap();
        assert!((f.px - 100.0).abs() < 1e-9 && f.source == FocalSource::Fov(90.0));
        assert!((f.vfov_deg(h) - 90.0).abs() < 1e-9);
        // --focal wins over everything.
        assert_eq!(photo_focal(&p, w, h, Some(123.0), Some(90.0)).unwrap().px, 123.0);
        // No EXIF: the default 50° vertical.
        let q = dir.path().join("q.png");
        std::fs::write(&q, b"not read as a JPEG").unwrap();
        let f = photo_focal(&q, w, h, None, None).unwrap();
        assert!((f.px - 100.0 / 25f64.to_radians().tan()).abs() < 1e-9);
        assert!(photo_focal(&q, w, h, Some(-1.0), None).is_err());
        assert!(photo_focal(&q, w, h, None, Some(180.0)).is_err());
    }
}
