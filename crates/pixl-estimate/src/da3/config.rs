//! [`Da3Config`]: the architecture of a single-view DA3 model, read from the official
//! `config.json`.
//!
//! The official checkpoints are saved by `DepthAnything3.save_pretrained` (huggingface_hub's
//! `PyTorchModelHubMixin`), whose `config.json` holds the constructor arguments: `model_name`
//! (the preset, e.g. `"da3metric-large"`, which picks `configs/<model_name>.yaml`). A `config`
//! object with the preset's `net` and `head` sections may accompany it. This loader accepts:
//!
//! - `{"model_name": "da3mono-large" | "da3metric-large"}` — the released presets;
//! - `{"model_name": ..., "config": {"net": {...}, "head": {...}}}` — sections with the yaml's keys
//!   (`name`, `out_layers`, `alt_start`, `qknorm_start`, `rope_start`, `cat_token`; `dim_in`,
//!   `output_dim`, `features`, `out_channels`, ...), where `net` may also give the ViT sizes
//!   explicitly (`embed_dim`, `depth`, `num_heads`, `mlp_ratio`, `img_size`, `patch_size`, the
//!   `DinoVisionTransformer` argument names) — how the test fixtures describe their tiny model.
//!
//! It refuses, with a message saying why: a file without `model_name` (another model's config),
//! the any-view and nested models (camera tokens, alternating attention, QK-norm, RoPE,
//! `cat_token`, DualDPT head), the SwiGLU `vitg` backbone, and head options the released mono /
//! metric models do not use. [`Da3Config::variant`] comes from the name (`mono` / `metric`).
use super::Da3Variant;
use serde::{Deserialize, Serialize};

/// Backbone (`model.backbone`, the official `DinoV2` wrapper around `DinoVisionTransformer`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Da3NetConfig {
    /// Preset name (`vits`, `vitb`, `vitl`) or any name when the sizes are explicit.
    pub name: String,
    pub embed_dim: usize,
    pub depth: usize,
    pub num_heads: usize,
    /// MLP hidden size = `embed_dim · mlp_ratio`.
    pub mlp_ratio: f64,
    /// Training image size: the position embedding covers `(img_size / patch_size)²` patches.
    pub img_size: usize,
    pub patch_size: usize,
    /// The four blocks whose outputs (after the final norm) feed the head, in block order
    /// whatever the listed order (as the official `get_intermediate_layers`).
    pub out_layers: [usize; 4],
    /// Any-view features, all off (−1 / false) in the single-view models.
    pub alt_start: i64,
    pub qknorm_start: i64,
    pub rope_start: i64,
    pub cat_token: bool,
}

/// DPT head (`model.head`, the official `DPT`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Da3HeadConfig {
    pub dim_in: usize,
    pub output_dim: usize,
    pub features: usize,
    pub out_channels: [usize; 4],
    pub patch_size: usize,
    /// Depth activation, `exp` in the released models.
    pub activation: String,
    pub use_sky_head: bool,
    /// Sky activation: `relu` (released), `sigmoid` or `linear`.
    pub sky_activation: String,
    pub pos_embed: bool,
    pub down_ratio: usize,
    pub use_ln_for_heads: bool,
    pub norm_type: String,
}

/// A single-view DA3 model: the official `config.json` layout, every field explicit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Da3Config {
    pub model_name: String,
    pub config: Da3Arch,
}

/// The `config` section: backbone and head.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Da3Arch {
    pub net: Da3NetConfig,
    pub head: Da3HeadConfig,
}

/// `net` as written in a file: everything optional, filled from the preset `name`.
#[derive(Deserialize, Default)]
struct RawNet {
    name: Option<String>,
    embed_dim: Option<usize>,
    depth: Option<usize>,
    num_heads: Option<usize>,
    mlp_ratio: Option<f64>,
    img_size: Option<usize>,
    patch_size: Option<usize>,
    out_layers: Option<Vec<usize>>,
    alt_start: Option<i64>,
    qknorm_start: Option<i64>,
    rope_start: Option<i64>,
    cat_token: Option<bool>,
}

