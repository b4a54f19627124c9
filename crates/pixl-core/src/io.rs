//! Image files in and out: PNG (8/16-bit), JPEG, OpenEXR.
//!
//! - PNG/JPEG load as stored (sRGB-encoded) values in [0, 1]; 16-bit PNG keeps all 16 bits
//!   (`v / 65535`, exact in f32), so a 16-bit PNG written back with [`write_image`] is identical.
//! - EXR loads `R,G,B[,A]` (or `Y`) as stored, linear.
//! - Before decoding, the header's size is checked: empty images and anything over
//!   [`MAX_PIXELS`] are refused without allocating.
//! - Every write is atomic ([`atomic_write`]): a temporary file beside the target, fsync, rename.
//!   A failure, or an interrupting signal (see [`crate::output`]), leaves no partial file behind.
//! - The extension decides the format: [`write_image`] dispatches on it, and [`write_png`] (and
//!   [`crate::exrio::write_exr_channels`]) refuse a path whose extension is not theirs, so no
//!   file ever holds bytes of another format than its name says.
//! - [`encode_png`] gives the bytes of a PNG file in memory (HTML reports, HTTP responses), the
//!   same samples as [`write_png`], optionally with fast compression ([`PngCompression`]).
use crate::error::{CoreError, Result};
use crate::exrio::{read_exr_channels, write_exr_channels, ExrChannels};
use crate::image::Image;
use std::fs::File;
use std::path::Path;

/// Largest image accepted, in pixels (8192 × 8192).
pub const MAX_PIXELS: usize = 8192 * 8192;

/// Refuses empty and oversized images, naming the file.
pub fn check_size(path: &Path, width: usize, height: usize) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(CoreError::Empty {
            path: path.to_owned(),
            width,
            height,
        });
    }
    if width.saturating_mul(height) > MAX_PIXELS {
        return Err(CoreError::TooLarge {
            path: path.to_owned(),
            width,
            height,
            limit: MAX_PIXELS,
        });
    }
    Ok(())
}

/// The lower-cased extension of a path ("" if none).
pub fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase()
}

/// Writes `path` atomically: `write` fills a temporary file in the same directory, which is
/// then fsynced and renamed over `path`. On any error the temporary file is removed; while it
/// exists it is registered with [`crate::output`], so an interrupting signal removes it too (and
/// a file being replaced keeps its old content).
pub fn atomic_write(path: &Path, write: impl FnOnce(&mut File) -> Result<()>) -> Result<()> {
    let dir = crate::output::parent_dir(path);
    if !dir.is_dir() {
        return Err(CoreError::Output {
            path: path.to_owned(),
            reason: if dir.exists() {
                format!("{} is not a folder", dir.display())
            } else {
                format!("the output folder {} does not exist", dir.display())
            },
        });
    }
    if path.is_dir() {
        return Err(CoreError::Output {
            path: path.to_owned(),
            reason: "is a folder; give a file name".into(),
        });
    }
    static COUNTER: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = COUNTER.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("out");
    let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
    let live = crate::output::register(&tmp, false);
    let result = (|| {
        let mut file = File::create(&tmp).map_err(|e| CoreError::io(path, e))?;
        if let Some(pause) = crate::output::test_write_delay() {
            std::thread::sleep(pause);
        }
        write(&mut file)?;
        file.sync_all().map_err(|e| CoreError::io(path, e))?;
        drop(file);
        Ok(())
    })();
    let result = result
        .and_then(|()| crate::output::commit(live, || std::fs::rename(&tmp, path)).map_err(|e| CoreError::io(path, e)));
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes bytes atomically.
pub fn atomic_write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    atomic_write(path, |f| {
        use std::io::Write;
        f.write_all(bytes).map_err(|e| CoreError::io(path, e))
    })
}

/// Reads a PNG, JPEG or EXR image with its own channel count (1–4); a PNG or JPEG upright, its
/// EXIF orientation applied.
pub fn read_image(path: &Path) -> Result<Image> {
    if !path.exists() {
        return Err(CoreError::NotFound { path: path.to_owned() });
    }
    match extension(path).as_str() {
        "png" | "jpg" | "jpeg" => read_ldr(path),
        "exr" => read_exr_image(path),
        _ => Err(CoreError::UnknownExtension {
            path: path.to_owned(),
            expected: "png, jpg, jpeg, exr",
        }),
    }
}

