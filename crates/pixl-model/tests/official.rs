//! The released checkpoint's loader on the tiny fixture written in the presumed official layout
//! (`fixtures/pixlrelight-official/`, made by its `make.py` from `native.safetensors` with an
//! independent Python inversion of the name table): the same code path as the hub files, the
//! same forward as our native model with the same weights, and every bad input named.
use candle_core::{DType, Device, Tensor};
use pixl_model::official::{self, FileKind, NameTable, OfficialError};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures/pixlrelight-official")
        .join(name)
}

fn rand(shape: &[usize], lo: f32, hi: f32, seed: u64) -> Tensor {
    let mut rng = pixl_core::Rng::new(seed);
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.uniform(lo, hi)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

fn max_abs_diff(a: &Tensor, b: &Tensor) -> f32 {
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar()
        .unwrap()
}

#[test]
fn fixture_loads_and_matches_the_native_model() {
    let table = NameTable::builtin();
    let off = official::load(&fixture("model.safetensors"), None, &table, &Device::Cpu, DType::F32).unwrap();
    let (mut native_cfg, native) = pixl_model::load(&fixture("native.safetensors"), &Device::Cpu, DType::F32).unwrap();
    // The one field no file can tell: the initial ConvNeXt layer scale (initialisation only).
    native_cfg.cond_encoder.layer_scale_init = off.config.cond_encoder.layer_scale_init;
    assert_eq!(
        off.config, native_cfg,
        "the header and config.yaml describe the native network"
    );
    assert!(off.inspection.ok(), "{}", off.inspection.to_text());
    // Odd sizes: padding, the position-grid resize and the class token all take part.
    let src = rand(&[2, 3, 40, 56], 0.05, 0.95, 1);
    let ct = rand(&[2, 9, 40, 56], 0.0, 1.5, 2);
    let (g0, b0) = native.gain_bias(&src, &ct).unwrap();
    let (g1, b1) = off.model.gain_bias(&src, &ct).unwrap();
    // Not trivial: the perturbed modulation moves the image.
    let gmax: f32 = g0
        .abs()
        .unwrap()
        .flatten_all()
        .unwrap()
        .max(0)
        .unwrap()
        .to_scalar()
        .unwrap();
    assert!(gmax > 1e-3, "gain {gmax}");
    let (dg, db) = (max_abs_diff(&g0, &g1), max_abs_diff(&b0, &b1));
    assert!(dg <= 1e-6 && db <= 1e-6, "gain differs by {dg}, bias by {db}");
    let d = max_abs_diff(
        &native.forward(&src, &ct).unwrap(),
        &off.model.forward(&src, &ct).unwrap(),
    );
    assert!(d <= 1e-6, "forward differs by {d}");
}

#[test]
fn inspection_of_the_fixture_is_clean_and_counts_every_parameter() {
    let table = NameTable::builtin();
    let r = official::inspect(&fixture("model.safetensors"), Some(&fixture("config.yaml")), &table).unwrap();
    assert!(r.ok(), "{}", r.to_text());
    assert_eq!(r.kind, FileKind::Official);
    let cfg = r.config.clone().unwrap();
    assert_eq!(
        r.matched.len(),
        pixl_model::checkpoint::param_shapes(&cfg).unwrap().len()
    );
    let total: usize = r.parts.iter().map(|p| p.1).sum();
    assert_eq!(total, cfg.param_count());
    for (part, n) in cfg.param_breakdown() {
        assert_eq!(r.parts.iter().find(|p| p.0 == part).map(|p| p.1), Some(n), "{part}");
    }
    let text = r.to_text();
    assert!(text.contains("result: OK"), "{text}");
    // Our own checkpoints are recognised as such.
    let n = official::inspect(&fixture("native.safetensors"), None, &table).unwrap();
    assert_eq!(n.kind, FileKind::Native);
    assert!(n.ok(), "{}", n.to_text());
}

/// A copy of the fixture with `edit` applied to its tensors, in `dir`, with the config beside it.
fn edited_copy(dir: &Path, edit: impl FnOnce(&mut HashMap<String, Tensor>)) -> PathBuf {
    let mut t = candle_core::safetensors::load(fixture("model.safetensors"), &Device::Cpu).unwrap();
    edit(&mut t);
    let p = dir.join("model.safetensors");
    candle_core::safetensors::save(&t, &p).unwrap();
    std::fs::copy(fixture("config.yaml"), dir.join("config.yaml")).unwrap();
    p
}

type Edit = dyn FnOnce(&mut HashMap<String, Tensor>);

#[test]
fn renamed_missing_and_misshaped_tensors_are_each_named() {
    let table = NameTable::builtin();
    let name = "net.trunk.blocks.1.attn.proj.weight";
    let cases: Vec<(&str, Box<Edit>)> = vec![
        (
            "renamed",
            Box::new(move |t| {
                let v = t.remove(name).unwrap();
                t.insert("net.trunk.blocks.1.attn.out_proj.weight".into(), v);
            }),
        ),
        (
            "missing",
            Box::new(move |t| {
                t.remove(name);
            }),
        ),
        (
            "misshaped",
            Box::new(move |t| {
                let v = t[name].narrow(0, 0, 16).unwrap();
                t.insert(name.into(), v);
            }),
        ),
    ];
    for (what, edit) in cases {
        let dir = tempfile::tempdir().unwrap();
        let p = edited_copy(dir.path(), edit);
        let r = official::inspect(&p, Some(&dir.path().join("config.yaml")), &table).unwrap();
        assert!(!r.ok(), "{what}");
        let text = r.to_text();
        assert!(text.contains(name), "{what}: {text}");
        match what {
            "renamed" => {
                assert_eq!(r.unused.len(), 1, "{text}");
                assert!(text.contains("attn.out_proj.weight"), "{text}");
                assert_eq!(r.missing.len(), 1, "{text}");
            }
            "missing" => assert_eq!((r.missing.len(), r.unused.len()), (1, 0), "{text}"),
            _ => assert_eq!((r.mismatched.len(), r.missing.len()), (1, 0), "{text}"),
        }
        let e = official::load(&p, None, &table, &Device::Cpu, DType::F32)
            .err()
            .unwrap();
        assert!(matches!(e, OfficialError::Mismatch { .. }), "{what}: {e}");
        assert!(e.to_string().contains("pixl models inspect"), "{e}");
    }
}

#[test]
fn bad_inputs_are_one_clear_error_each() {
    let table = NameTable::builtin();
    let dir = tempfile::tempdir().unwrap();
    // A truncated download.
    let bytes = std::fs::read(fixture("model.safetensors")).unwrap();
    let cut = dir.path().join("cut.safetensors");
    std::fs::write(&cut, &bytes[..bytes.len() - 100]).unwrap();
    let e = official::load(&cut, Some(&fixture("config.yaml")), &table, &Device::Cpu, DType::F32)
        .err()
        .unwrap();
    assert!(matches!(e, OfficialError::NotSafetensors { .. }), "{e}");
    assert!(e.to_string().contains("interrupted download"), "{e}");
    // Another model's config.yaml.
    let yaml = std::fs::read_to_string(fixture("config.yaml")).unwrap();
    let other = dir.path().join("da3.yaml");
    std::fs::write(&other, yaml.replace("name: PIXLRelight", "name: DepthAnything3Net")).unwrap();
    let e = official::load(
        &fixture("model.safetensors"),
        Some(&other),
        &table,
        &Device::Cpu,
        DType::F32,
    )
    .err()
    .unwrap();
    assert!(e.to_string().contains("DepthAnything3Net"), "{e}");
    // A config that disagrees with the weights.
    let wide = dir.path().join("wide.yaml");
    std::fs::write(
        &wide,
        yaml.replace("embed_dim: 32", "embed_dim: 64")
            .replace("dim_in: 32", "dim_in: 64"),
    )
    .unwrap();
    let e = official::load(
        &fixture("model.safetensors"),
        Some(&wide),
        &table,
        &Device::Cpu,
        DType::F32,
    )
    .err()
    .unwrap();
    assert!(matches!(e, OfficialError::Mismatch { .. }), "{e}");
    assert!(e.to_string().contains("width 64"), "{e}");
    // Not a safetensors file at all.
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"not a checkpoint").unwrap();
    assert!(matches!(
        official::inspect(&junk, None, &table),
        Err(OfficialError::NotSafetensors { .. })
    ));
}

