//! The configuration files of a diffusers-format Marigold-IID checkpoint, read and checked
//! before any weight is touched: `model_index.json` (pipeline class, targets and their colour
//! spaces, default steps and resolution), `unet/config.json` (mapped onto candle-transformers'
//! `UNet2DConditionModelConfig`), `vae/config.json` and `text_encoder/config.json`.
//!
//! Every `Err` is a sentence naming the key that is missing or not supported, so a folder of
//! another model (a depth Marigold, Stable Diffusion itself) is refused up front. A normals
//! checkpoint is read too: [`PipelineKind`] tells the two pipelines apart.
use candle_transformers::models::stable_diffusion::unet_2d::{BlockConfig, UNet2DConditionModelConfig};
use serde_json::{Map, Value};

type Obj = Map<String, Value>;

fn parse(text: &str) -> Result<Obj, String> {
    let v: Value = serde_json::from_str(text).map_err(|e| format!("not valid JSON: {e}"))?;
    match v {
        Value::Object(o) => Ok(o),
        _ => Err("not a JSON object".into()),
    }
}

fn usize_of(o: &Obj, k: &str, default: Option<usize>) -> Result<usize, String> {
    match o.get(k) {
        None | Some(Value::Null) => default.ok_or_else(|| format!("`{k}` is missing")),
        Some(v) => v
            .as_u64()
            .map(|x| x as usize)
            .ok_or_else(|| format!("`{k}` must be a non-negative integer, found {v}")),
    }
}

fn f64_of(o: &Obj, k: &str, default: f64) -> Result<f64, String> {
    match o.get(k) {
        None | Some(Value::Null) => Ok(default),
        Some(v) => v.as_f64().ok_or_else(|| format!("`{k}` must be a number, found {v}")),
    }
}

fn bool_of(o: &Obj, k: &str, default: bool) -> Result<bool, String> {
    match o.get(k) {
        None | Some(Value::Null) => Ok(default),
        Some(v) => v
            .as_bool()
            .ok_or_else(|| format!("`{k}` must be true or false, found {v}")),
    }
}

fn str_of<'a>(o: &'a Obj, k: &str) -> Option<&'a str> {
    o.get(k).and_then(Value::as_str)
}

fn usize_list(o: &Obj, k: &str) -> Result<Vec<usize>, String> {
    let a = o
        .get(k)
        .and_then(Value::as_array)
        .ok_or_else(|| format!("`{k}` must be a list of integers"))?;
    a.iter()
        .map(|v| {
            v.as_u64()
                .map(|x| x as usize)
                .ok_or_else(|| format!("`{k}` must be a list of integers"))
        })
        .collect()
}

fn str_list(o: &Obj, k: &str) -> Result<Vec<String>, String> {
    let a = o
        .get(k)
        .and_then(Value::as_array)
        .ok_or_else(|| format!("`{k}` must be a list of names"))?;
    a.iter()
        .map(|v| {
            v.as_str()
                .map(str::to_string)
                .ok_or_else(|| format!("`{k}` must be a list of names"))
        })
        .collect()
}

/// Colour space a target is predicted in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PredictionSpace {
    /// sRGB-encoded values in [0, 1] (Appearance albedo).
    Srgb,
    /// Linear values in [0, 1].
    Linear,
    /// Three single-channel maps stacked as RGB (Appearance "material": roughness, metallicity).
    Stack,
    /// Unit surface normals in [−1, 1], camera space (the normals pipeline's one target).
    Normals,
}

/// Which Marigold pipeline a checkpoint is, from `model_index.json`'s `_class_name`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PipelineKind {
    /// `MarigoldIntrinsicsPipeline` (`prediction_type` "intrinsics"): Marigold-IID.
    Intrinsics,
    /// `MarigoldNormalsPipeline` (`prediction_type` "normals"): one 3-channel normals target.
    Normals,
}

