//! The training loop (paper §3.3, App. A): pairs from the [`Sampler`], C_T corrupted on the fly
//! (App. C, per-sample seeds from `(seed, step, index)`), loss eq. 5, gradient accumulation over
//! `accumulate` micro-batches, global-norm clipping, AdamW with the warm-up/cosine schedule.
//!
//! Outputs under `run.out_dir`: `log.jsonl` (one JSON object per logged step), `samples/
//! step_<N>.png` grids (rows: samples; columns: source | albedo | shading | residual |
//! prediction | target), `train-state.safetensors` (full resumable state, [`crate::state`]) and
//! `model.safetensors` (weights only, loadable by `pixl_model::load`); with `[optim] ema_decay`
//! also `model-ema.safetensors`, the weights' exponential moving average ([`Ema`]), updated after
//! every optimiser step and resumed with the rest of the state.
//!
//! A run can be bounded by time (`[run] max_minutes`: the cosine of the learning rate then runs
//! over the time, [`LrSchedule::lr_at_progress`]), checkpoint by time as well as by steps
//! (`[run] checkpoint_minutes`), and read a data set that grows while it trains (`[data]
//! refresh_every`: the set is opened again every so many steps and its new scenes join the
//! sampler, [`Sampler::add_scenes`]; logged as `{"event": "data", ...}`).
//!
//! Precision (`[optim] precision`): f32 by default; `bf16` computes each micro-batch with a bf16
//! copy of the f32 master weights ([`crate::precision`]), gradients and AdamW stay f32.
//! `[optim] checkpoint = true` recomputes every encoder/trunk block in the backward pass
//! ([`crate::recompute`]); same loss, same gradients up to summation order.
use crate::config::{AugmentSection, TrainConfig};
use crate::error::{Result, TrainError};
use crate::loss::{Objective, Perceptual};
use crate::optim::{clip_global_norm, AdamW, Ema, LrSchedule};
use crate::precision::{compute_model, Precision};
use crate::recompute;
use crate::sampler::{DiskLoader, Loader, Sample, Sampler};
use crate::state::{self, Meta, State, MODEL_EMA_FILE, MODEL_FILE, STATE_FILE};
use candle_core::{Device, Tensor, Var};
use candle_nn::VarMap;
use pixl_core::{Image, Rng};
use pixl_data::SceneEntry;
use pixl_model::{Config, PixlRelight};
use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

const STREAM_AUGMENT: u64 = 0xA06;

/// What one optimiser step did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct StepReport {
    /// Steps completed after this one.
    pub step: u64,
    pub loss: f32,
    pub l1: f32,
    pub perceptual: Option<f32>,
    pub lr: f64,
    pub grad_norm: f64,
    pub images_per_s: f64,
}

pub struct Trainer {
    pub cfg: TrainConfig,
    pub model_cfg: Config,
    model: PixlRelight,
    varmap: VarMap,
    opt: AdamW,
    /// The weights' moving average (`[optim] ema_decay` > 0).
    ema: Option<Ema>,
    sampler: Sampler,
    loader: Box<dyn Loader>,
    perceptual: Option<Perceptual>,
    device: Device,
    /// Optimiser steps completed.
    pub step: u64,
    /// The clock of a run bounded by time (`[run] max_minutes`), started by [`Trainer::run`].
    clock: Option<Clock>,
    /// The next micro-batch, prepared on another thread while the previous step ran, with the
    /// micro-step it belongs to (used only when that step comes; dropped when the data change).
    prefetched: Option<(u64, Result<Batch>)>,
}

/// One micro-batch as the model takes it: source `(B,3,H,W)`, target `(B,3,H,W)` and C_T
/// `(B,9,H,W)`, corrupted when augmentation is on.
struct Batch {
    src: Tensor,
    tgt: Tensor,
    ct: Tensor,
    images: usize,
}

/// The micro-batch of `micro_step`: drawn by the sampler, stacked and corrupted as `augment`
/// says. A pure function of its arguments, so it can be prepared ahead of its step on another
/// thread with the same result.
fn prepare_batch(
    sampler: &Sampler,
    loader: &dyn Loader,
    augment: &AugmentSection,
    seed: u64,
    micro_step: u64,
    device: &Device,
) -> Result<Batch> {
    let samples = sampler.batch(micro_step, loader)?;
    let (src, tgt, ct) = Trainer::to_tensors(&samples, device)?;
    let ct = if augment.enabled {
        let seeds = augment_seeds(seed, micro_step, samples.len());
        let corrupted: Vec<bool> = samples.iter().map(|s| augment.coarse || !s.coarse_ct).collect();
        let cfg = pixl_intrinsics::augment::AugmentConfig::paper();
        pixl_intrinsics::augment::corrupt_where(&ct, &seeds, &corrupted, &cfg)?
    } else {
        ct
    };
    Ok(Batch {
        src,
        tgt,
        ct,
        images: samples.len(),
    })
}

