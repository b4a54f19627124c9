//! The released PIXLRelight checkpoint (`config.yaml` + `model.safetensors`, Hugging Face
//! `mlfarinha/pixlrelight`, licence [`LICENCE`]) loaded unchanged into [`PixlRelight`].
//!
//! Three pieces of data decide how, none of them compiled into the network code:
//! - the **name table** ([`names::NameTable`], `names.toml`): their tensor names ↔ ours, and the
//!   release's conventions (gain definition, source scaling, padding);
//! - **`config.yaml`** ([`yaml::OfficialYaml`]): heads, readout blocks, RoPE frequency — what
//!   tensor shapes cannot tell;
//! - the **safetensors header**: every width, depth and count that shapes determine (ViT width,
//!   patch, depths, ConvNeXt stages, registers, DPT channels), and whether DINOv2's class token
//!   and LayerScale are there, so the network matches the file rather than a preset.
//!
//! [`inspect`] compares a file with the table and reports tensors matched, in the file but unused,
//! expected but missing, and mis-shaped, plus every disagreement between `config.yaml` and the
//! header; [`load`] refuses a file whose inspection is not clean (the error says to run
//! `pixl models inspect`) and otherwise builds the network from the memory-mapped file, applying
//! the conventions to the weights (a whole gain becomes ours by subtracting 1 from the gain
//! channels' bias; ImageNet normalisation of the source is folded into the patch embedding), so
//! that the forward pass and everything downstream (full-resolution path, memory plan, CUDA) are
//! those of our own checkpoints.
//!
//! The mapping is **unverified against the released file** (see the crate README); a tiny
//! checkpoint written in the presumed layout (`fixtures/pixlrelight-official/`) goes through
//! exactly this code path in the tests.
pub mod names;
pub mod yaml;

use crate::checkpoint::param_shapes;
use crate::config::{spread_readouts, Config, ConfigError, ConvNextConfig, DptConfig, TrunkConfig, VitConfig};
use crate::model::PixlRelight;
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
pub use names::{Conventions, Gain, NameTable, NamesError, SourceNorm, Theirs};
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::io::Read;
use std::path::{Path, PathBuf};
pub use yaml::{OfficialYaml, YamlError};

/// The release's licence, shown before a download and in every run that uses it.
pub const LICENCE: &str = "CC BY-NC 4.0 — non-commercial use only";