/// ImageNet normalisation of the source folded into the patch embedding: the folded network on
/// raw sRGB gives the gain and bias the unfolded one gives on normalised input.
#[test]
fn imagenet_source_normalisation_folds_exactly() {
    let text = pixl_model::official::names::BUILTIN.replace("source_norm = \"srgb\"", "source_norm = \"imagenet\"");
    let table = NameTable::parse(&text, "test").unwrap();
    let folded = official::load(&fixture("model.safetensors"), None, &table, &Device::Cpu, DType::F32).unwrap();
    let (_, native) = pixl_model::load(&fixture("native.safetensors"), &Device::Cpu, DType::F32).unwrap();
    let src = rand(&[1, 3, 32, 48], 0.0, 1.0, 3);
    let ct = rand(&[1, 9, 32, 48], 0.0, 1.0, 4);
    let mean = Tensor::new(&[0.485f32, 0.456, 0.406], &Device::Cpu)
        .unwrap()
        .reshape((1, 3, 1, 1))
        .unwrap();
    let std = Tensor::new(&[0.229f32, 0.224, 0.225], &Device::Cpu)
        .unwrap()
        .reshape((1, 3, 1, 1))
        .unwrap();
    let normed = src.broadcast_sub(&mean).unwrap().broadcast_div(&std).unwrap();
    let (g0, b0) = native.gain_bias(&normed, &ct).unwrap();
    let (g1, b1) = folded.model.gain_bias(&src, &ct).unwrap();
    let (dg, db) = (max_abs_diff(&g0, &g1), max_abs_diff(&b0, &b1));
    assert!(dg < 1e-4 && db < 1e-4, "gain {dg}, bias {db}");
}