/// Reads an image as 3-channel RGB: grey is replicated, alpha dropped.
pub fn read_rgb(path: &Path) -> Result<Image> {
    let img = read_image(path)?;
    match img.channels {
        3 => Ok(img),
        4 => Ok(img.select_channels(0..3)),
        1 | 2 => {
            let mut out = Image::new(img.width, img.height, 3);
            for (o, px) in out.data.chunks_exact_mut(3).zip(img.data.chunks_exact(img.channels)) {
                o.fill(px[0]);
            }
            Ok(out)
        }
        n => Err(CoreError::Channels {
            path: path.to_owned(),
            expected: "1 to 4".into(),
            found: n.to_string(),
        }),
    }
}

/// Reads RGB and checks every value is finite.
pub fn read_rgb_finite(path: &Path) -> Result<Image> {
    let img = read_rgb(path)?;
    ensure_finite(path, &img)?;
    Ok(img)
}

/// Errors with the count and first location of non-finite values.
pub fn ensure_finite(path: &Path, img: &Image) -> Result<()> {
    if let Some((count, x, y, c)) = img.find_non_finite() {
        let channel = ["R", "G", "B", "A"]
            .get(c)
            .map(|s| s.to_string())
            .unwrap_or(c.to_string());
        return Err(CoreError::NonFinite {
            path: path.to_owned(),
            count,
            x,
            y,
            channel,
        });
    }
    Ok(())
}

fn read_ldr(path: &Path) -> Result<Image> {
    let fmt = if extension(path) == "png" { "PNG" } else { "JPEG" };
    let decode = |e: image::ImageError| CoreError::Decode {
        path: path.to_owned(),
        format: fmt,
        reason: e.to_string(),
    };
    let open = || -> Result<image::ImageReader<std::io::BufReader<File>>> {
        image::ImageReader::open(path)
            .map_err(|e| CoreError::io(path, e))?
            .with_guessed_format()
            .map_err(|e| CoreError::io(path, e))
    };
    // PNG: the IHDR chunk (bytes 16..24) holds the size; check it before the decoder reads on.
    let mut head = [0u8; 24];
    let got = {
        use std::io::Read;
        let mut f = File::open(path).map_err(|e| CoreError::io(path, e))?;
        f.read(&mut head).map_err(|e| CoreError::io(path, e))?
    };
    if got == 24 && head.starts_with(b"\x89PNG\r\n\x1a\n") && &head[12..16] == b"IHDR" {
        let w = u32::from_be_bytes([head[16], head[17], head[18], head[19]]);
        let h = u32::from_be_bytes([head[20], head[21], head[22], head[23]]);
        check_size(path, w as usize, h as usize)?;
    }
    let (w, h) = open()?.into_dimensions().map_err(decode)?;
    check_size(path, w as usize, h as usize)?;
    let mut reader = open()?;
    let mut limits = image::Limits::default();
    limits.max_alloc = Some((MAX_PIXELS as u64) * 16);
    reader.limits(limits);
    // Upright as a viewer shows it: the EXIF orientation (phone photos are often stored
    // sideways with a rotate tag) is applied.
    let mut decoder = reader.into_decoder().map_err(decode)?;
    let orientation = {
        use image::ImageDecoder;
        decoder
            .orientation()
            .unwrap_or(image::metadata::Orientation::NoTransforms)
    };
    let mut dyn_img = image::DynamicImage::from_decoder(decoder).map_err(decode)?;
    dyn_img.apply_orientation(orientation);
    let (w, h) = (dyn_img.width() as usize, dyn_img.height() as usize);
    use image::DynamicImage as D;
    let img = match dyn_img {
        D::ImageLuma8(_) | D::ImageLuma16(_) => {
            let g = dyn_img.into_luma16();
            Image::from_vec(w, h, 1, g.into_raw().into_iter().map(|v| v as f32 / 65535.0).collect())?
        }
        D::ImageLumaA8(_) | D::ImageLumaA16(_) => {
            let g = dyn_img.into_luma_alpha16();
            Image::from_vec(w, h, 2, g.into_raw().into_iter().map(|v| v as f32 / 65535.0).collect())?
        }
        D::ImageRgba8(_) | D::ImageRgba16(_) | D::ImageRgba32F(_) => {
            let g = dyn_img.into_rgba16();
            Image::from_vec(w, h, 4, g.into_raw().into_iter().map(|v| v as f32 / 65535.0).collect())?
        }
        _ => {
            let g = dyn_img.into_rgb16();
            Image::from_vec(w, h, 3, g.into_raw().into_iter().map(|v| v as f32 / 65535.0).collect())?
        }
    };
    Ok(img)
}