impl PipelineKind {
    /// The diffusers pipeline class.
    pub fn class_name(self) -> &'static str {
        match self {
            PipelineKind::Intrinsics => "MarigoldIntrinsicsPipeline",
            PipelineKind::Normals => "MarigoldNormalsPipeline",
        }
    }

    fn prediction_type(self) -> &'static str {
        match self {
            PipelineKind::Intrinsics => "intrinsics",
            PipelineKind::Normals => "normals",
        }
    }
}

/// One predicted target (one 4-channel latent, one RGB decode).
#[derive(Clone, Debug, PartialEq)]
pub struct Target {
    pub name: String,
    pub space: PredictionSpace,
    /// For [`PredictionSpace::Stack`]: the names of the three channels (`None` = unused).
    pub sub_targets: Vec<Option<String>>,
    /// Predicted up to an unknown scale (lighting shading/residual).
    pub up_to_scale: bool,
}

/// `model_index.json` of a `MarigoldIntrinsicsPipeline` or `MarigoldNormalsPipeline` checkpoint.
#[derive(Clone, Debug, PartialEq)]
pub struct PipelineConfig {
    pub kind: PipelineKind,
    /// IID: from `target_properties`; normals: one target `normals` ([`PredictionSpace::Normals`]).
    pub targets: Vec<Target>,
    pub default_steps: Option<usize>,
    pub default_resolution: Option<usize>,
    /// Normals: whether the decoded z spans [−1, 1] (`true`, diffusers' default) or only [0, 1]
    /// (`false`: the decoded z is mapped by `z/2 + 1/2`). Always `true` for IID.
    pub use_full_z_range: bool,
}

impl PipelineConfig {
    pub fn from_json(text: &str) -> Result<Self, String> {
        let o = parse(text)?;
        let class = str_of(&o, "_class_name").unwrap_or("");
        let kind = [PipelineKind::Intrinsics, PipelineKind::Normals]
            .into_iter()
            .find(|k| k.class_name() == class)
            .ok_or_else(|| {
                format!(
                    "_class_name {class:?}: not a Marigold intrinsics (IID) checkpoint, which is a \
MarigoldIntrinsicsPipeline, nor a Marigold normals one (MarigoldNormalsPipeline)"
                )
            })?;
        if let Some(p) = str_of(&o, "prediction_type") {
            if p != kind.prediction_type() {
                return Err(format!(
                    "prediction_type {p:?}: expected {:?} for a {class}",
                    kind.prediction_type()
                ));
            }
        }
        let default_steps = usize_of(&o, "default_denoising_steps", Some(0)).ok().filter(|s| *s > 0);
        let default_resolution = usize_of(&o, "default_processing_resolution", Some(0))
            .ok()
            .filter(|s| *s > 0);
        if kind == PipelineKind::Normals {
            return Ok(Self {
                kind,
                targets: vec![Target {
                    name: "normals".into(),
                    space: PredictionSpace::Normals,
                    sub_targets: Vec::new(),
                    up_to_scale: false,
                }],
                default_steps,
                default_resolution,
                use_full_z_range: bool_of(&o, "use_full_z_range", true)?,
            });
        }
        let props = o
            .get("target_properties")
            .and_then(Value::as_object)
            .ok_or("`target_properties` is missing")?;
        let names = str_list(props, "target_names")?;
        if names.is_empty() {
            return Err("`target_properties.target_names` is empty".into());
        }
        let mut targets = Vec::with_capacity(names.len());
        for name in names {
            let p = props.get(&name).and_then(Value::as_object);
            let space = match p.and_then(|p| str_of(p, "prediction_space")).unwrap_or("srgb") {
                "srgb" => PredictionSpace::Srgb,
                "linear" => PredictionSpace::Linear,
                "stack" => PredictionSpace::Stack,
                other => {
                    return Err(format!(
                        "target_properties.{name}.prediction_space {other:?} is not supported"
                    ))
                }
            };
            let sub_targets = match p.and_then(|p| p.get("sub_target_names")).and_then(Value::as_array) {
                Some(a) => a.iter().map(|v| v.as_str().map(str::to_string)).collect(),
                None => Vec::new(),
            };
            if space == PredictionSpace::Stack && sub_targets.len() != 3 {
                return Err(format!("target_properties.{name}.sub_target_names must have 3 entries"));
            }
            let up_to_scale = p
                .map(|p| bool_of(p, "up_to_scale", false))
                .transpose()?
                .unwrap_or(false);
            targets.push(Target {
                name,
                space,
                sub_targets,
                up_to_scale,
            });
        }
        Ok(Self {
            kind,
            targets,
            default_steps,
            default_resolution,
            use_full_z_range: true,
        })
    }