/// ImageNet statistics (DINOv2's input normalisation), for [`SourceNorm::Imagenet`].
const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// Everything that can stop an official checkpoint from loading.
#[derive(Debug, thiserror::Error)]
pub enum OfficialError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a valid safetensors file (truncated or corrupt?): {msg}")]
    NotSafetensors { path: PathBuf, msg: String },
    #[error(transparent)]
    Yaml(#[from] YamlError),
    #[error(transparent)]
    Names(#[from] NamesError),
    #[error("{path}: does not match the name table ({count} problem(s); first: {first}). Run `pixl models inspect {path}` for the full list")]
    Mismatch { path: PathBuf, count: usize, first: String },
    #[error("{path}: the network it describes is invalid: {source}")]
    Config { path: PathBuf, source: ConfigError },
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

/// A tensor as a safetensors header lists it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Stored {
    pub shape: Vec<usize>,
    pub dtype: String,
}

/// A safetensors header: tensors by name, and the `__metadata__` strings.
pub type Header = (BTreeMap<String, Stored>, HashMap<String, String>);

/// The header of a safetensors file: tensors and metadata. Checks that the file is as long as
/// the header says (a truncated download is named as such) without reading the data.
pub fn read_header(path: &Path) -> Result<Header, OfficialError> {
    let io = |source| OfficialError::Io {
        path: path.to_owned(),
        source,
    };
    let bad = |msg: String| OfficialError::NotSafetensors {
        path: path.to_owned(),
        msg,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let file_len = file.metadata().map_err(io)?.len();
    let mut len = [0u8; 8];
    file.read_exact(&mut len)
        .map_err(|e| bad(format!("cannot read the 8-byte header length: {e}")))?;
    let n = u64::from_le_bytes(len);
    if n > 100_000_000 || 8 + n > file_len {
        return Err(bad(format!("header length {n} does not fit a {file_len}-byte file")));
    }
    let mut header = vec![0u8; n as usize];
    file.read_exact(&mut header)
        .map_err(|e| bad(format!("truncated header: {e}")))?;
    let json: serde_json::Map<String, serde_json::Value> =
        serde_json::from_slice(&header).map_err(|e| bad(format!("header is not a JSON object: {e}")))?;
    let mut tensors = BTreeMap::new();
    let mut metadata = HashMap::new();
    let mut end = 0u64;
    for (name, v) in json {
        if name == "__metadata__" {
            if let Some(m) = v.as_object() {
                for (k, v) in m {
                    metadata.insert(k.clone(), v.as_str().unwrap_or_default().to_string());
                }
            }
            continue;
        }
        let entry = v
            .as_object()
            .ok_or_else(|| bad(format!("tensor `{name}`: not an object")))?;
        let dtype = entry
            .get("dtype")
            .and_then(|d| d.as_str())
            .unwrap_or_default()
            .to_string();
        let shape: Option<Vec<usize>> = entry
            .get("shape")
            .and_then(|s| s.as_array())
            .map(|a| a.iter().filter_map(|x| x.as_u64().map(|x| x as usize)).collect());
        let offsets: Option<Vec<u64>> = entry
            .get("data_offsets")
            .and_then(|s| s.as_array())
            .map(|a| a.iter().filter_map(|x| x.as_u64()).collect());
        let (Some(shape), Some(offsets)) = (shape, offsets) else {
            return Err(bad(format!("tensor `{name}`: no shape or data_offsets")));
        };
        if offsets.len() != 2 || offsets[0] > offsets[1] {
            return Err(bad(format!("tensor `{name}`: bad data_offsets {offsets:?}")));
        }
        end = end.max(offsets[1]);
        tensors.insert(name, Stored { shape, dtype });
    }
    if 8 + n + end > file_len {
        return Err(bad(format!(
            "the header lists {} bytes of tensor data but the file holds {} (an interrupted download?)",
            end,
            file_len.saturating_sub(8 + n)
        )));
    }
    Ok((tensors, metadata))
}

/// Whether a file is one of ours (it carries our `format` metadata) or not.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FileKind {
    /// Our checkpoint format (config in the metadata, our names).
    Native,
    /// Anything else, read through the name table (the official release).
    Official,
}

/// One tensor found where the table says.
#[derive(Clone, Debug, Serialize)]
pub struct Matched {
    pub theirs: String,
    pub ours: String,
    pub shape: Vec<usize>,
}

/// A tensor the network needs that is not in the file.
#[derive(Clone, Debug, Serialize)]
pub struct Missing {
    pub theirs: String,
    pub ours: String,
    pub expected: Vec<usize>,
}

/// A tensor of the wrong shape (in the file's orientation) or of a non-float dtype.
#[derive(Clone, Debug, Serialize)]
pub struct Mismatched {
    pub theirs: String,
    pub ours: String,
    pub expected: Vec<usize>,
    pub found: Vec<usize>,
    pub dtype: String,
}

/// What [`inspect`] found: paste-able into a bug report ([`Inspection::to_text`]).
#[derive(Clone, Debug, Serialize)]
pub struct Inspection {
    pub file: PathBuf,
    pub config_file: Option<PathBuf>,
    pub kind: FileKind,
    /// Where the name table came from.
    pub table: String,
    /// The network the file and `config.yaml` describe (absent if the header does not say enough).
    pub config: Option<Config>,
    pub conventions: Option<Conventions>,
    pub matched: Vec<Matched>,
    /// In the file, mapped by no rule or onto no tensor of the network.
    pub unused: Vec<(String, Vec<usize>)>,
    /// In the file, listed as never used by an `[[ignore]]` entry.
    pub ignored: Vec<String>,
    pub missing: Vec<Missing>,
    pub mismatched: Vec<Mismatched>,
    /// Disagreements between `config.yaml` and the header, and what could not be determined.
    pub problems: Vec<String>,
    /// Assumptions made where neither says (printed, not errors).
    pub notes: Vec<String>,
    /// Parameters in the file per part of the network (by our top-level names; `unused` last).
    pub parts: Vec<(String, usize)>,
}

impl Inspection {
    /// No unused, missing or mis-shaped tensor and no problem: the file loads.
    pub fn ok(&self) -> bool {
        self.config.is_some()
            && self.unused.is_empty()
            && self.missing.is_empty()
            && self.mismatched.is_empty()
            && self.problems.is_empty()
    }

    /// Every problem, one line each, in a fixed order.
    pub fn problem_lines(&self) -> Vec<String> {
        let mut out: Vec<String> = self.problems.clone();
        out.extend(
            self.missing
                .iter()
                .map(|m| format!("missing: `{}` {:?} (ours `{}`)", m.theirs, m.expected, m.ours)),
        );
        out.extend(self.mismatched.iter().map(|m| {
            format!(
                "shape: `{}` is {:?} {}, expected {:?} (ours `{}`)",
                m.theirs, m.found, m.dtype, m.expected, m.ours
            )
        }));
        out.extend(
            self.unused
                .iter()
                .map(|(n, s)| format!("unused: `{n}` {s:?} (no rule maps it onto the network)")),
        );
        out
    }

    /// A plain-text report.
    pub fn to_text(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let _ = writeln!(s, "file:    {} ({:?})", self.file.display(), self.kind);
        if let Some(c) = &self.config_file {
            let _ = writeln!(s, "config:  {}", c.display());
        }
        let _ = writeln!(s, "table:   {}", self.table);
        if let Some(c) = &self.conventions {
            let _ = writeln!(
                s,
                "conventions: gain {:?}, source {:?}, pad to {}",
                c.gain, c.source_norm, c.pad_multiple
            );
        }
        let _ = writeln!(
            s,
            "tensors: {} matched, {} unused, {} ignored, {} missing, {} mis-shaped",
            self.matched.len(),
            self.unused.len(),
            self.ignored.len(),
            self.missing.len(),
            self.mismatched.len()
        );
        let total: usize = self.parts.iter().map(|p| p.1).sum();
        let _ = writeln!(s, "parameters: {:.2} M", total as f64 / 1e6);
        for (part, n) in &self.parts {
            let _ = writeln!(s, "  {part:<14} {:>10.3} M", *n as f64 / 1e6);
        }
        if let Some(c) = &self.config {
            let _ = writeln!(
                s,
                "network: d {} patch {} | ViT {} blocks {} heads{}{} | ConvNeXt {:?}/{:?} | trunk {} blocks {} heads {} registers, readouts {:?}, RoPE {} | DPT {:?}/{}/{}",
                c.dim,
                c.patch,
                c.src_encoder.depth,
                c.src_encoder.heads,
                if c.src_encoder.cls_token { ", class token" } else { "" },
                if c.src_encoder.layer_scale { ", LayerScale" } else { "" },
                c.cond_encoder.dims,
                c.cond_encoder.depths,
                c.trunk.depth,
                c.trunk.heads,
                c.trunk.registers,
                c.trunk.readouts,
                c.trunk.rope_base,
                c.head.out_channels,
                c.head.features,
                c.head.hidden
            );
        }
        for n in &self.notes {
            let _ = writeln!(s, "note: {n}");
        }
        let lines = self.problem_lines();
        for l in &lines {
            let _ = writeln!(s, "PROBLEM {l}");
        }
        let _ = writeln!(
            s,
            "{}",
            if self.ok() {
                "result: OK, every tensor matched"
            } else {
                "result: MISMATCH"
            }
        );
        s
    }
}

/// The file's tensors under our names (for an official file, through the table).
struct View<'a> {
    stored: &'a BTreeMap<String, Stored>,
    table: &'a NameTable,
}

