//! The empty-prompt text embedding Marigold conditions its UNet on, computed with the
//! checkpoint's own CLIP text encoder (transformers `CLIPTextModel`, `last_hidden_state`) and
//! cached beside the weights.
//!
//! The pipeline tokenises `""` without padding, so the encoder sees exactly two tokens,
//! `[<|startoftext|>, <|endoftext|>]`, whose ids are read from `tokenizer/vocab.json` (the
//! special-token strings from `tokenizer/tokenizer_config.json` when it names them). The encoder
//! is the standard pre-norm transformer: token + position embeddings, `num_hidden_layers` ×
//! (LN → causal multi-head attention → residual, LN → fc1 → activation → fc2 → residual), final
//! LN. Result: `(1, 2, hidden_size)` (`[1, 2, 1024]` for SD2).
//!
//! The cache file is `text_encoder/pixl-empty-embedding.safetensors` (tensor `empty_embedding`);
//! when the folder is read-only the embedding is simply recomputed next time.
use super::config::{TextActivation, TextConfig};
use crate::error::EstimateError;
use candle_core::{DType, Device, Tensor};
use candle_nn::{layer_norm, linear, LayerNorm, Linear, Module, VarBuilder};
use std::path::{Path, PathBuf};

/// File name of the cached embedding inside `text_encoder/`.
pub const CACHE_FILE: &str = "pixl-empty-embedding.safetensors";

struct Layer {
    ln1: LayerNorm,
    q: Linear,
    k: Linear,
    v: Linear,
    out: Linear,
    ln2: LayerNorm,
    fc1: Linear,
    fc2: Linear,
}

/// A CLIP text encoder (only what a short unpadded prompt needs).
pub struct TextEncoder {
    cfg: TextConfig,
    token: Tensor,
    position: Tensor,
    layers: Vec<Layer>,
    final_ln: LayerNorm,
}

impl TextEncoder {
    /// `vb` at the checkpoint root: tensors `text_model.*` (how transformers' `CLIPTextModel`
    /// saves them), or the same names without the `text_model.` prefix (how some exports save
    /// the inner model).
    pub fn new(cfg: TextConfig, vb: VarBuilder) -> candle_core::Result<Self> {
        let prefixed = vb.contains_tensor("text_model.embeddings.token_embedding.weight");
        let t = if prefixed { vb.pp("text_model") } else { vb };
        let e = t.pp("embeddings");
        let h = cfg.hidden_size;
        let token = e.get((cfg.vocab_size, h), "token_embedding.weight")?;
        let position = e.get((cfg.max_position_embeddings, h), "position_embedding.weight")?;
        let eps = cfg.layer_norm_eps;
        let layers = (0..cfg.num_hidden_layers)
            .map(|i| {
                let l = t.pp("encoder").pp("layers").pp(i.to_string());
                let a = l.pp("self_attn");
                Ok(Layer {
                    ln1: layer_norm(h, eps, l.pp("layer_norm1"))?,
                    q: linear(h, h, a.pp("q_proj"))?,
                    k: linear(h, h, a.pp("k_proj"))?,
                    v: linear(h, h, a.pp("v_proj"))?,
                    out: linear(h, h, a.pp("out_proj"))?,
                    ln2: layer_norm(h, eps, l.pp("layer_norm2"))?,
                    fc1: linear(h, cfg.intermediate_size, l.pp("mlp").pp("fc1"))?,
                    fc2: linear(cfg.intermediate_size, h, l.pp("mlp").pp("fc2"))?,
                })
            })
            .collect::<candle_core::Result<Vec<_>>>()?;
        let final_ln = layer_norm(h, eps, t.pp("final_layer_norm"))?;
        Ok(Self {
            cfg,
            token,
            position,
            layers,
            final_ln,
        })
    }

    /// `last_hidden_state` for one sequence of token ids: `(1, len, hidden)`.
    pub fn forward(&self, ids: &[u32]) -> candle_core::Result<Tensor> {
        let n = ids.len();
        if n == 0 || n > self.cfg.max_position_embeddings {
            candle_core::bail!("text encoder: {n} tokens (1..={})", self.cfg.max_position_embeddings);
        }
        if let Some(bad) = ids.iter().find(|&&i| i as usize >= self.cfg.vocab_size) {
            candle_core::bail!(
                "text encoder: token id {bad} outside the vocabulary ({})",
                self.cfg.vocab_size
            );
        }
        let dev = self.token.device();
        let idx = Tensor::new(ids, dev)?;
        let mut x = (self.token.index_select(&idx, 0)? + self.position.narrow(0, 0, n)?)?.unsqueeze(0)?;
        let heads = self.cfg.num_attention_heads;
        let hd = self.cfg.hidden_size / heads;
        let scale = (hd as f64).powf(-0.5);
        // Causal mask: −inf above the diagonal.
        let mask: Vec<f32> = (0..n * n)
            .map(|k| if k % n > k / n { f32::NEG_INFINITY } else { 0.0 })
            .collect();
        let mask = Tensor::from_vec(mask, (n, n), dev)?;
        let split =
            |t: Tensor| -> candle_core::Result<Tensor> { t.reshape((1, n, heads, hd))?.transpose(1, 2)?.contiguous() };
        for l in &self.layers {
            let h = l.ln1.forward(&x)?;
            let q = split((l.q.forward(&h)? * scale)?)?;
            let k = split(l.k.forward(&h)?)?;
            let v = split(l.v.forward(&h)?)?;
            let att = q.matmul(&k.t()?)?.broadcast_add(&mask)?;
            let att = candle_nn::ops::softmax_last_dim(&att)?;
            let o = att.matmul(&v)?.transpose(1, 2)?.reshape((1, n, heads * hd))?;
            x = (x + l.out.forward(&o)?)?;
            let h = l.fc1.forward(&l.ln2.forward(&x)?)?;
            let h = match self.cfg.activation {
                TextActivation::Gelu => h.gelu_erf()?,
                TextActivation::GeluTanh => h.gelu()?,
                TextActivation::QuickGelu => (&h * candle_nn::ops::sigmoid(&(&h * 1.702)?)?)?,
            };
            x = (x + l.fc2.forward(&h)?)?;
        }
        self.final_ln.forward(&x)
    }
}

