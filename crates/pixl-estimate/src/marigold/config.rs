//! The configuration files of a diffusers-format Marigold-IID checkpoint, read and checked
//! before any weight is touched: `model_index.json` (pipeline class, targets and their colour
//! spaces, default steps and resolution), `unet/config.json` (the SD2-family
//! `UNet2DConditionModel`, [`UnetConfig`]), `vae/config.json` and `text_encoder/config.json`.
//!
//! Every `Err` is a sentence naming the key that is missing or not supported, so a folder of
//! another model (a depth Marigold, Stable Diffusion itself) is refused up front. A normals
//! checkpoint is read too: [`PipelineKind`] tells the two pipelines apart.
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

/// Which block a level of the UNet's encoder half is (diffusers' `down_block_types`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DownBlockType {
    /// ResNets, each followed by a `Transformer2DModel`.
    CrossAttnDownBlock2D,
    /// ResNets only.
    DownBlock2D,
}

/// Which block a level of the UNet's decoder half is (diffusers' `up_block_types`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UpBlockType {
    CrossAttnUpBlock2D,
    UpBlock2D,
}

/// The UNet's `config.json` (diffusers `UNet2DConditionModel`), the Stable Diffusion 2 family:
/// the fields keep diffusers' names, and those diffusers accepts as an int or a per-block list
/// are stored per block. [`UnetConfig::from_json`] refuses every setting that changes the
/// network beyond this family (class or addition embeddings, another mid block, dual or
/// cross-only attention, per-layer transformer depths, …).
#[derive(Clone, Debug, PartialEq)]
pub struct UnetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    /// `2x − 1` on the input before `conv_in`.
    pub center_input_sample: bool,
    /// The sinusoidal timestep embedding as `[cos, sin]` (true) or `[sin, cos]`.
    pub flip_sin_to_cos: bool,
    /// Frequencies `exp(−ln(10⁴)·k / (half − freq_shift))`.
    pub freq_shift: f64,
    pub down_block_types: Vec<DownBlockType>,
    /// Listed from the lowest resolution up, as diffusers stores them.
    pub up_block_types: Vec<UpBlockType>,
    pub block_out_channels: Vec<usize>,
    /// ResNets per down block (up blocks have one more), per block.
    pub layers_per_block: Vec<usize>,
    /// Padding of the stride-2 3×3 downsampling convolutions (0: one zero row and column added
    /// at the bottom and right first, as diffusers does).
    pub downsample_padding: usize,
    /// The mid block's ResNets divide their output by this.
    pub mid_block_scale_factor: f64,
    /// GroupNorm groups of every ResNet, transformer input and `conv_norm_out`.
    pub norm_num_groups: usize,
    /// GroupNorm epsilon of the ResNets and `conv_norm_out` (the transformers' GroupNorm uses
    /// 1e-6 and their LayerNorms 1e-5, as in diffusers).
    pub norm_eps: f64,
    /// Width of the text conditioning the cross-attention reads.
    pub cross_attention_dim: usize,
    /// `BasicTransformerBlock`s per `Transformer2DModel`, per block (the mid block uses the last).
    pub transformer_layers_per_block: Vec<usize>,
    /// Per block, the **number of attention heads** (the mid block uses the last): diffusers
    /// reads `num_attention_heads or attention_head_dim` as the head count, refuses a non-null
    /// `num_attention_heads`, and SD2 configs store the heads here (`[5, 10, 20, 20]`, heads of
    /// dimension 64).
    pub attention_head_dim: Vec<usize>,
    /// `proj_in` / `proj_out` of the transformers as linear layers (true) or 1×1 convolutions.
    pub use_linear_projection: bool,
    /// diffusers computes the attention scores in f32 when set; without effect here (all f32).
    pub upcast_attention: bool,
}

impl UnetConfig {
    /// Stable Diffusion 2's UNet (`stabilityai/stable-diffusion-2`, the network Marigold
    /// fine-tunes) with `in_channels` → `out_channels`.
    pub fn sd2(in_channels: usize, out_channels: usize) -> Self {
        use DownBlockType::*;
        use UpBlockType::*;
        Self {
            in_channels,
            out_channels,
            center_input_sample: false,
            flip_sin_to_cos: true,
            freq_shift: 0.0,
            down_block_types: vec![
                CrossAttnDownBlock2D,
                CrossAttnDownBlock2D,
                CrossAttnDownBlock2D,
                DownBlock2D,
            ],
            up_block_types: vec![UpBlock2D, CrossAttnUpBlock2D, CrossAttnUpBlock2D, CrossAttnUpBlock2D],
            block_out_channels: vec![320, 640, 1280, 1280],
            layers_per_block: vec![2; 4],
            downsample_padding: 1,
            mid_block_scale_factor: 1.0,
            norm_num_groups: 32,
            norm_eps: 1e-5,
            cross_attention_dim: 1024,
            transformer_layers_per_block: vec![1; 4],
            attention_head_dim: vec![5, 10, 20, 20],
            use_linear_projection: true,
            upcast_attention: false,
        }
    }

