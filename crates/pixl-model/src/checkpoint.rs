//! Building, saving and loading network weights.
//!
//! File format: safetensors, every tensor f32 (or one of f16/bf16, all the same, as recorded in
//! the metadata), PyTorch-style dotted names (`src_encoder.blocks.0.attn.qkv.weight`; full list
//! in the crate README), and in the safetensors `__metadata__`:
//! `format = "pixlrelight"`, `format_version = "1"`, `dtype = "F32"` and `config` = the
//! [`Config`] as JSON, so a weights file alone rebuilds the network.
//!
//! Loading checks the file against the names and shapes the config's network asks for and
//! rejects, naming the file and the tensor: a missing tensor, an unexpected tensor, a shape or a
//! dtype mismatch, a truncated or non-safetensors file, and missing or invalid config metadata.
//!
//! [`build_trainable`] gives a deterministic initialisation from a seed (candle's own CPU RNG
//! cannot be seeded): every variable, in sorted-name order, is overwritten from
//! `pixl_core::Rng::for_stream(seed, [fnv1a(name)])` by the rule in [`init_rule`].
use crate::config::{Config, ConfigError};
use crate::model::PixlRelight;
use candle_core::safetensors::Load;
use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{VarBuilder, VarMap};
use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

/// Value of the `format` metadata key.
pub const FORMAT: &str = "pixlrelight";
/// Value of the `format_version` metadata key.
pub const FORMAT_VERSION: &str = "1";

/// Everything that can go wrong building, saving or loading weights. Every variant names the
/// file (and the tensor where there is one).
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a valid safetensors file (truncated or corrupt?): {msg}")]
    NotSafetensors { path: PathBuf, msg: String },
    #[error("{path}: no model config in the safetensors metadata (key `config`); not a pixlrelight checkpoint")]
    MissingConfig { path: PathBuf },
    #[error("{path}: invalid model config in the metadata: {source}")]
    InvalidConfig { path: PathBuf, source: ConfigError },
    #[error("{path}: missing tensor `{name}` ({count} missing in all)")]
    MissingTensor { path: PathBuf, name: String, count: usize },
    #[error("{path}: unexpected tensor `{name}` ({count} unexpected in all); the config does not use it")]
    UnexpectedTensor { path: PathBuf, name: String, count: usize },
    #[error("{path}: tensor `{name}` has shape {found:?}, expected {expected:?}")]
    ShapeMismatch {
        path: PathBuf,
        name: String,
        expected: Vec<usize>,
        found: Vec<usize>,
    },
    #[error("{path}: tensor `{name}` has dtype {found}, expected {expected}")]
    DtypeMismatch {
        path: PathBuf,
        name: String,
        expected: String,
        found: String,
    },
    #[error("{path}: {source}")]
    Write {
        path: PathBuf,
        source: pixl_core::CoreError,
    },
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

pub type Result<T, E = CheckpointError> = std::result::Result<T, E>;

/// A `VarBuilder` backend that records every requested name and shape and hands out
/// zero-stride broadcast tensors, so no memory is allocated: the paper network's 727 M
/// parameters are enumerated in milliseconds.
struct ShapeRecorder(Arc<Mutex<BTreeMap<String, Vec<usize>>>>);

impl SimpleBackend for ShapeRecorder {
    fn get(&self, s: Shape, name: &str, _: candle_nn::Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        if let Ok(mut m) = self.0.lock() {
            m.insert(name.to_string(), s.dims().to_vec());
        }
        Tensor::zeros((), dtype, dev)?.broadcast_as(s)
    }

    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("shape recorder: no shape given for `{name}`")
    }

    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

/// Every parameter of the network `cfg` describes: name → shape, sorted by name.
pub fn param_shapes(cfg: &Config) -> Result<BTreeMap<String, Vec<usize>>> {
    let shapes = Arc::new(Mutex::new(BTreeMap::new()));
    let vb = VarBuilder::from_backend(Box::new(ShapeRecorder(shapes.clone())), DType::F32, Device::Cpu);
    PixlRelight::new(cfg, vb)?;
    let out = shapes
        .lock()
        .map(|m| m.clone())
        .map_err(|_| candle_core::Error::Msg("shape recorder poisoned".into()))?;
    Ok(out)
}

fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ b as u64).wrapping_mul(0x0100_0000_01b3)
    })
}

/// How [`build_trainable`] initialises a parameter.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Init {
    Zeros,
    Const(f32),
    /// Normal with this std, resampled outside ±2σ.
    TruncNormal(f32),
    /// Uniform in `±bound`.
    Uniform(f32),
}

