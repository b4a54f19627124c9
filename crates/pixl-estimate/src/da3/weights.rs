//! The tensors of a single-view DA3 checkpoint, by their official names, and the check of a
//! `model.safetensors` against them before anything is built.
//!
//! Names are those of `DepthAnything3.state_dict()` (the network under `model.`):
//! `model.backbone.pretrained.{cls_token, pos_embed, patch_embed.proj, blocks.N.{norm1,
//! attn.qkv, attn.proj, ls1.gamma, norm2, mlp.fc1, mlp.fc2, ls2.gamma}, norm}` and
//! `model.head.{projects.i, resize_layers.{0,1,3}, scratch.{layerK_rn, refinenetK.{resConfUnit1
//! (K ≤ 3), resConfUnit2, out_conv}, output_conv1, output_conv2.{0,2}, sky_output_conv2.{0,2}}}`
//! (406 tensors for ViT-L). Stored dtypes f32, f16 and bf16 are accepted (upcast to f32 on load).
use super::config::Da3Config;
use crate::error::EstimateError;
use candle_core::safetensors::MmapedSafetensors;
use candle_core::{DType, Device};
use candle_nn::VarBuilder;
use std::collections::BTreeMap;
use std::path::Path;

/// Prefix of the backbone tensors.
pub const BACKBONE: &str = "model.backbone.pretrained";
/// Prefix of the head tensors.
pub const HEAD: &str = "model.head";

/// Every tensor the model reads, with its shape, in a stable order.
pub fn expected_tensors(cfg: &Da3Config) -> Vec<(String, Vec<usize>)> {
    let (n, h) = (cfg.net(), cfg.head());
    let (c, p, g) = (n.embed_dim, n.patch_size, cfg.pos_grid());
    let mut t: Vec<(String, Vec<usize>)> = Vec::new();
    let mut add = |name: String, shape: Vec<usize>| t.push((name, shape));
    add(format!("{BACKBONE}.cls_token"), vec![1, 1, c]);
    add(format!("{BACKBONE}.pos_embed"), vec![1, g * g + 1, c]);
    add(format!("{BACKBONE}.patch_embed.proj.weight"), vec![c, 3, p, p]);
    add(format!("{BACKBONE}.patch_embed.proj.bias"), vec![c]);
    let hidden = cfg.mlp_hidden();
    for i in 0..n.depth {
        let b = format!("{BACKBONE}.blocks.{i}");
        for norm in ["norm1", "norm2"] {
            add(format!("{b}.{norm}.weight"), vec![c]);
            add(format!("{b}.{norm}.bias"), vec![c]);
        }
        add(format!("{b}.attn.qkv.weight"), vec![3 * c, c]);
        add(format!("{b}.attn.qkv.bias"), vec![3 * c]);
        add(format!("{b}.attn.proj.weight"), vec![c, c]);
        add(format!("{b}.attn.proj.bias"), vec![c]);
        add(format!("{b}.ls1.gamma"), vec![c]);
        add(format!("{b}.ls2.gamma"), vec![c]);
        add(format!("{b}.mlp.fc1.weight"), vec![hidden, c]);
        add(format!("{b}.mlp.fc1.bias"), vec![hidden]);
        add(format!("{b}.mlp.fc2.weight"), vec![c, hidden]);
        add(format!("{b}.mlp.fc2.bias"), vec![c]);
    }
    add(format!("{BACKBONE}.norm.weight"), vec![c]);
    add(format!("{BACKBONE}.norm.bias"), vec![c]);

    let (oc, f) = (h.out_channels, h.features);
    for (i, &o) in oc.iter().enumerate() {
        add(format!("{HEAD}.projects.{i}.weight"), vec![o, c, 1, 1]);
        add(format!("{HEAD}.projects.{i}.bias"), vec![o]);
    }
    add(format!("{HEAD}.resize_layers.0.weight"), vec![oc[0], oc[0], 4, 4]);
    add(format!("{HEAD}.resize_layers.0.bias"), vec![oc[0]]);
    add(format!("{HEAD}.resize_layers.1.weight"), vec![oc[1], oc[1], 2, 2]);
    add(format!("{HEAD}.resize_layers.1.bias"), vec![oc[1]]);
    add(format!("{HEAD}.resize_layers.3.weight"), vec![oc[3], oc[3], 3, 3]);
    add(format!("{HEAD}.resize_layers.3.bias"), vec![oc[3]]);
    let s = format!("{HEAD}.scratch");
    for (i, &o) in oc.iter().enumerate() {
        add(format!("{s}.layer{}_rn.weight", i + 1), vec![f, o, 3, 3]);
    }
    for k in 1..=4 {
        let units: &[&str] = if k == 4 {
            &["resConfUnit2"]
        } else {
            &["resConfUnit1", "resConfUnit2"]
        };
        for u in units {
            for conv in ["conv1", "conv2"] {
                add(format!("{s}.refinenet{k}.{u}.{conv}.weight"), vec![f, f, 3, 3]);
                add(format!("{s}.refinenet{k}.{u}.{conv}.bias"), vec![f]);
            }
        }
        add(format!("{s}.refinenet{k}.out_conv.weight"), vec![f, f, 1, 1]);
        add(format!("{s}.refinenet{k}.out_conv.bias"), vec![f]);
    }
    add(format!("{s}.output_conv1.weight"), vec![f / 2, f, 3, 3]);
    add(format!("{s}.output_conv1.bias"), vec![f / 2]);
    for head in ["output_conv2", "sky_output_conv2"] {
        add(format!("{s}.{head}.0.weight"), vec![32, f / 2, 3, 3]);
        add(format!("{s}.{head}.0.bias"), vec![32]);
        add(format!("{s}.{head}.2.weight"), vec![1, 32, 1, 1]);
        add(format!("{s}.{head}.2.bias"), vec![1]);
    }
    t
}

