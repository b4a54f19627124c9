//! Splitting weights into parts and joining them back, on `tiny`: byte identity without
//! conversion, bit-exact bf16/f16 conversion, and every refusal (missing part, parts of two
//! splits, a tensor over the limit, overwriting, a corrupt part).
use candle_core::{DType, Device, Tensor};
use pixl_model::parts::{self, Overwrite, PartsError, SplitOptions};
use pixl_model::{build_trainable, checkpoint, Config};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Parts of at most 300 kB: `tiny` (2.8 MB in f32) makes about ten.
const LIMIT: u64 = 300_000;

fn save_tiny(dir: &Path, name: &str, seed: u64) -> PathBuf {
    let (varmap, _) = build_trainable(&Config::tiny(), seed, &Device::Cpu).unwrap();
    let path = dir.join(name);
    pixl_model::save(&path, &varmap, &Config::tiny()).unwrap();
    path
}

fn opts(dtype: Option<DType>, max_part_bytes: u64) -> SplitOptions {
    SplitOptions {
        dtype,
        max_part_bytes,
        overwrite: Overwrite::Refuse,
    }
}

fn paths(summary: &parts::SplitSummary) -> Vec<PathBuf> {
    summary.parts.iter().map(|p| p.path.clone()).collect()
}

/// Every tensor of a safetensors file, and its metadata.
fn read_all(path: &Path) -> (HashMap<String, Tensor>, HashMap<String, String>) {
    let bytes = std::fs::read(path).unwrap();
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let tensors = candle_core::safetensors::load_buffer(&bytes, &Device::Cpu).unwrap();
    (tensors, meta.metadata().clone().unwrap_or_default())
}

fn bits_u16(t: &Tensor) -> Vec<u16> {
    match t.dtype() {
        DType::BF16 => t
            .flatten_all()
            .unwrap()
            .to_vec1::<half::bf16>()
            .unwrap()
            .iter()
            .map(|v| v.to_bits())
            .collect(),
        DType::F16 => t
            .flatten_all()
            .unwrap()
            .to_vec1::<half::f16>()
            .unwrap()
            .iter()
            .map(|v| v.to_bits())
            .collect(),
        other => panic!("not a 16-bit tensor: {other:?}"),
    }
}

#[test]
fn split_then_join_is_byte_identical_to_the_saved_file() {
    let dir = tempfile::tempdir().unwrap();
    // safetensors writes the metadata from a HashMap, in an order that changes with every save:
    // several saves, several orders, each must come back exactly.
    for seed in 0..3 {
        let w = save_tiny(dir.path(), &format!("w{seed}.safetensors"), seed);
        let original = std::fs::read(&w).unwrap();
        let out = dir.path().join(format!("parts{seed}"));
        let split = parts::split(&w, &out, &opts(None, LIMIT)).unwrap();
        let n = split.parts.len();
        assert!(n >= 5, "only {n} parts");
        assert_eq!((split.source_dtype, split.dtype), (DType::F32, DType::F32));
        let mut tensors = 0;
        for (i, p) in split.parts.iter().enumerate() {
            let name = p.path.file_name().unwrap().to_str().unwrap().to_string();
            assert_eq!(name, format!("w{seed}-{:05}-of-{n:05}.safetensors", i + 1));
            let size = std::fs::metadata(&p.path).unwrap().len();
            assert_eq!(size, p.bytes);
            assert!(size <= LIMIT, "{name}: {size} bytes");
            let (t, meta) = read_all(&p.path);
            assert_eq!(t.len(), p.tensors);
            tensors += t.len();
            assert_eq!(meta["part_index"], format!("{:05}", i + 1));
            assert_eq!(meta["part_count"], format!("{n:05}"));
            assert_eq!(meta["parts_id"], split.parts_id);
            assert_eq!(meta["format"], "pixlrelight");
            // a part alone is not a checkpoint
            assert!(checkpoint::load(&p.path, &Device::Cpu, DType::F32).is_err());
        }
        assert_eq!(tensors, checkpoint::param_shapes(&Config::tiny()).unwrap().len());

        // given in any order
        let mut given = paths(&split);
        given.reverse();
        given.swap(0, n / 2);
        let joined = dir.path().join(format!("joined{seed}.safetensors"));
        let summary = parts::join(&given, &joined, Overwrite::Refuse).unwrap();
        assert_eq!(summary.parts, paths(&split));
        assert_eq!(summary.bytes, original.len() as u64);
        assert!(
            std::fs::read(&joined).unwrap() == original,
            "seed {seed}: joined bytes differ"
        );

        // one part stands for its set
        let again = dir.path().join(format!("again{seed}.safetensors"));
        parts::join(&[split.parts[n - 1].path.clone()], &again, Overwrite::Refuse).unwrap();
        assert!(std::fs::read(&again).unwrap() == original);
    }
}