    /// The target names in latent order.
    pub fn target_names(&self) -> Vec<&str> {
        self.targets.iter().map(|t| t.name.as_str()).collect()
    }
}

/// The UNet's `config.json`, mapped onto candle-transformers' config; refuses anything the SD2
/// UNet of Marigold does not use.
#[derive(Clone, Debug)]
pub struct UnetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub candle: UNet2DConditionModelConfig,
}

impl UnetConfig {
    pub fn from_json(text: &str) -> Result<Self, String> {
        let o = parse(text)?;
        let class = str_of(&o, "_class_name").unwrap_or("");
        if class != "UNet2DConditionModel" {
            return Err(format!("_class_name {class:?}: expected UNet2DConditionModel"));
        }
        for (k, ok) in [
            ("act_fn", "silu"),
            ("time_embedding_type", "positional"),
            ("mid_block_type", "UNetMidBlock2DCrossAttn"),
            ("resnet_time_scale_shift", "default"),
        ] {
            if let Some(v) = str_of(&o, k) {
                if v != ok {
                    return Err(format!("`{k}` {v:?} is not supported (expected {ok:?})"));
                }
            }
        }
        for k in [
            "class_embed_type",
            "addition_embed_type",
            "encoder_hid_dim",
            "time_cond_proj_dim",
            "num_class_embeds",
        ] {
            if o.get(k).is_some_and(|v| !v.is_null()) {
                return Err(format!("`{k}` is set; this UNet variant is not supported"));
            }
        }
        for k in ["dual_cross_attention", "only_cross_attention", "center_input_sample"] {
            if bool_of(&o, k, false)? {
                return Err(format!("`{k}` true is not supported"));
            }
        }
        let channels = usize_list(&o, "block_out_channels")?;
        let down = str_list(&o, "down_block_types")?;
        let up = str_list(&o, "up_block_types")?;
        let n = channels.len();
        if n == 0 || down.len() != n || up.len() != n {
            return Err(format!(
                "block_out_channels ({n}), down_block_types ({}) and up_block_types ({}) must have the same positive length",
                down.len(),
                up.len()
            ));
        }
        let layers = |k: &str| -> Result<Vec<usize>, String> {
            match o.get(k) {
                None | Some(Value::Null) => Ok(vec![1; n]),
                Some(Value::Number(x)) => Ok(vec![x.as_u64().unwrap_or(1) as usize; n]),
                Some(Value::Array(_)) => {
                    let v = usize_list(&o, k)?;
                    if v.len() == n {
                        Ok(v)
                    } else {
                        Err(format!("`{k}` must have one entry per block ({n})"))
                    }
                }
                Some(v) => Err(format!("`{k}` must be an integer or a list, found {v}")),
            }
        };
        let transformer_layers = layers("transformer_layers_per_block")?;
        // diffusers: `num_attention_heads or attention_head_dim` (SD2 stores heads in the latter).
        let heads_key = if o.get("num_attention_heads").is_some_and(|v| !v.is_null()) {
            "num_attention_heads"
        } else {
            "attention_head_dim"
        };
        let heads = layers(heads_key)?;
        let mut blocks = Vec::with_capacity(n);
        for i in 0..n {
            let cross = match down[i].as_str() {
                "CrossAttnDownBlock2D" => true,
                "DownBlock2D" => false,
                other => return Err(format!("down_block_types[{i}] {other:?} is not supported")),
            };
            let want_up = if cross { "CrossAttnUpBlock2D" } else { "UpBlock2D" };
            if up[n - 1 - i] != want_up {
                return Err(format!(
                    "up_block_types[{}] {:?} does not mirror down_block_types[{i}] {:?}",
                    n - 1 - i,
                    up[n - 1 - i],
                    down[i]
                ));
            }
            if heads[i] == 0 || channels[i] % heads[i] != 0 {
                return Err(format!(
                    "{heads_key}[{i}] = {} does not divide block_out_channels[{i}] = {}",
                    heads[i], channels[i]
                ));
            }
            blocks.push(BlockConfig {
                out_channels: channels[i],
                use_cross_attn: cross.then_some(transformer_layers[i]),
                attention_head_dim: heads[i],
            });
        }
        // candle-transformers 0.11.1's DownBlock2D / UpBlock2D build their ResNets with 32
        // groups whatever the config says; SD2 (and so Marigold) uses 32.
        let norm_num_groups = usize_of(&o, "norm_num_groups", Some(32))?;
        if norm_num_groups != 32 {
            return Err(format!(
                "norm_num_groups {norm_num_groups} is not supported (the SD2 UNet uses 32)"
            ));
        }
        if channels.iter().any(|c| c % norm_num_groups != 0) {
            return Err(format!(
                "norm_num_groups {norm_num_groups} must divide every block's channels"
            ));
        }
        let candle = UNet2DConditionModelConfig {
            center_input_sample: false,
            flip_sin_to_cos: bool_of(&o, "flip_sin_to_cos", true)?,
            freq_shift: f64_of(&o, "freq_shift", 0.0)?,
            blocks,
            layers_per_block: usize_of(&o, "layers_per_block", Some(2))?,
            downsample_padding: usize_of(&o, "downsample_padding", Some(1))?,
            mid_block_scale_factor: f64_of(&o, "mid_block_scale_factor", 1.0)?,
            norm_num_groups,
            norm_eps: f64_of(&o, "norm_eps", 1e-5)?,
            cross_attention_dim: usize_of(&o, "cross_attention_dim", Some(1280))?,
            // candle-transformers 0.11.1's sliced attention fails on shapes (rank error), so the
            // full score matrix is formed: heads × N² f32, about 1 GB at 768 px (N = 96·72).
            sliced_attention_size: None,
            use_linear_projection: bool_of(&o, "use_linear_projection", false)?,
        };
        Ok(Self {
            in_channels: usize_of(&o, "in_channels", Some(4))?,
            out_channels: usize_of(&o, "out_channels", Some(4))?,
            candle,
        })
    }
}

