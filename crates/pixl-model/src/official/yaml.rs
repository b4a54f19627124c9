//! The official `config.yaml` (OmegaConf): the `net` and `head` sub-modules' arguments.
//!
//! Layout, as Depth Anything 3's `configs/*.yaml` (same `create_object` helper): the network
//! class in an `__object__: {path, name, args}` entry (or Hydra's `_target_: module.Class`), then
//! `net:` and `head:` entries, each with its own class entry and keyword arguments — at the top
//! level or under `model:`. Everything outside `net`/`head` (training settings, `rgbx`, which is
//! Marigold-IID-Lighting, loaded separately) is not read.
//!
//! Inside `net` and `head` every key must be understood: an unknown key, or a value that asks for
//! something the network does not do, is an error naming the key (`model.net.alt_start`), so a
//! release that differs is reported rather than run wrongly.
use serde_yaml::Value;
use std::path::Path;

/// The config file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum YamlError {
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("{path}: not valid YAML: {msg}")]
    Parse { path: String, msg: String },
    #[error("{path}: describes `{class}`, not PIXLRelight (is this another model's config.yaml?)")]
    WrongModel { path: String, class: String },
    #[error("{path}: no `net` and `head` entries (at the top level or under `model`): not a PIXLRelight config.yaml")]
    NoModel { path: String },
    #[error("{path}: `{key}`: unknown key; the loader understands {known}. Please report it with the output of `pixl models inspect`")]
    UnknownKey { path: String, key: String, known: String },
    #[error("{path}: `{key}` = {value}: {why}")]
    Unsupported {
        path: String,
        key: String,
        value: String,
        why: String,
    },
}

/// The `net` entry's arguments (DA3's `DinoV2` keywords).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct NetArgs {
    /// `name`: `vits`, `vitb`, `vitl` or `vitg` (width, depth and heads of the ViT).
    pub name: Option<String>,
    pub embed_dim: Option<usize>,
    pub depth: Option<usize>,
    pub num_heads: Option<usize>,
    /// Blocks read out by the DPT head (`out_layers`).
    pub out_layers: Option<Vec<usize>>,
    pub patch_size: Option<usize>,
    pub num_register_tokens: Option<usize>,
    /// RoPE base frequency (`rope_freq`).
    pub rope_freq: Option<f64>,
    /// `rope_start`: read, not used (RoPE is in every trunk block).
    pub rope_start: Option<i64>,
}

/// The `head` entry's arguments (DA3's `DPT` keywords).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct HeadArgs {
    pub dim_in: Option<usize>,
    pub output_dim: Option<usize>,
    pub features: Option<usize>,
    pub out_channels: Option<Vec<usize>>,
}

/// What `config.yaml` says about the network.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OfficialYaml {
    /// The network class named at the top (`PIXLRelight`), if any.
    pub class: Option<String>,
    /// Where `net`/`head` were found: `net` or `model.net`.
    pub net_key: String,
    pub net: NetArgs,
    pub head: HeadArgs,
}

/// Width, depth and heads of DINOv2's named sizes.
pub fn vit_size(name: &str) -> Option<(usize, usize, usize)> {
    match name {
        "vits" => Some((384, 12, 6)),
        "vitb" => Some((768, 12, 12)),
        "vitl" => Some((1024, 24, 16)),
        "vitg" => Some((1536, 40, 24)),
        _ => None,
    }
}

const CLASS_KEYS: [&str; 6] = [
    "__object__",
    "_target_",
    "_partial_",
    "_recursive_",
    "_convert_",
    "_args_",
];
const NET_KEYS: [&str; 13] = [
    "name",
    "embed_dim",
    "depth",
    "num_heads",
    "out_layers",
    "patch_size",
    "num_register_tokens",
    "rope_freq",
    "rope_start",
    "alt_start",
    "qknorm_start",
    "cat_token",
    "pretrained",
];
const HEAD_KEYS: [&str; 5] = ["dim_in", "output_dim", "features", "out_channels", "use_sky_head"];

/// The class a mapping names: `__object__.name` or the last part of `_target_`.
fn class_of(m: &serde_yaml::Mapping) -> Option<String> {
    if let Some(Value::Mapping(o)) = m.get("__object__") {
        if let Some(Value::String(n)) = o.get("name") {
            return Some(n.clone());
        }
    }
    match m.get("_target_") {
        Some(Value::String(t)) => t.rsplit('.').next().map(str::to_string),
        _ => None,
    }
}

fn show(v: &Value) -> String {
    serde_yaml::to_string(v)
        .map(|s| s.trim().to_string())
        .unwrap_or_else(|_| "?".into())
}

struct Reader<'a> {
    path: &'a str,
}

