//! The network's hyper-parameters (paper §3.3 "Implementation details", Appendix A table
//! "Architecture"), as one serde [`Config`] with named presets.
//!
//! Sections mirror the checkpoint prefixes: `src_encoder` (ViT over `I_S`), `cond_encoder`
//! (ConvNeXt over `C_T`), `trunk` (self-attention blocks with registers and 2D RoPE) and `head`
//! (DPT). `dim` (the paper's `d`) is shared by the ViT, the fused tokens and the trunk.
//!
//! Presets: [`Config::paper`] (ViT-L + ConvNeXt-B + 24-block trunk, 726.4 M parameters with our
//! DPT head; the paper says ≈ 640 M, see the crate README), [`Config::small`] (33.3 M) and
//! [`Config::tiny`] (0.73 M, tests and CPU training). Readouts of the smaller presets are spread
//! over depth as the paper's `{4, 11, 17, 23}` are over 24 blocks ([`spread_readouts`]).
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Patch size `p` of both encoders unless a config says otherwise (the paper's ViT-L/16). The
/// ConvNeXt's strides follow it (stem 4, then one 2× downsampling per stage while the stride is
/// below `p`), so that its grid equals the ViT's.
pub const PATCH: usize = 16;

/// Patch sizes the encoders can share: `4 · 2^k`, `k ≤ 3` (the ConvNeXt has three transitions).
pub const PATCH_SIZES: [usize; 4] = [4, 8, 16, 32];

fn default_patch() -> usize {
    PATCH
}

fn is_default_patch(p: &usize) -> bool {
    *p == PATCH
}

fn is_false(b: &bool) -> bool {
    !*b
}

/// Source encoder (ViT, paper §3.2 "Asymmetric Feature Encoders").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VitConfig {
    /// Number of transformer blocks (ViT-L: 24).
    pub depth: usize,
    /// Attention heads (ViT-L: 16).
    pub heads: usize,
    /// Hidden width of the MLP as a multiple of `dim` (ViT: 4).
    pub mlp_ratio: usize,
    /// Side of the square grid the learned position embedding is stored at; it is resized
    /// bilinearly to each image's grid (paper training resolution 512 / 16 = 32).
    pub pos_grid: usize,
    /// Learned per-channel LayerScale on both residual branches of every block (`ls1.gamma`,
    /// `ls2.gamma`, as DINOv2 has). Default off (our own checkpoints); on when a checkpoint in
    /// the official layout carries them.
    #[serde(default, skip_serializing_if = "is_false")]
    pub layer_scale: bool,
    /// A learned class token (`cls_token`, `(1, 1, d)`) prepended before the blocks and dropped
    /// after them, with its own position-embedding row (`pos_embed` is then
    /// `(1, 1 + pos_grid², d)`, the class token's row first, as in DINOv2). Default off.
    #[serde(default, skip_serializing_if = "is_false")]
    pub cls_token: bool,
}

/// Intrinsics encoder (ConvNeXt, paper §3.2).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConvNextConfig {
    /// Channels of the four stages (ConvNeXt-B: 128, 256, 512, 1024).
    pub dims: [usize; 4],
    /// Blocks per stage (ConvNeXt-B: 3, 3, 27, 3).
    pub depths: [usize; 4],
    /// Initial value of the per-channel layer scale `gamma` (ConvNeXt: 1e-6).
    pub layer_scale_init: f64,
}

/// Transformer trunk (paper §3.2 "Transformer Trunk").
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrunkConfig {
    /// Number of self-attention blocks `L` (paper: 24).
    pub depth: usize,
    /// Attention heads (paper: 16). `dim / heads` must be divisible by 4 (2D RoPE).
    pub heads: usize,
    /// MLP hidden width as a multiple of `dim`.
    pub mlp_ratio: usize,
    /// Learnable register tokens prepended to the patch tokens (paper: 8).
    pub registers: usize,
    /// RoPE base frequency (paper: 100).
    pub rope_base: f64,
    /// Zero-based indices of the blocks whose outputs feed the DPT head (paper: 4, 11, 17, 23).
    /// The last one must be `depth - 1`.
    pub readouts: [usize; 4],
    /// LayerScale in every block (`ls1.gamma`, `ls2.gamma`), as [`VitConfig::layer_scale`].
    #[serde(default, skip_serializing_if = "is_false")]
    pub layer_scale: bool,
}

