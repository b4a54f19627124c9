//! The Marigold UNet (`marigold::unet`, diffusers' SD2-family `UNet2DConditionModel`) against
//! an independent implementation, candle-transformers' `UNet2DConditionModel`, on random weights
//! of SD2-like shapes (four levels, three cross-attention levels then a plain one, two ResNets
//! per down block, heads per level, 32 GroupNorm groups, a latent whose sides are not multiples
//! of 8), with linear and 1×1-convolution projections; and what `unet/config.json` settings are
//! accepted or refused.
//!
//! candle-transformers' GEGLU uses the tanh approximation of GELU where diffusers (and our
//! UNet) use the exact erf form, the one difference between the two networks. Measured on these
//! shapes (outputs up to 2.3): 4.0e-4 max abs difference; with the tanh form swapped into our
//! UNet for a check, 4.9e-6. The tolerance, 1e-3, covers the first with a margin.
#[path = "marigold_common/reference_unet.rs"]
mod reference_unet;

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use candle_transformers::models::stable_diffusion::unet_2d as reference;
use pixl_core::rng::Rng;
use pixl_estimate::marigold::config::UpBlockType;
use pixl_estimate::marigold::unet::UNet2DConditionModel;
use pixl_estimate::marigold::UnetConfig;
use reference_unet::reference_config;
use std::collections::HashMap;

/// SD2's structure at a small width: channels (32, 64, 96, 96), 16-channel heads.
fn small_sd2(use_linear_projection: bool) -> UnetConfig {
    UnetConfig {
        block_out_channels: vec![32, 64, 96, 96],
        attention_head_dim: vec![2, 4, 6, 6],
        cross_attention_dim: 48,
        use_linear_projection,
        ..UnetConfig::sd2(8, 4)
    }
}

/// Every tensor candle-transformers' UNet asks for, redrawn from a seed: norm scales
/// 1 + 0.2·N, biases 0.1·N, other weights N(0, 1/fan_in).
fn random_weights(cfg: &UnetConfig, seed: u64) -> HashMap<String, Tensor> {
    let dev = Device::Cpu;
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &dev);
    reference::UNet2DConditionModel::new(vb, cfg.in_channels, cfg.out_channels, false, reference_config(cfg))
        .expect("candle-transformers' UNet builds");
    let data = varmap.data().lock().expect("varmap lock");
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    let mut rng = Rng::new(seed);
    names
        .into_iter()
        .map(|name| {
            let dims = data[name].dims().to_vec();
            let n: usize = dims.iter().product();
            let fan_in = (n / dims[0]).max(1) as f32;
            let is_norm = dims.len() == 1 && name.contains("norm");
            let values: Vec<f32> = (0..n)
                .map(|_| {
                    let z = rng.normal();
                    if is_norm && name.ends_with("weight") {
                        1.0 + 0.2 * z
                    } else if name.ends_with("bias") {
                        0.1 * z
                    } else {
                        z / fan_in.sqrt()
                    }
                })
                .collect();
            (name.clone(), Tensor::from_vec(values, dims, &dev).expect("tensor"))
        })
        .collect()
}

fn randn(shape: &[usize], seed: u64) -> Tensor {
    let mut rng = Rng::new(seed);
    let n = shape.iter().product();
    Tensor::from_vec((0..n).map(|_| rng.normal()).collect::<Vec<f32>>(), shape, &Device::Cpu).unwrap()
}

fn max_abs(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims());
    (a - b)
        .unwrap()
        .abs()
        .unwrap()
        .max_all()
        .unwrap()
        .to_scalar::<f32>()
        .unwrap()
}

fn matches_candle_transformers(use_linear_projection: bool) {
    let cfg = small_sd2(use_linear_projection);
    let weights = random_weights(&cfg, 11);
    let dev = Device::Cpu;
    let vb = VarBuilder::from_tensors(weights, DType::F32, &dev);
    let ours = UNet2DConditionModel::new(&cfg, vb.clone()).unwrap();
    let theirs = reference::UNet2DConditionModel::new(vb, 8, 4, false, reference_config(&cfg)).unwrap();
    // 12 × 10: the upsamplers go 2 → 3 → 6 → 12 and 2 → 3 → 5 → 10 (the skips' sizes).
    let x = randn(&[2, 8, 12, 10], 1);
    let ctx = randn(&[2, 7, 48], 2);
    for t in [999.0, 249.0] {
        let got = ours.forward(&x, t, &ctx).unwrap();
        let want = theirs.forward(&x, t, &ctx).unwrap();
        let scale = want.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap();
        let err = max_abs(&got, &want);
        eprintln!(
            "linear projection {use_linear_projection}, t = {t}: max abs error {err:.2e} (output max {scale:.2})"
        );
        assert!(scale > 0.5, "a degenerate output ({scale})");
        assert!(err <= 1e-3, "max abs error {err:.3e}");
    }
}

#[test]
fn unet_matches_candle_transformers_with_linear_projections() {
    matches_candle_transformers(true);
}

#[test]
fn unet_matches_candle_transformers_with_conv_projections() {
    matches_candle_transformers(false);
}

