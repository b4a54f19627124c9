//! The corruption pipeline (paper App. C): one statistical test per augmentation of its defining
//! property, plus the gate, determinism, identity and range guarantees.
use candle_core::{Device, Tensor};
use pixl_intrinsics::augment::{corrupt, corrupt_ct, corrupt_where, Aug, AugmentConfig, Plan};
use pixl_intrinsics::ct::Ct;

const W: usize = 32;
const H: usize = 32;
const N: usize = W * H;

/// A C_T with a bright square (edges), a ramp and per-channel offsets, values in [0.05, 0.95].
fn scene() -> Vec<f32> {
    let mut v = vec![0f32; 9 * N];
    for c in 0..9 {
        for y in 0..H {
            for x in 0..W {
                let inside = (10..22).contains(&x) && (8..20).contains(&y);
                let ramp = 0.3 * x as f32 / (W - 1) as f32 + 0.2 * y as f32 / (H - 1) as f32;
                v[c * N + y * W + x] = 0.05 + 0.02 * c as f32 + ramp + if inside { 0.35 } else { 0.0 };
            }
        }
    }
    v
}

/// Vertical step: 0.2 left of column 16, 0.8 from it on, every channel.
fn step() -> Vec<f32> {
    (0..9 * N).map(|i| if i % W < 16 { 0.2 } else { 0.8 }).collect()
}

fn run(input: &[f32], seed: u64, cfg: &AugmentConfig) -> Vec<f32> {
    let t = Tensor::from_vec(input.to_vec(), (1, 9, H, W), &Device::Cpu).unwrap();
    corrupt(&t, &[seed], cfg)
        .unwrap()
        .flatten_all()
        .unwrap()
        .to_vec1::<f32>()
        .unwrap()
}

fn range(v: &[f32], c: usize) -> (f32, f32) {
    let ch = &v[c * N..(c + 1) * N];
    (
        ch.iter().copied().fold(f32::INFINITY, f32::min),
        ch.iter().copied().fold(f32::NEG_INFINITY, f32::max),
    )
}

fn changed_pixels(a: &[f32], b: &[f32]) -> Vec<usize> {
    (0..N)
        .filter(|&p| (0..9).any(|c| a[c * N + p] != b[c * N + p]))
        .collect()
}

/// Fraction of `n` Bernoulli(p) draws lies within p ± 3σ.
fn assert_rate(name: &str, hits: usize, n: usize, p: f64) {
    let rate = hits as f64 / n as f64;
    let sigma = (p * (1.0 - p) / n as f64).sqrt();
    assert!(
        (rate - p).abs() <= 3.0 * sigma,
        "{name}: rate {rate:.4}, expected {p} ± {:.4}",
        3.0 * sigma
    );
}

#[test]
fn gate_and_each_probability_fire_at_their_rates() {
    let cfg = AugmentConfig::default();
    let plans: Vec<Plan> = (0..10_000u64).map(|s| Plan::draw(s, &cfg)).collect();
    let applied: Vec<&Plan> = plans.iter().filter(|p| p.applied).collect();
    assert_rate("gate", applied.len(), plans.len(), 0.70);
    // Gate off means nothing fires.
    assert!(plans.iter().filter(|p| !p.applied).all(|p| *p == Plan::default()));
    let n = applied.len();
    let count = |f: &dyn Fn(&Plan) -> bool| applied.iter().filter(|p| f(p)).count();
    assert_rate("cast (albedo)", count(&|p| p.cast[0].is_some()), n, 0.50);
    assert_rate("cast (residual)", count(&|p| p.cast[2].is_some()), n, 0.50);
    assert_rate("gamma (shading)", count(&|p| p.gamma[1].is_some()), n, 0.30);
    assert_rate("holes", count(&|p| p.holes.is_some()), n, 0.50);
    assert_rate("cracks", count(&|p| p.cracks.is_some()), n, 0.50);
    assert_rate("salt-and-pepper", count(&|p| p.salt_pepper.is_some()), n, 0.25);
    assert_rate("noise", count(&|p| p.noise.is_some()), n, 0.50);
    assert_rate("blur", count(&|p| p.blur.is_some()), n, 0.25);
    assert_rate("posterize", count(&|p| p.posterize.is_some()), n, 0.25);
    // Strengths stay in their ranges and cover them.
    let levels: Vec<u32> = applied.iter().filter_map(|p| p.posterize).collect();
    assert_eq!((levels.iter().min(), levels.iter().max()), (Some(&12), Some(&64)));
    assert!(applied.iter().filter_map(|p| p.blur).all(|s| (0.4..=1.2).contains(&s)));
    assert!(applied
        .iter()
        .filter_map(|p| p.holes)
        .all(|h| (0.005..=0.04).contains(&h.fraction)));
}

