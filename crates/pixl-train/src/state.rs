//! The training checkpoint: one safetensors file holding everything a bit-exact resume needs —
//! weights (`param.<name>`), AdamW moments (`adam_m.<name>`, `adam_v.<name>`), the weights'
//! moving average when the run keeps one (`ema.<name>`, [`crate::optim::Ema`]), all f32, and in
//! the metadata the step, the optimiser's update count, the run seed (which, with the step, is
//! the whole RNG and data-order state: every random draw is a function of `(seed, step, index)`),
//! the data-set fingerprint and the model config.
//!
//! Written atomically (temporary file, fsync, rename — [`pixl_core::io::atomic_write_bytes`]):
//! a process killed mid-write leaves the previous checkpoint intact.
use crate::error::{Result, TrainError};
use candle_core::{Device, Tensor};
use safetensors::tensor::{Dtype, TensorView};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

pub const STATE_FILE: &str = "train-state.safetensors";
pub const MODEL_FILE: &str = "model.safetensors";
/// The weights' moving average (`[optim] ema_decay`), a model file like [`MODEL_FILE`].
pub const MODEL_EMA_FILE: &str = "model-ema.safetensors";

/// Scalar state of a run.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Meta {
    pub format: String,
    pub step: u64,
    pub optimizer_steps: u64,
    pub seed: u64,
    /// `<count>:<first scene>:<last scene>` of the training scenes.
    pub data_fingerprint: String,
    pub model_config: String,
}

pub const FORMAT: &str = "pixlrelight-train-state-v1";

/// Tensors by name, plus [`Meta`].
pub struct State {
    pub meta: Meta,
    pub tensors: BTreeMap<String, Tensor>,
}

fn f32_bytes(t: &Tensor) -> Result<Vec<u8>> {
    let v: Vec<f32> = t.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1()?;
    Ok(v.iter().flat_map(|x| x.to_le_bytes()).collect())
}

pub fn save(path: &Path, state: &State) -> Result<()> {
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = state
        .tensors
        .iter()
        .map(|(k, t)| Ok((k.clone(), t.dims().to_vec(), f32_bytes(t)?)))
        .collect::<Result<_>>()?;
    let views = bytes
        .iter()
        .map(|(k, shape, b)| {
            TensorView::new(Dtype::F32, shape.clone(), b)
                .map(|v| (k.clone(), v))
                .map_err(|e| TrainError::Other(format!("safetensors view of {k}: {e}")))
        })
        .collect::<Result<Vec<_>>>()?;
    let meta_json = serde_json::to_string(&state.meta).map_err(|e| TrainError::Other(e.to_string()))?;
    let metadata = HashMap::from([("train_state".to_string(), meta_json)]);
    let data = safetensors::serialize(views, Some(metadata)).map_err(|e| TrainError::File {
        path: path.to_owned(),
        reason: format!("serialising checkpoint: {e}"),
    })?;
    pixl_core::io::atomic_write_bytes(path, &data)?;
    Ok(())
}

pub fn load(path: &Path, device: &Device) -> Result<State> {
    let bytes = std::fs::read(path).map_err(|e| TrainError::io(path, e))?;
    let bad = |reason: String| TrainError::File {
        path: path.to_owned(),
        reason,
    };
    let st =
        safetensors::SafeTensors::deserialize(&bytes).map_err(|e| bad(format!("not a training checkpoint: {e}")))?;
    let (_, header) = safetensors::SafeTensors::read_metadata(&bytes).map_err(|e| bad(e.to_string()))?;
    let meta_json = header
        .metadata()
        .as_ref()
        .and_then(|m| m.get("train_state"))
        .ok_or_else(|| {
            bad("no train_state metadata (is this a model file rather than a training checkpoint?)".into())
        })?;
    let meta: Meta = serde_json::from_str(meta_json).map_err(|e| bad(format!("bad train_state metadata: {e}")))?;
    if meta.format != FORMAT {
        return Err(bad(format!("checkpoint format {:?}, expected {FORMAT:?}", meta.format)));
    }
    let mut tensors = BTreeMap::new();
    for (name, view) in st.tensors() {
        if view.dtype() != Dtype::F32 {
            return Err(bad(format!("tensor {name} is {:?}, expected F32", view.dtype())));
        }
        let data: Vec<f32> = view
            .data()
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        tensors.insert(name.to_string(), Tensor::from_vec(data, view.shape(), device)?);
    }
    Ok(State { meta, tensors })
}