/// Opens `path` and checks its tensors against [`expected_tensors`]: every expected tensor is
/// present with its shape and a float dtype, and nothing else is stored. Returns a
/// `VarBuilder` that reads them as f32 on `device`.
pub fn load(cfg: &Da3Config, path: &Path, device: &Device) -> Result<VarBuilder<'static>, EstimateError> {
    if !path.is_file() {
        return Err(EstimateError::Io {
            path: path.to_owned(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "weight file not found"),
        });
    }
    // SAFETY: the file is mapped read-only; the mapping lives inside the VarBuilder's backend and
    // is only read. As with every mmap, another process truncating the file meanwhile is UB; the
    // weight files are not modified while a model loads.
    let st = unsafe { MmapedSafetensors::new(path) }.map_err(|e| EstimateError::Weights {
        path: path.to_owned(),
        reason: e.to_string(),
    })?;
    let stored: BTreeMap<String, (Vec<usize>, safetensors::Dtype)> = st
        .tensors()
        .into_iter()
        .map(|(name, view)| (name, (view.shape().to_vec(), view.dtype())))
        .collect();
    check(cfg, path, &stored)?;
    Ok(VarBuilder::from_backend(Box::new(st), DType::F32, device.clone()))
}

/// The name/shape/dtype check of [`load`], on a listing of the stored tensors.
pub fn check(
    cfg: &Da3Config,
    path: &Path,
    stored: &BTreeMap<String, (Vec<usize>, safetensors::Dtype)>,
) -> Result<(), EstimateError> {
    let expected = expected_tensors(cfg);
    for (name, shape) in &expected {
        let Some((found, dtype)) = stored.get(name) else {
            return Err(EstimateError::MissingTensor {
                path: path.to_owned(),
                name: name.clone(),
                expected: shape.clone(),
            });
        };
        if found != shape {
            return Err(EstimateError::TensorShape {
                path: path.to_owned(),
                name: name.clone(),
                expected: shape.clone(),
                found: found.clone(),
            });
        }
        if !matches!(
            dtype,
            safetensors::Dtype::F32 | safetensors::Dtype::F16 | safetensors::Dtype::BF16
        ) {
            return Err(EstimateError::TensorDtype {
                path: path.to_owned(),
                name: name.clone(),
                dtype: format!("{dtype:?}"),
            });
        }
    }
    if stored.len() != expected.len() {
        let known: std::collections::HashSet<&str> = expected.iter().map(|(n, _)| n.as_str()).collect();
        if let Some(extra) = stored.keys().find(|k| !known.contains(k.as_str())) {
            return Err(EstimateError::UnexpectedTensor {
                path: path.to_owned(),
                name: extra.clone(),
            });
        }
    }
    Ok(())
}
