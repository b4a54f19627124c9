//! Checkpoint round trip and every loading error, on `tiny`.
use candle_core::{DType, Device, Tensor};
use pixl_core::Rng;
use pixl_model::checkpoint::{load, load_into_varmap, read_config, save, save_tensors, CheckpointError};
use pixl_model::{build_trainable, Config};
use std::collections::HashMap;
use std::path::Path;

fn rand_tensor(rng: &mut Rng, shape: &[usize], lo: f32, hi: f32) -> Tensor {
    let n: usize = shape.iter().product();
    Tensor::from_vec(
        (0..n).map(|_| rng.uniform(lo, hi)).collect::<Vec<f32>>(),
        shape,
        &Device::Cpu,
    )
    .unwrap()
}

fn to_vec(t: &Tensor) -> Vec<f32> {
    t.flatten_all().unwrap().to_vec1::<f32>().unwrap()
}

fn max_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, |m, d| if d.is_nan() { f32::INFINITY } else { m.max(d) })
}

/// A tiny network whose output conv is non-zero (so outputs depend on every weight), its
/// tensors and a file holding them.
fn trained_like(dir: &Path) -> (candle_nn::VarMap, HashMap<String, Tensor>, std::path::PathBuf) {
    let (vm, _) = build_trainable(&Config::tiny(), 5, &Device::Cpu).unwrap();
    {
        let data = vm.data().lock().unwrap();
        let w = &data["modulation.conv.weight"];
        w.set(&rand_tensor(&mut Rng::new(1), w.dims(), -0.1, 0.1)).unwrap();
    }
    let tensors: HashMap<String, Tensor> = vm
        .data()
        .lock()
        .unwrap()
        .iter()
        .map(|(k, v)| (k.clone(), v.as_tensor().copy().unwrap().detach()))
        .collect();
    let path = dir.join("w.safetensors");
    save(&path, &vm, &Config::tiny()).unwrap();
    (vm, tensors, path)
}

#[test]
fn save_then_load_gives_identical_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let (vm, tensors, path) = trained_like(dir.path());
    let cfg = Config::tiny();
    // Plain tensors (inference fast paths, as `load` gives) and the VarMap (training paths).
    let plain = pixl_model::PixlRelight::new(
        &cfg,
        candle_nn::VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu),
    )
    .unwrap();
    let trained =
        pixl_model::PixlRelight::new(&cfg, candle_nn::VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu)).unwrap();
    let (cfg2, loaded) = load(&path, &Device::Cpu, DType::F32).unwrap();
    assert_eq!(cfg2, cfg);
    assert_eq!(read_config(&path).unwrap(), cfg);
    let mut rng = Rng::new(3);
    let src = rand_tensor(&mut rng, &[1, 3, 32, 48], 0.0, 1.0);
    let ct = rand_tensor(&mut rng, &[1, 9, 32, 48], 0.0, 2.0);
    let a = to_vec(&plain.forward(&src, &ct).unwrap());
    let b = to_vec(&loaded.forward(&src, &ct).unwrap());
    assert!(
        a == b,
        "loaded network differs from the saved one: max diff {}",
        max_diff(&a, &b)
    );
    let t = to_vec(&trained.forward(&src, &ct).unwrap());
    assert!(
        max_diff(&a, &t) < 1e-5,
        "fast and training paths differ by {}",
        max_diff(&a, &t)
    );
    assert!(
        max_diff(&a, &to_vec(&src)) > 1e-4,
        "the output conv is non-zero, the output must differ from the source"
    );
    // into a fresh VarMap
    let (vm2, model2) = build_trainable(&cfg, 77, &Device::Cpu).unwrap();
    let before = to_vec(&model2.forward(&src, &ct).unwrap());
    assert!(max_diff(&before, &t) > 1e-4);
    load_into_varmap(&path, &vm2).unwrap();
    let after = to_vec(&model2.forward(&src, &ct).unwrap());
    assert!(after == t, "resumed VarMap differs: max diff {}", max_diff(&after, &t));
    // build_inference gives the same network as build_trainable + freeze
    let (vm3, _) = build_trainable(&cfg, 12, &Device::Cpu).unwrap();
    let frozen = pixl_model::freeze(&cfg, &vm3, DType::F32, &Device::Cpu).unwrap();
    let direct = pixl_model::build_inference(&cfg, 12, DType::F32, &Device::Cpu).unwrap();
    let ff = to_vec(&frozen.features(&src, &ct).unwrap());
    let fd = to_vec(&direct.features(&src, &ct).unwrap());
    assert!(ff.iter().any(|v| *v > 0.0), "features are all zero");
    assert!(
        ff == fd,
        "build_inference differs from freeze: max diff {}",
        max_diff(&ff, &fd)
    );
    // bf16 inference still returns the source exactly when the output conv is zero
    let (fresh_vm, _) = build_trainable(&cfg, 8, &Device::Cpu).unwrap();
    let p2 = dir.path().join("fresh.safetensors");
    save(&p2, &fresh_vm, &cfg).unwrap();
    let (_, bf) = load(&p2, &Device::Cpu, DType::BF16).unwrap();
    assert!(
        to_vec(&bf.forward(&src, &ct).unwrap()) == to_vec(&src),
        "bf16 fresh network is not the identity"
    );
}