/// The initialisation rule, by name and shape:
/// `modulation.conv.*` and every `*.bias` → zeros (the identity prior of Eq. 4);
/// `*.gamma` (ConvNeXt layer scale) → `layer_scale_init`; other 1-D `*.weight` (norms) → ones;
/// DPT-head convs (`head.*`, 4-D) → PyTorch's default `U(±1/√fan_in)`; everything else
/// (linear and encoder conv weights, `pos_embed`, `registers`) → truncated normal, std 0.02.
pub fn init_rule(name: &str, shape: &[usize], cfg: &Config) -> Init {
    if name.starts_with("modulation.") || name.ends_with(".bias") {
        Init::Zeros
    } else if name.ends_with(".gamma") {
        Init::Const(cfg.cond_encoder.layer_scale_init as f32)
    } else if shape.len() == 1 {
        Init::Const(1.0)
    } else if name.starts_with("head.") && shape.len() == 4 {
        let fan_in = (shape[1] * shape[2] * shape[3]).max(1);
        Init::Uniform(1.0 / (fan_in as f32).sqrt())
    } else {
        Init::TruncNormal(0.02)
    }
}

fn init_values(init: Init, n: usize, rng: &mut pixl_core::Rng) -> Vec<f32> {
    match init {
        Init::Zeros => vec![0.0; n],
        Init::Const(c) => vec![c; n],
        Init::Uniform(b) => (0..n).map(|_| rng.uniform(-b, b)).collect(),
        Init::TruncNormal(std) => (0..n)
            .map(|_| loop {
                let z = rng.normal();
                if z.abs() <= 2.0 {
                    break z * std;
                }
            })
            .collect(),
    }
}

/// A trainable network: every parameter a `Var` in the returned `VarMap`, f32, initialised
/// deterministically from `seed` (same seed → bitwise the same weights). The modulation conv is
/// zero, so the network returns its source exactly.
pub fn build_trainable(cfg: &Config, seed: u64, device: &Device) -> Result<(VarMap, PixlRelight)> {
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, device);
    let model = PixlRelight::new(cfg, vb)?;
    {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| candle_core::Error::Msg("VarMap lock poisoned".into()))?;
        let mut names: Vec<&String> = data.keys().collect();
        names.sort();
        for name in names {
            let var = &data[name];
            let shape = var.dims().to_vec();
            let mut rng = pixl_core::Rng::for_stream(seed, &[fnv1a(name)]);
            let values = init_values(init_rule(name, &shape, cfg), var.elem_count(), &mut rng);
            var.set(&Tensor::from_vec(values, shape, device)?)?;
        }
    }
    Ok((varmap, model))
}

/// The network [`build_trainable`] would build from `seed` (bitwise the same values), as plain
/// tensors of `dtype` for inference and benchmarks: half the memory (no `VarMap`), fast paths.
pub fn build_inference(cfg: &Config, seed: u64, dtype: DType, device: &Device) -> Result<PixlRelight> {
    let mut tensors = HashMap::new();
    for (name, shape) in param_shapes(cfg)? {
        let mut rng = pixl_core::Rng::for_stream(seed, &[fnv1a(&name)]);
        let n = shape.iter().product();
        let values = init_values(init_rule(&name, &shape, cfg), n, &mut rng);
        tensors.insert(name, Tensor::from_vec(values, shape, device)?.to_dtype(dtype)?);
    }
    Ok(PixlRelight::new(cfg, VarBuilder::from_tensors(tensors, dtype, device))?)
}

/// An inference copy of a trainable network: the `VarMap`'s current values as plain tensors
/// (copied and detached, so later training steps do not change it and pixl-nn takes its fast
/// paths) of `dtype` on `device`. Use it to evaluate or
/// benchmark a network built by [`build_trainable`]; the `Var`-backed model runs the slower
/// differentiable paths.
pub fn freeze(cfg: &Config, varmap: &VarMap, dtype: DType, device: &Device) -> Result<PixlRelight> {
    let tensors: HashMap<String, Tensor> = {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| candle_core::Error::Msg("VarMap lock poisoned".into()))?;
        let mut out = HashMap::with_capacity(data.len());
        for (k, v) in data.iter() {
            out.insert(
                k.clone(),
                v.as_tensor().copy()?.detach().to_device(device)?.to_dtype(dtype)?,
            );
        }
        out
    };
    Ok(PixlRelight::new(cfg, VarBuilder::from_tensors(tensors, dtype, device))?)
}