impl View<'_> {
    /// The shape of our tensor `ours` in our orientation, if the file has it.
    fn shape(&self, ours: &str) -> Option<Vec<usize>> {
        let (theirs, transpose) = self.table.theirs(ours)?;
        let s = self.stored.get(&theirs)?.shape.clone();
        Some(if transpose { s.into_iter().rev().collect() } else { s })
    }

    fn dim(&self, ours: &str, axis: usize) -> Option<usize> {
        self.shape(ours).and_then(|s| s.get(axis).copied())
    }

    /// Number of consecutive `{prefix}.{i}.` groups present (0, 1, …).
    fn count(&self, prefix: &str, probe: &str) -> usize {
        (0..)
            .take_while(|i| self.shape(&format!("{prefix}.{i}.{probe}")).is_some())
            .count()
    }

    fn theirs(&self, ours: &str) -> String {
        self.table
            .theirs(ours)
            .map(|t| t.0)
            .unwrap_or_else(|| format!("(no rule for {ours})"))
    }
}

/// The network the header (and `config.yaml`) describe. Problems go to `problems`, assumptions
/// to `notes`; `None` when a size the network needs cannot be found.
fn infer(v: &View, y: Option<&OfficialYaml>, problems: &mut Vec<String>, notes: &mut Vec<String>) -> Option<Config> {
    let mut need = |ours: &str, axis: usize, what: &str| {
        let d = v.dim(ours, axis);
        if d.is_none() {
            problems.push(format!("cannot tell {what}: `{}` is not in the file", v.theirs(ours)));
        }
        d
    };
    let dim = need("src_encoder.patch_embed.proj.weight", 0, "the token width d");
    let patch = need("src_encoder.patch_embed.proj.weight", 2, "the patch size");
    let vit_hidden = need("src_encoder.blocks.0.mlp.fc1.weight", 0, "the ViT's MLP width");
    let trunk_hidden = need("trunk.blocks.0.mlp.fc1.weight", 0, "the trunk's MLP width");
    let pos_rows = need("src_encoder.pos_embed", 1, "the position grid");
    let registers = need("trunk.registers", 1, "the number of registers");
    let mut dims = [0usize; 4];
    for (s, d) in dims.iter_mut().enumerate() {
        *d = need(
            &format!("cond_encoder.stages.{s}.blocks.0.conv_dw.weight"),
            0,
            "the ConvNeXt widths",
        )?;
    }
    let mut out_channels = [0usize; 4];
    for (i, o) in out_channels.iter_mut().enumerate() {
        *o = need(&format!("head.projects.{i}.weight"), 0, "the DPT channels")?;
    }
    let features = need("head.scratch.layer1_rn.weight", 0, "the DPT features")?;
    let hidden = need("head.scratch.output_conv2.0.weight", 0, "the DPT output width C'")?;
    let outputs = need("modulation.conv.weight", 0, "the head's output channels")?;
    let (dim, patch, vit_hidden, trunk_hidden, pos_rows, registers) =
        (dim?, patch?, vit_hidden?, trunk_hidden?, pos_rows?, registers?);
    if outputs != 6 {
        problems.push(format!(
            "`{}` has {outputs} output channels; PIXLRelight's head has 6 (gain, bias)",
            v.theirs("modulation.conv.weight")
        ));
    }
    let cls_token = v.shape("src_encoder.cls_token").is_some();
    let pos_cells = pos_rows.saturating_sub(usize::from(cls_token));
    let pos_grid = (pos_cells as f64).sqrt().round() as usize;
    if pos_grid * pos_grid != pos_cells {
        problems.push(format!(
            "`{}` has {pos_rows} rows: not a square grid{}",
            v.theirs("src_encoder.pos_embed"),
            if cls_token { " after the class token's row" } else { "" }
        ));
    }
    let vit_depth = v.count("src_encoder.blocks", "norm1.weight");
    let trunk_depth = v.count("trunk.blocks", "norm1.weight");
    let mut depths = [0usize; 4];
    for (s, d) in depths.iter_mut().enumerate() {
        *d = v.count(&format!("cond_encoder.stages.{s}.blocks"), "conv_dw.weight");
    }
    if v.shape("cond_encoder.stages.4.blocks.0.conv_dw.weight").is_some() {
        problems.push("the ConvNeXt has more than 4 stages".into());
    }
    // What shapes cannot say comes from config.yaml, else from the paper.
    let (y_dim, y_depth, y_heads) = y.map(|y| y.vit()).unwrap_or((None, None, None));
    let net = y.map(|y| y.net_key.clone()).unwrap_or_else(|| "net".into());
    if let Some(d) = y_dim.filter(|d| *d != dim) {
        problems.push(format!(
            "{net}: width {d}, but the file's patch embedding is {dim} wide"
        ));
    }
    if let Some(d) = y_depth.filter(|d| *d != vit_depth) {
        problems.push(format!("{net}: depth {d}, but the file holds {vit_depth} ViT blocks"));
    }
    if let Some(p) = y.and_then(|y| y.net.patch_size).filter(|p| *p != patch) {
        problems.push(format!(
            "{net}.patch_size = {p}, but the file's patch embedding is {patch}×{patch}"
        ));
    }
    if let Some(r) = y.and_then(|y| y.net.num_register_tokens).filter(|r| *r != registers) {
        problems.push(format!(
            "{net}.num_register_tokens = {r}, but the file holds {registers}"
        ));
    }
    let heads = y_heads.unwrap_or_else(|| {
        notes.push(format!(
            "attention heads not in config.yaml: assumed d / 64 = {} (DINOv2's head width)",
            (dim / 64).max(1)
        ));
        (dim / 64).max(1)
    });
    let rope_base = y.and_then(|y| y.net.rope_freq).unwrap_or_else(|| {
        notes.push("RoPE frequency not in config.yaml: assumed 100 (the paper's Appendix A)".into());
        100.0
    });
    let readouts = match y.and_then(|y| y.net.out_layers.clone()) {
        Some(l) => {
            let rel: Vec<usize> = if l.iter().all(|&i| i < trunk_depth) {
                l.clone()
            } else if l.iter().all(|&i| i >= vit_depth && i < vit_depth + trunk_depth) {
                notes.push(format!(
                    "{net}.out_layers {l:?} count the ViT's {vit_depth} blocks first"
                ));
                l.iter().map(|i| i - vit_depth).collect()
            } else {
                problems.push(format!(
                    "{net}.out_layers = {l:?} does not index the file's {trunk_depth} trunk blocks"
                ));
                return None;
            };
            match <[usize; 4]>::try_from(rel) {
                Ok(r) => r,
                Err(_) => {
                    problems.push(format!("{net}.out_layers = {l:?}: the DPT head reads four blocks"));
                    return None;
                }
            }
        }
        None => {
            notes.push(
                "readout blocks not in config.yaml: spread over the trunk as the paper's {4, 11, 17, 23} over 24"
                    .into(),
            );
            spread_readouts(trunk_depth.max(4))
        }
    };
    if let Some(h) = y.map(|y| &y.head) {
        let head = y
            .map(|y| y.net_key.replace("net", "head"))
            .unwrap_or_else(|| "head".into());
        if let Some(d) = h.dim_in.filter(|d| *d != dim) {
            problems.push(format!("{head}.dim_in = {d}, but the trunk is {dim} wide"));
        }
        if let Some(f) = h.features.filter(|f| *f != features) {
            problems.push(format!("{head}.features = {f}, but the file's DPT has {features}"));
        }
        if let Some(o) = h.out_channels.as_ref().filter(|o| o.as_slice() != out_channels) {
            problems.push(format!(
                "{head}.out_channels = {o:?}, but the file's DPT has {out_channels:?}"
            ));
        }
    }
    if dim == 0 || vit_hidden % dim != 0 || trunk_hidden % dim != 0 {
        problems.push(format!(
            "MLP widths {vit_hidden} / {trunk_hidden} are not multiples of d = {dim}"
        ));
        return None;
    }
    let cfg = Config {
        dim,
        patch,
        norm_eps: 1e-6,
        src_encoder: VitConfig {
            depth: vit_depth,
            heads,
            mlp_ratio: vit_hidden / dim,
            pos_grid,
            layer_scale: v.shape("src_encoder.blocks.0.ls1.gamma").is_some(),
            cls_token,
        },
        cond_encoder: ConvNextConfig {
            dims,
            depths,
            layer_scale_init: 1e-6,
        },
        trunk: TrunkConfig {
            depth: trunk_depth,
            heads,
            mlp_ratio: trunk_hidden / dim,
            registers,
            rope_base,
            readouts,
            layer_scale: v.shape("trunk.blocks.0.ls1.gamma").is_some(),
        },
        head: DptConfig {
            out_channels,
            features,
            hidden,
        },
    };
    if let Err(e) = cfg.validate() {
        problems.push(format!("the network the file describes is not valid: {e}"));
        return None;
    }
    Some(cfg)
}

