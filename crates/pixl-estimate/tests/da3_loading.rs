//! Loading DA3 checkpoints: config.json formats accepted and refused, and weight files with a
//! missing, renamed, mis-shaped, extra or integer tensor refused with the tensor's name.
mod da3_common;

use candle_core::{DType, Device, Tensor};
use da3_common::tiny;
use pixl_estimate::da3::weights::expected_tensors;
use pixl_estimate::da3::{Da3, Da3Config, Da3Variant};
use pixl_estimate::EstimateError;
use std::collections::HashMap;

fn tiny_tensors() -> HashMap<String, Tensor> {
    candle_core::safetensors::load(tiny().join("model.safetensors"), &Device::Cpu).unwrap()
}

/// Writes `tensors` as a checkpoint and tries to load it with the tiny config.
fn load_with(tensors: &HashMap<String, Tensor>) -> Result<Da3, EstimateError> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("model.safetensors");
    candle_core::safetensors::save(tensors, &path).unwrap();
    Da3::from_files(&tiny().join("config.json"), &path, &Device::Cpu)
}

fn config_error(text: &str) -> String {
    match Da3Config::from_json(text) {
        Ok(c) => panic!("accepted: {c:?}"),
        Err(e) => e,
    }
}

const BLOCK_QKV: &str = "model.backbone.pretrained.blocks.2.attn.qkv.weight";
const SKY_CONV: &str = "model.head.scratch.sky_output_conv2.2.weight";

#[test]
fn missing_tensor_is_refused_by_name() {
    let mut t = tiny_tensors();
    t.remove(SKY_CONV);
    match load_with(&t) {
        Err(EstimateError::MissingTensor { name, expected, .. }) => {
            assert_eq!(name, SKY_CONV);
            assert_eq!(expected, vec![1, 32, 1, 1]);
        }
        other => panic!("expected MissingTensor, got {:?}", other.err()),
    }
}

#[test]
fn renamed_tensor_is_refused_by_name() {
    let mut t = tiny_tensors();
    let v = t.remove(BLOCK_QKV).unwrap();
    t.insert(BLOCK_QKV.replace("qkv", "to_qkv"), v);
    let err = load_with(&t).err().expect("refused");
    assert!(
        matches!(&err, EstimateError::MissingTensor { name, .. } if name == BLOCK_QKV),
        "{err}"
    );
    assert!(err.to_string().contains(BLOCK_QKV), "{err}");
}

#[test]
fn misshaped_tensor_is_refused_by_name() {
    let mut t = tiny_tensors();
    let v = t.remove(BLOCK_QKV).unwrap(); // (96, 32)
    t.insert(BLOCK_QKV.into(), v.narrow(0, 0, 64).unwrap());
    match load_with(&t) {
        Err(EstimateError::TensorShape {
            name, expected, found, ..
        }) => {
            assert_eq!(name, BLOCK_QKV);
            assert_eq!((expected, found), (vec![96, 32], vec![64, 32]));
        }
        other => panic!("expected TensorShape, got {:?}", other.err()),
    }
}

#[test]
fn extra_tensor_is_refused_by_name() {
    let mut t = tiny_tensors();
    t.insert(
        "model.backbone.pretrained.camera_token".into(),
        Tensor::zeros((1, 2, 32), DType::F32, &Device::Cpu).unwrap(),
    );
    match load_with(&t) {
        Err(EstimateError::UnexpectedTensor { name, .. }) => assert_eq!(name, "model.backbone.pretrained.camera_token"),
        other => panic!("expected UnexpectedTensor, got {:?}", other.err()),
    }
}

#[test]
fn integer_tensor_is_refused_by_name() {
    let mut t = tiny_tensors();
    let name = "model.backbone.pretrained.norm.bias";
    t.insert(name.into(), Tensor::zeros(32, DType::U8, &Device::Cpu).unwrap());
    match load_with(&t) {
        Err(EstimateError::TensorDtype { name: n, .. }) => assert_eq!(n, name),
        other => panic!("expected TensorDtype, got {:?}", other.err()),
    }
}

#[test]
fn bf16_weights_load() {
    let t: HashMap<String, Tensor> = tiny_tensors()
        .into_iter()
        .map(|(k, v)| (k, v.to_dtype(DType::BF16).unwrap()))
        .collect();
    let m = load_with(&t).expect("bf16 checkpoint loads");
    let xs = Tensor::zeros((1, 3, 28, 42), DType::F32, &Device::Cpu).unwrap();
    let (depth, sky) = m.forward(&xs).unwrap();
    assert_eq!((depth.dims(), sky.dims()), (&[1, 28, 42][..], &[1, 28, 42][..]));
}