#[test]
fn the_bundled_demo_weights_come_back_byte_identical() {
    let w = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-weights/pixl-tiny-synth.safetensors");
    let dir = tempfile::tempdir().unwrap();
    let split = parts::split(&w, dir.path(), &opts(None, LIMIT)).unwrap();
    let joined = dir.path().join("joined.safetensors");
    parts::join(&paths(&split), &joined, Overwrite::Refuse).unwrap();
    assert!(std::fs::read(&joined).unwrap() == std::fs::read(&w).unwrap());
}

#[test]
fn bf16_and_f16_splits_hold_the_rounded_weights_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let w = save_tiny(dir.path(), "w.safetensors", 7);
    let (original, _) = read_all(&w);
    let f32_bytes = std::fs::metadata(&w).unwrap().len();
    for dtype in [DType::BF16, DType::F16] {
        let out = dir.path().join(format!("{dtype:?}"));
        let split = parts::split(&w, &out, &opts(Some(dtype), LIMIT)).unwrap();
        assert_eq!((split.source_dtype, split.dtype), (DType::F32, dtype));
        assert!(split.parts.iter().all(|p| p.bytes <= LIMIT));
        let joined = dir.path().join(format!("w-{dtype:?}.safetensors"));
        let summary = parts::join(&paths(&split), &joined, Overwrite::Refuse).unwrap();
        assert_eq!(summary.dtype, dtype);
        // half the data, the same header but for the dtype
        assert!(
            summary.bytes < f32_bytes / 2 + 30_000,
            "{} vs {f32_bytes}",
            summary.bytes
        );
        let (tensors, meta) = read_all(&joined);
        assert_eq!(meta["dtype"], format!("{dtype:?}"));
        assert!(!meta.contains_key("part_index") && !meta.contains_key("parts_id"));
        assert_eq!(tensors.len(), original.len());
        for (name, t) in &original {
            let got = &tensors[name];
            assert_eq!(got.dtype(), dtype, "{name}");
            assert_eq!(got.dims(), t.dims(), "{name}");
            assert_eq!(bits_u16(got), bits_u16(&t.to_dtype(dtype).unwrap()), "{name}");
        }
        // an independent rounding of one tensor: half's round-to-nearest-even
        let name = "trunk.blocks.0.attn.qkv.weight";
        let values = original[name].flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let expected: Vec<u16> = match dtype {
            DType::BF16 => values.iter().map(|v| half::bf16::from_f32(*v).to_bits()).collect(),
            _ => values.iter().map(|v| half::f16::from_f32(*v).to_bits()).collect(),
        };
        assert_eq!(bits_u16(&tensors[name]), expected);
        let (cfg, _model) = checkpoint::load(&joined, &Device::Cpu, DType::F32).unwrap();
        assert_eq!(cfg, Config::tiny());
    }
}

#[test]
fn a_missing_part_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let w = save_tiny(dir.path(), "w.safetensors", 0);
    let split = parts::split(&w, &dir.path().join("parts"), &opts(None, LIMIT)).unwrap();
    let n = split.parts.len();
    let mut given = paths(&split);
    let gone = given.remove(1);
    std::fs::remove_file(&gone).unwrap();
    let out = dir.path().join("j.safetensors");
    let e = parts::join(&given, &out, Overwrite::Refuse).unwrap_err();
    assert!(
        matches!(e, PartsError::MissingPart { index: 2, count, .. } if count == n),
        "{e}"
    );
    let e = parts::join(&given[..1], &out, Overwrite::Refuse).unwrap_err();
    assert!(
        matches!(&e, PartsError::MissingPartFile { path, index: 2, .. } if *path == gone),
        "{e}"
    );
    assert!(e.to_string().contains("part 2 of"), "{e}");
    assert!(!out.exists());
}

