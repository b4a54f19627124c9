//! Optimisation (paper App. A, Table 3): AdamW with β = (0.9, 0.95), weight decay 0.05,
//! linear warm-up then cosine learning rate, gradients clipped by their **global** norm.
//!
//! The optimiser is our own rather than `candle_nn::AdamW` because its moments must be saved
//! and restored bit-exactly, and because weight decay is per parameter:
//! [`decays`] exempts biases, norm weights, layer scales (every tensor of rank ≤ 1), the
//! register tokens and the position embeddings — the usual ViT practice.
//!
//! Update (PyTorch's `AdamW`, step `t` from 1): `θ ← θ·(1 − lr·wd)`, then
//! `m ← β1·m + (1−β1)·g`, `v ← β2·v + (1−β2)·g²`, `θ ← θ − lr·(m/(1−β1ᵗ)) / (√(v/(1−β2ᵗ)) + ε)`.
use candle_core::{Result, Tensor, Var};
use std::collections::BTreeMap;

/// Learning-rate schedule: `lr(s) = peak · s / warmup` for `s ≤ warmup`, then
/// `final + ½(peak − final)(1 + cos(π (s − warmup)/(total − warmup)))` up to `total`, then `final`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LrSchedule {
    pub peak_lr: f64,
    pub final_lr: f64,
    pub warmup_steps: u64,
    pub total_steps: u64,
}

impl Default for LrSchedule {
    /// The paper's: warm-up 2 500 steps to 5e-5, cosine to 1e-5 at 200 000.
    fn default() -> Self {
        Self {
            peak_lr: 5e-5,
            final_lr: 1e-5,
            warmup_steps: 2_500,
            total_steps: 200_000,
        }
    }
}

impl LrSchedule {
    pub fn lr(&self, step: u64) -> f64 {
        if step < self.warmup_steps {
            return self.peak_lr * step as f64 / self.warmup_steps as f64;
        }
        if step >= self.total_steps || self.total_steps <= self.warmup_steps {
            return if step >= self.total_steps {
                self.final_lr
            } else {
                self.peak_lr
            };
        }
        let t = (step - self.warmup_steps) as f64 / (self.total_steps - self.warmup_steps) as f64;
        self.cosine(t)
    }

    /// The rate of a run paced by time rather than by `total_steps` (`[run] max_minutes`): the
    /// same linear warm-up over `warmup_steps`, then the cosine at `progress` ∈ [0, 1], the
    /// fraction of the time after the warm-up that has passed (clamped).
    pub fn lr_at_progress(&self, step: u64, progress: f64) -> f64 {
        if step < self.warmup_steps {
            return self.peak_lr * step as f64 / self.warmup_steps as f64;
        }
        self.cosine(if progress.is_nan() {
            0.0
        } else {
            progress.clamp(0.0, 1.0)
        })
    }

    /// Cosine from `peak_lr` at `t = 0` to `final_lr` at `t = 1`.
    fn cosine(&self, t: f64) -> f64 {
        self.final_lr + 0.5 * (self.peak_lr - self.final_lr) * (1.0 + (std::f64::consts::PI * t).cos())
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AdamWConfig {
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    pub weight_decay: f64,
}

impl Default for AdamWConfig {
    fn default() -> Self {
        Self {
            beta1: 0.9,
            beta2: 0.95,
            eps: 1e-8,
            weight_decay: 0.05,
        }
    }
}

/// Whether parameter `name` of shape `dims` gets weight decay (see the module docs).
pub fn decays(name: &str, dims: &[usize]) -> bool {
    let exempt_name = name.contains("registers") || name.contains("pos_embed") || name.ends_with("gamma");
    dims.len() >= 2 && !exempt_name && !name.ends_with(".bias")
}

/// One parameter and its moments.
pub struct Param {
    pub name: String,
    pub var: Var,
    pub m: Tensor,
    pub v: Tensor,
    pub decay: bool,
}

/// AdamW over named parameters (sorted by name).
pub struct AdamW {
    pub cfg: AdamWConfig,
    pub params: Vec<Param>,
    /// Number of updates taken so far (`t` of the bias corrections is `steps + 1`).
    pub steps: u64,
}

impl AdamW {
    pub fn new(vars: BTreeMap<String, Var>, cfg: AdamWConfig) -> Result<Self> {
        let params = vars
            .into_iter()
            .map(|(name, var)| {
                let m = var.as_tensor().zeros_like()?;
                let v = m.clone();
                let decay = decays(&name, var.dims());
                Ok(Param { name, var, m, v, decay })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { cfg, params, steps: 0 })
    }

    /// One update with gradients `grads[i]` for `params[i]` (`None`: parameter untouched by the
    /// loss — its moments still decay, as in PyTorch only when a gradient exists; we skip it).
    pub fn step(&mut self, grads: &[Option<Tensor>], lr: f64) -> Result<()> {
        let t = (self.steps + 1) as i32;
        let (b1, b2) = (self.cfg.beta1, self.cfg.beta2);
        let (bc1, bc2) = (1.0 - b1.powi(t), 1.0 - b2.powi(t));
        for (p, g) in self.params.iter_mut().zip(grads) {
            let Some(g) = g else { continue };
            // Detached: the optimiser's arithmetic must not join the autograd graph, or every
            // step would keep the previous steps' tensors alive through m, v and θ.
            let g = g.detach();
            let m = ((&p.m * b1)? + (&g * (1.0 - b1))?)?.detach();
            let v = ((&p.v * b2)? + (g.sqr()? * (1.0 - b2))?)?.detach();
            let mut theta = p.var.as_tensor().detach();
            if p.decay && self.cfg.weight_decay != 0.0 {
                theta = (theta * (1.0 - lr * self.cfg.weight_decay))?;
            }
            let denom = ((&v / bc2)?.sqrt()? + self.cfg.eps)?;
            let update = ((&m / bc1)? / denom)?;
            p.var.set(&(theta - (update * lr)?)?.detach())?;
            p.m = m;
            p.v = v;
        }
        self.steps += 1;
        Ok(())
    }
}

/// Global L2 norm of all gradients, `√(Σ_i ‖g_i‖²)`, accumulated in f64.
pub fn global_norm(grads: &[Option<Tensor>]) -> Result<f64> {
    let mut sum = 0.0f64;
    for g in grads.iter().flatten() {
        sum += g
            .to_dtype(candle_core::DType::F64)?
            .sqr()?
            .sum_all()?
            .to_scalar::<f64>()?;
    }
    Ok(sum.sqrt())
}

/// Clips gradients by their global norm (PyTorch's `clip_grad_norm_`): when the norm exceeds
/// `max_norm`, every gradient is scaled by `max_norm / (norm + 1e-6)`. Returns the norm before
/// clipping. A non-finite norm is an error (the step would destroy the weights).
pub fn clip_global_norm(grads: &mut [Option<Tensor>], max_norm: f64) -> Result<f64> {
    let norm = global_norm(grads)?;
    if !norm.is_finite() {
        return Err(candle_core::Error::Msg(format!(
            "gradient norm is {norm}; refusing to step"
        )));
    }
    if norm > max_norm {
        let scale = max_norm / (norm + 1e-6);
        for g in grads.iter_mut().flatten() {
            *g = (&*g * scale)?;
        }
    }
    Ok(norm)
}