/// The ids of `<|startoftext|>` and `<|endoftext|>` (or the tokenizer's own BOS/EOS strings).
pub fn empty_prompt_ids(tokenizer_dir: &Path) -> Result<[u32; 2], EstimateError> {
    let read = |name: &str| -> Result<String, EstimateError> {
        let p = tokenizer_dir.join(name);
        std::fs::read_to_string(&p).map_err(|source| EstimateError::Io { path: p, source })
    };
    let config_err = |path: PathBuf, reason: String| EstimateError::Config { path, reason };
    let mut bos = "<|startoftext|>".to_string();
    let mut eos = "<|endoftext|>".to_string();
    let tc = tokenizer_dir.join("tokenizer_config.json");
    if tc.is_file() {
        let v: serde_json::Value =
            serde_json::from_str(&read("tokenizer_config.json")?).map_err(|e| config_err(tc.clone(), e.to_string()))?;
        let name = |k: &str| -> Option<String> {
            match v.get(k)? {
                serde_json::Value::String(s) => Some(s.clone()),
                serde_json::Value::Object(o) => o.get("content")?.as_str().map(str::to_string),
                _ => None,
            }
        };
        if let Some(b) = name("bos_token") {
            bos = b;
        }
        if let Some(e) = name("eos_token") {
            eos = e;
        }
    }
    let vp = tokenizer_dir.join("vocab.json");
    let vocab: serde_json::Map<String, serde_json::Value> =
        serde_json::from_str(&read("vocab.json")?).map_err(|e| config_err(vp.clone(), e.to_string()))?;
    let id = |tok: &str| -> Result<u32, EstimateError> {
        vocab
            .get(tok)
            .and_then(|v| v.as_u64())
            .and_then(|v| u32::try_from(v).ok())
            .ok_or_else(|| config_err(vp.clone(), format!("the vocabulary has no token {tok:?}")))
    };
    Ok([id(&bos)?, id(&eos)?])
}

/// The cached embedding if present and well-formed.
pub fn read_cache(text_dir: &Path, hidden: Option<usize>, device: &Device) -> Option<Tensor> {
    let p = text_dir.join(CACHE_FILE);
    let t = candle_core::safetensors::load(&p, device)
        .ok()?
        .remove("empty_embedding")?;
    let dims = t.dims().to_vec();
    let ok = dims.len() == 3 && dims[0] == 1 && dims[1] >= 1 && hidden.is_none_or(|h| dims[2] == h);
    if !ok {
        tracing::warn!("{}: ignoring a cached embedding of shape {dims:?}", p.display());
        return None;
    }
    t.to_dtype(DType::F32).ok()
}

/// Writes the cache atomically; a read-only folder is not an error (logged).
pub fn write_cache(text_dir: &Path, emb: &Tensor) {
    let p = text_dir.join(CACHE_FILE);
    let tmp = text_dir.join(format!(".{CACHE_FILE}.tmp{}", std::process::id()));
    let res = emb
        .to_device(&Device::Cpu)
        .and_then(|e| candle_core::safetensors::save(&[("empty_embedding", e)].into_iter().collect(), &tmp))
        .map_err(|e| e.to_string())
        .and_then(|_| std::fs::rename(&tmp, &p).map_err(|e| e.to_string()));
    if let Err(e) = res {
        let _ = std::fs::remove_file(&tmp);
        tracing::debug!("not caching the empty-prompt embedding at {}: {e}", p.display());
    }
}

#[cfg(test)]
mod prefix_tests {
    use super::*;

    /// The appearance fixture's text encoder, and the same tensors saved without the
    /// `text_model.` prefix, give the same embedding bit for bit.
    #[test]
    fn names_with_or_without_the_text_model_prefix_load_alike() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/marigold/appearance/text_encoder");
        let cfg = TextConfig::from_json(&std::fs::read_to_string(dir.join("config.json")).unwrap()).unwrap();
        let tensors = candle_core::safetensors::load(dir.join("model.safetensors"), &Device::Cpu).unwrap();
        assert!(tensors.keys().all(|k| k.starts_with("text_model.")));
        let stripped: std::collections::HashMap<String, Tensor> = tensors
            .iter()
            .map(|(k, v)| (k.trim_start_matches("text_model.").to_string(), v.clone()))
            .collect();
        let ids = [0u32, 1];
        let embed = |t: std::collections::HashMap<String, Tensor>| {
            let vb = VarBuilder::from_tensors(t, DType::F32, &Device::Cpu);
            let enc = TextEncoder::new(cfg.clone(), vb).unwrap();
            enc.forward(&ids)
                .unwrap()
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap()
        };
        let a = embed(tensors);
        let b = embed(stripped);
        assert_eq!(a, b);
        assert!(a.iter().any(|v| *v != 0.0));
    }
}