#[test]
fn parts_of_two_splits_are_not_mixed() {
    let dir = tempfile::tempdir().unwrap();
    // Two checkpoints of the same network: same names, shapes, dtype and config, other values.
    let a = save_tiny(dir.path(), "w.safetensors", 0);
    let a_split = parts::split(&a, &dir.path().join("a"), &opts(None, LIMIT)).unwrap();
    let b = save_tiny(dir.path(), "w.safetensors", 1);
    let b_split = parts::split(&b, &dir.path().join("b"), &opts(None, LIMIT)).unwrap();
    assert_eq!(a_split.parts.len(), b_split.parts.len());
    assert_ne!(a_split.parts_id, b_split.parts_id);
    let mut given = paths(&a_split);
    given[1] = b_split.parts[1].path.clone();
    let out = dir.path().join("j.safetensors");
    let e = parts::join(&given, &out, Overwrite::Refuse).unwrap_err();
    assert!(
        matches!(&e, PartsError::MixedSplits { path, .. } if *path == given[1]),
        "{e}"
    );
    // the same file split with another limit is another split too
    let c_split = parts::split(&a, &dir.path().join("c"), &opts(None, 2 * LIMIT)).unwrap();
    let e = parts::join(
        &[a_split.parts[0].path.clone(), c_split.parts[1].path.clone()],
        &out,
        Overwrite::Refuse,
    )
    .unwrap_err();
    assert!(matches!(e, PartsError::MixedSplits { .. }), "{e}");
    // a part given twice
    let mut twice = paths(&a_split);
    twice.push(twice[0].clone());
    let e = parts::join(&twice, &out, Overwrite::Refuse).unwrap_err();
    assert!(matches!(e, PartsError::DuplicatePart { index: 1, .. }), "{e}");
    assert!(!out.exists());
}

#[test]
fn a_tensor_larger_than_the_limit_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let w = save_tiny(dir.path(), "w.safetensors", 0);
    let shapes = checkpoint::param_shapes(&Config::tiny()).unwrap();
    let (largest, shape) = shapes.iter().max_by_key(|(_, s)| s.iter().product::<usize>()).unwrap();
    let data = 4 * shape.iter().product::<usize>() as u64;
    // room for the data, not for the header too
    let out = dir.path().join("parts");
    let e = parts::split(&w, &out, &opts(None, data)).unwrap_err();
    match &e {
        PartsError::TensorTooLarge {
            name,
            data: d,
            needs,
            limit,
            ..
        } => {
            assert_eq!((name, *d, *limit), (largest, data, data));
            assert!(*needs > data);
        }
        other => panic!("{other}"),
    }
    assert!(e.to_string().contains(largest.as_str()), "{e}");
    assert!(!out.exists(), "a refused split leaves no folder");
    // in bf16 the same limit is enough
    parts::split(&w, &out, &opts(Some(DType::BF16), data)).unwrap();
    // a dtype pixl does not write
    let e = parts::split(&w, &out, &opts(Some(DType::U8), LIMIT)).unwrap_err();
    assert!(matches!(e, PartsError::UnsupportedDtype { .. }), "{e}");
}