/// The VAE's `config.json` (diffusers `AutoencoderKL`).
#[derive(Clone, Debug, PartialEq)]
pub struct VaeConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub block_out_channels: Vec<usize>,
    pub layers_per_block: usize,
    pub latent_channels: usize,
    pub norm_num_groups: usize,
    pub scaling_factor: f64,
    pub use_quant_conv: bool,
    pub use_post_quant_conv: bool,
}

impl VaeConfig {
    pub fn from_json(text: &str) -> Result<Self, String> {
        let o = parse(text)?;
        let class = str_of(&o, "_class_name").unwrap_or("");
        if class != "AutoencoderKL" {
            return Err(format!("_class_name {class:?}: expected AutoencoderKL"));
        }
        let block_out_channels = usize_list(&o, "block_out_channels")?;
        let n = block_out_channels.len();
        for (k, want) in [
            ("down_block_types", "DownEncoderBlock2D"),
            ("up_block_types", "UpDecoderBlock2D"),
        ] {
            if o.contains_key(k) {
                let v = str_list(&o, k)?;
                if v.len() != n || v.iter().any(|t| t != want) {
                    return Err(format!("`{k}` must be {n} × {want:?}"));
                }
            }
        }
        if n == 0 {
            return Err("`block_out_channels` is empty".into());
        }
        if !bool_of(&o, "mid_block_add_attention", true)? {
            return Err("`mid_block_add_attention` false is not supported".into());
        }
        let norm_num_groups = usize_of(&o, "norm_num_groups", Some(32))?;
        if norm_num_groups == 0 || block_out_channels.iter().any(|c| c % norm_num_groups != 0) {
            return Err(format!(
                "norm_num_groups {norm_num_groups} must divide every block's channels"
            ));
        }
        let cfg = Self {
            in_channels: usize_of(&o, "in_channels", Some(3))?,
            out_channels: usize_of(&o, "out_channels", Some(3))?,
            block_out_channels,
            layers_per_block: usize_of(&o, "layers_per_block", Some(1))?,
            latent_channels: usize_of(&o, "latent_channels", Some(4))?,
            norm_num_groups,
            scaling_factor: f64_of(&o, "scaling_factor", 0.18215)?,
            use_quant_conv: bool_of(&o, "use_quant_conv", true)?,
            use_post_quant_conv: bool_of(&o, "use_post_quant_conv", true)?,
        };
        if cfg.in_channels != 3 || cfg.out_channels != 3 {
            return Err("the VAE must map 3 channels to 3 channels".into());
        }
        if !(cfg.scaling_factor.is_finite() && cfg.scaling_factor > 0.0) {
            return Err("`scaling_factor` must be positive".into());
        }
        Ok(cfg)
    }