/// DPT head (paper §3.2 "Modulation Head"), as in DPT / Depth Anything.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DptConfig {
    /// Channels of the four reassembled maps before the 3×3 `layer*_rn` convs (DA ViT-L:
    /// 256, 512, 1024, 1024).
    pub out_channels: [usize; 4],
    /// Fusion width (DPT: 256).
    pub features: usize,
    /// Channels `C'` of the full-resolution map `F` fed to the 1×1 modulation conv (DA: 32).
    pub hidden: usize,
}

/// All hyper-parameters of [`crate::PixlRelight`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// Token width `d` of both encoders' outputs, the fusion and the trunk (paper: 1024).
    pub dim: usize,
    /// Patch size `p`: one token per `p × p` pixels (paper: 16; default 16, and configs or
    /// checkpoints that do not name it mean 16). One of [`PATCH_SIZES`].
    #[serde(default = "default_patch", skip_serializing_if = "is_default_patch")]
    pub patch: usize,
    /// Epsilon of every layer norm.
    pub norm_eps: f64,
    pub src_encoder: VitConfig,
    pub cond_encoder: ConvNextConfig,
    pub trunk: TrunkConfig,
    pub head: DptConfig,
}

/// An invalid configuration or an unreadable config file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("unknown model preset {0:?} (expected tiny, small or paper, or a .toml/.json file)")]
    UnknownPreset(String),
    #[error("cannot read config file {path}: {source}")]
    Io { path: String, source: std::io::Error },
    #[error("cannot parse config file {path}: {msg}")]
    Parse { path: String, msg: String },
    #[error("invalid model config: {0}")]
    Invalid(String),
}

/// Readout indices spread over `depth` blocks as `{4, 11, 17, 23}` are over 24: block
/// `round(f·depth) - 1` for `f ∈ {5/24, 12/24, 18/24, 24/24}`, made strictly increasing.
pub fn spread_readouts(depth: usize) -> [usize; 4] {
    let mut out = [0usize; 4];
    for (i, f) in [5.0, 12.0, 18.0, 24.0].iter().enumerate() {
        let r = ((f / 24.0 * depth as f64).round() as usize).max(1) - 1;
        out[i] = if i > 0 { r.max(out[i - 1] + 1) } else { r };
    }
    out
}

impl Config {
    /// The paper's model: ViT-L source encoder, ConvNeXt-B intrinsics encoder, 24-block trunk
    /// (d = 1024, 16 heads, 8 registers, RoPE base 100, readouts {4, 11, 17, 23}), DPT head with
    /// 256 features.
    pub fn paper() -> Self {
        Self {
            dim: 1024,
            patch: PATCH,
            norm_eps: 1e-6,
            src_encoder: VitConfig {
                depth: 24,
                heads: 16,
                mlp_ratio: 4,
                pos_grid: 32,
                layer_scale: false,
                cls_token: false,
            },
            cond_encoder: ConvNextConfig {
                dims: [128, 256, 512, 1024],
                depths: [3, 3, 27, 3],
                layer_scale_init: 1e-6,
            },
            trunk: TrunkConfig {
                depth: 24,
                heads: 16,
                mlp_ratio: 4,
                registers: 8,
                rope_base: 100.0,
                readouts: [4, 11, 17, 23],
                layer_scale: false,
            },
            head: DptConfig {
                out_channels: [256, 512, 1024, 1024],
                features: 256,
                hidden: 32,
            },
        }
    }

