//! Vectorisable f32 math for the CPU kernels: `exp`, the row softmax built on it, `erf` and the
//! exact GELU built on that.
//!
//! [`exp`] is branch-free (clamp, Cody–Waite range reduction `x = n·ln2 + r`, a degree-6
//! polynomial for `eʳ` on `|r| ≤ ln2/2` with the Cephes `expf` coefficients, and `2ⁿ` built
//! from its exponent bits), so loops over slices compile to SIMD. Accuracy: within 2 ulp of
//! `f32::exp` on `[-87, 88]` (tested against f64); inputs below −87 give `e⁻⁸⁷ ≈ 1.6e-38`
//! instead of a smaller number or 0, inputs above 88 give `e⁸⁸`; NaN stays NaN.
//!
//! [`erf`]: `1 − erfc(|x|)` with the sign of `x`, `erfc(z) = t·exp(−z² + P(t))`, `t = 1/(1 + z/2)`,
//! `P` the degree-9 Chebyshev fit of Press et al. (Numerical Recipes, `erfcc`, fractional error
//! of `erfc` below 1.2e-7): absolute error below 3e-7 in f32 on the whole line (tested against
//! f64), branch-free. [`gelu_in_place`] applies `0.5·x·(1 + erf(x/√2))`, PyTorch's exact GELU.
//!
//! [`softmax_rows_unnormalised`] and [`gelu_in_place`] are compiled three times (AVX-512, AVX2+FMA, baseline) and
//! picks the widest the CPU has at run time.

/// `eˣ` in f32, see the module notes for its range and accuracy.
#[inline(always)]
pub fn exp(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    // 1.5·2²³: adding it rounds to an integer held in the low mantissa bits.
    const ROUND: f32 = 12_582_912.0;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.clamp(-87.0, 88.0);
    let t = x * LOG2E + ROUND;
    let n = t - ROUND;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = 1.987_569_2e-4;
    let p = p * r + 1.398_2e-3;
    let p = p * r + 8.333_452e-3;
    let p = p * r + 4.166_579_6e-2;
    let p = p * r + 0.166_666_65;
    let p = p * r + 0.5;
    let er = p * (r * r) + r + 1.0;
    let n_int = (t.to_bits() as i32).wrapping_sub(ROUND.to_bits() as i32);
    er * f32::from_bits(((n_int + 127) << 23) as u32)
}

/// `erf(x)` in f32, see the module notes for its accuracy.
#[inline(always)]
pub fn erf(x: f32) -> f32 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let p = 0.170_872_77f32;
    let p = p * t - 0.822_152_23;
    let p = p * t + 1.488_515_9;
    let p = p * t - 1.135_204;
    let p = p * t + 0.278_868_07;
    let p = p * t - 0.186_288_06;
    let p = p * t + 0.096_784_18;
    let p = p * t + 0.374_091_96;
    let p = p * t + 1.000_023_7;
    let p = p * t - 1.265_512_2;
    let erfc = t * exp(p - z * z);
    (1.0 - erfc).copysign(x)
}

