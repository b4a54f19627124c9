//! Gradient checkpointing and bf16 compute against the plain f32 backward.
//!
//! The network is `tiny` from `build_trainable`, with the zero-initialised modulation conv
//! replaced by random values: with it at zero every gradient upstream of it is exactly zero,
//! which would make "the gradients agree" vacuous. Each test also checks that every parameter
//! receives a non-zero gradient.
mod common;

use candle_core::{DType, Device, Tensor, Var};
use common::fake_set;
use pixl_model::{Config, PixlRelight};
use pixl_train::optim::{AdamW, AdamWConfig, LrSchedule};
use pixl_train::precision::{compute_model, Precision};
use pixl_train::recompute::{checkpointed, plain, MicroReport};
use pixl_train::{TrainConfig, Trainer};
use std::collections::BTreeMap;

struct Setup {
    cfg: Config,
    model: PixlRelight,
    opt: AdamW,
    vars: Vec<Var>,
    src: Tensor,
    ct: Tensor,
    tgt: Tensor,
}

/// `tiny`, seed 3, modulation conv random; a batch of 2 at 40×24 (padded to 48×32: the crop
/// and edge replication are on the path).
fn setup() -> Setup {
    let dev = Device::Cpu;
    let cfg = Config::tiny();
    let (varmap, model) = pixl_model::build_trainable(&cfg, 3, &dev).unwrap();
    let vars: BTreeMap<String, Var> = varmap.data().lock().unwrap().clone().into_iter().collect();
    for (name, var) in &vars {
        if name.starts_with("modulation.") {
            let noise = pixl_nn::testing::uniform(var.shape().clone(), -0.3, 0.3, 11, &dev).unwrap();
            var.set(&noise.to_dtype(DType::F32).unwrap()).unwrap();
        }
    }
    let opt = AdamW::new(vars, AdamWConfig::default()).unwrap();
    let vars: Vec<Var> = opt.params.iter().map(|p| p.var.clone()).collect();
    let u = |c: usize, seed: u64| {
        pixl_nn::testing::uniform((2, c, 40, 24), 0.0, 1.0, seed, &dev)
            .unwrap()
            .to_dtype(DType::F32)
            .unwrap()
    };
    Setup {
        cfg,
        model,
        opt,
        vars,
        src: u(3, 1),
        ct: u(9, 2),
        tgt: u(3, 4),
    }
}

type StepFn = fn(
    &PixlRelight,
    &Tensor,
    &Tensor,
    &Tensor,
    &pixl_train::loss::Objective,
    f64,
    &[Var],
    &mut [Option<Tensor>],
) -> pixl_train::Result<MicroReport>;

/// Loss report and gradients of every parameter for `model` (the two micro-batches of an
/// `accumulate = 2` step: the same batch twice, divisor 2).
fn grads_of(s: &Setup, model: &PixlRelight, f: StepFn) -> (Vec<MicroReport>, Vec<Tensor>) {
    let mut grads = vec![None; s.vars.len()];
    let reports = (0..2)
        .map(|_| {
            f(
                model,
                &s.src,
                &s.ct,
                &s.tgt,
                &pixl_train::loss::Objective::l1_only(),
                2.0,
                &s.vars,
                &mut grads,
            )
            .unwrap()
        })
        .collect();
    let grads = grads
        .into_iter()
        .zip(&s.opt.params)
        .map(|(g, p)| g.unwrap_or_else(|| panic!("{}: no gradient", p.name)))
        .collect();
    (reports, grads)
}

fn to_f64(t: &Tensor) -> Vec<f64> {
    t.to_dtype(DType::F64)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1()
        .unwrap()
}

fn max_abs(v: &[f64]) -> f64 {
    v.iter()
        .fold(0.0, |m, x| if x.is_nan() { f64::NAN } else { m.max(x.abs()) })
}

/// Every gradient finite, f32 and not identically zero.
fn check_nonzero(s: &Setup, grads: &[Tensor]) {
    for (g, p) in grads.iter().zip(&s.opt.params) {
        assert_eq!(g.dtype(), DType::F32, "{}", p.name);
        let v = to_f64(g);
        let m = max_abs(&v);
        assert!(m.is_finite() && m > 0.0, "{}: max |grad| = {m}", p.name);
    }
}

#[test]
fn checkpointed_gradients_equal_plain_gradients() {
    let s = setup();
    let (r_plain, g_plain) = grads_of(&s, &s.model, plain);
    let (r_ckpt, g_ckpt) = grads_of(&s, &s.model, checkpointed);
    // Same operations on the same values: the loss is bitwise the same.
    assert_eq!(r_plain, r_ckpt);
    assert!(r_plain[0].loss.is_finite() && r_plain[0].loss > 0.0);
    check_nonzero(&s, &g_plain);
    let mut worst = (0.0f64, String::new());
    for ((a, b), p) in g_ckpt.iter().zip(&g_plain).zip(&s.opt.params) {
        let (a, b) = (to_f64(a), to_f64(b));
        let diff: Vec<f64> = a.iter().zip(&b).map(|(x, y)| x - y).collect();
        // Relative to the tensor's largest gradient; NaN compares false and fails.
        let rel = max_abs(&diff) / max_abs(&b);
        assert!(rel <= 1e-5, "{}: max relative error {rel}", p.name);
        if rel > worst.0 {
            worst = (rel, p.name.clone());
        }
    }
    eprintln!(
        "{} parameters, worst relative error {:.3e} ({})",
        g_plain.len(),
        worst.0,
        worst.1
    );
}

