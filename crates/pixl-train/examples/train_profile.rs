//! Where a training step's time goes: forward (graph kept) and backward of each part of the
//! network, timed segment by segment on random data.
//!
//! `cargo run --release -p pixl-train --example train_profile -- [CONFIG] [W] [H] [BATCH] [RUNS]`
//! (defaults: small 256 256 2 3). Each part's forward runs on a detached `Var` input; its
//! backward propagates `Σ out ⊙ G` for a fixed random `G`. Parts: the patch embedding, the source
//! encoder's blocks, the intrinsics (ConvNeXt) encoder, the fusion, the trunk's blocks and the
//! tail (readout norms, DPT head, modulation, L1 loss). Medians over RUNS; then the time of the
//! last run by op kind (`pixl_nn::profile` spans; the rest is candle's own ops and its gradient
//! bookkeeping).
use candle_core::{Tensor, Var};
use pixl_model::Config;
use pixl_train::loss::Objective;
use std::time::Instant;

fn rand(shape: &[usize], seed: u64) -> candle_core::Result<Tensor> {
    let mut rng = pixl_core::Rng::new(seed);
    let n: usize = shape.iter().product();
    Tensor::from_vec(
        (0..n).map(|_| rng.f32()).collect::<Vec<_>>(),
        shape,
        &candle_core::Device::Cpu,
    )
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// (forward ms, backward ms) of `f` on a fresh leaf made from `input`.
fn time_part(
    input: Option<&Tensor>,
    f: &dyn Fn(Option<&Tensor>) -> candle_core::Result<Tensor>,
) -> candle_core::Result<(f64, f64, Tensor)> {
    let leaf = input.map(Var::from_tensor).transpose()?;
    let t0 = Instant::now();
    let out = f(leaf.as_ref().map(|v| v.as_tensor()))?;
    let t1 = Instant::now();
    let g = rand(out.dims(), 7)?;
    let store = (&out * &g)?.sum_all()?.backward()?;
    let t2 = Instant::now();
    drop(store);
    Ok((
        (t1 - t0).as_secs_f64() * 1e3,
        (t2 - t1).as_secs_f64() * 1e3,
        out.detach(),
    ))
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize, d: &str| args.get(i).cloned().unwrap_or_else(|| d.to_string());
    let cfg = Config::from_name_or_file(&arg(0, "small"))?;
    let (w, h, b, runs): (usize, usize, usize, usize) = (
        arg(1, "256").parse()?,
        arg(2, "256").parse()?,
        arg(3, "2").parse()?,
        arg(4, "3").parse()?,
    );
    let (_varmap, model) = pixl_model::build_trainable(&cfg, 0, &candle_core::Device::Cpu)?;
    let src = rand(&[b, 3, h, w], 1)?;
    let ct = rand(&[b, 9, h, w], 2)?;
    let tgt = rand(&[b, 3, h, w], 3)?;
    let names = [
        "embed",
        "src blocks",
        "convnext",
        "fuse",
        "trunk blocks",
        "tail",
        "(affine+loss)",
    ];
    let mut fwd = vec![vec![]; names.len()];
    let mut bwd = vec![vec![]; names.len()];
    for run in 0..runs + 1 {
        // Op-kind spans over the timed runs (the first run warms up).
        pixl_nn::profile::take();
        pixl_nn::profile::enable(run > 0);
        let p = model.prepare(&src, &ct)?;
        let mut rec = |i: usize, r: (f64, f64, Tensor)| {
            fwd[i].push(r.0);
            bwd[i].push(r.1);
            r.2
        };
        let x = rec(0, time_part(None, &|_| model.src_encoder().embed(&p.src))?);
        let mut x = x;
        let (mut f_sum, mut b_sum) = (0.0, 0.0);
        for j in 0..model.src_encoder().depth() {
            let (f, bw, o) = time_part(Some(&x), &|i| model.src_encoder().block(j, i.unwrap()))?;
            f_sum += f;
            b_sum += bw;
            x = o;
        }
        rec(1, (f_sum, b_sum, x.clone()));
        let cond = rec(
            2,
            time_part(Some(&p.ct), &|i| {
                let mut q = p.clone();
                q.ct = i.unwrap().clone();
                model.cond_tokens(&q)
            })?,
        );
        let mut hdn = rec(3, time_part(Some(&x), &|i| model.fuse_tokens(i.unwrap(), &cond))?);
        let (mut f_sum, mut b_sum) = (0.0, 0.0);
        let mut taps = vec![];
        for j in 0..model.trunk().depth() {
            let (f, bw, o) = time_part(Some(&hdn), &|i| model.trunk().block(j, i.unwrap(), &p.grid))?;
            f_sum += f;
            b_sum += bw;
            if model.trunk().readouts().contains(&j) {
                taps.push(o.clone());
            }
            hdn = o;
        }
        rec(4, (f_sum, b_sum, hdn));
        let leaves: Vec<Var> = taps.iter().map(Var::from_tensor).collect::<candle_core::Result<_>>()?;
        let lt: Vec<Tensor> = leaves.iter().map(|v| v.as_tensor().clone()).collect();
        let t0 = Instant::now();
        let pred = model.tail_unclipped(&lt, &src, &p)?;
        let loss =
            |pred: &Tensor| pixl_train::loss::loss(pred, &tgt, &Objective::l1_only()).map_err(anyhow::Error::from);
        let total = loss(&pred)?.total;
        let t1 = Instant::now();
        let _store = total.backward()?;
        let t2 = Instant::now();
        fwd[5].push((t1 - t0).as_secs_f64() * 1e3);
        bwd[5].push((t2 - t1).as_secs_f64() * 1e3);
        // The modulation's affine step and the loss alone (inside the tail above).
        let (g, b) = model.tail_gain_bias(&lt, &p)?;
        let (g, b) = (Var::from_tensor(&g.detach())?, Var::from_tensor(&b.detach())?);
        let t0 = Instant::now();
        let pred = pixl_model::modulation::Modulation::affine(&src, g.as_tensor(), b.as_tensor())?;
        let total = loss(&pred)?.total;
        let t1 = Instant::now();
        let _store = total.backward()?;
        let t2 = Instant::now();
        fwd[6].push((t1 - t0).as_secs_f64() * 1e3);
        bwd[6].push((t2 - t1).as_secs_f64() * 1e3);
    }
    println!("{:<14} {:>10} {:>10}", "part", "fwd ms", "bwd ms");
    let (mut tf, mut tb) = (0.0, 0.0);
    for (i, n) in names.iter().enumerate() {
        let (f, bw) = (median(fwd[i][1..].to_vec()), median(bwd[i][1..].to_vec()));
        if i < 6 {
            tf += f;
            tb += bw;
        }
        println!("{n:<14} {f:>10.1} {bw:>10.1}");
    }
    println!("{:<14} {tf:>10.1} {tb:>10.1}", "total");
    let mut kinds = pixl_nn::profile::take();
    kinds.sort_by(|a, b| b.1.total_cmp(&a.1));
    println!("\nop kind (last run)                   ms  calls");
    for (kind, secs, calls) in kinds {
        println!("{kind:<34} {:>7.1} {calls:>6}", secs * 1e3);
    }
    Ok(())
}
