//! Shared helpers of the Marigold tests: fixture paths and copies, reference tensors, error
//! measures, and the UNet config of candle-transformers' SD UNet that matches one of ours.
#![allow(dead_code)]
use candle_core::{DType, Device, Tensor};
use pixl_core::Image;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// `fixtures/marigold` at the repository root.
pub fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/marigold")
}

/// The reference tensors of `fixtures/marigold/<name>` (a safetensors file).
pub fn load(name: &str) -> HashMap<String, Tensor> {
    let p = fixtures().join(name);
    candle_core::safetensors::load(&p, &Device::Cpu).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

pub fn f32s(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

pub fn max_abs(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    a.iter()
        .zip(b)
        .fold(0f64, |m, (&x, &y)| m.max((x as f64 - y as f64).abs()))
}

/// A copy of a fixture folder (loading caches the text embedding beside the weights, so tests
/// load copies).
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

/// A case file's `image` (1, 3, H, W) as an interleaved [`Image`].
pub fn photo(case: &HashMap<String, Tensor>) -> Image {
    let t = &case["image"];
    let (_, _, h, w) = t.dims4().unwrap();
    let v = f32s(t);
    Image::from_fn(w, h, 3, |x, y, c| v[(c * h + y) * w + x])
}