/// Per-sample corruption seeds of micro-batch `micro_step` of a run with seed `seed`.
fn augment_seeds(seed: u64, micro_step: u64, n: usize) -> Vec<u64> {
    (0..n)
        .map(|i| Rng::for_stream(seed, &[STREAM_AUGMENT, micro_step, i as u64]).next_u64())
        .collect()
}

/// When a time-bounded run started, how long it may take, and the fraction of that time that had
/// passed when the warm-up ended (the cosine runs over the rest).
#[derive(Clone, Copy, Debug)]
struct Clock {
    start: Instant,
    budget: Duration,
    warmup_end: Option<f64>,
}

impl Clock {
    fn fraction(&self) -> f64 {
        self.start.elapsed().as_secs_f64() / self.budget.as_secs_f64().max(1e-9)
    }
}

/// Overwrites the fresh weights in `varmap` with those of checkpoint `path`, which must store
/// the model config `cfg` (`[model] init_weights`).
fn init_from(path: &Path, cfg: &Config, varmap: &VarMap) -> Result<()> {
    let stored = pixl_model::checkpoint::read_config(path)?;
    if stored != *cfg {
        return Err(TrainError::File {
            path: path.to_owned(),
            reason: format!(
                "[model] init_weights holds a different model config than this run's preset \
                 (stored width d = {}, trunk depth {}, patch {}; this run d = {}, trunk depth {}, patch {}): \
                 set [model] preset to the checkpoint's config",
                stored.dim, stored.trunk.depth, stored.patch, cfg.dim, cfg.trunk.depth, cfg.patch
            ),
        });
    }
    pixl_model::checkpoint::load_into_varmap(path, varmap)?;
    tracing::info!("initialised the weights from {}", path.display());
    Ok(())
}

