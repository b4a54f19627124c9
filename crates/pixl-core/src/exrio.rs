//! Named-channel OpenEXR I/O: the layer under C_T files (`albedo.R`, …) and Cycles render-pass
//! files (`ViewLayer.Diffuse Direct.R`, …).
//!
//! Reading accepts single-part and multi-part files (Blender 5 writes one part per pass), with
//! f16, f32 or u32 samples, and returns every channel as `f32` under its *full* name: in a
//! multi-part file the part's layer name is prefixed (`<part>.<channel>`) unless the channel
//! name already carries it. All parts must share one size. The header is checked against
//! [`crate::io::MAX_PIXELS`] before any pixel is allocated.
//!
//! Writing produces one single-part file with f32 samples, ZIP-compressed, atomically, and only
//! to a path ending in `.exr`.
use crate::error::{CoreError, Result};
use crate::io::{atomic_write, check_size};
use std::path::Path;

/// Channels of one EXR image, all of one size, row-major (`y * width + x`).
#[derive(Clone, Debug, Default)]
pub struct ExrChannels {
    pub width: usize,
    pub height: usize,
    pub channels: Vec<(String, Vec<f32>)>,
}

impl ExrChannels {
    pub fn new(width: usize, height: usize) -> Self {
        Self {
            width,
            height,
            channels: Vec::new(),
        }
    }

    pub fn get(&self, name: &str) -> Option<&[f32]> {
        self.channels.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }

    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.channels.iter().map(|(n, _)| n.as_str())
    }

    /// Channel `ch` of render pass `pass`, named `<pass>.<ch>` or `<…>.<pass>.<ch>` (a view-layer
    /// prefix), under the pass's long (Blender 4/5) or short (older) name, long first.
    pub fn pass_channel(&self, pass: &crate::passes::Pass, ch: &str) -> Option<&[f32]> {
        [pass.long, pass.short].iter().find_map(|name| {
            let suffix = format!("{name}.{ch}");
            let dotted = format!(".{suffix}");
            self.channels
                .iter()
                .find(|(n, _)| *n == suffix || n.ends_with(&dotted))
                .map(|(_, d)| d.as_slice())
        })
    }

    /// Adds a channel; its length must be `width * height`.
    pub fn push(&mut self, name: impl Into<String>, data: Vec<f32>) -> Result<()> {
        let name = name.into();
        if data.len() != self.width * self.height {
            return Err(CoreError::Invalid(format!(
                "channel {name} has {} samples, expected {}x{}",
                data.len(),
                self.width,
                self.height
            )));
        }
        self.channels.push((name, data));
        Ok(())
    }
}

/// Reads every channel of every part of an EXR file. The file is streamed, not read into memory
/// first, and the decoded channels are moved into the result, not copied: the peak is about the
/// decoded samples once.
pub fn read_exr_channels(path: &Path) -> Result<ExrChannels> {
    if !path.exists() {
        return Err(CoreError::NotFound { path: path.to_owned() });
    }
    let open = || {
        std::fs::File::open(path)
            .map(std::io::BufReader::new)
            .map_err(|e| CoreError::io(path, e))
    };
    read_exr_channels_with(open, path)
}

/// Reads every channel of every part of an in-memory EXR file; `path` only names it in errors.
pub fn read_exr_channels_from_bytes(bytes: &[u8], path: &Path) -> Result<ExrChannels> {
    read_exr_channels_with(|| Ok(std::io::Cursor::new(bytes)), path)
}

/// The reader behind both: `open` gives a fresh reader at the start of the file (once for the
/// header check, once for the pixels).
fn read_exr_channels_with<R: std::io::Read + std::io::Seek>(
    open: impl Fn() -> Result<R>,
    path: &Path,
) -> Result<ExrChannels> {
    use exr::prelude::*;
    let decode = |e: exr::error::Error| CoreError::Decode {
        path: path.to_owned(),
        format: "OpenEXR",
        reason: e.to_string(),
    };
    let bad = |reason: String| CoreError::Decode {
        path: path.to_owned(),
        format: "OpenEXR",
        reason,
    };
    let meta = exr::meta::MetaData::read_from_buffered(open()?, false).map_err(decode)?;
    let Some(first) = meta.headers.first() else {
        return Err(bad("no image parts".into()));
    };
    let (w, h) = (first.layer_size.width(), first.layer_size.height());
    check_size(path, w, h)?;
    let mut total_samples = 0usize;
    for hd in meta.headers.iter() {
        if hd.layer_size.width() != w || hd.layer_size.height() != h {
            return Err(bad(format!(
                "parts differ in size ({}x{} vs {w}x{h}); all passes must share one size",
                hd.layer_size.width(),
                hd.layer_size.height()
            )));
        }
        if hd.deep {
            return Err(bad("deep data is not supported".into()));
        }
        total_samples = total_samples.saturating_add(hd.channels.list.len().saturating_mul(w * h));
    }
    // Refuse before decoding: the header alone decides how much memory the pixels take.
    if total_samples > crate::io::MAX_PIXELS.saturating_mul(16) {
        return Err(bad(format!("{total_samples} samples announced, over the limit")));
    }
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_buffered(open()?)
        .map_err(decode)?;
    let mut out = ExrChannels::new(w, h);
    for layer in image.layer_data {
        let prefix = layer.attributes.layer_name.as_ref().map(|t| t.to_string());
        for ch in layer.channel_data.list {
            let ch_name = ch.name.to_string();
            let name = match &prefix {
                Some(p) if !p.is_empty() && !ch_name.starts_with(&format!("{p}.")) => format!("{p}.{ch_name}"),
                _ => ch_name,
            };
            let data: Vec<f32> = match ch.sample_data {
                FlatSamples::F32(v) => v,
                other => other.values_as_f32().collect(),
            };
            if data.len() != w * h {
                return Err(bad(format!(
                    "channel {name} has {} samples, expected {w}x{h} (subsampled channels are not supported)",
                    data.len()
                )));
            }
            out.channels.push((name, data));
        }
    }
    Ok(out)
}

