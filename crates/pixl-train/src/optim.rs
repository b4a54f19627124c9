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
//!
//! [`Ema`]: an optional exponential moving average of the weights (`[optim] ema_decay`).
use candle_core::{CpuStorage, DType, Layout, Result, Tensor, Var};
use rayon::prelude::*;
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
                // Two buffers of their own: the CPU update writes them in place.
                let m = var.as_tensor().zeros_like()?;
                let v = var.as_tensor().zeros_like()?;
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
            if fused_cpu(&[p.var.as_tensor(), &p.m, &p.v, g]) {
                let wd = if p.decay { self.cfg.weight_decay } else { 0.0 };
                step_in_place(p, g, lr, wd, &self.cfg, (bc1, bc2))?;
                continue;
            }
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

/// An exponential moving average of the weights (Polyak averaging; not in the paper): after
/// update `t` (from 0) of the optimiser, `ema ← r·ema + (1 − r)·θ` with
/// `r = min(decay, (1 + t) / (10 + t))` — the rate ramps up over the first updates so that the
/// average of a fresh run forgets its random start quickly. The average starts at the weights the
/// run starts from (a fine-tune's starting weights, or the random initialisation).
pub struct Ema {
    pub decay: f64,
    /// One tensor per optimiser parameter, in the optimiser's (name) order.
    pub shadow: Vec<Tensor>,
}

impl Ema {
    /// An average equal to the current `params`.
    pub fn new(params: &[Param], decay: f64) -> Result<Self> {
        let shadow = params
            .iter()
            .map(|p| p.var.as_tensor().detach().copy())
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { decay, shadow })
    }

    /// The rate `r` of update `t` (0-based).
    pub fn rate(&self, t: u64) -> f64 {
        let t = t as f64;
        self.decay.min((1.0 + t) / (10.0 + t))
    }

    /// Folds the weights after update `t` (0-based) of the optimiser into the average.
    pub fn update(&mut self, params: &[Param], t: u64) -> Result<()> {
        let r = self.rate(t);
        for (s, p) in self.shadow.iter_mut().zip(params) {
            let theta = p.var.as_tensor().detach();
            *s = ((&*s * r)? + (theta * (1.0 - r))?)?.detach();
        }
        Ok(())
    }
}

/// Whether every tensor is a contiguous f32 CPU tensor (the fused in-place update applies).
fn fused_cpu(ts: &[&Tensor]) -> bool {
    ts.iter()
        .all(|t| t.device().is_cpu() && t.dtype() == DType::F32 && t.is_contiguous())
        && ts.windows(2).all(|w| w[0].dims() == w[1].dims())
}

/// The AdamW update of one parameter in place, in f32, one pass per buffer: `m` and `v` from
/// `g`, then `θ` from `m` and `v` (the arithmetic of the tensor path, in the same order; no
/// temporaries). The moments are fresh buffers of their own (made by `zeros_like` or loaded),
/// and the parameter's storage is the `Var`'s, shared with the model that reads it.
fn step_in_place(p: &mut Param, g: &Tensor, lr: f64, wd: f64, cfg: &AdamWConfig, (bc1, bc2): (f64, f64)) -> Result<()> {
    let g = g.detach();
    p.m.inplace_op2(
        &g,
        &Moment {
            beta: cfg.beta1 as f32,
            square: false,
        },
    )?;
    p.v.inplace_op2(
        &g,
        &Moment {
            beta: cfg.beta2 as f32,
            square: true,
        },
    )?;
    let update = Update {
        lr: lr as f32,
        keep: (1.0 - lr * wd) as f32,
        bc1: bc1 as f32,
        bc2: bc2 as f32,
        eps: cfg.eps as f32,
        decay: wd != 0.0,
    };
    p.var.as_tensor().inplace_op3(&p.m, &p.v, &update)
}

/// `x ← β·x + (1 − β)·g` (or `·g²` when `square`), in place.
struct Moment {
    beta: f32,
    square: bool,
}

