//! Inputs written by hand for the tests, and checks on what a folder holds after a run.
use pixl_core::exrio::{write_exr_channels, ExrChannels};
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;
use std::path::{Path, PathBuf};

/// A fresh temporary folder (removed when dropped).
pub fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().expect("tempdir")
}

/// A path as the `&str` of an argument.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// A path in this repository (fixtures, assets), from its root.
pub fn repo_path(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..").join(rel)
}

/// Writes `bytes` at `path`, making its folder; returns the path.
pub fn write_file(path: &Path, bytes: impl AsRef<[u8]>) -> PathBuf {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).unwrap();
    }
    std::fs::write(path, bytes).unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
    path.to_owned()
}

/// Writes `img` at `path` in the format its extension names (PNG 16-bit, JPEG, EXR); returns
/// the path.
pub fn write_image(path: &Path, img: &Image) -> PathBuf {
    pixl_core::io::write_image(path, img).unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
    path.to_owned()
}

/// Writes `img` as an 8-bit PNG; returns the path.
pub fn write_png8(path: &Path, img: &Image) -> PathBuf {
    pixl_core::io::write_png(path, img, pixl_core::io::PngDepth::Eight)
        .unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
    path.to_owned()
}

/// Writes a one-channel depth map `w × h`, `depth(x, y)` metres, as EXR; returns the path.
pub fn write_depth(path: &Path, w: usize, h: usize, depth: impl Fn(usize, usize) -> f32) -> PathBuf {
    write_image(path, &Image::from_fn(w, h, 1, |x, y, _| depth(x, y)))
}

/// Writes an `h × w` little-endian f32 NumPy array (`.npy` version 1.0), row-major.
pub fn write_npy_f32(path: &Path, h: usize, w: usize, vals: &[f32]) -> PathBuf {
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({h}, {w}), }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend_from_slice(&(header.len() as u16).to_le_bytes());
    b.extend_from_slice(header.as_bytes());
    b.extend(vals.iter().flat_map(|v| v.to_le_bytes()));
    write_file(path, b)
}

/// Writes the C_T file of albedo, shading and residual (`pixl_intrinsics::ct::write_ct`);
/// returns the path.
pub fn write_ct(path: &Path, albedo: Image, shading: Image, residual: Image) -> PathBuf {
    let ct = Ct::new(albedo, shading, residual).expect("a valid C_T");
    pixl_intrinsics::ct::write_ct(path, &ct).unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
    path.to_owned()
}

/// Writes a C_T file channel by channel (`albedo|shading|residual` × `R|G|B`, in that order), the
/// values `values(group, channel)`, unchecked (non-finite values included); returns the path.
pub fn write_ct_channels(path: &Path, w: usize, h: usize, values: impl Fn(&str, &str) -> Vec<f32>) -> PathBuf {
    let mut ch = ExrChannels::new(w, h);
    for group in ["albedo", "shading", "residual"] {
        for c in ["R", "G", "B"] {
            ch.push(format!("{group}.{c}"), values(group, c)).expect("push");
        }
    }
    write_exr_channels(path, &ch).unwrap_or_else(|e| panic!("write {}: {e}", path.display()));
    path.to_owned()
}

/// Copies the first `1/divisor` of the bytes of `src` to `dst` (a truncated file); returns `dst`.
pub fn truncated_copy(src: &Path, dst: &Path, divisor: usize) -> PathBuf {
    let bytes = std::fs::read(src).unwrap();
    write_file(dst, &bytes[..bytes.len() / divisor])
}

/// CRC-32 (IEEE), to craft PNG chunks by hand.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// A PNG that is only a signature and an IHDR announcing `w × h` RGB8 (no pixel data).
pub fn png_header_only(w: u32, h: u32) -> Vec<u8> {
    let mut v = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = b"IHDR".to_vec();
    chunk.extend_from_slice(&w.to_be_bytes());
    chunk.extend_from_slice(&h.to_be_bytes());
    chunk.extend_from_slice(&[8, 2, 0, 0, 0]);
    v.extend_from_slice(&13u32.to_be_bytes());
    v.extend_from_slice(&chunk);
    v.extend_from_slice(&crc32(&chunk).to_be_bytes());
    v
}

/// A scene's TOML: a `w × h` camera 3 m back with a 40° field of view looking at a unit sphere,
/// then `rest` (the object's material, lights, …).
pub fn sphere_scene(w: u32, h: u32, rest: &str) -> String {
    format!(
        "[camera]\nwidth = {w}\nheight = {h}\nfov_y_deg = 40.0\nposition = [0.0, 0.0, 3.0]\n\n\
         [[objects]]\nshape = {{ type = \"sphere\", radius = 1.0 }}\n{rest}"
    )
}

/// Copies a folder recursively.
pub fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), &to).unwrap();
        }
    }
}

/// Every file under `dir` (relative paths, sorted), folders included; nothing for a missing
/// folder.
pub fn tree(dir: &Path) -> Vec<String> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<String>) {
        if let Ok(rd) = std::fs::read_dir(d) {
            for e in rd.flatten() {
                let p = e.path();
                out.push(p.strip_prefix(root).unwrap_or(&p).display().to_string());
                if p.is_dir() {
                    walk(root, &p, out);
                }
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

/// Asserts that no temporary file of an atomic write (`.tmp-`, `.pixl-probe-`) is left under
/// `dir`.
#[track_caller]
pub fn assert_no_temp_files(dir: &Path) {
    for f in tree(dir) {
        assert!(!f.contains(".tmp-") && !f.contains(".pixl-probe-"), "left behind: {f}");
    }
}

/// Asserts that `dir` holds nothing but the files named `keep` (`context` is for the message).
#[track_caller]
pub fn assert_only(dir: &Path, keep: &[&str], context: &str) {
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let n = e.file_name().to_string_lossy().into_owned();
        assert!(keep.contains(&n.as_str()), "left behind: {n} ({context})");
    }
}