fn vars_of(varmap: &VarMap) -> Result<BTreeMap<String, Var>> {
    let data = varmap
        .data()
        .lock()
        .map_err(|_| TrainError::Other("VarMap lock poisoned".into()))?;
    Ok(data.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
}

fn fingerprint(scenes: &[SceneEntry]) -> String {
    let first = scenes.first().map(|s| s.name.as_str()).unwrap_or("");
    let last = scenes.last().map(|s| s.name.as_str()).unwrap_or("");
    format!("{}:{first}:{last}", scenes.len())
}

impl Trainer {
    /// A fresh run over the dataset named in `cfg`, read from disk.
    pub fn new(cfg: TrainConfig, device: &Device) -> Result<Self> {
        cfg.validate()?;
        let ds = pixl_data::open(&cfg.data.dataset, cfg.data.split)?;
        let loader = Box::new(DiskLoader::new(cfg.data.cache));
        Self::with_data(cfg, ds.scenes().to_vec(), loader, device)
    }

    /// A fresh run over given scenes and loader.
    pub fn with_data(
        cfg: TrainConfig,
        scenes: Vec<SceneEntry>,
        loader: Box<dyn Loader>,
        device: &Device,
    ) -> Result<Self> {
        cfg.validate()?;
        let model_cfg = Config::from_name_or_file(&cfg.model.preset)
            .map_err(|e| TrainError::Config(format!("[model] preset: {e}")))?;
        let (varmap, model) = pixl_model::build_trainable(&model_cfg, cfg.model.init_seed, device)?;
        if let Some(path) = &cfg.model.init_weights {
            init_from(path, &model_cfg, &varmap)?;
        }
        let opt = AdamW::new(vars_of(&varmap)?, cfg.optim.adamw.clone())?;
        let ema = match cfg.optim.ema_decay {
            d if d > 0.0 => Some(Ema::new(&opt.params, d)?),
            _ => None,
        };
        let sampler = Sampler::new(scenes, cfg.data.sampler.clone(), cfg.optim.batch_size, cfg.run.seed)?;
        let (coarse, pairs) = sampler.coarse_pairs();
        if coarse > 0 {
            tracing::info!(
                "coarse C_T exists for {coarse} of {pairs} ordered pairs: about {:.1} % of samples are conditioned on one",
                100.0 * sampler.coarse_fraction()
            );
        }
        let perceptual = match (&cfg.loss.vgg, cfg.loss.perceptual_weight > 0.0) {
            (Some(p), true) => Some(Perceptual::load(p, device)?),
            _ => None,
        };
        match (perceptual.is_none(), cfg.loss.ssim_weight > 0.0) {
            (true, false) => tracing::info!("perceptual weight is 0: training with the L1 loss only"),
            (true, true) => tracing::info!(
                "perceptual weight is 0: training with L1 + {} x (1 - SSIM)",
                cfg.loss.ssim_weight
            ),
            (false, true) => tracing::info!("adding {} x (1 - SSIM) to the paper's loss", cfg.loss.ssim_weight),
            (false, false) => {}
        }
        if cfg.loss.scale_corrected > 0.0 {
            tracing::info!(
                "{} of the L1 term taken after a per-channel least-squares scale correction",
                cfg.loss.scale_corrected
            );
        }
        if ema.is_some() {
            tracing::info!(
                "keeping a moving average of the weights (decay {}): {}",
                cfg.optim.ema_decay,
                cfg.run.out_dir.join(MODEL_EMA_FILE).display()
            );
        }
        Ok(Self {
            cfg,
            model_cfg,
            model,
            varmap,
            opt,
            ema,
            sampler,
            loader,
            perceptual,
            device: device.clone(),
            step: 0,
            clock: None,
            prefetched: None,
        })
    }

    /// Restores weights, optimiser moments and step from `out_dir/train-state.safetensors`.
    pub fn restore(&mut self) -> Result<()> {
        self.prefetched = None;
        let path = self.state_path();
        let st = state::load(&path, &self.device)?;
        let mismatch = |what: &str, a: &str, b: &str| TrainError::File {
            path: path.clone(),
            reason: format!("checkpoint {what} {a:?} differs from this run's {b:?}; resume needs the same setup"),
        };
        let fp = fingerprint(self.sampler.scenes());
        if self.cfg.data.refresh_every > 0 {
            tracing::info!("[data] refresh_every: the data set may have grown since the checkpoint; not compared");
        } else if st.meta.data_fingerprint != fp {
            return Err(mismatch("data set", &st.meta.data_fingerprint, &fp));
        }
        if st.meta.seed != self.cfg.run.seed {
            return Err(mismatch(
                "seed",
                &st.meta.seed.to_string(),
                &self.cfg.run.seed.to_string(),
            ));
        }
        if st.meta.model_config != self.model_cfg.to_json() {
            return Err(mismatch("model config", "(stored)", &self.cfg.model.preset));
        }
        let get = |key: String| {
            st.tensors.get(&key).cloned().ok_or_else(|| TrainError::File {
                path: path.clone(),
                reason: format!("tensor {key} missing"),
            })
        };
        for p in self.opt.params.iter_mut() {
            p.var.set(&get(format!("param.{}", p.name))?)?;
            p.m = get(format!("adam_m.{}", p.name))?;
            p.v = get(format!("adam_v.{}", p.name))?;
        }
        if let Some(ema) = self.ema.as_mut() {
            if self
                .opt
                .params
                .iter()
                .all(|p| st.tensors.contains_key(&format!("ema.{}", p.name)))
            {
                for (s, p) in ema.shadow.iter_mut().zip(&self.opt.params) {
                    *s = get(format!("ema.{}", p.name))?;
                }
            } else {
                tracing::warn!(
                    "{} holds no moving average of the weights: [optim] ema_decay starts one from the restored weights",
                    path.display()
                );
                *ema = Ema::new(&self.opt.params, ema.decay)?;
            }
        }
        self.opt.steps = st.meta.optimizer_steps;
        self.step = st.meta.step;
        Ok(())
    }

    pub fn state_path(&self) -> PathBuf {
        self.cfg.run.out_dir.join(STATE_FILE)
    }

    pub fn model_path(&self) -> PathBuf {
        self.cfg.run.out_dir.join(MODEL_FILE)
    }

    /// Where the weights' moving average is written, when the run keeps one.
    pub fn ema_model_path(&self) -> Option<PathBuf> {
        self.ema.as_ref().map(|_| self.cfg.run.out_dir.join(MODEL_EMA_FILE))
    }

    /// The weights' moving average by parameter name, when the run keeps one.
    pub fn ema_weights(&self) -> Option<HashMap<String, Tensor>> {
        let ema = self.ema.as_ref()?;
        Some(
            self.opt
                .params
                .iter()
                .zip(&ema.shadow)
                .map(|(p, s)| (p.name.clone(), s.clone()))
                .collect(),
        )
    }

    pub fn model(&self) -> &PixlRelight {
        &self.model
    }

    pub fn schedule(&self) -> &LrSchedule {
        &self.cfg.optim.schedule
    }

    /// The scenes the sampler draws from (more after a refresh of a growing set).
    pub fn scenes(&self) -> &[SceneEntry] {
        self.sampler.scenes()
    }

    pub fn sampler(&self) -> &Sampler {
        &self.sampler
    }

    /// Opens the data set again and adds its new scenes to the sampler (`[data] refresh_every`);
    /// returns how many joined. Only scenes with all their files are listed by the data sets, and
    /// a set that cannot be read right now (say, a manifest being replaced) adds nothing.
    pub fn refresh_data(&mut self) -> usize {
        match pixl_data::open(&self.cfg.data.dataset, self.cfg.data.split) {
            Ok(ds) => {
                self.prefetched = None;
                self.sampler.add_scenes(ds.scenes().to_vec())
            }
            Err(e) => {
                tracing::warn!(
                    "reading the data set again: {e}; keeping the {} scenes",
                    self.sampler.scenes().len()
                );
                0
            }
        }
    }

    /// The learning rate of the coming step: by step, or by time in a time-bounded run.
    fn lr_now(&mut self) -> f64 {
        let schedule = &self.cfg.optim.schedule;
        let Some(clock) = self.clock.as_mut() else {
            return schedule.lr(self.step);
        };
        let f = clock.fraction();
        if self.step < schedule.warmup_steps {
            return schedule.lr(self.step);
        }
        let w = *clock.warmup_end.get_or_insert(f);
        schedule.lr_at_progress(self.step, (f - w) / (1.0 - w).max(1e-9))
    }

    /// Writes the training state and the weights-only model file (both atomically).
    pub fn save_checkpoint(&self) -> Result<()> {
        std::fs::create_dir_all(&self.cfg.run.out_dir).map_err(|e| TrainError::io(&self.cfg.run.out_dir, e))?;
        let mut tensors = BTreeMap::new();
        for p in &self.opt.params {
            tensors.insert(format!("param.{}", p.name), p.var.as_tensor().clone());
            tensors.insert(format!("adam_m.{}", p.name), p.m.clone());
            tensors.insert(format!("adam_v.{}", p.name), p.v.clone());
        }
        if let Some(ema) = &self.ema {
            for (p, s) in self.opt.params.iter().zip(&ema.shadow) {
                tensors.insert(format!("ema.{}", p.name), s.clone());
            }
        }
        let meta = Meta {
            format: state::FORMAT.into(),
            step: self.step,
            optimizer_steps: self.opt.steps,
            seed: self.cfg.run.seed,
            data_fingerprint: fingerprint(self.sampler.scenes()),
            model_config: self.model_cfg.to_json(),
        };
        state::save(&self.state_path(), &State { meta, tensors })?;
        pixl_model::save(&self.model_path(), &self.varmap, &self.model_cfg)?;
        if let (Some(path), Some(weights)) = (self.ema_model_path(), self.ema_weights()) {
            pixl_model::save_tensors(&path, &weights, &self.model_cfg)?;
        }
        Ok(())
    }

    /// Stacks samples into `(src, target, ct)` tensors `(B,3,H,W)`, `(B,3,H,W)`, `(B,9,H,W)`.
    pub fn to_tensors(samples: &[Sample], device: &Device) -> Result<(Tensor, Tensor, Tensor)> {
        let (w, h) = (samples[0].source.width, samples[0].source.height);
        let stack = |f: &dyn Fn(&Sample) -> &Image, c: usize| -> Result<Tensor> {
            let data: Vec<f32> = samples.iter().flat_map(|s| f(s).to_chw()).collect();
            Ok(Tensor::from_vec(data, (samples.len(), c, h, w), device)?)
        };
        Ok((
            stack(&|s| &s.source, 3)?,
            stack(&|s| &s.target, 3)?,
            stack(&|s| &s.ct, 9)?,
        ))
    }

    /// One optimiser step (with `accumulate` micro-batches).
    pub fn train_step(&mut self) -> Result<StepReport> {
        let t0 = Instant::now();
        let accum = self.cfg.optim.accumulate;
        let lr = self.lr_now();
        let mut grads: Vec<Option<Tensor>> = vec![None; self.opt.params.len()];
        let vars: Vec<Var> = self.opt.params.iter().map(|p| p.var.clone()).collect();
        let (mut loss_sum, mut l1_sum, mut perc_sum, mut images) = (0.0f32, 0.0f32, None::<f32>, 0usize);
        for micro in 0..accum {
            let micro_step = self.step * accum as u64 + micro as u64;
            let (augment, seed) = (&self.cfg.augment, self.cfg.run.seed);
            let batch = match self.prefetched.take() {
                Some((k, batch)) if k == micro_step => batch?,
                _ => prepare_batch(
                    &self.sampler,
                    self.loader.as_ref(),
                    augment,
                    seed,
                    micro_step,
                    &self.device,
                )?,
            };
            images += batch.images;
            let compute;
            let model = match self.cfg.optim.precision {
                Precision::F32 => &self.model,
                p => {
                    compute = compute_model(&self.model_cfg, &self.opt.params, p.dtype(), &self.device)?;
                    &compute
                }
            };
            let step_fn = if self.cfg.optim.checkpoint {
                recompute::checkpointed
            } else {
                recompute::plain
            };
            // The next micro-batch is drawn on another thread while this one trains.
            let (sampler, loader, device) = (&self.sampler, self.loader.as_ref(), &self.device);
            let objective = Objective {
                perceptual: self.perceptual.as_ref(),
                weight: self.cfg.loss.perceptual_weight,
                ssim_weight: self.cfg.loss.ssim_weight,
                scale_corrected: self.cfg.loss.scale_corrected,
            };
            let (r, next) = std::thread::scope(|scope| {
                let ahead = scope.spawn(move || prepare_batch(sampler, loader, augment, seed, micro_step + 1, device));
                let r = step_fn(
                    model,
                    &batch.src,
                    &batch.ct,
                    &batch.tgt,
                    &objective,
                    accum as f64,
                    &vars,
                    &mut grads,
                );
                let next = ahead
                    .join()
                    .unwrap_or_else(|_| Err(TrainError::Other("preparing the next batch panicked".into())));
                (r, next)
            });
            self.prefetched = Some((micro_step + 1, next));
            let r = r?;
            loss_sum += r.loss;
            l1_sum += r.l1 / accum as f32;
            if let Some(p) = r.perceptual {
                perc_sum = Some(perc_sum.unwrap_or(0.0) + p / accum as f32);
            }
        }
        if !loss_sum.is_finite() {
            return Err(TrainError::Other(format!(
                "loss is {loss_sum} at step {}; stopping",
                self.step
            )));
        }
        let grad_norm = clip_global_norm(&mut grads, self.cfg.optim.clip_norm)?;
        self.opt.step(&grads, lr)?;
        if let Some(ema) = self.ema.as_mut() {
            ema.update(&self.opt.params, self.opt.steps - 1)?;
        }
        self.step += 1;
        let secs = t0.elapsed().as_secs_f64().max(1e-9);
        Ok(StepReport {
            step: self.step,
            loss: loss_sum,
            l1: l1_sum,
            perceptual: perc_sum,
            lr,
            grad_norm,
            images_per_s: images as f64 / secs,
        })
    }

    /// A grid for the first samples of `step`: rows of source | albedo | shading | residual |
    /// prediction | target (C_T shown as the network sees it, uncorrupted, clipped to [0, 1]).
    pub fn sample_grid(&self, step: u64, rows: usize) -> Result<Image> {
        let samples = self.sampler.batch(step, self.loader.as_ref())?;
        let samples = &samples[..rows.min(samples.len()).max(1)];
        let (src, _, ct) = Self::to_tensors(samples, &self.device)?;
        let pred = self.model.forward(&src, &ct)?.to_dtype(candle_core::DType::F32)?;
        let (w, h) = (samples[0].source.width, samples[0].source.height);
        let mut grid_rows = Vec::new();
        for (i, s) in samples.iter().enumerate() {
            let p: Vec<f32> = pred.get(i)?.flatten_all()?.to_vec1()?;
            let pred_img = Image::from_chw(w, h, 3, &p)?;
            let clip = |img: Image| img.map(|v| v.clamp(0.0, 1.0));
            let parts = [
                s.source.clone(),
                clip(s.ct.select_channels(0..3)),
                clip(s.ct.select_channels(3..6)),
                clip(s.ct.select_channels(6..9)),
                pred_img,
                s.target.clone(),
            ];
            grid_rows.push(Image::hstack(&parts.iter().collect::<Vec<_>>())?);
        }
        Ok(vstack(&grid_rows))
    }

    /// Trains until `cfg.run.steps` (or `[run] max_minutes`), logging, writing sample grids and
    /// checkpoints, reading a growing data set again; `on_step` sees every step (for a progress
    /// bar). A final checkpoint is written at the end.
    pub fn run(&mut self, mut on_step: impl FnMut(&StepReport)) -> Result<()> {
        let out = self.cfg.run.out_dir.clone();
        std::fs::create_dir_all(out.join("samples")).map_err(|e| TrainError::io(&out, e))?;
        let log_path = out.join("log.jsonl");
        let mut log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .map_err(|e| TrainError::io(&log_path, e))?;
        let start = serde_json::json!({"event": "start", "step": self.step, "l1_only": self.perceptual.is_none() && self.cfg.loss.ssim_weight == 0.0,
            "ssim_weight": self.cfg.loss.ssim_weight, "ema_decay": self.cfg.optim.ema_decay});
        writeln!(log, "{start}").map_err(|e| TrainError::io(&log_path, e))?;
        let minutes = |m: f64| Duration::from_secs_f64(m * 60.0);
        self.clock = self.cfg.run.max_minutes.map(|m| Clock {
            start: Instant::now(),
            budget: minutes(m),
            warmup_end: None,
        });
        let every = self.cfg.run.checkpoint_minutes.map(minutes);
        let mut last_checkpoint = Instant::now();
        while self.step < self.cfg.run.steps && self.clock.is_none_or(|c| c.fraction() < 1.0) {
            let report = self.train_step()?;
            on_step(&report);
            let s = report.step;
            let refresh = self.cfg.data.refresh_every;
            if refresh > 0 && s % refresh == 0 {
                let added = self.refresh_data();
                if added > 0 {
                    tracing::info!(
                        "{added} new scene(s) joined the data set ({} in all)",
                        self.sampler.scenes().len()
                    );
                    let line = serde_json::json!({"event": "data", "step": s, "added": added, "scenes": self.sampler.scenes().len()});
                    writeln!(log, "{line}").map_err(|e| TrainError::io(&log_path, e))?;
                }
            }
            if s % self.cfg.run.log_every == 0 || s == self.cfg.run.steps {
                let line = serde_json::to_string(&report).map_err(|e| TrainError::Other(e.to_string()))?;
                writeln!(log, "{line}").map_err(|e| TrainError::io(&log_path, e))?;
            }
            if s % self.cfg.run.sample_every == 0 {
                let grid = self.sample_grid(s, 4)?;
                pixl_core::io::write_png(
                    &out.join(format!("samples/step_{s:07}.png")),
                    &grid,
                    pixl_core::io::PngDepth::Eight,
                )?;
            }
            if s % self.cfg.run.checkpoint_every == 0 || every.is_some_and(|d| last_checkpoint.elapsed() >= d) {
                self.save_checkpoint()?;
                last_checkpoint = Instant::now();
            }
        }
        if self.step < self.cfg.run.steps {
            let line =
                serde_json::json!({"event": "time_limit", "step": self.step, "max_minutes": self.cfg.run.max_minutes});
            writeln!(log, "{line}").map_err(|e| TrainError::io(&log_path, e))?;
        }
        self.save_checkpoint()
    }
}

fn vstack(rows: &[Image]) -> Image {
    let w = rows.iter().map(|r| r.width).max().unwrap_or(0);
    let ch = rows.first().map(|r| r.channels).unwrap_or(3);
    let h: usize = rows.iter().map(|r| r.height).sum();
    let mut out = Image::new(w, h, ch);
    let mut y0 = 0;
    for r in rows {
        for y in 0..r.height {
            let src = &r.data[y * r.width * ch..(y + 1) * r.width * ch];
            let dst = ((y0 + y) * w) * ch;
            out.data[dst..dst + src.len()].copy_from_slice(src);
        }
        y0 += r.height;
    }
    out
}
