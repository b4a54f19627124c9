//! Peak memory and step time of training steps, with and without gradient checkpointing
//! (BENCHMARKS.md, "Training step: precision, checkpointing, memory"). Run it under `/usr/bin/time -v`
//! for the peak RSS:
//!
//! ```text
//! cargo run --release -p pixl-train --example train_memory -- PRESET SIZE BATCH STEPS CHECKPOINT [PRECISION]
//! /usr/bin/time -v target/release/examples/train_memory small 256 2 3 true f32
//! ```
//!
//! One optimiser step = the loss of a random `(BATCH, 3, SIZE, SIZE)` batch (L1 only), its
//! gradients (plain or checkpointed, `pixl_train::recompute`), global-norm clipping and AdamW.
//! Prints the loss and wall time of every step.
use candle_core::{DType, Device, Tensor, Var};
use pixl_train::optim::{clip_global_norm, AdamW, AdamWConfig};
use pixl_train::precision::{compute_model, Precision};
use pixl_train::recompute::{checkpointed, plain};
use std::collections::BTreeMap;
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 5 {
        return Err("usage: train_memory PRESET SIZE BATCH STEPS CHECKPOINT(true|false) [f32|bf16]".into());
    }
    let cfg = pixl_model::Config::from_name_or_file(&args[0])?;
    let size: usize = args[1].parse()?;
    let batch: usize = args[2].parse()?;
    let steps: usize = args[3].parse()?;
    let ckpt: bool = args[4].parse()?;
    let precision = match args.get(5).map(String::as_str) {
        None | Some("f32") => Precision::F32,
        Some("bf16") => Precision::Bf16,
        Some(p) => return Err(format!("precision {p}: f32 or bf16").into()),
    };
    let dev = Device::Cpu;
    let (varmap, model) = pixl_model::build_trainable(&cfg, 0, &dev)?;
    let vars: BTreeMap<String, Var> = varmap
        .data()
        .lock()
        .map_err(|_| "VarMap lock poisoned")?
        .clone()
        .into_iter()
        .collect();
    let mut opt = AdamW::new(vars, AdamWConfig::default())?;
    let list: Vec<Var> = opt.params.iter().map(|p| p.var.clone()).collect();
    let u = |c: usize, seed: u64| -> candle_core::Result<Tensor> {
        pixl_nn::testing::uniform((batch, c, size, size), 0.0, 1.0, seed, &dev)?.to_dtype(DType::F32)
    };
    let (src, ct, tgt) = (u(3, 1)?, u(9, 2)?, u(3, 3)?);
    println!(
        "preset {} ({} params), {batch}×{size}², checkpoint {ckpt}, {precision:?}",
        args[0],
        cfg.param_count()
    );
    for step in 0..steps {
        let t0 = Instant::now();
        let compute;
        let m = match precision {
            Precision::F32 => &model,
            p => {
                compute = compute_model(&cfg, &opt.params, p.dtype(), &dev)?;
                &compute
            }
        };
        let f = if ckpt { checkpointed } else { plain };
        let mut grads = vec![None; list.len()];
        let r = f(
            m,
            &src,
            &ct,
            &tgt,
            &pixl_train::loss::Objective::l1_only(),
            1.0,
            &list,
            &mut grads,
        )?;
        clip_global_norm(&mut grads, 1.0)?;
        opt.step(&grads, 1e-4)?;
        println!("step {step}: loss {:.6}, {:.2} s", r.loss, t0.elapsed().as_secs_f64());
    }
    Ok(())
}