    /// About 33 M parameters: d = 384, 6-block ViT, 8-block trunk, a 1/1/3/1 ConvNeXt.
    pub fn small() -> Self {
        Self {
            dim: 384,
            patch: PATCH,
            norm_eps: 1e-6,
            src_encoder: VitConfig {
                depth: 6,
                heads: 6,
                mlp_ratio: 4,
                pos_grid: 32,
                layer_scale: false,
                cls_token: false,
            },
            cond_encoder: ConvNextConfig {
                dims: [48, 96, 192, 384],
                depths: [1, 1, 3, 1],
                layer_scale_init: 1e-6,
            },
            trunk: TrunkConfig {
                depth: 8,
                heads: 6,
                mlp_ratio: 4,
                registers: 4,
                rope_base: 100.0,
                readouts: spread_readouts(8),
                layer_scale: false,
            },
            head: DptConfig {
                out_channels: [48, 96, 192, 384],
                features: 128,
                hidden: 32,
            },
        }
    }

    /// Under 2 M parameters (about 0.7 M), for tests and CPU training: d = 64, 2 heads.
    /// The layer scale starts at 0.1 rather than 1e-6 so the ConvNeXt blocks matter within a
    /// short CPU run.
    pub fn tiny() -> Self {
        Self {
            dim: 64,
            patch: PATCH,
            norm_eps: 1e-6,
            src_encoder: VitConfig {
                depth: 2,
                heads: 2,
                mlp_ratio: 4,
                pos_grid: 16,
                layer_scale: false,
                cls_token: false,
            },
            cond_encoder: ConvNextConfig {
                dims: [16, 32, 64, 64],
                depths: [1, 1, 1, 1],
                layer_scale_init: 0.1,
            },
            trunk: TrunkConfig {
                depth: 4,
                heads: 2,
                mlp_ratio: 4,
                registers: 4,
                rope_base: 100.0,
                readouts: spread_readouts(4),
                layer_scale: false,
            },
            head: DptConfig {
                out_channels: [16, 32, 64, 64],
                features: 32,
                hidden: 16,
            },
        }
    }