#[test]
fn existing_files_and_inputs_are_not_overwritten() {
    let dir = tempfile::tempdir().unwrap();
    let w = save_tiny(dir.path(), "w.safetensors", 0);
    let out = dir.path().join("parts");
    let split = parts::split(&w, &out, &opts(None, LIMIT)).unwrap();
    let before = std::fs::read(&split.parts[0].path).unwrap();
    // again, and as bf16 (fewer parts: other names), are both refused
    for dtype in [None, Some(DType::BF16)] {
        let e = parts::split(&w, &out, &opts(dtype, LIMIT)).unwrap_err();
        assert!(
            matches!(&e, PartsError::PartsExist { first, .. } if *first == split.parts[0].path),
            "{e}"
        );
    }
    assert_eq!(std::fs::read(&split.parts[0].path).unwrap(), before);
    // allowed, the bf16 set replaces the f32 one: the folder holds one set, which joins
    let mut allow = opts(Some(DType::BF16), LIMIT);
    allow.overwrite = Overwrite::Allow;
    let bf16 = parts::split(&w, &out, &allow).unwrap();
    assert!(bf16.parts.len() < split.parts.len());
    assert_eq!(
        bf16.removed,
        paths(&split),
        "every f32 part goes (other names: -of-N differs)"
    );
    let mut left: Vec<PathBuf> = std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().path()).collect();
    left.sort();
    assert_eq!(left, paths(&bf16));
    let e = parts::join(&left, &dir.path().join("bf16.safetensors"), Overwrite::Refuse);
    assert_eq!(e.unwrap().dtype, DType::BF16);
    let mut allow = opts(None, LIMIT);
    allow.overwrite = Overwrite::Allow;
    let split = parts::split(&w, &out, &allow).unwrap();

    // the input under a part's name (a hard link) is refused even when overwriting is allowed
    let linked = dir.path().join("linked");
    std::fs::create_dir(&linked).unwrap();
    let n = split.parts.len();
    std::fs::hard_link(&w, linked.join(parts::part_name("w", 1, n))).unwrap();
    let e = parts::split(&w, &linked, &allow).unwrap_err();
    assert!(matches!(e, PartsError::OutputIsInput { .. }), "{e}");

    // join: an existing output only when allowed, one of its parts never
    let joined = dir.path().join("j.safetensors");
    std::fs::write(&joined, b"old").unwrap();
    let e = parts::join(&paths(&split), &joined, Overwrite::Refuse).unwrap_err();
    assert!(matches!(e, PartsError::Exists { .. }), "{e}");
    assert_eq!(std::fs::read(&joined).unwrap(), b"old");
    parts::join(&paths(&split), &joined, Overwrite::Allow).unwrap();
    assert!(std::fs::read(&joined).unwrap() == std::fs::read(&w).unwrap());
    let e = parts::join(&paths(&split), &split.parts[2].path, Overwrite::Allow).unwrap_err();
    assert!(matches!(e, PartsError::OutputIsInput { .. }), "{e}");
    assert_eq!(
        std::fs::metadata(&split.parts[2].path).unwrap().len(),
        split.parts[2].bytes
    );
}

#[test]
fn a_changed_part_or_a_plain_checkpoint_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let w = save_tiny(dir.path(), "w.safetensors", 0);
    let split = parts::split(&w, &dir.path().join("parts"), &opts(None, LIMIT)).unwrap();
    // one bit of one weight flipped in transit
    let victim = &split.parts[1].path;
    let mut bytes = std::fs::read(victim).unwrap();
    let last = bytes.len() - 3;
    bytes[last] ^= 1;
    std::fs::write(victim, &bytes).unwrap();
    let out = dir.path().join("j.safetensors");
    let e = parts::join(&paths(&split), &out, Overwrite::Refuse).unwrap_err();
    assert!(matches!(e, PartsError::HashMismatch { .. }), "{e}");
    assert!(!out.exists());
    // a whole checkpoint is not a part
    let e = parts::join(&[w.clone(), split.parts[0].path.clone()], &out, Overwrite::Refuse).unwrap_err();
    assert!(matches!(&e, PartsError::NotAPart { path, .. } if *path == w), "{e}");
    // nor is a file that is no safetensors at all
    let junk = dir.path().join("junk-00001-of-00001.safetensors");
    std::fs::write(&junk, b"not weights").unwrap();
    let e = parts::join(&[junk], &out, Overwrite::Refuse).unwrap_err();
    assert!(e.to_string().contains("not a valid safetensors file"), "{e}");
    let e = parts::join(&[], &out, Overwrite::Refuse).unwrap_err();
    assert!(matches!(e, PartsError::NoParts), "{e}");
}