/// The name table to use: `path`, else `$PIXL_OFFICIAL_NAMES`, else the built-in one.
pub fn name_table(path: Option<&Path>) -> Result<NameTable, OfficialError> {
    let env = std::env::var_os("PIXL_OFFICIAL_NAMES").map(PathBuf::from);
    match path.map(Path::to_path_buf).or(env) {
        Some(p) => {
            let text = std::fs::read_to_string(&p).map_err(|source| OfficialError::Io {
                path: p.clone(),
                source,
            })?;
            Ok(NameTable::parse(&text, &p.display().to_string())?)
        }
        None => Ok(NameTable::builtin()),
    }
}

/// `config.yaml` beside the weights file, if there is one.
pub fn config_beside(weights: &Path) -> Option<PathBuf> {
    let p = weights.with_file_name("config.yaml");
    p.is_file().then_some(p)
}

const PARTS: [&str; 6] = ["src_encoder", "cond_encoder", "fuse", "trunk", "head", "modulation"];

/// Compares `weights` (and `config`, the release's `config.yaml`) with the name table. Fails only
/// when a file cannot be read at all; everything else is in the report.
pub fn inspect(weights: &Path, config: Option<&Path>, table: &NameTable) -> Result<Inspection, OfficialError> {
    let (stored, metadata) = read_header(weights)?;
    let mut problems = Vec::new();
    let mut notes = Vec::new();
    let mut report = Inspection {
        file: weights.to_owned(),
        config_file: config.map(Path::to_owned),
        kind: FileKind::Official,
        table: table.origin.clone(),
        config: None,
        conventions: Some(table.conventions),
        matched: vec![],
        unused: vec![],
        ignored: vec![],
        missing: vec![],
        mismatched: vec![],
        problems: vec![],
        notes: vec![],
        parts: vec![],
    };
    let native = metadata.get("format").map(String::as_str) == Some(crate::checkpoint::FORMAT);
    let identity;
    let table = if native {
        report.kind = FileKind::Native;
        report.conventions = None;
        report.table = "(none: our own format)".into();
        identity = NameTable::parse(
            "[conventions]\ngain = \"residual\"\nsource_norm = \"srgb\"\npad_multiple = 16\n[[rule]]\nours = \"{n}\"\ntheirs = \"{n}\"\n",
            "identity",
        )?;
        &identity
    } else {
        table
    };
    let cfg = if native {
        match metadata.get("config").map(|j| Config::from_json(j)) {
            Some(Ok(c)) => Some(c),
            Some(Err(e)) => {
                problems.push(format!("the config in the metadata is invalid: {e}"));
                None
            }
            None => {
                problems.push("our format, but no config in the metadata".into());
                None
            }
        }
    } else {
        let yaml = config.map(OfficialYaml::read).transpose()?;
        if yaml.is_none() {
            notes.push("no config.yaml given: heads, readouts and RoPE frequency assumed".into());
        }
        let cfg = infer(
            &View { stored: &stored, table },
            yaml.as_ref(),
            &mut problems,
            &mut notes,
        );
        if let Some(c) = cfg.as_ref().filter(|c| c.patch != table.conventions.pad_multiple) {
            problems.push(format!(
                "the name table pads inputs to a multiple of {}, the network to its patch size {}: not implemented",
                table.conventions.pad_multiple, c.patch
            ));
        }
        cfg
    };
    let expected = match &cfg {
        Some(c) => param_shapes(c).map_err(|e| OfficialError::Candle(candle_core::Error::Msg(e.to_string())))?,
        None => BTreeMap::new(),
    };
    // Tensors of ours the file should hold, under their names.
    let mut wanted: BTreeMap<String, (String, Vec<usize>)> = BTreeMap::new();
    for (ours, shape) in &expected {
        match table.theirs(ours) {
            Some((theirs, transpose)) => {
                let s = if transpose {
                    shape.iter().rev().copied().collect()
                } else {
                    shape.clone()
                };
                wanted.insert(theirs, (ours.clone(), s));
            }
            None => problems.push(format!("no rule maps our `{ours}` to a name in the file")),
        }
    }
    let mut parts: BTreeMap<&str, usize> = BTreeMap::new();
    for (theirs, st) in &stored {
        let n: usize = st.shape.iter().product();
        match wanted.get(theirs) {
            Some((ours, shape)) => {
                let part = PARTS
                    .iter()
                    .find(|p| ours.starts_with(&format!("{p}.")))
                    .copied()
                    .unwrap_or("other");
                *parts.entry(part).or_default() += n;
                let float = ["F32", "F16", "BF16"].contains(&st.dtype.as_str());
                if &st.shape != shape || !float {
                    report.mismatched.push(Mismatched {
                        theirs: theirs.clone(),
                        ours: ours.clone(),
                        expected: shape.clone(),
                        found: st.shape.clone(),
                        dtype: st.dtype.clone(),
                    });
                } else {
                    report.matched.push(Matched {
                        theirs: theirs.clone(),
                        ours: ours.clone(),
                        shape: st.shape.clone(),
                    });
                }
            }
            None if table.ours(theirs) == Theirs::Ignored => {
                *parts.entry("ignored").or_default() += n;
                report.ignored.push(theirs.clone());
            }
            None => {
                *parts.entry("unused").or_default() += n;
                report.unused.push((theirs.clone(), st.shape.clone()));
            }
        }
    }
    for (theirs, (ours, shape)) in &wanted {
        if !stored.contains_key(theirs) {
            report.missing.push(Missing {
                theirs: theirs.clone(),
                ours: ours.clone(),
                expected: shape.clone(),
            });
        }
    }
    report.parts = PARTS
        .iter()
        .chain(&["other", "ignored", "unused"])
        .filter_map(|p| parts.get(p).map(|n| (p.to_string(), *n)))
        .collect();
    report.config = cfg;
    report.problems = problems;
    report.notes = notes;
    Ok(report)
}