impl Reader<'_> {
    fn unsupported(&self, key: &str, v: &Value, why: &str) -> YamlError {
        YamlError::Unsupported {
            path: self.path.to_string(),
            key: key.to_string(),
            value: show(v),
            why: why.to_string(),
        }
    }

    fn usize(&self, key: &str, v: &Value) -> Result<usize, YamlError> {
        v.as_u64()
            .map(|n| n as usize)
            .ok_or_else(|| self.unsupported(key, v, "expected a non-negative integer"))
    }

    fn list(&self, key: &str, v: &Value) -> Result<Vec<usize>, YamlError> {
        v.as_sequence()
            .ok_or_else(|| self.unsupported(key, v, "expected a list of integers"))?
            .iter()
            .map(|x| self.usize(key, x))
            .collect()
    }

    /// The keys of `m` other than the class entries, each checked against `known`.
    fn entries<'m>(
        &self,
        prefix: &str,
        m: &'m serde_yaml::Mapping,
        known: &[&str],
    ) -> Result<Vec<(String, &'m Value)>, YamlError> {
        let mut out = Vec::new();
        for (k, v) in m {
            let k = k.as_str().map(str::to_string).unwrap_or_else(|| show(k));
            if CLASS_KEYS.contains(&k.as_str()) {
                continue;
            }
            if !known.contains(&k.as_str()) {
                return Err(YamlError::UnknownKey {
                    path: self.path.to_string(),
                    key: format!("{prefix}.{k}"),
                    known: known.join(", "),
                });
            }
            out.push((format!("{prefix}.{k}"), v));
        }
        Ok(out)
    }
}

