//! The loss and every parameter's gradient of one plain training micro-batch, written to a file
//! so that another implementation can check them (scripts/check-train-grads.sh compares them
//! with a float64 PyTorch computation, `scripts/bench/pixl_torch.py grads`).
//!
//! Gradients:
//!   `cargo run --release -p pixl-train --example train_grads -- --weights W.safetensors
//!    --inputs I.safetensors --out G.safetensors`
//! loads the checkpoint `W` into a trainable network (every parameter a `Var`, as a training run
//! initialised from weights), reads `src` `(B, 3, H, W)`, `ct` `(B, 9, H, W)` and `tgt`
//! `(B, 3, H, W)` from `I`, runs `pixl_train::recompute::plain` (the L1 objective alone, divisor
//! 1: the loss of `bench train-step`, before clipping and the optimiser) and writes each
//! parameter's gradient (f32) under the parameter's name; the loss is in the metadata (`loss`).
//! A parameter the loss does not reach gets no tensor (and is listed on stderr).
//!
//! Inputs:
//!   `... --example train_grads -- --make-inputs [--size 200x136] [--batch 2] [--seed 1]
//!    --out I.safetensors`
//! writes uniform random `src`, `ct` and `tgt` in [0, 1) (f32, from `pixl_core::Rng`).
use anyhow::{bail, Context};
use candle_core::{Device, Tensor, Var};
use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;

struct Args {
    make_inputs: bool,
    weights: Option<PathBuf>,
    inputs: Option<PathBuf>,
    out: PathBuf,
    size: (usize, usize),
    batch: usize,
    seed: u64,
}

fn parse_size(s: &str) -> anyhow::Result<(usize, usize)> {
    let (w, h) = s
        .to_ascii_lowercase()
        .split_once('x')
        .map(|(w, h)| (w.to_string(), h.to_string()))
        .with_context(|| format!("size {s:?} is not WIDTHxHEIGHT"))?;
    Ok((w.parse()?, h.parse()?))
}

fn parse_args() -> anyhow::Result<Args> {
    let mut a = Args {
        make_inputs: false,
        weights: None,
        inputs: None,
        out: PathBuf::new(),
        size: (200, 136),
        batch: 2,
        seed: 1,
    };
    let mut out = None;
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        if flag == "--make-inputs" {
            a.make_inputs = true;
            continue;
        }
        if flag == "-h" || flag == "--help" {
            eprintln!(
                "usage: train_grads --weights W --inputs I --out G\n       \
                 train_grads --make-inputs [--size WxH] [--batch B] [--seed S] --out I"
            );
            std::process::exit(0);
        }
        let value = it.next().with_context(|| format!("{flag} needs a value"))?;
        match flag.as_str() {
            "--weights" => a.weights = Some(value.into()),
            "--inputs" => a.inputs = Some(value.into()),
            "--out" => out = Some(PathBuf::from(value)),
            "--size" => a.size = parse_size(&value)?,
            "--batch" => a.batch = value.parse()?,
            "--seed" => a.seed = value.parse()?,
            // Accepted for symmetry with the scripts; the inputs do not depend on the network.
            "--config" => {}
            _ => bail!("unknown argument {flag} (see --help)"),
        }
    }
    a.out = out.context("--out is required")?;
    Ok(a)
}

fn uniform(rng: &mut pixl_core::Rng, shape: (usize, usize, usize, usize)) -> candle_core::Result<Tensor> {
    let n = shape.0 * shape.1 * shape.2 * shape.3;
    Tensor::from_vec((0..n).map(|_| rng.f32()).collect::<Vec<f32>>(), shape, &Device::Cpu)
}

fn write(path: &PathBuf, tensors: &BTreeMap<String, Tensor>, meta: HashMap<String, String>) -> anyhow::Result<()> {
    let bytes = safetensors::serialize(tensors.iter().map(|(k, t)| (k.as_str(), t)), Some(meta))?;
    std::fs::write(path, bytes).with_context(|| format!("writing {}", path.display()))
}