/// `head` as written in a file, with the official `DPT.__init__` defaults.
#[derive(Deserialize, Default)]
struct RawHead {
    dim_in: Option<usize>,
    output_dim: Option<usize>,
    features: Option<usize>,
    out_channels: Option<Vec<usize>>,
    patch_size: Option<usize>,
    activation: Option<String>,
    use_sky_head: Option<bool>,
    sky_activation: Option<String>,
    pos_embed: Option<bool>,
    down_ratio: Option<usize>,
    use_ln_for_heads: Option<bool>,
    norm_type: Option<String>,
}

/// `(embed_dim, depth, num_heads)` of the official `vit_*` builders.
fn vit_preset(name: &str) -> Option<(usize, usize, usize)> {
    match name {
        "vits" => Some((384, 12, 6)),
        "vitb" => Some((768, 12, 12)),
        "vitl" => Some((1024, 24, 16)),
        _ => None,
    }
}

impl Da3Config {
    /// The released `da3metric-large` architecture: ViT-L/14 (1024 wide, 24 blocks, 16 heads,
    /// 37×37 position grid), out layers [4, 11, 17, 23], DPT(256, [256, 512, 1024, 1024]).
    pub fn large() -> Self {
        Self::large_named("da3metric-large")
    }

    /// The released `da3mono-large` architecture (identical to [`Da3Config::large`]).
    pub fn mono_large() -> Self {
        Self::large_named("da3mono-large")
    }

    fn large_named(model_name: &str) -> Self {
        Self {
            model_name: model_name.to_owned(),
            config: Da3Arch {
                net: Da3NetConfig {
                    name: "vitl".into(),
                    embed_dim: 1024,
                    depth: 24,
                    num_heads: 16,
                    mlp_ratio: 4.0,
                    img_size: 518,
                    patch_size: 14,
                    out_layers: [4, 11, 17, 23],
                    alt_start: -1,
                    qknorm_start: -1,
                    rope_start: -1,
                    cat_token: false,
                },
                head: Self::head_defaults(1024, 256, [256, 512, 1024, 1024]),
            },
        }
    }

    /// The tiny model of the test fixtures (`fixtures/da3/tiny`, `scripts/fixtures/da3.py`):
    /// ViT 32 wide, 6 blocks, 4 heads, 5×5 position grid, DPT(16, [8, 16, 24, 32]).
    pub fn tiny() -> Self {
        Self {
            model_name: "da3mono-tiny".into(),
            config: Da3Arch {
                net: Da3NetConfig {
                    name: "vit-tiny".into(),
                    embed_dim: 32,
                    depth: 6,
                    num_heads: 4,
                    mlp_ratio: 4.0,
                    img_size: 70,
                    patch_size: 14,
                    out_layers: [1, 2, 3, 4],
                    alt_start: -1,
                    qknorm_start: -1,
                    rope_start: -1,
                    cat_token: false,
                },
                head: Self::head_defaults(32, 16, [8, 16, 24, 32]),
            },
        }
    }

    fn head_defaults(dim_in: usize, features: usize, out_channels: [usize; 4]) -> Da3HeadConfig {
        Da3HeadConfig {
            dim_in,
            output_dim: 1,
            features,
            out_channels,
            patch_size: 14,
            activation: "exp".into(),
            use_sky_head: true,
            sky_activation: "relu".into(),
            pos_embed: false,
            down_ratio: 1,
            use_ln_for_heads: false,
            norm_type: "idt".into(),
        }
    }

    /// The net section.
    pub fn net(&self) -> &Da3NetConfig {
        &self.config.net
    }

    /// The head section.
    pub fn head(&self) -> &Da3HeadConfig {
        &self.config.head
    }

    /// Mono or metric, from the model name.
    pub fn variant(&self) -> Da3Variant {
        if self.model_name.contains("metric") {
            Da3Variant::Metric
        } else {
            Da3Variant::Mono
        }
    }