#[test]
fn all_probabilities_zero_is_bit_identical() {
    let x = scene();
    let off = AugmentConfig::disabled();
    let gate_only = AugmentConfig::default().only(Aug::None);
    for seed in 0..5 {
        assert_eq!(run(&x, seed, &off), x);
        assert_eq!(
            run(&x, seed, &gate_only),
            x,
            "gate fired, nothing else: clipping to own range is exact"
        );
    }
}

#[test]
fn same_seed_same_output_different_seeds_differ() {
    let x = scene();
    let cfg = AugmentConfig::default();
    let applied: Vec<u64> = (0..50).filter(|&s| Plan::draw(s, &cfg).applied).take(4).collect();
    let outs: Vec<Vec<f32>> = applied.iter().map(|&s| run(&x, s, &cfg)).collect();
    for (s, o) in applied.iter().zip(&outs) {
        assert_eq!(&run(&x, *s, &cfg), o);
    }
    for i in 0..outs.len() {
        for j in i + 1..outs.len() {
            assert_ne!(outs[i], outs[j], "seeds {} and {}", applied[i], applied[j]);
        }
    }
    // A batch gives each sample what it gets alone.
    let t = Tensor::from_vec([x.clone(), x.clone(), x.clone()].concat(), (3, 9, H, W), &Device::Cpu).unwrap();
    let b = corrupt(&t, &applied[..3], &cfg).unwrap();
    for (k, want) in outs.iter().take(3).enumerate() {
        assert_eq!(
            &b.get(k).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap(),
            want
        );
    }
}

#[test]
fn output_stays_in_the_input_range_per_channel() {
    let x = scene();
    let cfg = AugmentConfig {
        p_apply: 1.0,
        ..AugmentConfig::default()
    };
    for seed in 0..24 {
        let y = run(&x, seed, &cfg);
        assert!(y.iter().all(|v| v.is_finite()));
        for c in 0..9 {
            let (lo, hi) = range(&x, c);
            let (ylo, yhi) = range(&y, c);
            assert!(
                ylo >= lo && yhi <= hi,
                "seed {seed} channel {c}: [{ylo}, {yhi}] outside [{lo}, {hi}]"
            );
        }
    }
}

#[test]
fn color_cast_is_affine_per_channel_within_ranges() {
    let x = scene();
    let cfg = AugmentConfig {
        cast_p: 0.5,
        ..AugmentConfig::default().only(Aug::ColorCast)
    };
    let mut fired_groups = 0;
    for seed in 0..12 {
        let y = run(&x, seed, &cfg);
        for c in 0..9 {
            let (lo, hi) = range(&x, c);
            // Least squares on unclipped pixels.
            let pts: Vec<(f64, f64)> = (0..N)
                .map(|p| (x[c * N + p] as f64, y[c * N + p] as f64))
                .filter(|&(_, b)| b > lo as f64 + 1e-6 && b < hi as f64 - 1e-6)
                .collect();
            assert!(pts.len() > N / 4, "seed {seed} channel {c}: almost everything clipped");
            let n = pts.len() as f64;
            let (mx, my) = (
                pts.iter().map(|p| p.0).sum::<f64>() / n,
                pts.iter().map(|p| p.1).sum::<f64>() / n,
            );
            let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
            let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
            let (slope, icpt) = (sxy / sxx, my - sxy / sxx * mx);
            let resid = pts.iter().map(|p| (p.1 - slope * p.0 - icpt).abs()).fold(0.0, f64::max);
            assert!(resid < 1e-5, "not affine: {resid}");
            assert!((0.85 - 1e-5..=1.15 + 1e-5).contains(&slope), "slope {slope}");
            assert!((-0.06 - 1e-5..=0.06 + 1e-5).contains(&icpt), "bias {icpt}");
            if c % 3 == 0 && (slope - 1.0).abs() > 1e-6 {
                fired_groups += 1;
            }
        }
    }
    // 36 group draws at p = 0.5: expect about 18.
    assert!((8..=28).contains(&fired_groups), "{fired_groups}");
}

