//! Reading a diffusers/transformers `.safetensors` weight file for f32 inference: the file is
//! memory-mapped and every floating-point tensor is converted to f32 once, straight from the
//! mapped bytes (an f32 tensor is one copy, an f16 or bf16 one is one conversion pass, with no
//! intermediate f16 tensor), tensors and large tensors' chunks in parallel on rayon's pool.
//!
//! Contract of [`load`]: `path` → a [`VarBuilder`] over f32 tensors on `device`, named as in the
//! file. Tensors of other dtypes (an old CLIP file's i64 `position_ids` buffer) are left out: a
//! network that asks for one gets the usual missing-tensor error. A file that is not a readable
//! safetensors file is an [`EstimateError::Weights`] naming it.
use crate::error::EstimateError;
use candle_core::safetensors::MmapedSafetensors;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use half::{bf16, f16};
use rayon::prelude::*;
use safetensors::tensor::TensorView;
use safetensors::Dtype;
use std::collections::HashMap;
use std::path::Path;

/// Values per parallel task when converting one tensor.
const CHUNK: usize = 1 << 16;

/// The f32 tensors of the safetensors file at `path`, on `device`.
pub fn load(path: &Path, device: &Device) -> Result<VarBuilder<'static>, EstimateError> {
    let error = |reason: String| EstimateError::Weights {
        path: path.to_owned(),
        reason,
    };
    // SAFETY (mmap): the file is opened read-only and not modified while mapped.
    let file = unsafe { MmapedSafetensors::new(path) }.map_err(|e| error(e.to_string()))?;
    let views = file.tensors();
    let tensors = views
        .par_iter()
        .filter_map(|(name, view)| {
            to_f32(view, device)
                .map(|t| t.map(|t| (name.clone(), t)))
                .map_err(|e| error(format!("tensor `{name}`: {e}")))
                .transpose()
        })
        .collect::<Result<HashMap<String, Tensor>, EstimateError>>()?;
    Ok(VarBuilder::from_tensors(tensors, DType::F32, device))
}

/// One tensor as f32 (`None` for a non-float dtype).
fn to_f32(view: &TensorView<'_>, device: &Device) -> candle_core::Result<Option<Tensor>> {
    let shape = view.shape().to_vec();
    let n: usize = shape.iter().product();
    let bytes = view.data();
    let size = match view.dtype() {
        Dtype::F32 => 4,
        Dtype::F16 | Dtype::BF16 => 2,
        _ => return Ok(None),
    };
    if bytes.len() != n * size {
        candle_core::bail!("{} bytes for {n} values of {:?}", bytes.len(), view.dtype());
    }
    let mut out = vec![0f32; n];
    let dtype = view.dtype();
    out.par_chunks_mut(CHUNK)
        .zip(bytes.par_chunks(CHUNK * size))
        .for_each(|(dst, src)| match dtype {
            Dtype::F32 => {
                for (d, b) in dst.iter_mut().zip(src.chunks_exact(4)) {
                    *d = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                }
            }
            Dtype::F16 => {
                for (d, b) in dst.iter_mut().zip(src.chunks_exact(2)) {
                    *d = f16::from_le_bytes([b[0], b[1]]).to_f32();
                }
            }
            _ => {
                for (d, b) in dst.iter_mut().zip(src.chunks_exact(2)) {
                    *d = bf16::from_le_bytes([b[0], b[1]]).to_f32();
                }
            }
        });
    Tensor::from_vec(out, shape, device).map(Some)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// f32, f16 and bf16 tensors come back as the same f32 values; an i64 one is left out.
    #[test]
    fn every_float_dtype_becomes_f32() {
        let dev = Device::Cpu;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.safetensors");
        let values: Vec<f32> = (0..70_000).map(|i| (i as f32 * 0.37).sin() * 3.0).collect();
        let t = Tensor::from_vec(values, (7, 10_000), &dev).unwrap();
        let ids = Tensor::arange(0i64, 5, &dev).unwrap();
        let tensors = HashMap::from([
            ("a".to_string(), t.clone()),
            ("b".to_string(), t.to_dtype(DType::F16).unwrap()),
            ("c".to_string(), t.to_dtype(DType::BF16).unwrap()),
            ("ids".to_string(), ids),
        ]);
        candle_core::safetensors::save(&tensors, &path).unwrap();
        let vb = load(&path, &dev).unwrap();
        let diff = |name: &str, want: &Tensor| {
            let got = vb.get((7, 10_000), name).unwrap();
            assert_eq!(got.dtype(), DType::F32);
            let want = want.to_dtype(DType::F32).unwrap();
            (got - want)
                .unwrap()
                .abs()
                .unwrap()
                .max_all()
                .unwrap()
                .to_scalar::<f32>()
                .unwrap()
        };
        assert_eq!(diff("a", &t), 0.0);
        assert_eq!(diff("b", &t.to_dtype(DType::F16).unwrap()), 0.0);
        assert_eq!(diff("c", &t.to_dtype(DType::BF16).unwrap()), 0.0);
        assert!(!vb.contains_tensor("ids"));
        let bad = dir.path().join("bad.safetensors");
        std::fs::write(&bad, b"not a safetensors file").unwrap();
        assert!(matches!(load(&bad, &dev), Err(EstimateError::Weights { .. })));
    }
}