fn make_inputs(a: &Args) -> anyhow::Result<()> {
    let (w, h) = a.size;
    anyhow::ensure!(w > 0 && h > 0 && a.batch > 0, "size and batch must be positive");
    let mut rng = pixl_core::Rng::new(a.seed);
    let mut t = BTreeMap::new();
    t.insert("src".to_string(), uniform(&mut rng, (a.batch, 3, h, w))?);
    t.insert("ct".to_string(), uniform(&mut rng, (a.batch, 9, h, w))?);
    t.insert("tgt".to_string(), uniform(&mut rng, (a.batch, 3, h, w))?);
    let meta = HashMap::from([("seed".to_string(), a.seed.to_string())]);
    write(&a.out, &t, meta)?;
    eprintln!(
        "wrote {} (batch {}, {w}x{h}, seed {})",
        a.out.display(),
        a.batch,
        a.seed
    );
    Ok(())
}

fn gradients(a: &Args) -> anyhow::Result<()> {
    use pixl_train::loss::Objective;
    let weights = a.weights.as_ref().context("--weights is required")?;
    let inputs = a.inputs.as_ref().context("--inputs is required")?;
    let device = Device::Cpu;

    // As a training run initialised from a checkpoint: a fresh trainable network of the file's
    // config, then the file's values loaded into its VarMap.
    let cfg = pixl_model::read_config(weights)?;
    let (varmap, model) = pixl_model::build_trainable(&cfg, 0, &device)?;
    pixl_model::load_into_varmap(weights, &varmap)?;
    let vars: BTreeMap<String, Var> = varmap
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("VarMap lock poisoned"))?
        .iter()
        .map(|(k, v)| (k.clone(), v.clone()))
        .collect();
    let names: Vec<String> = vars.keys().cloned().collect();
    let params: Vec<Var> = vars.into_values().collect();

    let loaded = candle_core::safetensors::load(inputs, &device)?;
    let get = |k: &str| -> anyhow::Result<Tensor> {
        loaded
            .get(k)
            .with_context(|| format!("{}: no tensor {k:?}", inputs.display()))?
            .to_dtype(candle_core::DType::F32)
            .map_err(Into::into)
    };
    let (src, ct, tgt) = (get("src")?, get("ct")?, get("tgt")?);

    let mut grads: Vec<Option<Tensor>> = vec![None; params.len()];
    let start = std::time::Instant::now();
    let r = pixl_train::recompute::plain(&model, &src, &ct, &tgt, &Objective::l1_only(), 1.0, &params, &mut grads)?;
    let secs = start.elapsed().as_secs_f64();

    let mut out = BTreeMap::new();
    let mut missing = vec![];
    for (name, g) in names.iter().zip(grads) {
        match g {
            Some(g) => {
                out.insert(name.clone(), g.to_dtype(candle_core::DType::F32)?.contiguous()?);
            }
            None => missing.push(name.as_str()),
        }
    }
    let (b, _, h, w) = src.dims4()?;
    let meta = HashMap::from([
        ("loss".to_string(), format!("{:e}", r.loss)),
        ("impl".to_string(), "pixl".to_string()),
    ]);
    write(&a.out, &out, meta)?;
    eprintln!(
        "pixl: loss {:.6e}, {} gradients written to {} (batch {b}, {w}x{h}; forward + backward {:.1} s)",
        r.loss,
        out.len(),
        a.out.display(),
        secs
    );
    if !missing.is_empty() {
        eprintln!(
            "pixl: {} parameters got no gradient: {}",
            missing.len(),
            missing.join(", ")
        );
    }
    Ok(())
}

fn main() -> anyhow::Result<()> {
    let a = parse_args()?;
    if a.make_inputs {
        make_inputs(&a)
    } else {
        gradients(&a)
    }
}