    /// Names accepted by [`Config::preset`].
    pub const PRESETS: [&'static str; 3] = ["tiny", "small", "paper"];

    /// A preset by name (`tiny`, `small`, `paper`).
    pub fn preset(name: &str) -> Result<Self, ConfigError> {
        match name {
            "tiny" => Ok(Self::tiny()),
            "small" => Ok(Self::small()),
            "paper" => Ok(Self::paper()),
            _ => Err(ConfigError::UnknownPreset(name.to_string())),
        }
    }

    /// A preset name, or else a path to a `.toml` or `.json` config file.
    pub fn from_name_or_file(spec: &str) -> Result<Self, ConfigError> {
        if Self::PRESETS.contains(&spec) {
            return Self::preset(spec);
        }
        let path = Path::new(spec);
        if path.extension().is_some() || path.exists() {
            return Self::from_file(path);
        }
        Err(ConfigError::UnknownPreset(spec.to_string()))
    }

    /// Loads a TOML (`.toml`) or JSON (any other extension) config file and validates it.
    pub fn from_file(path: &Path) -> Result<Self, ConfigError> {
        let shown = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: shown.clone(),
            source,
        })?;
        let is_toml = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("toml"));
        let cfg: Self = if is_toml {
            toml::from_str(&text).map_err(|e| ConfigError::Parse {
                path: shown.clone(),
                msg: e.to_string(),
            })?
        } else {
            serde_json::from_str(&text).map_err(|e| ConfigError::Parse {
                path: shown.clone(),
                msg: e.to_string(),
            })?
        };
        cfg.validate()?;
        Ok(cfg)
    }

    /// Parses and validates the JSON form (as stored in checkpoint metadata).
    pub fn from_json(text: &str) -> Result<Self, ConfigError> {
        let cfg: Self = serde_json::from_str(text).map_err(|e| ConfigError::Parse {
            path: "<checkpoint metadata>".into(),
            msg: e.to_string(),
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// The JSON form stored in checkpoint metadata.
    pub fn to_json(&self) -> String {
        // A struct of numbers and arrays always serialises.
        serde_json::to_string(self).unwrap_or_default()
    }

    /// Checks every constraint the network relies on.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let bad = |m: String| Err(ConfigError::Invalid(m));
        let (v, c, t, h) = (&self.src_encoder, &self.cond_encoder, &self.trunk, &self.head);
        if self.dim == 0 || v.depth == 0 || t.depth == 0 || v.mlp_ratio == 0 || t.mlp_ratio == 0 || v.pos_grid == 0 {
            return bad("dim, depths, mlp ratios and pos_grid must be positive".into());
        }
        if !PATCH_SIZES.contains(&self.patch) {
            return bad(format!("patch {} must be one of {PATCH_SIZES:?}", self.patch));
        }
        if !(self.norm_eps > 0.0 && self.norm_eps.is_finite()) {
            return bad(format!("norm_eps must be positive, got {}", self.norm_eps));
        }
        if v.heads == 0 || !self.dim.is_multiple_of(v.heads) {
            return bad(format!(
                "dim {} is not divisible by src_encoder.heads {}",
                self.dim, v.heads
            ));
        }
        if t.heads == 0 || !self.dim.is_multiple_of(t.heads) || !(self.dim / t.heads).is_multiple_of(4) {
            return bad(format!(
                "trunk head dim {} / {} must be an integer divisible by 4 (2D RoPE)",
                self.dim, t.heads
            ));
        }
        if c.dims.contains(&0) || c.depths.contains(&0) {
            return bad(format!(
                "cond_encoder dims {:?} and depths {:?} must be positive",
                c.dims, c.depths
            ));
        }
        if !(c.layer_scale_init.is_finite() && t.rope_base.is_finite() && t.rope_base > 0.0) {
            return bad("layer_scale_init and rope_base must be finite (rope_base > 0)".into());
        }
        if t.readouts.windows(2).any(|w| w[0] >= w[1]) || t.readouts[3] + 1 != t.depth {
            return bad(format!(
                "trunk.readouts {:?} must be strictly increasing and end at the last block {}",
                t.readouts,
                t.depth.saturating_sub(1)
            ));
        }
        if h.out_channels.contains(&0) || h.features < 2 || h.hidden == 0 {
            return bad("head out_channels, features (>= 2) and hidden must be positive".into());
        }
        Ok(())
    }

    /// Whether ConvNeXt stage `s` (1–3) opens with a 2× downsampling (2×2 conv, stride 2) or
    /// only changes width (1×1 conv): stride after the stem is 4, and stage `s` halves the
    /// resolution while that keeps the stride at most `patch` (`4·2^s ≤ p`).
    pub fn cond_downsamples(&self, s: usize) -> bool {
        (4usize << s) <= self.patch
    }

    /// Trunk head dimension `dim / trunk.heads`.
    pub fn trunk_head_dim(&self) -> usize {
        self.dim / self.trunk.heads
    }

    /// Parameter count per top-level module, computed in closed form from the config (no
    /// tensors). Tested against the real `VarMap` for `tiny` and `small`.
    pub fn param_breakdown(&self) -> Vec<(&'static str, usize)> {
        let d = self.dim;
        let lin = |i: usize, o: usize| i * o + o;
        let conv = |i: usize, o: usize, k: usize| i * o * k * k + o;
        let ln = |c: usize| 2 * c;
        let block = |r: usize, ls: bool| {
            ln(d) + lin(d, 3 * d) + lin(d, d) + ln(d) + lin(d, r * d) + lin(r * d, d) + if ls { 2 * d } else { 0 }
        };
        let v = &self.src_encoder;
        let cls = usize::from(v.cls_token);
        let src = conv(3, d, self.patch)
            + (cls + v.pos_grid * v.pos_grid) * d
            + cls * d
            + v.depth * block(v.mlp_ratio, v.layer_scale)
            + ln(d);
        let c = &self.cond_encoder;
        let mut cond = conv(9, c.dims[0], 4) + ln(c.dims[0]);
        for s in 0..4 {
            let ch = c.dims[s];
            if s > 0 {
                let k = if self.cond_downsamples(s) { 2 } else { 1 };
                cond += ln(c.dims[s - 1]) + conv(c.dims[s - 1], ch, k);
            }
            cond += c.depths[s] * (conv(1, ch, 7) + ln(ch) + lin(ch, 4 * ch) + lin(4 * ch, ch) + ch);
        }
        cond += ln(c.dims[3]) + lin(c.dims[3], d);
        let fuse = lin(2 * d, d) + lin(d, d);
        let t = &self.trunk;
        let trunk = t.registers * d + t.depth * block(t.mlp_ratio, t.layer_scale) + ln(d);
        let h = &self.head;
        let (oc, f) = (h.out_channels, h.features);
        let mut head = (0..4).map(|i| conv(d, oc[i], 1)).sum::<usize>();
        head += conv(oc[0], oc[0], 4) + conv(oc[1], oc[1], 2) + conv(oc[3], oc[3], 3);
        head += oc.iter().map(|&o| o * f * 9).sum::<usize>();
        let rcu = 2 * conv(f, f, 3);
        head += 4 * (rcu + conv(f, f, 1)) + 3 * rcu;
        head += conv(f, f / 2, 3) + conv(f / 2, h.hidden, 3);
        let modulation = conv(h.hidden, 6, 1);
        vec![
            ("src_encoder", src),
            ("cond_encoder", cond),
            ("fuse", fuse),
            ("trunk", trunk),
            ("head", head),
            ("modulation", modulation),
        ]
    }

    /// Total parameter count (sum of [`Config::param_breakdown`]).
    pub fn param_count(&self) -> usize {
        self.param_breakdown().iter().map(|(_, n)| n).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readouts_match_the_paper_for_24_blocks() {
        assert_eq!(spread_readouts(24), [4, 11, 17, 23]);
        assert_eq!(spread_readouts(4), [0, 1, 2, 3]);
        assert_eq!(spread_readouts(8), [1, 3, 5, 7]);
    }

    #[test]
    fn presets_validate_and_round_trip_through_json_and_toml() {
        for name in Config::PRESETS {
            let cfg = Config::preset(name).unwrap();
            cfg.validate().unwrap();
            assert_eq!(Config::from_json(&cfg.to_json()).unwrap(), cfg);
            let dir = tempfile::tempdir().unwrap();
            let p = dir.path().join("c.toml");
            std::fs::write(&p, toml::to_string(&cfg).unwrap()).unwrap();
            assert_eq!(Config::from_file(&p).unwrap(), cfg);
        }
    }

    /// Configs and checkpoint metadata written before `patch` existed mean 16, and the default
    /// is not written out (so their JSON is unchanged); another size round-trips.
    #[test]
    fn patch_defaults_to_16_and_round_trips() {
        let mut json: serde_json::Value = serde_json::from_str(&Config::tiny().to_json()).unwrap();
        assert!(json.get("patch").is_none());
        assert_eq!(Config::from_json(&json.to_string()).unwrap().patch, 16);
        json["patch"] = serde_json::json!(8);
        let c = Config::from_json(&json.to_string()).unwrap();
        assert_eq!(c.patch, 8);
        assert_eq!(Config::from_json(&c.to_json()).unwrap(), c);
        assert!(c.cond_downsamples(1) && !c.cond_downsamples(2) && !c.cond_downsamples(3));
        let t = Config::tiny();
        assert!(t.cond_downsamples(1) && t.cond_downsamples(2) && !t.cond_downsamples(3));
        json["patch"] = serde_json::json!(12);
        assert!(Config::from_json(&json.to_string()).is_err());
    }

    #[test]
    fn invalid_configs_are_rejected() {
        let mut c = Config::tiny();
        c.trunk.readouts = [0, 2, 1, 3];
        assert!(matches!(c.validate(), Err(ConfigError::Invalid(_))));
        let mut c = Config::tiny();
        c.trunk.heads = 3;
        assert!(c.validate().is_err());
        assert!(matches!(Config::preset("huge"), Err(ConfigError::UnknownPreset(_))));
    }

    #[test]
    fn paper_parameter_count_is_in_the_papers_range() {
        let n = Config::paper().param_count();
        assert!((600_000_000..760_000_000).contains(&n), "{n}");
        let s = Config::small().param_count();
        assert!((20_000_000..40_000_000).contains(&s), "{s}");
        assert!(Config::tiny().param_count() < 2_000_000);
    }
}