/// Saves the `VarMap` of a network built with `cfg` (see [`save_tensors`]).
pub fn save(path: &Path, varmap: &VarMap, cfg: &Config) -> Result<()> {
    let tensors: HashMap<String, Tensor> = {
        let data = varmap
            .data()
            .lock()
            .map_err(|_| candle_core::Error::Msg("VarMap lock poisoned".into()))?;
        data.iter().map(|(k, v)| (k.clone(), v.as_tensor().clone())).collect()
    };
    save_tensors(path, &tensors, cfg)
}

/// Saves `tensors` as f32 safetensors with `cfg` in the metadata, atomically. The names and
/// shapes must be exactly those of the network `cfg` describes.
pub fn save_tensors(path: &Path, tensors: &HashMap<String, Tensor>, cfg: &Config) -> Result<()> {
    cfg.validate()?;
    let expected = param_shapes(cfg)?;
    let found: BTreeMap<String, (Vec<usize>, String)> = tensors
        .iter()
        .map(|(k, t)| (k.clone(), (t.dims().to_vec(), "F32".to_string())))
        .collect();
    check_against(path, &expected, &found, "F32")?;
    let mut f32s: Vec<(String, Tensor)> = Vec::with_capacity(tensors.len());
    for (name, t) in tensors {
        f32s.push((
            name.clone(),
            t.to_dtype(DType::F32)?.to_device(&Device::Cpu)?.contiguous()?,
        ));
    }
    f32s.sort_by(|a, b| a.0.cmp(&b.0));
    let meta = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("format_version".to_string(), FORMAT_VERSION.to_string()),
        ("dtype".to_string(), "F32".to_string()),
        ("config".to_string(), cfg.to_json()),
    ]);
    let bytes = safetensors::serialize(f32s.iter().map(|(k, t)| (k.as_str(), t)), Some(meta)).map_err(|e| {
        CheckpointError::NotSafetensors {
            path: path.to_owned(),
            msg: e.to_string(),
        }
    })?;
    pixl_core::io::atomic_write_bytes(path, &bytes).map_err(|source| CheckpointError::Write {
        path: path.to_owned(),
        source,
    })
}

/// Compares what a file holds (name → (shape, dtype)) with what is expected (name → shape, all
/// of `dtype`). The first problem, in a fixed order (missing, unexpected, shape, dtype), wins.
pub(crate) fn check_against(
    path: &Path,
    expected: &BTreeMap<String, Vec<usize>>,
    found: &BTreeMap<String, (Vec<usize>, String)>,
    dtype: &str,
) -> Result<()> {
    let p = || path.to_owned();
    let missing: Vec<&String> = expected.keys().filter(|k| !found.contains_key(*k)).collect();
    if let Some(name) = missing.first() {
        return Err(CheckpointError::MissingTensor {
            path: p(),
            name: name.to_string(),
            count: missing.len(),
        });
    }
    let extra: Vec<&String> = found.keys().filter(|k| !expected.contains_key(*k)).collect();
    if let Some(name) = extra.first() {
        return Err(CheckpointError::UnexpectedTensor {
            path: p(),
            name: name.to_string(),
            count: extra.len(),
        });
    }
    for (name, shape) in expected {
        let (fshape, fdtype) = &found[name];
        if fshape != shape {
            return Err(CheckpointError::ShapeMismatch {
                path: p(),
                name: name.clone(),
                expected: shape.clone(),
                found: fshape.clone(),
            });
        }
        if fdtype != dtype {
            return Err(CheckpointError::DtypeMismatch {
                path: p(),
                name: name.clone(),
                expected: dtype.to_string(),
                found: fdtype.clone(),
            });
        }
    }
    Ok(())
}

pub(crate) fn read_bytes(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|source| CheckpointError::Io {
        path: path.to_owned(),
        source,
    })
}

pub(crate) fn config_from_metadata(path: &Path, meta: Option<&HashMap<String, String>>) -> Result<(Config, String)> {
    let meta = meta.ok_or_else(|| CheckpointError::MissingConfig { path: path.to_owned() })?;
    let json = meta
        .get("config")
        .ok_or_else(|| CheckpointError::MissingConfig { path: path.to_owned() })?;
    let cfg = Config::from_json(json).map_err(|source| CheckpointError::InvalidConfig {
        path: path.to_owned(),
        source,
    })?;
    let dtype = meta.get("dtype").cloned().unwrap_or_else(|| "F32".to_string());
    if !["F32", "F16", "BF16"].contains(&dtype.as_str()) {
        return Err(CheckpointError::DtypeMismatch {
            path: path.to_owned(),
            name: "(metadata `dtype`)".into(),
            expected: "F32, F16 or BF16".into(),
            found: dtype,
        });
    }
    Ok((cfg, dtype))
}