    /// Width of the time embedding: `4 · block_out_channels[0]`.
    pub fn time_embed_dim(&self) -> usize {
        4 * self.block_out_channels[0]
    }

    pub fn from_json(text: &str) -> Result<Self, String> {
        let o = parse(text)?;
        let class = str_of(&o, "_class_name").unwrap_or("");
        if class != "UNet2DConditionModel" {
            return Err(format!("_class_name {class:?}: expected UNet2DConditionModel"));
        }
        for (k, ok) in [
            ("act_fn", "silu"),
            ("time_embedding_type", "positional"),
            ("resnet_time_scale_shift", "default"),
            ("attention_type", "default"),
        ] {
            match o.get(k) {
                None | Some(Value::Null) => {}
                Some(Value::String(v)) if v == ok => {}
                Some(v) => return Err(format!("`{k}` {v} is not supported (expected {ok:?})")),
            }
        }
        match o.get("mid_block_type") {
            None => {}
            Some(Value::String(v)) if v == "UNetMidBlock2DCrossAttn" => {}
            Some(Value::Null) => {
                return Err("`mid_block_type` null (a UNet without a mid block) is not supported".into())
            }
            Some(v) => {
                return Err(format!(
                    "`mid_block_type` {v} is not supported (expected \"UNetMidBlock2DCrossAttn\")"
                ))
            }
        }
        for k in [
            "class_embed_type",
            "addition_embed_type",
            "addition_time_embed_dim",
            "encoder_hid_dim",
            "encoder_hid_dim_type",
            "time_cond_proj_dim",
            "num_class_embeds",
            "projection_class_embeddings_input_dim",
            "time_embedding_dim",
            "time_embedding_act_fn",
            "timestep_post_act",
            "cross_attention_norm",
            "reverse_transformer_layers_per_block",
        ] {
            if o.get(k).is_some_and(|v| !v.is_null()) {
                return Err(format!("`{k}` is set; this UNet variant is not supported"));
            }
        }
        if o.get("num_attention_heads").is_some_and(|v| !v.is_null()) {
            return Err(
                "`num_attention_heads` is set: diffusers refuses it too (the head count is read from \
`attention_head_dim`)"
                    .into(),
            );
        }
        for k in [
            "dual_cross_attention",
            "class_embeddings_concat",
            "resnet_skip_time_act",
            "mid_block_only_cross_attention",
        ] {
            if bool_of(&o, k, false)? {
                return Err(format!("`{k}` true is not supported"));
            }
        }
        match o.get("only_cross_attention") {
            None | Some(Value::Null) | Some(Value::Bool(false)) => {}
            Some(Value::Array(a)) if a.iter().all(|v| v == &Value::Bool(false)) => {}
            Some(v) => return Err(format!("`only_cross_attention` {v} is not supported (only false)")),
        }
        for k in ["conv_in_kernel", "conv_out_kernel"] {
            let v = usize_of(&o, k, Some(3))?;
            if v != 3 {
                return Err(format!("`{k}` {v} is not supported (expected 3)"));
            }
        }
        let out_scale = f64_of(&o, "resnet_out_scale_factor", 1.0)?;
        if out_scale != 1.0 {
            return Err(format!(
                "`resnet_out_scale_factor` {out_scale} is not supported (expected 1)"
            ));
        }

        let block_out_channels = usize_list(&o, "block_out_channels")?;
        let n = block_out_channels.len();
        let down_block_types = str_list(&o, "down_block_types")?
            .iter()
            .enumerate()
            .map(|(i, t)| match t.as_str() {
                "CrossAttnDownBlock2D" => Ok(DownBlockType::CrossAttnDownBlock2D),
                "DownBlock2D" => Ok(DownBlockType::DownBlock2D),
                other => Err(format!("down_block_types[{i}] {other:?} is not supported")),
            })
            .collect::<Result<Vec<_>, _>>()?;
        let up_block_types = str_list(&o, "up_block_types")?
            .iter()
            .enumerate()
            .map(|(i, t)| match t.as_str() {
                "CrossAttnUpBlock2D" => Ok(UpBlockType::CrossAttnUpBlock2D),
                "UpBlock2D" => Ok(UpBlockType::UpBlock2D),
                other => Err(format!("up_block_types[{i}] {other:?} is not supported")),
            })
            .collect::<Result<Vec<_>, _>>()?;
        if n == 0 || down_block_types.len() != n || up_block_types.len() != n {
            return Err(format!(
                "block_out_channels ({n}), down_block_types ({}) and up_block_types ({}) must have the same positive length",
                down_block_types.len(),
                up_block_types.len()
            ));
        }
        if let Some(i) = block_out_channels.iter().position(|&c| c == 0) {
            return Err(format!("block_out_channels[{i}] is 0"));
        }
        let cfg = Self {
            in_channels: usize_of(&o, "in_channels", Some(4))?,
            out_channels: usize_of(&o, "out_channels", Some(4))?,
            center_input_sample: bool_of(&o, "center_input_sample", false)?,
            flip_sin_to_cos: bool_of(&o, "flip_sin_to_cos", true)?,
            freq_shift: f64_of(&o, "freq_shift", 0.0)?,
            down_block_types,
            up_block_types,
            layers_per_block: per_block(&o, "layers_per_block", 2, n)?,
            downsample_padding: usize_of(&o, "downsample_padding", Some(1))?,
            mid_block_scale_factor: f64_of(&o, "mid_block_scale_factor", 1.0)?,
            norm_num_groups: match o.get("norm_num_groups") {
                Some(Value::Null) => return Err("`norm_num_groups` null (no GroupNorm) is not supported".into()),
                _ => usize_of(&o, "norm_num_groups", Some(32))?,
            },
            norm_eps: f64_of(&o, "norm_eps", 1e-5)?,
            cross_attention_dim: match o.get("cross_attention_dim") {
                Some(Value::Array(_)) => {
                    return Err("a per-block `cross_attention_dim` list is not supported (give one integer)".into())
                }
                _ => usize_of(&o, "cross_attention_dim", Some(1280))?,
            },
            transformer_layers_per_block: per_block(&o, "transformer_layers_per_block", 1, n)?,
            attention_head_dim: per_block(&o, "attention_head_dim", 8, n)?,
            use_linear_projection: bool_of(&o, "use_linear_projection", false)?,
            upcast_attention: bool_of(&o, "upcast_attention", false)?,
            block_out_channels,
        };
        cfg.check()?;
        Ok(cfg)
    }