/// bf16 compute over f32 master weights: gradients arrive on the f32 `Var`s, every one finite
/// and non-zero, and close to the f32 gradients (per-tensor cosine similarity and the relative
/// error of the whole gradient vector; measured values in the eprintln).
#[test]
fn bf16_compute_gradients_match_f32() {
    let s = setup();
    let (r32, g32) = grads_of(&s, &s.model, plain);
    let bf = compute_model(&s.cfg, &s.opt.params, Precision::Bf16.dtype(), &Device::Cpu).unwrap();
    assert_eq!(bf.dtype(), DType::BF16);
    for (name, f) in [("plain", plain as StepFn), ("checkpointed", checkpointed as StepFn)] {
        let (r16, g16) = grads_of(&s, &bf, f);
        check_nonzero(&s, &g16);
        let loss_rel = ((r16[0].loss - r32[0].loss) / r32[0].loss).abs();
        let (mut num, mut den, mut worst_cos) = (0.0f64, 0.0f64, (1.0f64, String::new()));
        for ((a, b), p) in g16.iter().zip(&g32).zip(&s.opt.params) {
            let (a, b) = (to_f64(a), to_f64(b));
            let dot: f64 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
            let na = a.iter().map(|x| x * x).sum::<f64>().sqrt();
            let nb = b.iter().map(|x| x * x).sum::<f64>().sqrt();
            let cos = dot / (na * nb);
            if cos.is_nan() || cos < worst_cos.0 {
                worst_cos = (cos, p.name.clone());
            }
            num += a.iter().zip(&b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>();
            den += b.iter().map(|x| x * x).sum::<f64>();
        }
        let global_rel = (num / den).sqrt();
        eprintln!(
            "bf16 {name}: loss rel err {loss_rel:.2e}, global gradient rel err {global_rel:.3e}, \
             worst cosine {:.5} ({})",
            worst_cos.0, worst_cos.1
        );
        assert!(loss_rel < 1e-2, "bf16 loss {} vs f32 {}", r16[0].loss, r32[0].loss);
        assert!(global_rel < 5e-2, "global relative gradient error {global_rel}");
        assert!(worst_cos.0 > 0.99, "cosine {} for {}", worst_cos.0, worst_cos.1);
    }
}

/// 20 optimiser steps (2 micro-batches each, C_T corruption on) with and without
/// checkpointing give the same losses.
#[test]
fn checkpointed_training_run_matches_plain() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    fake_set(&data, 3, 3, 32);
    let run = |out: &str, checkpoint: bool| -> Vec<f32> {
        let mut cfg = TrainConfig::default();
        cfg.data.dataset = format!("folder:{}", data.display());
        cfg.data.split = pixl_data::Split::All;
        cfg.data.sampler.long_side = 32;
        cfg.loss.perceptual_weight = 0.0;
        cfg.optim.batch_size = 2;
        cfg.optim.accumulate = 2;
        cfg.optim.checkpoint = checkpoint;
        cfg.optim.schedule = LrSchedule {
            peak_lr: 1e-3,
            final_lr: 1e-4,
            warmup_steps: 5,
            total_steps: 40,
        };
        cfg.run.out_dir = dir.path().join(out);
        cfg.run.steps = 20;
        cfg.run.seed = 5;
        cfg.run.checkpoint_every = 1000;
        cfg.run.sample_every = 1000;
        let mut t = Trainer::new(cfg, &Device::Cpu).unwrap();
        let mut losses = Vec::new();
        t.run(|r| losses.push(r.loss)).unwrap();
        losses
    };
    let a = run("plain", false);
    let b = run("ckpt", true);
    assert_eq!(a.len(), 20);
    assert!(a.windows(2).any(|w| w[0] != w[1]), "{a:?}");
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| ((x - y) / x).abs() as f64)
        .fold(0.0f64, |m, r| if r.is_nan() { f64::NAN } else { m.max(r) });
    eprintln!("20-step losses: worst relative difference {worst:.3e}\nplain {a:?}\nckpt  {b:?}");
    assert!(worst <= 1e-6, "worst relative loss difference {worst}");
}

#[test]
fn config_keys_parse() {
    let cfg: TrainConfig = toml::from_str("[optim]\nprecision = \"bf16\"\ncheckpoint = true\n").unwrap();
    assert_eq!(cfg.optim.precision, Precision::Bf16);
    assert!(cfg.optim.checkpoint);
    let d = TrainConfig::default();
    assert_eq!(d.optim.precision, Precision::F32);
    assert!(!d.optim.checkpoint);
    assert!(toml::from_str::<TrainConfig>("[optim]\nprecision = \"fp8\"\n").is_err());
}