#[test]
fn gamma_is_a_power_per_channel_within_range() {
    let x = scene();
    let cfg = AugmentConfig {
        gamma_p: 0.3,
        ..AugmentConfig::default().only(Aug::Gamma)
    };
    let mut fired = 0;
    for seed in 0..12 {
        let y = run(&x, seed, &cfg);
        for c in 0..9 {
            let (lo, hi) = range(&x, c);
            let g: Vec<f64> = (0..N)
                .filter(|&p| {
                    let v = y[c * N + p];
                    v > lo + 1e-4 && v < hi - 1e-4 && (0.1..0.9).contains(&x[c * N + p])
                })
                .map(|p| (y[c * N + p] as f64).ln() / (x[c * N + p] as f64).ln())
                .collect();
            assert!(!g.is_empty());
            let (gmin, gmax) = (
                g.iter().copied().fold(f64::INFINITY, f64::min),
                g.iter().copied().fold(0.0, f64::max),
            );
            assert!(gmax - gmin < 1e-3, "one gamma per channel: [{gmin}, {gmax}]");
            assert!((0.75 - 1e-3..=1.35 + 1e-3).contains(&gmin), "gamma {gmin}");
            if c % 3 == 0 && (gmin - 1.0).abs() > 1e-4 {
                fired += 1;
            }
        }
    }
    // 36 group draws at p = 0.3: expect about 11.
    assert!((2..=20).contains(&fired), "{fired}");
}

#[test]
fn holes_touch_a_fraction_in_range_and_sit_at_the_channel_minimum() {
    let x = scene();
    let cfg = AugmentConfig::default().only(Aug::Holes);
    for seed in 0..10 {
        let y = run(&x, seed, &cfg);
        let holes = changed_pixels(&x, &y);
        let frac = holes.len() as f64 / N as f64;
        assert!(
            (0.005 - 1.0 / N as f64..=0.04 + 1.0 / N as f64).contains(&frac),
            "seed {seed}: fraction {frac}"
        );
        for &p in &holes {
            for c in 0..9 {
                let (lo, _) = range(&x, c);
                let v = y[c * N + p];
                assert!(
                    v >= lo && v <= lo + cfg.holes_noise_floor,
                    "seed {seed}: hole value {v}, channel min {lo}"
                );
            }
        }
    }
}

#[test]
fn edge_cracks_darken_only_near_edges_by_one_factor() {
    let x = step();
    let cfg = AugmentConfig::default().only(Aug::EdgeCracks);
    for seed in 0..8 {
        let y = run(&x, seed, &cfg);
        let cracked = changed_pixels(&x, &y);
        assert!(!cracked.is_empty(), "seed {seed}: no crack on a step edge");
        for &p in &cracked {
            let col = p % W;
            // Sobel sees columns 15–16; dilation by 1 reaches 14–17.
            assert!((14..=17).contains(&col), "seed {seed}: crack at column {col}");
            assert!((0..9).all(|c| y[c * N + p] <= x[c * N + p]), "cracks only darken");
        }
        // Darkened bright pixels (not clipped to the 0.2 floor) share one factor 1 − strength ∈ [0, 0.6].
        let bright: Vec<f32> = cracked
            .iter()
            .filter(|&&p| x[p] > 0.5 && y[p] > 0.2 + 1e-6)
            .map(|&p| y[p] / x[p])
            .collect();
        for f in &bright {
            assert!((0.0..=0.6 + 1e-5).contains(f), "factor {f}");
            assert!((f - bright[0]).abs() < 1e-5);
        }
    }
}