impl candle_core::InplaceOp2 for Moment {
    fn name(&self) -> &'static str {
        "adamw-moment"
    }

    fn cpu_fwd(&self, dst: &mut CpuStorage, dst_l: &Layout, g: &CpuStorage, g_l: &Layout) -> Result<()> {
        let (x, g) = (f32_mut(dst, dst_l)?, f32_ref(g, g_l)?);
        let (b, c) = (self.beta, 1.0 - self.beta);
        x.par_chunks_mut(CHUNK).zip(g.par_chunks(CHUNK)).for_each(|(x, g)| {
            if self.square {
                x.iter_mut().zip(g).for_each(|(x, &g)| *x = *x * b + (g * g) * c);
            } else {
                x.iter_mut().zip(g).for_each(|(x, &g)| *x = *x * b + g * c);
            }
        });
        Ok(())
    }
}

/// `θ ← θ·(1 − lr·wd) − lr·(m / bc1) / (√(v / bc2) + ε)`, in place.
struct Update {
    lr: f32,
    keep: f32,
    bc1: f32,
    bc2: f32,
    eps: f32,
    decay: bool,
}

impl candle_core::InplaceOp3 for Update {
    fn name(&self) -> &'static str {
        "adamw-update"
    }

    fn cpu_fwd(
        &self,
        dst: &mut CpuStorage,
        dst_l: &Layout,
        m: &CpuStorage,
        m_l: &Layout,
        v: &CpuStorage,
        v_l: &Layout,
    ) -> Result<()> {
        let (theta, m, v) = (f32_mut(dst, dst_l)?, f32_ref(m, m_l)?, f32_ref(v, v_l)?);
        theta
            .par_chunks_mut(CHUNK)
            .zip(m.par_chunks(CHUNK).zip(v.par_chunks(CHUNK)))
            .for_each(|(t, (m, v))| {
                for ((t, &m), &v) in t.iter_mut().zip(m).zip(v) {
                    let base = if self.decay { *t * self.keep } else { *t };
                    let denom = (v / self.bc2).sqrt() + self.eps;
                    *t = base - ((m / self.bc1) / denom) * self.lr;
                }
            });
        Ok(())
    }
}

/// Values per parallel task of the fused passes.
const CHUNK: usize = 1 << 15;

fn f32_ref<'a>(s: &'a CpuStorage, l: &Layout) -> Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&v[a..b]),
        _ => candle_core::bail!("AdamW: expected a contiguous f32 buffer"),
    }
}

fn f32_mut<'a>(s: &'a mut CpuStorage, l: &Layout) -> Result<&'a mut [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((a, b))) => Ok(&mut v[a..b]),
        _ => candle_core::bail!("AdamW: expected a contiguous f32 buffer"),
    }
}