/// A parsed, fully validated checkpoint.
pub(crate) struct Parsed<'a> {
    pub(crate) cfg: Config,
    pub(crate) tensors: safetensors::SafeTensors<'a>,
}

pub(crate) fn parse<'a>(
    path: &Path,
    bytes: &'a [u8],
    expected: Option<&BTreeMap<String, Vec<usize>>>,
) -> Result<Parsed<'a>> {
    let bad = |e: safetensors::SafeTensorError| CheckpointError::NotSafetensors {
        path: path.to_owned(),
        msg: e.to_string(),
    };
    let (_, metadata) = safetensors::SafeTensors::read_metadata(bytes).map_err(bad)?;
    let (cfg, dtype) = config_from_metadata(path, metadata.metadata().as_ref())?;
    let tensors = safetensors::SafeTensors::deserialize(bytes).map_err(bad)?;
    let found: BTreeMap<String, (Vec<usize>, String)> = tensors
        .tensors()
        .into_iter()
        .map(|(k, v)| (k, (v.shape().to_vec(), format!("{:?}", v.dtype()))))
        .collect();
    let own;
    let expected = match expected {
        Some(e) => e,
        None => {
            own = param_shapes(&cfg)?;
            &own
        }
    };
    check_against(path, expected, &found, &dtype)?;
    Ok(Parsed { cfg, tensors })
}

/// Loads a checkpoint for inference: plain tensors (no `Var`s, so pixl-nn takes its fast
/// paths) of `dtype` on `device`, and the config stored in the file.
pub fn load(path: &Path, device: &Device, dtype: DType) -> Result<(Config, PixlRelight)> {
    let bytes = read_bytes(path)?;
    load_bytes(path, &bytes, device, dtype)
}

/// [`load`] from the bytes of a checkpoint already in memory (e.g. weights compiled into a
/// binary); `name` stands for the file in error messages.
pub fn load_bytes(name: &Path, bytes: &[u8], device: &Device, dtype: DType) -> Result<(Config, PixlRelight)> {
    let parsed = parse(name, bytes, None)?;
    let mut map = HashMap::new();
    for (tensor, view) in parsed.tensors.tensors() {
        map.insert(tensor, view.load(device)?.to_dtype(dtype)?);
    }
    let cfg = parsed.cfg;
    let model = PixlRelight::new(&cfg, VarBuilder::from_tensors(map, dtype, device))?;
    Ok((cfg, model))
}

/// Reads only the config from a checkpoint's header (fast even for a 3 GB file; the tensors are
/// not checked — [`load`] does that).
pub fn read_config(path: &Path) -> Result<Config> {
    let mut file = std::fs::File::open(path).map_err(|source| CheckpointError::Io {
        path: path.to_owned(),
        source,
    })?;
    let not_st = |msg: String| CheckpointError::NotSafetensors {
        path: path.to_owned(),
        msg,
    };
    let mut len = [0u8; 8];
    file.read_exact(&mut len)
        .map_err(|e| not_st(format!("cannot read the 8-byte header length: {e}")))?;
    let n = u64::from_le_bytes(len);
    if n > 100_000_000 {
        return Err(not_st(format!("header length {n} is absurd")));
    }
    let mut header = vec![0u8; n as usize];
    file.read_exact(&mut header)
        .map_err(|e| not_st(format!("header of {n} bytes is truncated: {e}")))?;
    #[derive(serde::Deserialize)]
    struct Header {
        #[serde(rename = "__metadata__")]
        metadata: Option<HashMap<String, String>>,
    }
    let header: Header = serde_json::from_slice(&header).map_err(|e| not_st(format!("header is not JSON: {e}")))?;
    Ok(config_from_metadata(path, header.metadata.as_ref())?.0)
}

/// Loads a checkpoint's values into an existing `VarMap` (fine-tuning, resuming). The file
/// must hold exactly the `VarMap`'s names and shapes.
pub fn load_into_varmap(path: &Path, varmap: &VarMap) -> Result<()> {
    let bytes = read_bytes(path)?;
    let data = varmap
        .data()
        .lock()
        .map_err(|_| candle_core::Error::Msg("VarMap lock poisoned".into()))?;
    let expected: BTreeMap<String, Vec<usize>> = data.iter().map(|(k, v)| (k.clone(), v.dims().to_vec())).collect();
    let parsed = parse(path, &bytes, Some(&expected))?;
    for (name, view) in parsed.tensors.tensors() {
        let var = &data[&name];
        var.set(&view.load(var.device())?.to_dtype(var.dtype())?)?;
    }
    Ok(())
}