#[test]
fn salt_and_pepper_replaces_few_pixels_by_extremes() {
    let x = scene();
    let cfg = AugmentConfig::default().only(Aug::SaltPepper);
    let mut total = 0;
    for seed in 0..20 {
        let y = run(&x, seed, &cfg);
        let hit = changed_pixels(&x, &y);
        assert!(
            hit.len() as f64 <= (0.003 * N as f64).round(),
            "seed {seed}: {} pixels",
            hit.len()
        );
        total += hit.len();
        for &p in &hit {
            let salt = (0..9).all(|c| y[c * N + p] == range(&x, c).1);
            let pepper = (0..9).all(|c| y[c * N + p] == range(&x, c).0);
            assert!(salt || pepper, "seed {seed}: pixel {p} is neither salt nor pepper");
        }
    }
    assert!(total > 0);
}

#[test]
fn gaussian_noise_has_zero_mean_and_sigma_in_range() {
    // Mid-grey with two extreme pixels per channel so clipping to the input range is inactive.
    let mut x = vec![0.5f32; 9 * N];
    for c in 0..9 {
        x[c * N] = 0.0;
        x[c * N + 1] = 1.0;
    }
    let cfg = AugmentConfig::default().only(Aug::GaussianNoise);
    let mut sigmas = Vec::new();
    for seed in 0..10 {
        let y = run(&x, seed, &cfg);
        let d: Vec<f64> = (0..9 * N).filter(|i| i % N > 1).map(|i| (y[i] - x[i]) as f64).collect();
        let n = d.len() as f64;
        let mean = d.iter().sum::<f64>() / n;
        let sd = (d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!(
            mean.abs() <= 4.0 * sd / n.sqrt() + 1e-9,
            "seed {seed}: mean {mean}, sd {sd}"
        );
        assert!(sd <= 0.04 * 1.05, "seed {seed}: sd {sd}");
        sigmas.push(sd);
    }
    let spread = sigmas.iter().copied().fold(0.0, f64::max) - sigmas.iter().copied().fold(1.0, f64::min);
    assert!(spread > 0.005, "σ should vary with the seed: {sigmas:?}");
}

#[test]
fn blur_smooths_a_step_and_preserves_mass() {
    let x = step();
    let cfg = AugmentConfig::default().only(Aug::Blur);
    for seed in 0..4 {
        let y = run(&x, seed, &cfg);
        for c in [0, 4, 8] {
            for row in 0..H {
                let r = &y[c * N + row * W..c * N + (row + 1) * W];
                assert!(r.windows(2).all(|w| w[1] >= w[0] - 1e-6), "not monotone");
                assert!(
                    (r[0] - 0.2).abs() < 1e-5 && (r[W - 1] - 0.8).abs() < 1e-5,
                    "far field changed"
                );
                assert!(r[15] > 0.2 + 1e-3 && r[16] < 0.8 - 1e-3, "edge not smoothed");
                let mass: f32 = r.iter().sum::<f32>() - x[row * W..(row + 1) * W].iter().sum::<f32>();
                assert!(mass.abs() < 1e-4, "mass changed by {mass}");
            }
        }
    }
}

#[test]
fn posterize_leaves_at_most_levels_distinct_values() {
    // A ramp of 1024 distinct values per channel.
    let x: Vec<f32> = (0..9 * N)
        .map(|i| (i % N) as f32 / (N - 1) as f32 * 0.9 + 0.05)
        .collect();
    let cfg = AugmentConfig::default().only(Aug::Posterize);
    for seed in 0..8 {
        let y = run(&x, seed, &cfg);
        let mut distinct_all = Vec::new();
        for c in 0..9 {
            let mut v: Vec<u32> = y[c * N..(c + 1) * N].iter().map(|f| f.to_bits()).collect();
            v.sort_unstable();
            v.dedup();
            distinct_all.push(v.len());
            let err = (0..N).map(|p| (y[c * N + p] - x[c * N + p]).abs()).fold(0.0, f32::max);
            // Rounding to L evenly spaced levels moves a value at most half a step.
            assert!(
                err <= 0.9 / (2.0 * (v.len() as f32 - 1.0)) + 1e-5,
                "error {err} for {} levels",
                v.len()
            );
        }
        assert!(
            distinct_all.iter().all(|&d| (12..=64).contains(&d)),
            "seed {seed}: {distinct_all:?}"
        );
        assert!(
            distinct_all.iter().all(|&d| d == distinct_all[0]),
            "one level count per sample"
        );
    }
}

#[test]
fn bad_batches_are_refused_and_ct_convenience_matches() {
    let t = Tensor::zeros((1, 8, 4, 4), candle_core::DType::F32, &Device::Cpu).unwrap();
    assert!(corrupt(&t, &[1], &AugmentConfig::default())
        .unwrap_err()
        .to_string()
        .contains("9"));
    let t = Tensor::zeros((2, 9, 4, 4), candle_core::DType::F32, &Device::Cpu).unwrap();
    assert!(corrupt(&t, &[1], &AugmentConfig::default())
        .unwrap_err()
        .to_string()
        .contains("seeds"));
    let bad = AugmentConfig {
        holes_p: 1.5,
        ..AugmentConfig::default()
    };
    assert!(corrupt(&t, &[1, 2], &bad).unwrap_err().to_string().contains("holes_p"));

    let x = scene();
    let ct = Ct::from_chw(W, H, &x).unwrap();
    let cfg = AugmentConfig::default();
    let seed = (0..).find(|&s| Plan::draw(s, &cfg).applied).unwrap();
    assert_eq!(corrupt_ct(&ct, seed, &cfg).unwrap().to_chw(), run(&x, seed, &cfg));
}

/// `corrupt_where` gives, sample by sample, either the input or what `corrupt` gives the whole
/// batch; with every sample chosen, `corrupt`'s result; a wrong-length choice list is an error.
#[test]
fn corrupt_where_corrupts_exactly_the_chosen_samples() {
    let (b, h, w) = (4, 12, 10);
    let data: Vec<f32> = (0..b * 9 * h * w)
        .map(|i| ((i * 7919) % 1000) as f32 / 1000.0)
        .collect();
    let ct = Tensor::from_vec(data, (b, 9, h, w), &Device::Cpu).unwrap();
    let seeds = [11u64, 12, 13, 14];
    let cfg = AugmentConfig::paper();
    let all = corrupt(&ct, &seeds, &cfg).unwrap();
    let flat = |t: &Tensor, i: usize| t.get(i).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let which = [true, false, true, false];
    // A chosen and an unchosen sample must each be changed by the pipeline under their seeds, or
    // the test proves nothing.
    for pick in [true, false] {
        let changed = (0..b).any(|i| which[i] == pick && flat(&all, i) != flat(&ct, i));
        assert!(
            changed,
            "no {} sample is changed by its seed",
            if pick { "chosen" } else { "unchosen" }
        );
    }
    let some = corrupt_where(&ct, &seeds, &which, &cfg).unwrap();
    for (i, &w) in which.iter().enumerate() {
        let want = if w { flat(&all, i) } else { flat(&ct, i) };
        assert_eq!(flat(&some, i), want, "sample {i}");
    }
    let every = corrupt_where(&ct, &seeds, &[true; 4], &cfg).unwrap();
    for i in 0..b {
        assert_eq!(flat(&every, i), flat(&all, i));
    }
    let none = corrupt_where(&ct, &seeds, &[false; 4], &cfg).unwrap();
    assert_eq!(
        none.flatten_all().unwrap().to_vec1::<f32>().unwrap(),
        ct.flatten_all().unwrap().to_vec1::<f32>().unwrap()
    );
    assert!(corrupt_where(&ct, &seeds, &[true; 3], &cfg).is_err());
}