impl OfficialYaml {
    /// Reads and checks `config.yaml`.
    pub fn read(path: &Path) -> Result<Self, YamlError> {
        let shown = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| YamlError::Io {
            path: shown.clone(),
            source,
        })?;
        Self::parse(&text, &shown)
    }

    /// Parses the text of a `config.yaml`; `path` names it in errors.
    pub fn parse(text: &str, path: &str) -> Result<Self, YamlError> {
        let root: Value = serde_yaml::from_str(text).map_err(|e| YamlError::Parse {
            path: path.to_string(),
            msg: e.to_string(),
        })?;
        let r = Reader { path };
        let no_model = || YamlError::NoModel { path: path.to_string() };
        let root = root.as_mapping().ok_or_else(no_model)?;
        // `model:` holds the network where there is one; else the top level does.
        let (scope, prefix) = match root.get("model") {
            Some(Value::Mapping(m)) if m.contains_key("net") => (m, "model"),
            _ => (root, ""),
        };
        let class = class_of(scope).or_else(|| class_of(root));
        if let Some(c) = &class {
            if !c.to_ascii_lowercase().contains("pixlrelight") {
                return Err(YamlError::WrongModel {
                    path: path.to_string(),
                    class: c.clone(),
                });
            }
        }
        let (Some(Value::Mapping(net)), Some(Value::Mapping(head))) = (scope.get("net"), scope.get("head")) else {
            return Err(no_model());
        };
        let key = |k: &str| {
            if prefix.is_empty() {
                k.to_string()
            } else {
                format!("{prefix}.{k}")
            }
        };
        let mut out = OfficialYaml {
            class,
            net_key: key("net"),
            ..Default::default()
        };
        for (k, v) in r.entries(&key("net"), net, &NET_KEYS)? {
            let leaf = k.rsplit('.').next().unwrap_or_default();
            let n = &mut out.net;
            match leaf {
                "name" => {
                    let s = v.as_str().ok_or_else(|| r.unsupported(&k, v, "expected a string"))?;
                    if vit_size(s).is_none() {
                        return Err(r.unsupported(&k, v, "expected vits, vitb, vitl or vitg"));
                    }
                    n.name = Some(s.to_string());
                }
                "embed_dim" => n.embed_dim = Some(r.usize(&k, v)?),
                "depth" => n.depth = Some(r.usize(&k, v)?),
                "num_heads" => n.num_heads = Some(r.usize(&k, v)?),
                "out_layers" => n.out_layers = Some(r.list(&k, v)?),
                "patch_size" => n.patch_size = Some(r.usize(&k, v)?),
                "num_register_tokens" => n.num_register_tokens = Some(r.usize(&k, v)?),
                "rope_freq" => {
                    n.rope_freq = Some(
                        v.as_f64()
                            .filter(|f| *f > 0.0)
                            .ok_or_else(|| r.unsupported(&k, v, "expected a positive number"))?,
                    )
                }
                "rope_start" => n.rope_start = v.as_i64(),
                // DA3's any-view machinery: only its "off" values describe this network.
                "alt_start" | "qknorm_start" if v.as_i64() != Some(-1) => {
                    return Err(r.unsupported(
                        &k,
                        v,
                        "alternating attention / QK-norm are not implemented (only -1, off, is understood)",
                    ));
                }
                "cat_token" if v.as_bool() != Some(false) => {
                    return Err(r.unsupported(
                        &k,
                        v,
                        "class-token concatenation into the DPT head is not implemented (only false)",
                    ));
                }
                // Whether DINOv2 weights initialised training: no effect on a trained file.
                _ => {}
            }
        }
        for (k, v) in r.entries(&key("head"), head, &HEAD_KEYS)? {
            let leaf = k.rsplit('.').next().unwrap_or_default();
            let h = &mut out.head;
            match leaf {
                "dim_in" => h.dim_in = Some(r.usize(&k, v)?),
                "output_dim" => {
                    let d = r.usize(&k, v)?;
                    if d != 6 {
                        return Err(r.unsupported(
                            &k,
                            v,
                            "PIXLRelight's head outputs 6 channels (gain and bias); another model's config?",
                        ));
                    }
                    h.output_dim = Some(d);
                }
                "features" => h.features = Some(r.usize(&k, v)?),
                "out_channels" => {
                    let l = r.list(&k, v)?;
                    if l.len() != 4 {
                        return Err(r.unsupported(&k, v, "expected four channel counts"));
                    }
                    h.out_channels = Some(l);
                }
                "use_sky_head" if v.as_bool() != Some(false) => {
                    return Err(r.unsupported(&k, v, "a sky head belongs to a depth model"));
                }
                _ => {}
            }
        }
        Ok(out)
    }

    /// The ViT's width, depth and heads the config states (explicit keys over `name`).
    pub fn vit(&self) -> (Option<usize>, Option<usize>, Option<usize>) {
        let named = self.net.name.as_deref().and_then(vit_size);
        (
            self.net.embed_dim.or(named.map(|n| n.0)),
            self.net.depth.or(named.map(|n| n.1)),
            self.net.num_heads.or(named.map(|n| n.2)),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DA3_STYLE: &str = "
model:
  __object__:
    path: src.models.pixl_relight
    name: PIXLRelight
    args: as_params
  net:
    __object__: {path: src.models.dinov2, name: DinoV2, args: as_params}
    name: vitl
    out_layers: [4, 11, 17, 23]
    alt_start: -1
    qknorm_start: -1
    rope_start: 0
    cat_token: false
  head:
    __object__: {path: src.models.dpt, name: DPT, args: as_params}
    dim_in: 1024
    output_dim: 6
    features: 256
    out_channels: [256, 512, 1024, 1024]
  rgbx: {whatever: 1}
train: {lr: 5.0e-5}
";

    #[test]
    fn reads_the_da3_style_config() {
        let y = OfficialYaml::parse(DA3_STYLE, "c.yaml").unwrap();
        assert_eq!(y.class.as_deref(), Some("PIXLRelight"));
        assert_eq!(y.net_key, "model.net");
        assert_eq!(y.vit(), (Some(1024), Some(24), Some(16)));
        assert_eq!(y.net.out_layers, Some(vec![4, 11, 17, 23]));
        assert_eq!(y.head.out_channels, Some(vec![256, 512, 1024, 1024]));
        assert_eq!(y.head.features, Some(256));
    }

    #[test]
    fn reads_the_hydra_style_config() {
        let text = "_target_: pixlrelight.PIXLRelight\nnet:\n  _target_: x.DinoV2\n  embed_dim: 64\n  depth: 2\n  num_heads: 2\nhead:\n  _target_: x.DPT\n  output_dim: 6\n";
        let y = OfficialYaml::parse(text, "c.yaml").unwrap();
        assert_eq!(y.net_key, "net");
        assert_eq!(y.vit(), (Some(64), Some(2), Some(2)));
    }

    #[test]
    fn another_models_config_and_unknown_keys_are_named() {
        let da3 = DA3_STYLE.replace("name: PIXLRelight", "name: DepthAnything3Net");
        let e = OfficialYaml::parse(&da3, "c.yaml").unwrap_err();
        assert!(matches!(e, YamlError::WrongModel { .. }), "{e}");
        let e = OfficialYaml::parse(&DA3_STYLE.replace("output_dim: 6", "output_dim: 1"), "c.yaml").unwrap_err();
        assert!(e.to_string().contains("model.head.output_dim"), "{e}");
        let e = OfficialYaml::parse(&DA3_STYLE.replace("cat_token: false", "cat_token: true"), "c.yaml").unwrap_err();
        assert!(e.to_string().contains("model.net.cat_token"), "{e}");
        let e = OfficialYaml::parse(&DA3_STYLE.replace("rope_start: 0", "rope_theta: 0"), "c.yaml").unwrap_err();
        assert!(
            matches!(&e, YamlError::UnknownKey { key, .. } if key == "model.net.rope_theta"),
            "{e}"
        );
        assert!(matches!(
            OfficialYaml::parse("a: [1", "c.yaml"),
            Err(YamlError::Parse { .. })
        ));
        assert!(matches!(
            OfficialYaml::parse("a: 1", "c.yaml"),
            Err(YamlError::NoModel { .. })
        ));
    }
}