    /// Spatial downsampling factor, `2^(levels − 1)` (8 for SD).
    pub fn scale_factor(&self) -> usize {
        1 << (self.block_out_channels.len() - 1)
    }
}

/// The CLIP text encoder's `config.json` (transformers `CLIPTextModel`).
#[derive(Clone, Debug, PartialEq)]
pub struct TextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub max_position_embeddings: usize,
    pub layer_norm_eps: f64,
    pub activation: TextActivation,
}

/// The MLP activation of the text encoder.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TextActivation {
    /// `gelu`: exact (erf) GELU (SD2's OpenCLIP ViT-H).
    Gelu,
    /// `quick_gelu`: x·σ(1.702x) (OpenAI CLIP, SD1).
    QuickGelu,
    /// `gelu_new` / `gelu_pytorch_tanh`: the tanh approximation.
    GeluTanh,
}

impl TextConfig {
    pub fn from_json(text: &str) -> Result<Self, String> {
        let o = parse(text)?;
        let activation = match str_of(&o, "hidden_act").unwrap_or("quick_gelu") {
            "gelu" => TextActivation::Gelu,
            "quick_gelu" => TextActivation::QuickGelu,
            "gelu_new" | "gelu_pytorch_tanh" => TextActivation::GeluTanh,
            other => return Err(format!("`hidden_act` {other:?} is not supported")),
        };
        let cfg = Self {
            vocab_size: usize_of(&o, "vocab_size", None)?,
            hidden_size: usize_of(&o, "hidden_size", None)?,
            intermediate_size: usize_of(&o, "intermediate_size", None)?,
            num_hidden_layers: usize_of(&o, "num_hidden_layers", None)?,
            num_attention_heads: usize_of(&o, "num_attention_heads", None)?,
            max_position_embeddings: usize_of(&o, "max_position_embeddings", Some(77))?,
            layer_norm_eps: f64_of(&o, "layer_norm_eps", 1e-5)?,
            activation,
        };
        if cfg.num_attention_heads == 0 || !cfg.hidden_size.is_multiple_of(cfg.num_attention_heads) {
            return Err("`num_attention_heads` must divide `hidden_size`".into());
        }
        if cfg.max_position_embeddings < 2 {
            return Err("`max_position_embeddings` must be at least 2".into());
        }
        Ok(cfg)
    }
}