#[test]
fn missing_files_are_io_errors() {
    let dir = tempfile::tempdir().unwrap();
    assert!(matches!(
        Da3::load(dir.path(), &Device::Cpu),
        Err(EstimateError::Io { .. })
    ));
    std::fs::copy(tiny().join("config.json"), dir.path().join("config.json")).unwrap();
    let err = Da3::load(dir.path(), &Device::Cpu).err().expect("no weights");
    assert!(
        matches!(err, EstimateError::Io { .. }) && err.to_string().contains("model.safetensors"),
        "{err}"
    );
}

#[test]
fn official_preset_configs_parse() {
    let metric = Da3Config::from_json(r#"{"model_name": "da3metric-large"}"#).unwrap();
    assert_eq!(metric, Da3Config::large());
    assert_eq!(metric.variant(), Da3Variant::Metric);
    let mono = Da3Config::from_json(r#"{"model_name": "da3mono-large"}"#).unwrap();
    assert_eq!(mono, Da3Config::mono_large());
    assert_eq!(mono.variant(), Da3Variant::Mono);
    // With the preset's sections (the yaml's keys, `__object__` entries ignored).
    let with_sections = r#"{"model_name": "da3metric-large", "config": {
        "__object__": {"path": "depth_anything_3.model.da3", "name": "DepthAnything3Net", "args": "as_params"},
        "net": {"__object__": {"name": "DinoV2"}, "name": "vitl", "out_layers": [4, 11, 17, 23],
                "alt_start": -1, "qknorm_start": -1, "rope_start": -1, "cat_token": false},
        "head": {"dim_in": 1024, "output_dim": 1, "features": 256, "out_channels": [256, 512, 1024, 1024]}}}"#;
    assert_eq!(Da3Config::from_json(with_sections).unwrap(), Da3Config::large());
    // ViT-L: 342 backbone + 64 head tensors.
    assert_eq!(expected_tensors(&Da3Config::large()).len(), 406);
}

#[test]
fn fixture_config_parses_to_the_tiny_preset_and_round_trips() {
    let text = std::fs::read_to_string(tiny().join("config.json")).unwrap();
    let cfg = Da3Config::from_json(&text).unwrap();
    assert_eq!(cfg, Da3Config::tiny());
    let again = serde_json::to_string(&Da3Config::large()).unwrap();
    assert_eq!(Da3Config::from_json(&again).unwrap(), Da3Config::large());
}

#[test]
fn config_of_another_model_is_refused() {
    // A transformers Depth Anything config.json.
    let e = config_error(r#"{"model_type": "depth_anything", "architectures": ["DepthAnythingForDepthEstimation"]}"#);
    assert!(e.contains("model_name") && e.contains("not a Depth Anything 3"), "{e}");
    for name in ["da3-large", "da3-giant-1.1", "da3-small"] {
        let e = config_error(&format!(r#"{{"model_name": "{name}"}}"#));
        assert!(e.contains("any-view"), "{name}: {e}");
    }
    let e = config_error(r#"{"model_name": "da3nested-giant-large"}"#);
    assert!(e.contains("nested"), "{e}");
    let e = config_error(r#"{"model_name": "da3metric-large", "config": {"net": {"name": "vitl", "rope_start": 8}}}"#);
    assert!(e.contains("rope_start 8"), "{e}");
    let e = config_error(r#"{"model_name": "da3metric-large", "config": {"net": {"name": "vitg"}}}"#);
    assert!(e.contains("vitg"), "{e}");
    let e = config_error(r#"{"model_name": "da3metric-large", "config": {"head": {"output_dim": 2}}}"#);
    assert!(e.contains("output_dim 2"), "{e}");
    let e = config_error(r#"{"model_name": "da3mono-small"}"#);
    assert!(e.contains("config.net"), "{e}");
    let e = config_error("[1, 2]");
    assert!(e.contains("object"), "{e}");
}

#[test]
fn refused_config_file_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("config.json");
    std::fs::write(&cfg, r#"{"model_type": "dpt"}"#).unwrap();
    let err = Da3::from_files(&cfg, &tiny().join("model.safetensors"), &Device::Cpu)
        .err()
        .expect("refused");
    assert!(matches!(err, EstimateError::Config { .. }), "{err}");
    assert!(err.to_string().contains(&cfg.display().to_string()), "{err}");
}