fn read_exr_image(path: &Path) -> Result<Image> {
    let chans = read_exr_channels(path)?;
    let pick = |suffix: &str| -> Option<&[f32]> {
        chans.get(suffix).or_else(|| {
            let mut it = chans
                .channels
                .iter()
                .filter(|(n, _)| n.ends_with(&format!(".{suffix}")));
            match (it.next(), it.next()) {
                (Some((_, d)), None) => Some(d.as_slice()),
                _ => None,
            }
        })
    };
    let names: Vec<&str> = match (pick("R"), pick("G"), pick("B"), pick("Y")) {
        (Some(_), Some(_), Some(_), _) if pick("A").is_some() => vec!["R", "G", "B", "A"],
        (Some(_), Some(_), Some(_), _) => vec!["R", "G", "B"],
        (_, _, _, Some(_)) => vec!["Y"],
        _ => {
            let found: Vec<&str> = chans.names().collect();
            return Err(CoreError::Channels {
                path: path.to_owned(),
                expected: "R,G,B[,A] or Y".into(),
                found: found.join(","),
            });
        }
    };
    let planes: Vec<&[f32]> = names.iter().filter_map(|n| pick(n)).collect();
    let (w, h, ch) = (chans.width, chans.height, planes.len());
    let mut img = Image::new(w, h, ch);
    for (c, plane) in planes.iter().enumerate() {
        for (p, v) in plane.iter().enumerate() {
            img.data[p * ch + c] = *v;
        }
    }
    Ok(img)
}

/// Writes an image by extension: `.png` as 16-bit (values clamped to [0, 1]), `.jpg` as 8-bit
/// quality 95, `.exr` as f32 (values as they are). 1–4 channels.
pub fn write_image(path: &Path, img: &Image) -> Result<()> {
    match extension(path).as_str() {
        "png" => write_png(path, img, PngDepth::Sixteen),
        "jpg" | "jpeg" => write_jpeg(path, img),
        "exr" => write_exr_image(path, img),
        _ => Err(CoreError::UnknownExtension {
            path: path.to_owned(),
            expected: "png, jpg, jpeg, exr",
        }),
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PngDepth {
    Eight,
    Sixteen,
}

fn check_writable(path: &Path, img: &Image) -> Result<()> {
    if img.width == 0 || img.height == 0 {
        return Err(CoreError::Empty {
            path: path.to_owned(),
            width: img.width,
            height: img.height,
        });
    }
    if !(1..=4).contains(&img.channels) {
        return Err(CoreError::Channels {
            path: path.to_owned(),
            expected: "1 to 4".into(),
            found: img.channels.to_string(),
        });
    }
    Ok(())
}

/// How hard the PNG encoder works on the file's size.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PngCompression {
    /// The `image` crate's default level and adaptive filtering, as [`write_png`] writes.
    #[default]
    Default,
    /// Fast compression and the `Sub` filter: larger files, encoded several times faster (for
    /// interactive previews).
    Fast,
}

/// The encoder's samples and colour type for `img` at `depth` (1 to 4 channels: gray, gray +
/// alpha, RGB, RGBA): values clamped to [0, 1] and rounded to nearest, NaN as 0.
fn png_samples(img: &Image, depth: PngDepth) -> (Vec<u8>, image::ExtendedColorType) {
    let color = match (img.channels, depth) {
        (1, PngDepth::Eight) => image::ExtendedColorType::L8,
        (2, PngDepth::Eight) => image::ExtendedColorType::La8,
        (3, PngDepth::Eight) => image::ExtendedColorType::Rgb8,
        (4, PngDepth::Eight) => image::ExtendedColorType::Rgba8,
        (1, PngDepth::Sixteen) => image::ExtendedColorType::L16,
        (2, PngDepth::Sixteen) => image::ExtendedColorType::La16,
        (3, PngDepth::Sixteen) => image::ExtendedColorType::Rgb16,
        _ => image::ExtendedColorType::Rgba16,
    };
    let bytes: Vec<u8> = match depth {
        PngDepth::Eight => img
            .data
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect(),
        // PNG stores 16-bit samples big-endian; the encoder takes native-endian bytes.
        PngDepth::Sixteen => img
            .data
            .iter()
            .flat_map(|v| (((if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) }) * 65535.0).round() as u16).to_ne_bytes())
            .collect(),
    };
    (bytes, color)
}