    /// Parses the text of an official `config.json` (see the module docs for what is accepted)
    /// and checks that this port implements the model. The error says what is wrong.
    pub fn from_json(text: &str) -> Result<Self, String> {
        let value: serde_json::Value = serde_json::from_str(text).map_err(|e| format!("not valid JSON: {e}"))?;
        let obj = value.as_object().ok_or("not a JSON object")?;
        let Some(name) = obj.get("model_name") else {
            let mut keys: Vec<&str> = obj.keys().map(String::as_str).take(8).collect();
            keys.sort_unstable();
            return Err(format!(
                "not a Depth Anything 3 config.json: no `model_name` key (keys: {}); expected the file \
                 saved with the depth-anything/DA3MONO-LARGE or DA3METRIC-LARGE weights",
                keys.join(", ")
            ));
        };
        let name = name.as_str().ok_or("`model_name` is not a string")?.to_owned();
        let lower = name.to_ascii_lowercase();
        if lower.contains("nested") || obj.contains_key("anyview") {
            return Err(format!(
                "model `{name}` is a nested any-view + metric model; only the single-view \
                 da3mono-large and da3metric-large models are supported"
            ));
        }
        if !lower.contains("mono") && !lower.contains("metric") {
            return Err(format!(
                "model `{name}` is an any-view model (camera tokens, alternating attention, DualDPT \
                 head); only the single-view da3mono-large and da3metric-large models are supported"
            ));
        }
        let arch = obj.get("config").and_then(|c| c.as_object());
        let section =
            |key: &str| -> Option<&serde_json::Value> { arch.and_then(|a| a.get(key)).or_else(|| obj.get(key)) };
        for key in ["cam_dec", "cam_enc", "gs_head"] {
            if section(key).is_some_and(|v| !v.is_null()) {
                return Err(format!(
                    "model `{name}` has a `{key}` section: an any-view model, not supported"
                ));
            }
        }
        let raw_net: RawNet = match section("net") {
            Some(v) => serde_json::from_value(v.clone()).map_err(|e| format!("`net`: {e}"))?,
            None => RawNet::default(),
        };
        let raw_head: RawHead = match section("head") {
            Some(v) => serde_json::from_value(v.clone()).map_err(|e| format!("`head`: {e}"))?,
            None => RawHead::default(),
        };
        let known_large = matches!(lower.as_str(), "da3mono-large" | "da3metric-large");
        if section("net").is_none() && !known_large {
            return Err(format!(
                "model `{name}` is not a released preset (da3mono-large, da3metric-large) and the \
                 file has no `config.net` section describing it"
            ));
        }
        let net_name = raw_net.name.clone().unwrap_or_else(|| "vitl".into());
        if net_name == "vitg" {
            return Err("backbone `vitg` (SwiGLU feed-forward) is not supported".into());
        }
        let preset = vit_preset(&net_name);
        let need = |v: Option<usize>, key: &str, p: Option<usize>| -> Result<usize, String> {
            v.or(p)
                .ok_or_else(|| format!("`net.{key}` is required for backbone `{net_name}` (not vits/vitb/vitl)"))
        };
        let out_layers = raw_net.out_layers.unwrap_or_else(|| vec![4, 11, 17, 23]);
        let out_layers: [usize; 4] = out_layers
            .as_slice()
            .try_into()
            .map_err(|_| format!("`net.out_layers` must list 4 blocks, got {out_layers:?}"))?;
        let net = Da3NetConfig {
            embed_dim: need(raw_net.embed_dim, "embed_dim", preset.map(|p| p.0))?,
            depth: need(raw_net.depth, "depth", preset.map(|p| p.1))?,
            num_heads: need(raw_net.num_heads, "num_heads", preset.map(|p| p.2))?,
            name: net_name,
            mlp_ratio: raw_net.mlp_ratio.unwrap_or(4.0),
            img_size: raw_net.img_size.unwrap_or(518),
            patch_size: raw_net.patch_size.unwrap_or(14),
            out_layers,
            alt_start: raw_net.alt_start.unwrap_or(-1),
            qknorm_start: raw_net.qknorm_start.unwrap_or(-1),
            rope_start: raw_net.rope_start.unwrap_or(-1),
            cat_token: raw_net.cat_token.unwrap_or(false),
        };
        let out_channels = raw_head.out_channels.unwrap_or_else(|| vec![256, 512, 1024, 1024]);
        let out_channels: [usize; 4] = out_channels
            .as_slice()
            .try_into()
            .map_err(|_| format!("`head.out_channels` must have 4 entries, got {out_channels:?}"))?;
        let head = Da3HeadConfig {
            dim_in: raw_head.dim_in.unwrap_or(net.embed_dim),
            output_dim: raw_head.output_dim.unwrap_or(1),
            features: raw_head.features.unwrap_or(256),
            out_channels,
            patch_size: raw_head.patch_size.unwrap_or(14),
            activation: raw_head.activation.unwrap_or_else(|| "exp".into()),
            use_sky_head: raw_head.use_sky_head.unwrap_or(true),
            sky_activation: raw_head.sky_activation.unwrap_or_else(|| "relu".into()),
            pos_embed: raw_head.pos_embed.unwrap_or(false),
            down_ratio: raw_head.down_ratio.unwrap_or(1),
            use_ln_for_heads: raw_head.use_ln_for_heads.unwrap_or(false),
            norm_type: raw_head.norm_type.unwrap_or_else(|| "idt".into()),
        };
        let cfg = Self {
            model_name: name,
            config: Da3Arch { net, head },
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks that the configuration is one this port implements and is self-consistent.
    pub fn validate(&self) -> Result<(), String> {
        let (n, h) = (&self.config.net, &self.config.head);
        let name = &self.model_name;
        if n.alt_start != -1 || n.qknorm_start != -1 || n.rope_start != -1 || n.cat_token {
            return Err(format!(
                "model `{name}` uses any-view backbone features (alt_start {}, qknorm_start {}, \
                 rope_start {}, cat_token {}); only single-view models (all off) are supported",
                n.alt_start, n.qknorm_start, n.rope_start, n.cat_token
            ));
        }
        if n.embed_dim == 0 || n.num_heads == 0 || n.embed_dim % n.num_heads != 0 {
            return Err(format!(
                "`net.embed_dim` {} must be a positive multiple of `net.num_heads` {}",
                n.embed_dim, n.num_heads
            ));
        }
        if n.patch_size == 0 || n.img_size < n.patch_size {
            return Err(format!(
                "`net.img_size` {} must be at least `net.patch_size` {}",
                n.img_size, n.patch_size
            ));
        }
        let hidden = n.embed_dim as f64 * n.mlp_ratio;
        if !(hidden >= 1.0 && hidden.fract() == 0.0) {
            return Err(format!("`net.mlp_ratio` {} gives a non-integer MLP width", n.mlp_ratio));
        }
        let mut sorted = n.out_layers;
        sorted.sort_unstable();
        if sorted.windows(2).any(|w| w[0] == w[1]) {
            return Err(format!(
                "`net.out_layers` {:?} must name 4 distinct blocks",
                n.out_layers
            ));
        }
        if let Some(l) = n.out_layers.iter().find(|&&l| l >= n.depth) {
            return Err(format!(
                "`net.out_layers` names block {l}, but the backbone has {} blocks",
                n.depth
            ));
        }
        if h.dim_in != n.embed_dim {
            return Err(format!(
                "`head.dim_in` {} differs from `net.embed_dim` {}",
                h.dim_in, n.embed_dim
            ));
        }
        if h.patch_size != n.patch_size {
            return Err(format!(
                "`head.patch_size` {} differs from `net.patch_size` {}",
                h.patch_size, n.patch_size
            ));
        }
        if h.output_dim != 1 || h.activation != "exp" {
            return Err(format!(
                "head with output_dim {} and activation `{}`: only the single-channel `exp` depth head \
                 of the mono / metric models is supported",
                h.output_dim, h.activation
            ));
        }
        if !h.use_sky_head || !matches!(h.sky_activation.as_str(), "relu" | "sigmoid" | "linear") {
            return Err(format!(
                "sky head (use_sky_head {}, activation `{}`) not supported",
                h.use_sky_head, h.sky_activation
            ));
        }
        if h.pos_embed || h.down_ratio != 1 || h.use_ln_for_heads || h.norm_type != "idt" {
            return Err(format!(
                "head options pos_embed {}, down_ratio {}, use_ln_for_heads {}, norm_type `{}` are not \
                 supported (the mono / metric models use false, 1, false, `idt`)",
                h.pos_embed, h.down_ratio, h.use_ln_for_heads, h.norm_type
            ));
        }
        if h.features < 2 || h.features % 2 != 0 || h.out_channels.contains(&0) {
            return Err(format!(
                "`head.features` {} must be even and the out_channels positive",
                h.features
            ));
        }
        Ok(())
    }

    /// Side of the position-embedding grid (`img_size / patch_size`).
    pub fn pos_grid(&self) -> usize {
        self.config.net.img_size / self.config.net.patch_size
    }

    /// MLP hidden width.
    pub fn mlp_hidden(&self) -> usize {
        (self.config.net.embed_dim as f64 * self.config.net.mlp_ratio) as usize
    }
}