/// `img` as the `exr` crate's single-layer image: f32 channels, ZIP in blocks of 16 lines.
fn exr_image(
    img: &ExrChannels,
) -> exr::image::Image<exr::image::Layer<exr::image::AnyChannels<exr::image::FlatSamples>>> {
    use exr::prelude::*;
    let list: Vec<AnyChannel<FlatSamples>> = img
        .channels
        .iter()
        .map(|(n, d)| AnyChannel::new(n.as_str(), FlatSamples::F32(d.clone())))
        .collect();
    let layer = Layer::new(
        (img.width, img.height),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(list.into()),
    );
    exr::image::Image::from_layer(layer)
}

/// Writes all channels into one single-part f32 EXR, atomically. The path must end in `.exr`.
pub fn write_exr_channels(path: &Path, img: &ExrChannels) -> Result<()> {
    use exr::prelude::*;
    if crate::io::extension(path) != "exr" {
        return Err(CoreError::OutputExtension {
            path: path.to_owned(),
            expected: ".exr".into(),
        });
    }
    if img.width == 0 || img.height == 0 {
        return Err(CoreError::Empty {
            path: path.to_owned(),
            width: img.width,
            height: img.height,
        });
    }
    if img.channels.is_empty() {
        return Err(CoreError::Invalid(format!("{}: no channels to write", path.display())));
    }
    let image = exr_image(img);
    atomic_write(path, |file| {
        let mut w = std::io::BufWriter::new(file);
        // Blocks are compressed on several threads (exr's own pool) and written in increasing
        // line order, so the file is the same byte for byte as a one-thread write.
        image.write().to_buffered(&mut w).map_err(|e| CoreError::Encode {
            path: path.to_owned(),
            format: "OpenEXR",
            reason: e.to_string(),
        })?;
        use std::io::Write;
        w.flush().map_err(|e| CoreError::io(path, e))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pass channel is found under its long or short name, with or without a view-layer
    /// prefix; a name that merely ends in the same letters does not match.
    #[test]
    fn pass_channel_by_long_or_short_name() {
        let mut ex = ExrChannels::new(1, 1);
        ex.push("ViewLayer.Diffuse Direct.R", vec![1.0]).unwrap();
        ex.push("DiffCol.G", vec![2.0]).unwrap();
        ex.push("ViewLayer.XEmission.B", vec![3.0]).unwrap();
        assert_eq!(ex.pass_channel(&crate::passes::DIFF_DIR, "R"), Some(&[1.0][..]));
        assert_eq!(ex.pass_channel(&crate::passes::DIFF_COL, "G"), Some(&[2.0][..]));
        assert_eq!(ex.pass_channel(&crate::passes::EMIT, "B"), None);
        assert_eq!(ex.pass_channel(&crate::passes::DIFF_DIR, "G"), None);
    }

    /// The threaded writer gives the file a one-thread write gives, byte for byte, and it reads
    /// back exactly (an image of many ZIP blocks with incompressible noise and a flat channel).
    #[test]
    fn threaded_write_is_the_one_thread_file_and_reads_back() {
        use exr::prelude::*;
        let (w, h) = (80, 131);
        let mut img = ExrChannels::new(w, h);
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut noise = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 24) as f32 * 100.0 - 50.0
        };
        for name in ["ViewLayer.DiffDir.R", "ViewLayer.DiffDir.G", "ViewLayer.DiffDir.B"] {
            img.channels.push((name.into(), (0..w * h).map(|_| noise()).collect()));
        }
        img.channels.push(("ViewLayer.Alpha.A".into(), vec![1.0; w * h]));
        let dir = tempfile::tempdir().unwrap();
        let ours = dir.path().join("ours.exr");
        write_exr_channels(&ours, &img).unwrap();
        // The same image through exr's one-thread writer.
        let mut one = Vec::new();
        exr_image(&img)
            .write()
            .non_parallel()
            .to_buffered(std::io::Cursor::new(&mut one))
            .unwrap();
        let bytes = std::fs::read(&ours).unwrap();
        assert!(
            bytes == one,
            "threaded write differs ({} vs {} bytes)",
            bytes.len(),
            one.len()
        );
        let back = read_exr_channels(&ours).unwrap();
        assert_eq!((back.width, back.height), (w, h));
        for (name, data) in &img.channels {
            let got = back.channels.iter().find(|(n, _)| n == name).map(|(_, d)| d);
            let got = got.unwrap_or_else(|| panic!("{name} missing"));
            assert!(got.iter().zip(data).all(|(a, b)| a.to_bits() == b.to_bits()), "{name}");
        }
    }
}