/// Encodes `img` as a PNG into `out` (the size and channel count already checked).
fn encode_png_to(
    out: impl std::io::Write,
    img: &Image,
    depth: PngDepth,
    compression: PngCompression,
) -> std::result::Result<(), image::ImageError> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let (bytes, color) = png_samples(img, depth);
    let (w, h) = (img.width as u32, img.height as u32);
    match compression {
        PngCompression::Default => PngEncoder::new(out).write_image(&bytes, w, h, color),
        PngCompression::Fast => {
            PngEncoder::new_with_quality(out, CompressionType::Fast, FilterType::Sub).write_image(&bytes, w, h, color)
        }
    }
}

/// Writes a PNG (values clamped to [0, 1], rounded to nearest). The path must end in `.png`.
pub fn write_png(path: &Path, img: &Image, depth: PngDepth) -> Result<()> {
    if extension(path) != "png" {
        return Err(CoreError::OutputExtension {
            path: path.to_owned(),
            expected: ".png".into(),
        });
    }
    check_writable(path, img)?;
    atomic_write(path, |file| {
        let out = std::io::BufWriter::new(file);
        encode_png_to(out, img, depth, PngCompression::Default).map_err(|e| CoreError::Encode {
            path: path.to_owned(),
            format: "PNG",
            reason: e.to_string(),
        })
    })
}

/// The bytes of the PNG file [`write_png`] would write (with [`PngCompression::Default`]), in
/// memory: for embedding in a page or sending over HTTP. 1 to 4 channels (gray, gray + alpha,
/// RGB, RGBA), values clamped to [0, 1] and rounded to nearest, NaN as 0. Errors on an empty
/// image or another channel count.
pub fn encode_png(img: &Image, depth: PngDepth, compression: PngCompression) -> Result<Vec<u8>> {
    if img.width == 0 || img.height == 0 || !(1..=4).contains(&img.channels) {
        return Err(CoreError::Invalid(format!(
            "cannot encode a {}x{} image of {} channels as PNG (1 to 4 channels, not empty)",
            img.width, img.height, img.channels
        )));
    }
    let mut out = Vec::new();
    encode_png_to(&mut out, img, depth, compression)
        .map_err(|e| CoreError::Invalid(format!("encoding a PNG in memory: {e}")))?;
    Ok(out)
}

fn write_jpeg(path: &Path, img: &Image) -> Result<()> {
    check_writable(path, img)?;
    let rgb = match img.channels {
        3 => img.clone(),
        4 => img.select_channels(0..3),
        _ => img.select_channels(0..1),
    };
    let color = if rgb.channels == 3 {
        image::ExtendedColorType::Rgb8
    } else {
        image::ExtendedColorType::L8
    };
    let bytes: Vec<u8> = rgb
        .data
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    atomic_write(path, |file| {
        use image::ImageEncoder;
        let enc = image::codecs::jpeg::JpegEncoder::new_with_quality(std::io::BufWriter::new(file), 95);
        enc.write_image(&bytes, rgb.width as u32, rgb.height as u32, color)
            .map_err(|e| CoreError::Encode {
                path: path.to_owned(),
                format: "JPEG",
                reason: e.to_string(),
            })
    })
}

