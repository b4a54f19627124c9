//! Shared helpers of the DA3 tests: fixture paths, reference tensors, error measures.
#![allow(dead_code)]
use candle_core::{DType, Device, Tensor};
use std::collections::HashMap;
use std::path::PathBuf;

/// `fixtures/da3` at the repository root.
pub fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/da3")
}

/// `fixtures/da3/tiny`: the tiny model (config.json, model.safetensors, ...).
pub fn tiny() -> PathBuf {
    fixtures().join("tiny")
}

/// The reference tensors of one fixture file.
pub fn expected(name: &str) -> HashMap<String, Tensor> {
    let path = tiny().join(format!("expected_{name}.safetensors"));
    candle_core::safetensors::load(&path, &Device::Cpu).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

pub fn vec_f32(t: &Tensor) -> Vec<f32> {
    t.to_dtype(DType::F32)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

/// `max |a − b| / max |b|`: the largest error relative to the reference's scale (f64).
pub fn max_rel_err(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "lengths differ");
    let scale = b.iter().fold(0f64, |m, &v| m.max((v as f64).abs()));
    let err = a
        .iter()
        .zip(b)
        .fold(0f64, |m, (&x, &y)| m.max((x as f64 - y as f64).abs()));
    err / scale.max(f64::MIN_POSITIVE)
}

/// Asserts shapes agree and [`max_rel_err`] ≤ `tol`.
pub fn assert_close(what: &str, got: &Tensor, want: &Tensor, tol: f64) {
    assert_eq!(
        got.elem_count(),
        want.elem_count(),
        "{what}: {:?} vs reference {:?}",
        got.dims(),
        want.dims()
    );
    let err = max_rel_err(&vec_f32(got), &vec_f32(want));
    assert!(err <= tol, "{what}: max relative error {err:.3e} > {tol:.0e}");
}
