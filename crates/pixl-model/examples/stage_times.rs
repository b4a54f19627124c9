//! Wall time of each stage of the network's forward pass on the CPU (random weights and inputs):
//! the source encoder blocks, the intrinsics encoder, the trunk blocks and the head, summed by
//! kind over 3 runs after a warm-up; then the same time by operation kind
//! ([`pixl_nn::profile`]), the rest being what ran outside the instrumented ops. Where the
//! time goes, for optimisation work.
//!
//! `cargo run --release -p pixl-model --example stage_times -- small 512 [int8]` (threads:
//! `RAYON_NUM_THREADS`; `int8`: the linear layers in 8 bits, `PixlRelight::quantize_int8`).
use std::collections::BTreeMap;
use std::time::Instant;

use candle_core::{DType, Device, Result, Tensor};
use pixl_model::checkpoint::build_inference;
use pixl_model::fullres::gain_bias_staged;
use pixl_model::Config;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let preset = args.first().map(String::as_str).unwrap_or("small");
    let side: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(512);
    let cfg = Config::preset(preset).map_err(|e| candle_core::Error::Msg(e.to_string()))?;
    let dev = Device::Cpu;
    let mut model = build_inference(&cfg, 0, DType::F32, &dev).map_err(|e| candle_core::Error::Msg(e.to_string()))?;
    if args.get(2).map(String::as_str) == Some("int8") {
        let n = model.quantize_int8()?;
        println!("{n} linear layers in 8 bits");
    }
    let src = Tensor::rand(0f32, 1.0, (1, 3, side, side), &dev)?;
    let ct = Tensor::rand(0f32, 1.0, (1, 9, side, side), &dev)?;
    let mut totals: BTreeMap<String, f64> = BTreeMap::new();
    for run in 0..4 {
        pixl_nn::profile::enable(run > 0);
        let mut last = Instant::now();
        let mut record = |_: usize, _: usize, stage: &str| {
            let kind = stage
                .split(|c: char| c.is_ascii_digit())
                .next()
                .unwrap_or(stage)
                .trim()
                .to_string();
            if run > 0 {
                *totals.entry(kind).or_default() += last.elapsed().as_secs_f64() / 3.0;
            }
            last = Instant::now();
        };
        gain_bias_staged(&model, &src, &ct, &mut record)?;
    }
    pixl_nn::profile::enable(false);
    let all: f64 = totals.values().sum();
    println!("{preset} {side}x{side}: {:.0} ms per forward", all * 1e3);
    for (kind, t) in &totals {
        println!("  {kind:<40} {:>8.1} ms  {:>5.1} %", t * 1e3, 100.0 * t / all);
    }
    println!("by operation kind:");
    let mut ops = pixl_nn::profile::take();
    ops.sort_by(|a, b| b.1.total_cmp(&a.1));
    let mut listed = 0.0;
    for (kind, t, calls) in &ops {
        let t = t / 3.0;
        listed += t;
        println!(
            "  {kind:<40} {:>8.1} ms  {:>5.1} %  ({} calls)",
            t * 1e3,
            100.0 * t / all,
            calls / 3
        );
    }
    let rest = all - listed;
    println!(
        "  {:<40} {:>8.1} ms  {:>5.1} %",
        "other",
        rest * 1e3,
        100.0 * rest / all
    );
    Ok(())
}