/// The SD2 `unet/config.json` (the released Marigold-IID config, widened to 12 → 8).
const SD2_JSON: &str = r#"{
  "_class_name": "UNet2DConditionModel", "_diffusers_version": "0.33.0",
  "act_fn": "silu", "addition_embed_type": null, "addition_embed_type_num_heads": 64,
  "addition_time_embed_dim": null, "attention_head_dim": [5, 10, 20, 20], "attention_type": "default",
  "block_out_channels": [320, 640, 1280, 1280], "center_input_sample": false,
  "class_embed_type": null, "class_embeddings_concat": false, "conv_in_kernel": 3, "conv_out_kernel": 3,
  "cross_attention_dim": 1024, "cross_attention_norm": null,
  "down_block_types": ["CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"],
  "downsample_padding": 1, "dropout": 0.0, "dual_cross_attention": false, "encoder_hid_dim": null,
  "encoder_hid_dim_type": null, "flip_sin_to_cos": true, "freq_shift": 0, "in_channels": 12,
  "layers_per_block": 2, "mid_block_only_cross_attention": null, "mid_block_scale_factor": 1,
  "mid_block_type": "UNetMidBlock2DCrossAttn", "norm_eps": 1e-05, "norm_num_groups": 32,
  "num_attention_heads": null, "num_class_embeds": null, "only_cross_attention": false,
  "out_channels": 8, "projection_class_embeddings_input_dim": null, "resnet_out_scale_factor": 1.0,
  "resnet_skip_time_act": false, "resnet_time_scale_shift": "default",
  "reverse_transformer_layers_per_block": null, "sample_size": 96, "time_cond_proj_dim": null,
  "time_embedding_act_fn": null, "time_embedding_dim": null, "time_embedding_type": "positional",
  "timestep_post_act": null, "transformer_layers_per_block": 1,
  "up_block_types": ["UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"],
  "upcast_attention": false, "use_linear_projection": true
}"#;

/// `SD2_JSON` with `key` set to the JSON `value`.
fn with(key: &str, value: &str) -> String {
    let mut v: serde_json::Value = serde_json::from_str(SD2_JSON).unwrap();
    v[key] = serde_json::from_str(value).unwrap();
    v.to_string()
}

#[test]
fn sd2_config_reads_as_the_sd2_preset() {
    let cfg = UnetConfig::from_json(SD2_JSON).unwrap();
    assert_eq!(cfg, UnetConfig::sd2(12, 8));
    assert_eq!(cfg.up_block_types[0], UpBlockType::UpBlock2D);
    // Other group counts are honoured as long as they divide every width.
    let g8 = UnetConfig::from_json(&with("norm_num_groups", "8")).unwrap();
    assert_eq!(g8.norm_num_groups, 8);
    let err = UnetConfig::from_json(&with("norm_num_groups", "48")).unwrap_err();
    assert!(err.contains("norm_num_groups 48 must divide"), "{err}");
    // Per-block lists and single integers.
    let cfg = UnetConfig::from_json(&with("transformer_layers_per_block", "[1, 2, 3, 1]")).unwrap();
    assert_eq!(cfg.transformer_layers_per_block, vec![1, 2, 3, 1]);
    let cfg = UnetConfig::from_json(&with("attention_head_dim", "8")).unwrap();
    assert_eq!(cfg.attention_head_dim, vec![8; 4]);
    let cfg = UnetConfig::from_json(&with("upcast_attention", "true")).unwrap();
    assert!(cfg.upcast_attention);
}

#[test]
fn configs_beyond_the_sd2_family_are_refused_with_the_key() {
    for (key, value, says) in [
        ("mid_block_type", "null", "mid_block_type"),
        ("mid_block_type", "\"UNetMidBlock2DSimpleCrossAttn\"", "mid_block_type"),
        ("transformer_layers_per_block", "[[1, 2], 1, 1, 1]", "nested"),
        ("class_embed_type", "\"timestep\"", "class_embed_type"),
        ("addition_embed_type", "\"text_time\"", "addition_embed_type"),
        ("num_attention_heads", "8", "num_attention_heads"),
        ("only_cross_attention", "true", "only_cross_attention"),
        ("only_cross_attention", "[false, true, false, false]", "only_cross_attention"),
        ("dual_cross_attention", "true", "dual_cross_attention"),
        ("resnet_time_scale_shift", "\"scale_shift\"", "resnet_time_scale_shift"),
        ("time_embedding_type", "\"fourier\"", "time_embedding_type"),
        ("conv_in_kernel", "7", "conv_in_kernel"),
        ("cross_attention_dim", "[1024, 1024, 1024, 1024]", "cross_attention_dim"),
        ("attention_head_dim", "[5, 10, 20]", "attention_head_dim"),
        ("attention_head_dim", "[3, 10, 20, 20]", "attention_head_dim[0]"),
        ("down_block_types", "[\"CrossAttnDownBlock2D\", \"CrossAttnDownBlock2D\", \"CrossAttnDownBlock2D\", \"SimpleCrossAttnDownBlock2D\"]", "down_block_types[3]"),
        ("norm_num_groups", "null", "norm_num_groups"),
    ] {
        let err = UnetConfig::from_json(&with(key, value)).expect_err(&format!("{key} = {value} accepted"));
        assert!(err.contains(says), "{key} = {value}: {err}");
    }
}