/// Writes `tensors` as a raw safetensors file with the tiny config in its metadata, bypassing
/// `save`'s own checks.
fn write_raw(path: &Path, tensors: &HashMap<String, Tensor>, meta: Option<HashMap<String, String>>) {
    let mut v: Vec<(&String, &Tensor)> = tensors.iter().collect();
    v.sort_by(|a, b| a.0.cmp(b.0));
    let bytes = safetensors::serialize(v, meta).unwrap();
    std::fs::write(path, bytes).unwrap();
}

fn tiny_meta() -> Option<HashMap<String, String>> {
    Some(HashMap::from([
        ("config".to_string(), Config::tiny().to_json()),
        ("dtype".to_string(), "F32".to_string()),
    ]))
}

#[test]
fn each_loading_error_is_specific_and_names_the_tensor() {
    let dir = tempfile::tempdir().unwrap();
    let (_vm, tensors, good) = trained_like(dir.path());
    let p = dir.path().join("bad.safetensors");
    let load_err = |p: &Path| load(p, &Device::Cpu, DType::F32).expect_err("load must fail");

    let mut t = tensors.clone();
    t.remove("trunk.blocks.1.mlp.fc2.weight");
    write_raw(&p, &t, tiny_meta());
    match load_err(&p) {
        CheckpointError::MissingTensor { name, count, .. } => {
            assert_eq!((name.as_str(), count), ("trunk.blocks.1.mlp.fc2.weight", 1))
        }
        e => panic!("expected MissingTensor, got {e}"),
    }

    let mut t = tensors.clone();
    t.insert(
        "trunk.blocks.9.extra".into(),
        Tensor::zeros(3, DType::F32, &Device::Cpu).unwrap(),
    );
    write_raw(&p, &t, tiny_meta());
    match load_err(&p) {
        CheckpointError::UnexpectedTensor { name, .. } => assert_eq!(name, "trunk.blocks.9.extra"),
        e => panic!("expected UnexpectedTensor, got {e}"),
    }

    let mut t = tensors.clone();
    t.insert(
        "fuse.fc1.weight".into(),
        Tensor::zeros((64, 64), DType::F32, &Device::Cpu).unwrap(),
    );
    write_raw(&p, &t, tiny_meta());
    match load_err(&p) {
        CheckpointError::ShapeMismatch {
            name, expected, found, ..
        } => {
            assert_eq!(name, "fuse.fc1.weight");
            assert_eq!((expected, found), (vec![64, 128], vec![64, 64]));
        }
        e => panic!("expected ShapeMismatch, got {e}"),
    }

    let mut t = tensors.clone();
    let w = t["fuse.fc1.weight"].to_dtype(DType::F64).unwrap();
    t.insert("fuse.fc1.weight".into(), w);
    write_raw(&p, &t, tiny_meta());
    let e = load_err(&p);
    assert!(
        e.to_string().contains("fuse.fc1.weight") && e.to_string().contains("F64"),
        "{e}"
    );
    assert!(matches!(e, CheckpointError::DtypeMismatch { .. }), "{e}");

    write_raw(&p, &tensors, None);
    assert!(matches!(load_err(&p), CheckpointError::MissingConfig { .. }));
    let meta = HashMap::from([("config".to_string(), "{\"dim\": 3}".to_string())]);
    write_raw(&p, &tensors, Some(meta));
    assert!(matches!(load_err(&p), CheckpointError::InvalidConfig { .. }));

    let bytes = std::fs::read(&good).unwrap();
    std::fs::write(&p, &bytes[..bytes.len() - 100]).unwrap();
    let e = load_err(&p);
    assert!(matches!(e, CheckpointError::NotSafetensors { .. }), "{e}");
    assert!(e.to_string().contains("bad.safetensors"), "{e}");

    std::fs::write(&p, b"this is a PNG, honest\x89PNG\r\n").unwrap();
    assert!(matches!(load_err(&p), CheckpointError::NotSafetensors { .. }));
    assert!(matches!(read_config(&p), Err(CheckpointError::NotSafetensors { .. })));

    assert!(matches!(
        load_err(&dir.path().join("nope.safetensors")),
        CheckpointError::Io { .. }
    ));

    // load_into_varmap checks against the VarMap
    let (deeper_vm, _) = {
        let mut cfg = Config::tiny();
        cfg.trunk.depth = 5;
        cfg.trunk.readouts = pixl_model::config::spread_readouts(5);
        build_trainable(&cfg, 0, &Device::Cpu).unwrap()
    };
    match load_into_varmap(&good, &deeper_vm) {
        Err(CheckpointError::MissingTensor { name, .. }) => assert!(name.starts_with("trunk.blocks.4."), "{name}"),
        other => panic!("expected MissingTensor, got {:?}", other.err()),
    }
}

#[test]
fn save_refuses_tensors_that_do_not_match_the_config() {
    let dir = tempfile::tempdir().unwrap();
    let (_vm, mut tensors, _) = trained_like(dir.path());
    tensors.remove("head.scratch.output_conv1.bias");
    let p = dir.path().join("x.safetensors");
    let e = save_tensors(&p, &tensors, &Config::tiny()).unwrap_err();
    assert!(matches!(e, CheckpointError::MissingTensor { .. }), "{e}");
    assert!(!p.exists());
}