/// Global L2 norm of all gradients, `√(Σ_i ‖g_i‖²)`, accumulated in f64 (on the CPU in f32:
/// one parallel pass per gradient, no f64 copy).
pub fn global_norm(grads: &[Option<Tensor>]) -> Result<f64> {
    let mut sum = 0.0f64;
    for g in grads.iter().flatten() {
        if g.device().is_cpu() && g.dtype() == DType::F32 {
            let g = g.contiguous()?;
            let (storage, layout) = g.storage_and_layout();
            let candle_core::Storage::Cpu(s) = &*storage else {
                candle_core::bail!("global norm: expected a CPU gradient");
            };
            let v = f32_ref(s, layout)?;
            // Partial sums in chunk order, then added in order: the same total on every run.
            let partial: Vec<f64> = v
                .par_chunks(CHUNK)
                .map(|c| c.iter().map(|&x| (x as f64) * (x as f64)).sum::<f64>())
                .collect();
            sum += partial.iter().sum::<f64>();
            continue;
        }
        sum += g.to_dtype(DType::F64)?.sqr()?.sum_all()?.to_scalar::<f64>()?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// The average after a few updates equals the recurrence written out in f64, with the rate
    /// ramp `min(decay, (1 + t) / (10 + t))` and a parameter the optimiser skipped (no gradient)
    /// still averaged at its unchanged value.
    #[test]
    fn ema_follows_its_recurrence() -> Result<()> {
        let dev = Device::Cpu;
        let mut vars = BTreeMap::new();
        vars.insert(
            "a.weight".to_string(),
            Var::from_tensor(&pixl_nn::testing::uniform(&[4, 3], -1.0, 1.0, 1, &dev)?)?,
        );
        vars.insert(
            "b.bias".to_string(),
            Var::from_tensor(&pixl_nn::testing::uniform(&[5], -1.0, 1.0, 2, &dev)?)?,
        );
        let mut opt = AdamW::new(vars, AdamWConfig::default())?;
        let decay = 0.6;
        let mut ema = Ema::new(&opt.params, decay)?;
        let flat = |t: &Tensor| -> Result<Vec<f64>> { t.flatten_all()?.to_dtype(DType::F64)?.to_vec1() };
        let mut want: Vec<Vec<f64>> = opt
            .params
            .iter()
            .map(|p| flat(p.var.as_tensor()))
            .collect::<Result<_>>()?;
        for t in 0..6u64 {
            let g = pixl_nn::testing::uniform(&[4, 3], -1.0, 1.0, 50 + t, &dev)?;
            opt.step(&[Some(g), None], 0.05)?;
            ema.update(&opt.params, t)?;
            let r = decay.min((1.0 + t as f64) / (10.0 + t as f64));
            for (w, p) in want.iter_mut().zip(&opt.params) {
                for (w, x) in w.iter_mut().zip(flat(p.var.as_tensor())?) {
                    *w = r * *w + (1.0 - r) * x;
                }
            }
        }
        assert_eq!(ema.rate(0), 0.1);
        assert_eq!(ema.rate(100), decay);
        for (s, w) in ema.shadow.iter().zip(&want) {
            let got = flat(s)?;
            let err = got.iter().zip(w).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
            assert!(err < 1e-6, "EMA differs from its recurrence by {err}");
        }
        // The average lags the weights: it is not simply a copy of them.
        let lag = flat(&ema.shadow[0])?
            .iter()
            .zip(flat(opt.params[0].var.as_tensor())?)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(lag > 1e-3, "EMA equals the weights ({lag})");
        Ok(())
    }

    /// Three AdamW steps of the fused in-place CPU path (f32) against the tensor path (f64, which
    /// does not take the fused path), with and without weight decay and clipping.
    #[test]
    fn fused_update_matches_the_tensor_path() -> Result<()> {
        let dev = Device::Cpu;
        // In name order, as the optimiser keeps its parameters.
        let shapes: [(&str, &[usize]); 3] = [("a.bias", &[7]), ("a.weight", &[7, 5]), ("b.weight", &[3, 2, 3, 3])];
        let make = |dtype: DType| -> Result<AdamW> {
            let mut vars = BTreeMap::new();
            for (i, (name, dims)) in shapes.iter().enumerate() {
                let t = pixl_nn::testing::uniform(*dims, -1.0, 1.0, 10 + i as u64, &dev)?.to_dtype(dtype)?;
                vars.insert(name.to_string(), Var::from_tensor(&t)?);
            }
            AdamW::new(vars, AdamWConfig::default())
        };
        let (mut fused, mut plain) = (make(DType::F32)?, make(DType::F64)?);
        for step in 0..3u64 {
            let grads64: Vec<Option<Tensor>> = shapes
                .iter()
                .enumerate()
                .map(|(i, (_, dims))| {
                    pixl_nn::testing::uniform(*dims, -2.0, 2.0, 100 * step + i as u64, &dev).map(Some)
                })
                .collect::<Result<_>>()?;
            let mut g32: Vec<Option<Tensor>> = grads64
                .iter()
                .map(|g| g.as_ref().map(|g| g.to_dtype(DType::F32)).transpose())
                .collect::<Result<_>>()?;
            let mut g64 = grads64.clone();
            let (n32, n64) = (clip_global_norm(&mut g32, 3.0)?, clip_global_norm(&mut g64, 3.0)?);
            assert!((n32 - n64).abs() < 1e-5 * n64, "norm {n32} vs {n64}");
            fused.step(&g32, 1e-2)?;
            plain.step(&g64, 1e-2)?;
        }
        for (a, b) in fused.params.iter().zip(&plain.params) {
            for (x, y) in [(a.var.as_tensor(), b.var.as_tensor()), (&a.m, &b.m), (&a.v, &b.v)] {
                let d = pixl_nn::testing::max_abs_diff(&x.to_dtype(DType::F64)?, y)?;
                assert!(d < 1e-5, "{}: {d}", a.name);
            }
        }
        Ok(())
    }
}
