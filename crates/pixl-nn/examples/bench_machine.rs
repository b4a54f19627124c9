//! The machine's own limits, and what the `gemm` crate reaches of them on the network's shapes.
//!
//! - f32 FMA peak: a register-only loop of independent fused multiply-adds (AVX-512 and AVX2
//!   where the CPU has them), on 1 and on `T` threads (`RAYON_NUM_THREADS`, default all).
//! - Memory bandwidth: the STREAM triad `a = b + s·c` over three 64 MiB arrays, 1 and `T` threads.
//! - GEMM: `gemm::gemm` f32 on `T` threads (rayon) for `M×K · K×N` products of the relighting
//!   network (`paper`: d = 1024, 1032 tokens at 512²; `small`: d = 384), GFLOP/s and share of peak.
//!
//! `cargo run --release -p pixl-nn --example bench_machine` (scripts/bench/gemm_torch.py times
//! the same products in PyTorch).
use std::time::Instant;

fn threads() -> usize {
    std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// Runs `f` on `t` threads at once; returns the wall time of the slowest.
fn on_threads(t: usize, f: impl Fn() + Sync) -> f64 {
    let start = Instant::now();
    std::thread::scope(|s| {
        for _ in 0..t {
            s.spawn(&f);
        }
    });
    start.elapsed().as_secs_f64()
}

/// Register-only FMA loops: `ACC` independent accumulators of one vector width each, written
/// as plain `mul_add` on arrays so that the compiler emits packed FMAs for the enabled features.
#[cfg(target_arch = "x86_64")]
mod fma {
    pub const ACC: usize = 12;

    #[inline(always)]
    fn run<const N: usize>(iters: usize) -> f32 {
        let mut acc = [0f32; N];
        let (a, b) = (0.999_999f32, 1e-7f32);
        for _ in 0..iters {
            for x in acc.iter_mut() {
                *x = x.mul_add(a, b);
            }
        }
        acc.iter().sum()
    }

    #[target_feature(enable = "avx512f,fma")]
    pub unsafe fn avx512(iters: usize) -> f32 {
        run::<{ 16 * ACC }>(iters)
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn avx2(iters: usize) -> f32 {
        run::<{ 8 * ACC }>(iters)
    }
}

fn fma_peak(t: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        let iters = 50_000_000usize;
        type Loop = fn(usize) -> f32;
        let mut kinds: Vec<(&str, usize, Loop)> = Vec::new();
        if is_x86_feature_detected!("avx512f") {
            // SAFETY: the feature was detected at run time.
            kinds.push(("AVX-512", 16, |n| unsafe { fma::avx512(n) }));
        }
        if is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") {
            // SAFETY: the features were detected at run time.
            kinds.push(("AVX2", 8, |n| unsafe { fma::avx2(n) }));
        }
        for (name, lanes, f) in kinds {
            for nt in [1, t] {
                let flops = (iters * fma::ACC * lanes * 2 * nt) as f64;
                let best = (0..3)
                    .map(|_| {
                        on_threads(nt, || {
                            std::hint::black_box(f(std::hint::black_box(iters)));
                        })
                    })
                    .fold(f64::INFINITY, f64::min);
                println!("fma peak {name:<8} {nt} thread(s): {:>7.1} GFLOP/s", flops / best / 1e9);
            }
        }
    }
}

fn bandwidth(t: usize) {
    let n = 16 << 20; // 64 MiB per array
    let b = vec![1.0f32; n];
    let c = vec![2.0f32; n];
    let mut a = vec![0.0f32; n];
    for nt in [1, t] {
        let chunk = n.div_ceil(nt);
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let start = Instant::now();
            std::thread::scope(|s| {
                for ((a, b), c) in a.chunks_mut(chunk).zip(b.chunks(chunk)).zip(c.chunks(chunk)) {
                    s.spawn(move || {
                        for ((a, b), c) in a.iter_mut().zip(b).zip(c) {
                            *a = b + 3.0 * c;
                        }
                    });
                }
            });
            best = best.min(start.elapsed().as_secs_f64());
        }
        std::hint::black_box(&a);
        println!(
            "triad bandwidth   {nt} thread(s): {:>7.1} GB/s",
            (3 * n * 4) as f64 / best / 1e9
        );
    }
}

/// `M×K · K×N` products, best of 7. `B` is read row-major `(K, N)`, or — `transposed` — as a
/// linear layer reads its weight: `Wᵀ` with `W` stored `(N, K)` row-major.
fn gemm_rate(t: usize) {
    let shapes: [(&str, usize, usize, usize, bool); 12] = [
        ("paper qkv      ", 1032, 1024, 3072, false),
        ("paper mlp fc1  ", 1032, 1024, 4096, false),
        ("paper mlp fc2  ", 1032, 4096, 1024, false),
        ("paper proj     ", 1032, 1024, 1024, false),
        ("small mlp fc1  ", 1028, 384, 1536, false),
        ("small mlp fc2  ", 1028, 1536, 384, false),
        ("conv 3x3 64->32", 32, 576, 1024, false),
        ("conv 3x3 256   ", 256, 2304, 1024, false),
        ("conv 1x1 128   ", 128, 128, 65536, false),
        ("conv 1x1 32->6 ", 6, 32, 262_144, false),
        ("paper mlp fc1 Wt", 1032, 1024, 4096, true),
        ("paper mlp fc2 Wt", 1032, 4096, 1024, true),
    ];
    let par = if t > 1 {
        gemm::Parallelism::Rayon(t)
    } else {
        gemm::Parallelism::None
    };
    for (name, m, k, n, transposed) in shapes {
        let a: Vec<f32> = (0..m * k).map(|i| ((i * 7919) % 1000) as f32 * 1e-3).collect();
        let b: Vec<f32> = (0..k * n).map(|i| ((i * 104_729) % 1000) as f32 * 1e-3).collect();
        // (column stride, row stride) of B as a K×N matrix.
        let (b_cs, b_rs) = if transposed { (k as isize, 1) } else { (1, n as isize) };
        let mut c = vec![0f32; m * n];
        let mut best = f64::INFINITY;
        for _ in 0..7 {
            let start = Instant::now();
            // SAFETY: row-major A (m×k) and C (m×n); B (k×n) of k·n values with the strides above.
            unsafe {
                gemm::gemm(
                    m,
                    n,
                    k,
                    c.as_mut_ptr(),
                    1,
                    n as isize,
                    false,
                    a.as_ptr(),
                    1,
                    k as isize,
                    b.as_ptr(),
                    b_cs,
                    b_rs,
                    0.0f32,
                    1.0f32,
                    false,
                    false,
                    false,
                    par,
                );
            }
            best = best.min(start.elapsed().as_secs_f64());
        }
        std::hint::black_box(&c);
        let flops = 2.0 * (m * k * n) as f64;
        println!(
            "gemm {name} M={m:<5} K={k:<5} N={n:<5} {t} thread(s): {:>7.1} GFLOP/s",
            flops / best / 1e9
        );
    }
}

fn main() {
    let t = threads();
    rayon::ThreadPoolBuilder::new().num_threads(t).build_global().ok();
    fma_peak(t);
    bandwidth(t);
    gemm_rate(t);
}