fn write_exr_image(path: &Path, img: &Image) -> Result<()> {
    check_writable(path, img)?;
    let names: &[&str] = match img.channels {
        1 => &["Y"],
        2 => &["Y", "A"],
        3 => &["R", "G", "B"],
        _ => &["R", "G", "B", "A"],
    };
    let mut chans = ExrChannels::new(img.width, img.height);
    for (c, n) in names.iter().enumerate() {
        chans.push(*n, img.data.iter().skip(c).step_by(img.channels).copied().collect())?;
    }
    write_exr_channels(path, &chans)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A JPEG stored sideways with EXIF orientation 6 ("rotate 90° clockwise to view"): an 8×4
    /// image, left half red, right half blue, reads as 4×8 with the red half on top (the left
    /// column becomes the top row). Without the tag it reads as stored.
    #[test]
    fn jpeg_exif_orientation_is_applied() {
        let stored = image::RgbImage::from_fn(8, 4, |x, _| {
            if x < 4 {
                image::Rgb([255, 0, 0])
            } else {
                image::Rgb([0, 0, 255])
            }
        });
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 100)
            .encode_image(&stored)
            .unwrap();
        // APP1 "Exif": little-endian TIFF header, one IFD entry: 0x0112 Orientation, SHORT, 1, 6.
        let mut tiff = b"II*\0\x08\0\0\0".to_vec();
        tiff.extend_from_slice(&1u16.to_le_bytes());
        tiff.extend_from_slice(&[0x12, 0x01, 3, 0, 1, 0, 0, 0, 6, 0, 0, 0]);
        tiff.extend_from_slice(&0u32.to_le_bytes());
        let mut app1 = b"Exif\0\0".to_vec();
        app1.extend_from_slice(&tiff);
        let mut tagged = jpeg[..2].to_vec();
        tagged.extend_from_slice(&[0xFF, 0xE1]);
        tagged.extend_from_slice(&((app1.len() + 2) as u16).to_be_bytes());
        tagged.extend_from_slice(&app1);
        tagged.extend_from_slice(&jpeg[2..]);

        let dir = tempfile::tempdir().unwrap();
        let (plain, sideways) = (dir.path().join("plain.jpg"), dir.path().join("sideways.jpg"));
        std::fs::write(&plain, &jpeg).unwrap();
        std::fs::write(&sideways, &tagged).unwrap();
        let a = read_rgb(&plain).unwrap();
        assert_eq!((a.width, a.height), (8, 4));
        let b = read_rgb(&sideways).unwrap();
        assert_eq!((b.width, b.height), (4, 8));
        let red = |img: &Image, x: usize, y: usize| img.get(x, y, 0) > 0.8 && img.get(x, y, 2) < 0.2;
        assert!(red(&b, 0, 0) && red(&b, 3, 1), "top half is red");
        assert!(!red(&b, 0, 6) && !red(&b, 3, 7), "bottom half is blue");
    }

    #[test]
    fn png16_and_exr_roundtrip_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let img = Image::from_fn(7, 5, 3, |x, y, c| {
            ((x * 7919 + y * 104729 + c * 13) % 65536) as f32 / 65535.0
        });
        for name in ["a.png", "a.exr"] {
            let p = dir.path().join(name);
            write_image(&p, &img).unwrap();
            assert_eq!(read_rgb(&p).unwrap(), img, "{name}");
        }
        let hdr = img.map(|v| v * 100.0 - 3.0);
        let p = dir.path().join("hdr.exr");
        write_image(&p, &hdr).unwrap();
        assert_eq!(read_rgb(&p).unwrap(), hdr);
    }

    /// In memory: the bytes `write_png` writes, for 1 to 4 channels and both depths; fast
    /// compression decodes to the same pixels; empty images and 5 channels are refused.
    #[test]
    fn png_in_memory_is_the_file_png() {
        let dir = tempfile::tempdir().unwrap();
        for ch in 1..=4 {
            let img = Image::from_fn(9, 6, ch, |x, y, c| (x * 31 + y * 17 + c * 5) as f32 / 300.0 - 0.1);
            for depth in [PngDepth::Eight, PngDepth::Sixteen] {
                let p = dir.path().join("a.png");
                write_png(&p, &img, depth).unwrap();
                let bytes = encode_png(&img, depth, PngCompression::Default).unwrap();
                assert_eq!(bytes, std::fs::read(&p).unwrap(), "{ch} channels, {depth:?}");
                let fast = encode_png(&img, depth, PngCompression::Fast).unwrap();
                let decode = |b: &[u8]| image::load_from_memory(b).unwrap().into_rgba16().into_raw();
                assert_eq!(decode(&fast), decode(&bytes), "{ch} channels, {depth:?}");
            }
        }
        assert!(encode_png(&Image::new(0, 3, 3), PngDepth::Eight, PngCompression::Default).is_err());
        assert!(encode_png(&Image::new(2, 3, 5), PngDepth::Eight, PngCompression::Fast).is_err());
    }

    #[test]
    fn errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.png");
        std::fs::write(&p, b"\x89PNG\r\n\x1a\nnot really").unwrap();
        let e = read_rgb(&p).unwrap_err().to_string();
        assert!(e.contains("bad.png"), "{e}");
        assert!(matches!(
            read_rgb(&dir.path().join("none.png")),
            Err(CoreError::NotFound { .. })
        ));
        let e = write_image(&dir.path().join("no/such/dir/x.png"), &Image::new(2, 2, 3)).unwrap_err();
        assert!(e.to_string().contains("does not exist"), "{e}");
    }

    #[test]
    fn failed_write_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.bin");
        let r = atomic_write(&p, |_| Err(CoreError::Invalid("boom".into())));
        assert!(r.is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn the_extension_decides_the_format() {
        let dir = tempfile::tempdir().unwrap();
        let img = Image::new(4, 3, 3);
        let e = write_png(&dir.path().join("p.jpg"), &img, PngDepth::Eight).unwrap_err();
        assert!(e.to_string().contains("must end in .png"), "{e}");
        let ch = crate::exrio::ExrChannels {
            width: 4,
            height: 3,
            channels: vec![("Y".into(), vec![0.0; 12])],
        };
        let e = crate::exrio::write_exr_channels(&dir.path().join("x.png"), &ch).unwrap_err();
        assert!(e.to_string().contains("must end in .exr"), "{e}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        // A JPEG written by extension is a JPEG (SOI marker), a PNG a PNG.
        for (name, magic) in [("a.jpg", &b"\xff\xd8"[..]), ("a.png", &b"\x89PNG"[..])] {
            let p = dir.path().join(name);
            write_image(&p, &img).unwrap();
            assert!(std::fs::read(&p).unwrap().starts_with(magic), "{name}");
        }
    }

    /// The OS's message appears once in the whole chain (Display + every source).
    #[test]
    fn os_errors_are_stated_once() {
        let dir = tempfile::tempdir().unwrap();
        let e = std::fs::read(dir.path()).unwrap_err();
        let os = e.to_string();
        let err = CoreError::io(dir.path(), e);
        let mut chain = err.to_string();
        let mut src = std::error::Error::source(&err);
        while let Some(s) = src {
            chain.push_str(&format!(": {s}"));
            src = s.source();
        }
        assert_eq!(chain.matches(&os).count(), 1, "{chain}");
        // A write over a folder says so once, naming it.
        let e = write_image(dir.path(), &Image::new(2, 2, 3)).unwrap_err().to_string();
        assert!(
            e.contains("unsupported file extension") || e.contains("is a folder"),
            "{e}"
        );
        let sub = dir.path().join("d.png");
        std::fs::create_dir(&sub).unwrap();
        let e = atomic_write_bytes(&sub, b"x").unwrap_err().to_string();
        assert!(e.contains("d.png") && e.contains("is a folder"), "{e}");
    }
}