/// An official checkpoint loaded for inference.
pub struct Official {
    pub config: Config,
    pub model: PixlRelight,
    pub conventions: Conventions,
    /// The inspection it passed (notes on assumptions included).
    pub inspection: Inspection,
}

/// Loads the official release (or any file the name table describes) for inference: plain
/// tensors of `dtype` on `device`. `config` is its `config.yaml` (`None`: the one beside the
/// weights, if any). Refuses anything [`inspect`] does not pass.
pub fn load(
    weights: &Path,
    config: Option<&Path>,
    table: &NameTable,
    device: &Device,
    dtype: DType,
) -> Result<Official, OfficialError> {
    let config = config.map(Path::to_path_buf).or_else(|| config_beside(weights));
    let inspection = inspect(weights, config.as_deref(), table)?;
    if inspection.kind == FileKind::Native {
        return Err(OfficialError::Mismatch {
            path: weights.to_owned(),
            count: 1,
            first: "this is one of our own checkpoints; load it with pixl_model::load".into(),
        });
    }
    let lines = inspection.problem_lines();
    let Some(cfg) = inspection.config.clone().filter(|_| inspection.ok()) else {
        return Err(OfficialError::Mismatch {
            path: weights.to_owned(),
            count: lines.len().max(1),
            first: lines.first().cloned().unwrap_or_else(|| "unknown".into()),
        });
    };
    // SAFETY: mapped read-only and only read while the tensors are copied out below; as with
    // every mmap, another process truncating the file meanwhile is undefined behaviour.
    let st = unsafe { candle_core::safetensors::MmapedSafetensors::new(weights) }.map_err(|e| {
        OfficialError::NotSafetensors {
            path: weights.to_owned(),
            msg: e.to_string(),
        }
    })?;
    let conv = table.conventions;
    let mut tensors = HashMap::new();
    for m in &inspection.matched {
        let (_, transpose) = table.theirs(&m.ours).unwrap_or((String::new(), false));
        let mut t = st.load(&m.theirs, &Device::Cpu)?.to_dtype(DType::F32)?;
        if transpose {
            t = t.t()?.contiguous()?;
        }
        if m.ours == "modulation.conv.bias" && conv.gain == Gain::Whole {
            // Their gain is `1 + g`: ours is theirs − 1 on the three gain channels.
            let shift = Tensor::new(&[1f32, 1., 1., 0., 0., 0.], &Device::Cpu)?;
            t = t.sub(&shift)?;
        }
        tensors.insert(m.ours.clone(), t);
    }
    if conv.source_norm == SourceNorm::Imagenet {
        fold_imagenet(&mut tensors)?;
    }
    let tensors = tensors
        .into_iter()
        .map(|(k, t)| Ok((k, t.to_dtype(dtype)?.to_device(device)?)))
        .collect::<candle_core::Result<HashMap<_, _>>>()?;
    let model = PixlRelight::new(&cfg, VarBuilder::from_tensors(tensors, dtype, device))?;
    Ok(Official {
        config: cfg,
        model,
        conventions: conv,
        inspection,
    })
}

/// Folds `x ↦ (x − mean) / std` into the patch embedding: `W' = W / std[c]`,
/// `b' = b − Σ W mean[c] / std[c]` (exact: edge padding and the conv commute with a per-channel
/// affine map).
fn fold_imagenet(tensors: &mut HashMap<String, Tensor>) -> candle_core::Result<()> {
    let (wn, bn) = (
        "src_encoder.patch_embed.proj.weight",
        "src_encoder.patch_embed.proj.bias",
    );
    let (Some(w), Some(b)) = (tensors.get(wn), tensors.get(bn)) else {
        candle_core::bail!("no patch embedding to fold the source normalisation into");
    };
    let dev = w.device().clone();
    let inv_std = Tensor::new(&IMAGENET_STD.map(|s| 1.0 / s), &dev)?.reshape((1, 3, 1, 1))?;
    let mean = Tensor::new(&IMAGENET_MEAN, &dev)?.reshape((1, 3, 1, 1))?;
    let w2 = w.broadcast_mul(&inv_std)?;
    let shift = w2.broadcast_mul(&mean)?.sum((1, 2, 3))?;
    let b2 = b.sub(&shift)?;
    tensors.insert(wn.into(), w2);
    tensors.insert(bn.into(), b2);
    Ok(())
}