#[inline(always)]
pub(crate) fn gelu_generic(xs: &mut [f32]) {
    for v in xs.iter_mut() {
        let x = *v;
        *v = (erf(x * std::f32::consts::FRAC_1_SQRT_2) + 1.0) * 0.5 * x;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn gelu_avx512(xs: &mut [f32]) {
    gelu_generic(xs)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn gelu_avx2(xs: &mut [f32]) {
    gelu_generic(xs)
}

/// Exact GELU `0.5·x·(1 + erf(x/√2))` of every value, in place (the same operation order as
/// candle's `gelu_erf`, with [`erf`]).
pub fn gelu_in_place(xs: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { gelu_avx512(xs) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { gelu_avx2(xs) };
        }
    }
    gelu_generic(xs)
}

/// Lanes of the accumulators in the row loops: wide enough for one AVX-512 register.
const LANES: usize = 16;

#[inline(always)]
fn softmax_rows_generic(scores: &mut [f32], cols: usize, inv_sums: &mut [f32]) {
    for (row, inv) in scores.chunks_exact_mut(cols).zip(inv_sums.iter_mut()) {
        let mut maxes = [f32::NEG_INFINITY; LANES];
        let mut chunks = row.chunks_exact(LANES);
        for c in &mut chunks {
            for (m, &v) in maxes.iter_mut().zip(c) {
                *m = m.max(v);
            }
        }
        let tail_max = chunks.remainder().iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
        let max = maxes.iter().fold(tail_max, |m, &v| m.max(v));
        let mut sums = [0f32; LANES];
        let mut chunks = row.chunks_exact_mut(LANES);
        for c in &mut chunks {
            for (s, v) in sums.iter_mut().zip(c.iter_mut()) {
                *v = exp(*v - max);
                *s += *v;
            }
        }
        let mut sum = 0f32;
        for v in chunks.into_remainder() {
            *v = exp(*v - max);
            sum += *v;
        }
        *inv = 1.0 / (sum + sums.iter().sum::<f32>());
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn softmax_rows_avx512(scores: &mut [f32], cols: usize, inv_sums: &mut [f32]) {
    softmax_rows_generic(scores, cols, inv_sums)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn softmax_rows_avx2(scores: &mut [f32], cols: usize, inv_sums: &mut [f32]) {
    softmax_rows_generic(scores, cols, inv_sums)
}

/// Row-wise softmax numerators of a row-major `(rows, cols)` block: each row `x` becomes
/// `exp(x − max x)` in place, and `inv_sums[i]` receives `1 / Σ exp(x − max x)` of row `i`.
/// `scores.len()` must be `inv_sums.len() · cols`.
pub fn softmax_rows_unnormalised(scores: &mut [f32], cols: usize, inv_sums: &mut [f32]) {
    assert_eq!(scores.len(), inv_sums.len() * cols, "softmax block size");
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { softmax_rows_avx512(scores, cols, inv_sums) };
        }
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: as above.
            return unsafe { softmax_rows_avx2(scores, cols, inv_sums) };
        }
    }
    softmax_rows_generic(scores, cols, inv_sums)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ulps(a: f32, b: f32) -> u32 {
        (a.to_bits() as i64 - b.to_bits() as i64).unsigned_abs() as u32
    }

    #[test]
    fn exp_matches_f64_within_two_ulp() {
        let mut worst = 0;
        let mut x = -87.0f32;
        while x <= 88.0 {
            let want = (x as f64).exp() as f32;
            worst = worst.max(ulps(exp(x), want));
            x += 0.000_37;
        }
        assert!(worst <= 2, "worst error {worst} ulp");
        assert_eq!(exp(0.0), 1.0);
        assert!(exp(f32::NAN).is_nan());
        assert!(exp(-1000.0) > 0.0 && exp(-1000.0) < 2e-38);
    }

    #[test]
    fn erf_and_gelu_match_f64() {
        let mut worst = 0f64;
        let mut xs = Vec::new();
        let mut x = -12.0f32;
        while x <= 12.0 {
            let want = candle_core::cpu::erf::erf_f64(x as f64);
            worst = worst.max((erf(x) as f64 - want).abs());
            xs.push(x);
            x += 0.000_71;
        }
        assert!(worst < 3e-7, "erf: worst absolute error {worst:e}");
        assert_eq!(erf(0.0), 0.0);
        assert_eq!(erf(f32::INFINITY), 1.0);
        assert_eq!(erf(f32::NEG_INFINITY), -1.0);
        assert!(erf(f32::NAN).is_nan());
        // GELU through the dispatched (SIMD) path against f64, relative to max(|x|, 1).
        let mut g = xs.clone();
        gelu_in_place(&mut g);
        for (&x, &got) in xs.iter().zip(&g) {
            let x64 = x as f64;
            let want = 0.5 * x64 * (1.0 + candle_core::cpu::erf::erf_f64(x64 / std::f64::consts::SQRT_2));
            assert!(
                (got as f64 - want).abs() <= 3e-7 * x64.abs().max(1.0),
                "gelu({x}) = {got}, want {want}"
            );
        }
    }

    #[test]
    fn softmax_rows_match_f64() {
        // 3 rows of 37 columns (two full 16-lane chunks and a tail), varied magnitudes.
        let cols = 37;
        let mut scores: Vec<f32> = (0..3 * cols).map(|i| ((i * 7919) % 101) as f32 * 0.37 - 18.0).collect();
        let input = scores.clone();
        let mut inv = vec![0f32; 3];
        softmax_rows_unnormalised(&mut scores, cols, &mut inv);
        for r in 0..3 {
            let row = &input[r * cols..(r + 1) * cols];
            let max = row.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
            let sum: f64 = row.iter().map(|&v| (v as f64 - max).exp()).sum();
            for c in 0..cols {
                let want = (row[c] as f64 - max).exp() / sum;
                let got = scores[r * cols + c] as f64 * inv[r] as f64;
                assert!(
                    (got - want).abs() <= 1e-6 * want.max(1e-30) + 1e-12,
                    "row {r} col {c}: {got} vs {want}"
                );
            }
        }
    }
}
