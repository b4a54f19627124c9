//! Test helpers shared by the crates that build on `pixl-nn`: seeded random tensors and an f64
//! finite-difference gradient check.
//!
//! [`check_gradients`] compares candle's autograd gradient of the scalar
//! `L(x₁..xₙ) = Σ f(x₁..xₙ) ⊙ R` (with `R` a fixed pseudo-random tensor, so every output element
//! counts with its own weight) against central differences `(L(x+h) − L(x−h)) / 2h`, element by
//! element. Both evaluations see the inputs as `Var`s, so they run the same (differentiable) path
//! of every [`crate::needs_grad`]-dispatching op. Inputs must be f64.
use candle_core::{DType, Device, Result, Shape, Tensor, Var};

/// A deterministic test value in [−1, 1) for index `i` of stream `salt` (a multiplicative hash:
/// spread out, reproducible, no generator state to thread through index arithmetic).
pub fn hashed_value(i: usize, salt: usize) -> f32 {
    let h = (i.wrapping_mul(2_654_435_761) ^ salt.wrapping_mul(40_503)) % 2000;
    h as f32 / 1000.0 - 1.0
}

/// SplitMix64: a tiny, seedable generator for test data (not for anything statistical).
#[derive(Clone, Debug)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`, 53 random bits.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// An f64 tensor of `shape` with entries uniform in `[lo, hi)`, reproducible from `seed`.
pub fn uniform<S: Into<Shape>>(shape: S, lo: f64, hi: f64, seed: u64, device: &Device) -> Result<Tensor> {
    let shape = shape.into();
    let mut rng = SplitMix64(seed);
    let data: Vec<f64> = (0..shape.elem_count())
        .map(|_| lo + (hi - lo) * rng.next_f64())
        .collect();
    Tensor::from_vec(data, shape, device)
}

/// `max |a − b|` over all elements, computed in f64; NaN if either holds a NaN or the shapes
/// differ.
pub fn max_abs_diff(a: &Tensor, b: &Tensor) -> Result<f64> {
    if a.shape() != b.shape() {
        return Ok(f64::NAN);
    }
    let a = a.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    let b = b.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    Ok(max_abs_diff_slices(&a, &b))
}

fn max_abs_diff_slices(a: &[f64], b: &[f64]) -> f64 {
    let mut m = 0f64;
    for (x, y) in a.iter().zip(b) {
        let d = (x - y).abs();
        if d.is_nan() {
            return f64::NAN;
        }
        m = m.max(d);
    }
    m
}

/// The outcome of a gradient check for one input.
#[derive(Clone, Debug)]
pub struct GradCheck {
    /// Index of the input in the slice given to [`check_gradients`].
    pub input: usize,
    /// `max |autograd − numeric|` over the input's elements.
    pub max_abs_err: f64,
    /// `max(|autograd|, |numeric|)` over the input's elements.
    pub scale: f64,
}

impl GradCheck {
    /// `max_abs_err / scale` (with `scale` floored at 1e-12, so an all-zero gradient compares
    /// absolutely); NaN if anything was not finite, so `rel_err() < tol` fails on NaN.
    pub fn rel_err(&self) -> f64 {
        if !self.max_abs_err.is_finite() || !self.scale.is_finite() {
            return f64::NAN;
        }
        self.max_abs_err / self.scale.max(1e-12)
    }
}

/// Checks the autograd gradients of `f` with respect to every element of every input against
/// central differences with step `step` (1e-5 suits f64). See the module docs.
pub fn check_gradients<F>(f: F, inputs: &[Tensor], step: f64) -> Result<Vec<GradCheck>>
where
    F: Fn(&[Tensor]) -> Result<Tensor>,
{
    if let Some(t) = inputs.iter().find(|t| t.dtype() != DType::F64) {
        candle_core::bail!("check_gradients needs f64 inputs, got {:?}", t.dtype());
    }
    let vars = inputs.iter().map(Var::from_tensor).collect::<Result<Vec<_>>>()?;
    let tracked: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();
    let out = f(&tracked)?;
    let weights = uniform(out.shape(), -1.0, 1.0, 0x5EED_6AAD, out.device())?.to_dtype(out.dtype())?;
    let loss = |out: &Tensor| (out * &weights)?.sum_all();
    let grads = loss(&out)?.backward()?;

    let mut report = Vec::with_capacity(inputs.len());
    for (idx, var) in vars.iter().enumerate() {
        let analytic = match grads.get(var.as_tensor()) {
            Some(g) => g.flatten_all()?.to_vec1::<f64>()?,
            None => vec![0.0; var.elem_count()],
        };
        let base = inputs[idx].flatten_all()?.to_vec1::<f64>()?;
        let mut numeric = Vec::with_capacity(base.len());
        let eval_at = |e: usize, delta: f64| -> Result<f64> {
            let mut data = base.clone();
            data[e] += delta;
            let mut args = tracked.clone();
            args[idx] = Var::from_tensor(&Tensor::from_vec(data, inputs[idx].shape(), inputs[idx].device())?)?
                .as_tensor()
                .clone();
            loss(&f(&args)?)?.to_scalar::<f64>()
        };
        for e in 0..base.len() {
            numeric.push((eval_at(e, step)? - eval_at(e, -step)?) / (2.0 * step));
        }
        let scale = analytic.iter().chain(&numeric).fold(0f64, |m, v| {
            if m.is_nan() || v.is_nan() {
                f64::NAN
            } else {
                m.max(v.abs())
            }
        });
        report.push(GradCheck {
            input: idx,
            max_abs_err: max_abs_diff_slices(&analytic, &numeric),
            scale,
        });
    }
    Ok(report)
}

/// Runs [`check_gradients`] and fails with a message naming the worst input if any relative
/// error reaches `tol` (or is NaN).
pub fn assert_gradients<F>(name: &str, f: F, inputs: &[Tensor], tol: f64) -> Result<()>
where
    F: Fn(&[Tensor]) -> Result<Tensor>,
{
    for r in check_gradients(f, inputs, 1e-5)? {
        let err = r.rel_err();
        if err.is_nan() || err >= tol {
            candle_core::bail!(
                "{name}: gradient of input {} is off: relative error {err:e} (max abs {:e}, scale {:e}), tolerance {tol:e}",
                r.input,
                r.max_abs_err,
                r.scale
            );
        }
    }
    Ok(())
}