    /// The checks that need several fields: group and head counts that divide the widths they
    /// split, positive sizes.
    fn check(&self) -> Result<(), String> {
        let g = self.norm_num_groups;
        if g == 0 || self.block_out_channels.iter().any(|c| !c.is_multiple_of(g)) {
            return Err(format!(
                "norm_num_groups {g} must divide every block's channels {:?}",
                self.block_out_channels
            ));
        }
        if self.in_channels == 0 || self.out_channels == 0 || self.cross_attention_dim == 0 {
            return Err("in_channels, out_channels and cross_attention_dim must be positive".into());
        }
        let n = self.block_out_channels.len();
        let attention = (0..n)
            .filter(|&i| {
                self.down_block_types[i] == DownBlockType::CrossAttnDownBlock2D
                    || self.up_block_types[n - 1 - i] == UpBlockType::CrossAttnUpBlock2D
            })
            .chain([n - 1]); // the mid block
        for i in attention {
            let (heads, c) = (self.attention_head_dim[i], self.block_out_channels[i]);
            if heads == 0 || c % heads != 0 {
                return Err(format!(
                    "attention_head_dim[{i}] = {heads} (the number of heads) does not divide block_out_channels[{i}] = {c}"
                ));
            }
            if self.transformer_layers_per_block[i] == 0 {
                return Err(format!("transformer_layers_per_block[{i}] is 0"));
            }
        }
        if let Some(i) = self.layers_per_block.iter().position(|&l| l == 0) {
            return Err(format!("layers_per_block[{i}] is 0"));
        }
        Ok(())
    }
}

/// A setting diffusers takes as an int (the same for every block) or a list with one integer
/// per block; nested lists (per layer) are refused.
fn per_block(o: &Obj, k: &str, default: usize, n: usize) -> Result<Vec<usize>, String> {
    match o.get(k) {
        None | Some(Value::Null) => Ok(vec![default; n]),
        Some(Value::Number(x)) => x
            .as_u64()
            .map(|x| vec![x as usize; n])
            .ok_or_else(|| format!("`{k}` must be a non-negative integer, found {x}")),
        Some(Value::Array(a)) if a.iter().any(Value::is_array) => Err(format!(
            "`{k}` with one entry per layer (nested lists) is not supported"
        )),
        Some(Value::Array(_)) => {
            let v = usize_list(o, k)?;
            if v.len() == n {
                Ok(v)
            } else {
                Err(format!("`{k}` must have one entry per block ({n}), found {}", v.len()))
            }
        }
        Some(v) => Err(format!("`{k}` must be an integer or a list, found {v}")),
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
