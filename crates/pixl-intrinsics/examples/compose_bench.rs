//! Times `compose` on a synthetic full pass set (all 12 passes) and `corrupt` on one C_T.
//!
//! `cargo run --release -p pixl-intrinsics --example compose_bench -- [SIZE] [RUNS]`
//! (default 2048, 7 runs after 1 warm-up; prints min and median wall time).
use pixl_core::passes::{OPTIONAL_FOR_COMPOSE, REQUIRED_FOR_COMPOSE};
use pixl_core::{Image, Rng};
use pixl_intrinsics::augment::{corrupt, AugmentConfig};
use pixl_intrinsics::compose::{compose, ComposeOptions, PassSet};
use std::time::Instant;

fn stats(mut t: Vec<f64>) -> (f64, f64) {
    t.sort_by(f64::total_cmp);
    (t[0], t[t.len() / 2])
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(2048);
    let runs: usize = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(7);
    let mut rng = Rng::new(1);
    let mut set = PassSet::new("bench");
    for (k, pass) in REQUIRED_FOR_COMPOSE.iter().chain(OPTIONAL_FOR_COMPOSE).enumerate() {
        let data: Vec<f32> = (0..size * size * 3)
            .map(|_| rng.f32() * (1.0 + k as f32 * 0.3))
            .collect();
        set.insert(pass.short, Image::from_vec(size, size, 3, data)?)?;
    }
    let opts = ComposeOptions::default();
    compose(&set, &opts)?;
    let mut times = Vec::new();
    for _ in 0..runs {
        let t0 = Instant::now();
        let out = compose(&set, &opts)?;
        times.push(t0.elapsed().as_secs_f64());
        std::hint::black_box(out);
    }
    let (min, med) = stats(times);
    println!(
        "compose {size}x{size}, 12 passes, rescale on: min {:.1} ms, median {:.1} ms ({runs} runs, {} rayon threads)",
        min * 1e3,
        med * 1e3,
        rayon::current_num_threads()
    );

    let ct = compose(&set, &opts)?.ct;
    let side = size.min(512);
    let small: Vec<f32> = ct.to_chw().into_iter().take(9 * side * side).collect();
    let x = candle_core::Tensor::from_vec(small, (1, 9, side, side), &candle_core::Device::Cpu)?;
    let cfg = AugmentConfig {
        p_apply: 1.0,
        ..AugmentConfig::default()
    };
    let mut times = Vec::new();
    for seed in 0..runs as u64 {
        let t0 = Instant::now();
        std::hint::black_box(corrupt(&x, &[seed], &cfg)?);
        times.push(t0.elapsed().as_secs_f64());
    }
    let (min, med) = stats(times);
    println!(
        "corrupt 1x9x{side}x{side} (gate forced on, CPU): min {:.1} ms, median {:.1} ms",
        min * 1e3,
        med * 1e3
    );
    Ok(())
}
