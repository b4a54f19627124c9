//! The DDIM scheduler as Marigold-IID v1.1 configures it (diffusers `DDIMScheduler`): betas from
//! `scheduler_config.json`, optional zero-terminal-SNR rescaling, "trailing" / "leading" /
//! "linspace" timestep spacing, and the deterministic (η = 0) DDIM step for v-, ε- or
//! x₀-prediction.
//!
//! Contract: [`Ddim::timesteps`] and [`Ddim::step`] reproduce diffusers' `set_timesteps` and `step`
//! to f32 rounding: the tables are computed in f32 in the same order as PyTorch does
//! (`linspace` from both ends, sequential `cumprod`), the trailing spacing rounds the real-valued
//! step ratio (999/666/332 for 3 steps, where an integer ratio would give 999/666/333), and the
//! previous timestep is `t − num_train_timesteps / n` (integer division) with ᾱ of a negative
//! timestep being `final_alpha_cumprod` (1 with `set_alpha_to_one`, else ᾱ₀).
//!
//! Unsupported settings (another beta schedule, `thresholding`, `clip_sample`, a prediction type
//! other than the three, an unknown spacing) are refused by [`SchedulerConfig::from_json`] with
//! the key named, so a checkpoint is never run with a silently different scheduler.
use candle_core::{Result as CResult, Tensor};

/// What the network predicts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PredictionType {
    /// v = √ᾱ·ε − √(1−ᾱ)·x₀ (Marigold v1.1).
    VPrediction,
    /// The noise ε.
    Epsilon,
    /// The clean sample x₀.
    Sample,
}

/// How inference timesteps are spread over the training range.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Spacing {
    Trailing,
    Leading,
    Linspace,
}

/// The keys of `scheduler_config.json` the DDIM step depends on.
#[derive(Clone, Debug, PartialEq)]
pub struct SchedulerConfig {
    pub num_train_timesteps: usize,
    pub beta_start: f64,
    pub beta_end: f64,
    /// `scaled_linear` (√β linear) or `linear`.
    pub scaled_linear: bool,
    pub prediction_type: PredictionType,
    pub timestep_spacing: Spacing,
    pub steps_offset: usize,
    pub set_alpha_to_one: bool,
    pub rescale_betas_zero_snr: bool,
}

impl SchedulerConfig {
    /// Parses diffusers' `scheduler_config.json`; `Err` names the offending key.
    pub fn from_json(text: &str) -> Result<Self, String> {
        let v: serde_json::Value = serde_json::from_str(text).map_err(|e| format!("not valid JSON: {e}"))?;
        let obj = v.as_object().ok_or("not a JSON object")?;
        let class = obj.get("_class_name").and_then(|c| c.as_str()).unwrap_or("");
        if class != "DDIMScheduler" {
            return Err(format!(
                "_class_name {class:?}: only DDIMScheduler (the scheduler Marigold-IID ships) is supported"
            ));
        }
        let num = |k: &str, d: f64| -> Result<f64, String> {
            match obj.get(k) {
                None | Some(serde_json::Value::Null) => Ok(d),
                Some(x) => x.as_f64().ok_or_else(|| format!("`{k}` is not a number")),
            }
        };
        let flag = |k: &str, d: bool| -> Result<bool, String> {
            match obj.get(k) {
                None | Some(serde_json::Value::Null) => Ok(d),
                Some(x) => x.as_bool().ok_or_else(|| format!("`{k}` is not true/false")),
            }
        };
        let text_key = |k: &str, d: &'static str| -> Result<String, String> {
            match obj.get(k) {
                None | Some(serde_json::Value::Null) => Ok(d.to_string()),
                Some(x) => x
                    .as_str()
                    .map(str::to_string)
                    .ok_or_else(|| format!("`{k}` is not a string")),
            }
        };
        let num_train_timesteps = num("num_train_timesteps", 1000.0)?;
        if !((1.0..=100_000.0).contains(&num_train_timesteps) && num_train_timesteps.fract() == 0.0) {
            return Err(format!(
                "`num_train_timesteps` {num_train_timesteps} must be a positive integer"
            ));
        }
        let scaled_linear = match text_key("beta_schedule", "linear")?.as_str() {
            "scaled_linear" => true,
            "linear" => false,
            other => {
                return Err(format!(
                    "`beta_schedule` {other:?} is not supported (scaled_linear or linear)"
                ))
            }
        };
        if obj.contains_key("trained_betas") && !obj["trained_betas"].is_null() {
            return Err("`trained_betas` is not supported".into());
        }
        let prediction_type = match text_key("prediction_type", "epsilon")?.as_str() {
            "v_prediction" => PredictionType::VPrediction,
            "epsilon" => PredictionType::Epsilon,
            "sample" => PredictionType::Sample,
            other => {
                return Err(format!(
                    "`prediction_type` {other:?} is not supported (v_prediction, epsilon or sample)"
                ))
            }
        };
        let timestep_spacing = match text_key("timestep_spacing", "leading")?.as_str() {
            "trailing" => Spacing::Trailing,
            "leading" => Spacing::Leading,
            "linspace" => Spacing::Linspace,
            other => {
                return Err(format!(
                    "`timestep_spacing` {other:?} is not supported (trailing, leading or linspace)"
                ))
            }
        };
        if flag("thresholding", false)? {
            return Err("`thresholding` true is not supported".into());
        }
        if flag("clip_sample", true)? {
            return Err("`clip_sample` true is not supported (Marigold sets it false)".into());
        }
        let beta_start = num("beta_start", 0.0001)?;
        let beta_end = num("beta_end", 0.02)?;
        if !(beta_start > 0.0 && beta_end >= beta_start && beta_end < 1.0) {
            return Err(format!(
                "betas {beta_start}..{beta_end} must satisfy 0 < start ≤ end < 1"
            ));
        }
        let steps_offset = num("steps_offset", 0.0)?;
        Ok(Self {
            num_train_timesteps: num_train_timesteps as usize,
            beta_start,
            beta_end,
            scaled_linear,
            prediction_type,
            timestep_spacing,
            steps_offset: steps_offset.max(0.0) as usize,
            set_alpha_to_one: flag("set_alpha_to_one", true)?,
            rescale_betas_zero_snr: flag("rescale_betas_zero_snr", false)?,
        })
    }
}

/// `torch.linspace(start, end, n, dtype=float32)`: computed from both ends with fused
/// multiply-adds, as PyTorch's CPU kernel does.
fn linspace_f32(start: f32, end: f32, n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![start];
    }
    let step = (end - start) / (n - 1) as f32;
    let half = n / 2;
    (0..n)
        .map(|i| {
            if i < half {
                step.mul_add(i as f32, start)
            } else {
                (-step).mul_add((n - i - 1) as f32, end)
            }
        })
        .collect()
}

/// The DDIM scheduler's tables.
#[derive(Clone, Debug)]
pub struct Ddim {
    pub config: SchedulerConfig,
    /// β per training timestep (after the zero-SNR rescale when configured).
    pub betas: Vec<f32>,
    /// ᾱ per training timestep.
    pub alphas_cumprod: Vec<f32>,
    /// ᾱ used for the step whose previous timestep is negative.
    pub final_alpha_cumprod: f32,
}

/// One DDIM update's coefficients.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepAlphas {
    pub timestep: usize,
    pub alpha_prod_t: f32,
    pub alpha_prod_t_prev: f32,
}

impl Ddim {
    pub fn new(config: SchedulerConfig) -> Self {
        let n = config.num_train_timesteps;
        let mut betas: Vec<f32> = if config.scaled_linear {
            linspace_f32((config.beta_start.sqrt()) as f32, (config.beta_end.sqrt()) as f32, n)
                .into_iter()
                .map(|b| b * b)
                .collect()
        } else {
            linspace_f32(config.beta_start as f32, config.beta_end as f32, n)
        };
        if config.rescale_betas_zero_snr {
            betas = rescale_zero_terminal_snr(&betas);
        }
        let alphas_cumprod = cumprod(betas.iter().map(|b| 1.0 - b));
        let final_alpha_cumprod = if config.set_alpha_to_one {
            1.0
        } else {
            alphas_cumprod[0]
        };
        Self {
            config,
            betas,
            alphas_cumprod,
            final_alpha_cumprod,
        }
    }

    /// The inference timesteps for `steps` steps, in the order they are run (descending).
    pub fn timesteps(&self, steps: usize) -> Result<Vec<usize>, String> {
        let n = self.config.num_train_timesteps;
        if steps == 0 || steps > n {
            return Err(format!("the number of steps ({steps}) must be between 1 and {n}"));
        }
        let ts: Vec<i64> = match self.config.timestep_spacing {
            Spacing::Trailing => {
                // np.round(np.arange(n, 0, -n / steps)) - 1, in f64 as numpy does: numpy's length
                // is ceil(n / ratio), one more than `steps` for a few counts (61, 103, …) where the
                // extra element rounds to timestep −1; that element is dropped here.
                let ratio = n as f64 / steps as f64;
                let len = (n as f64 / ratio).ceil() as usize;
                (0..len)
                    .map(|k| round_half_even(n as f64 - ratio * k as f64) as i64 - 1)
                    .filter(|t| *t >= 0)
                    .collect()
            }
            Spacing::Leading => {
                let ratio = (n / steps) as i64;
                (0..steps as i64)
                    .rev()
                    .map(|i| i * ratio + self.config.steps_offset as i64)
                    .collect()
            }
            Spacing::Linspace => {
                // np.linspace(0, n - 1, steps).round()[::-1]
                (0..steps)
                    .rev()
                    .map(|i| {
                        let x = if steps == 1 {
                            0.0
                        } else {
                            (n - 1) as f64 * i as f64 / (steps - 1) as f64
                        };
                        round_half_even(x) as i64
                    })
                    .collect()
            }
        };
        ts.into_iter()
            .map(|t| {
                usize::try_from(t)
                    .ok()
                    .filter(|t| *t < n)
                    .ok_or_else(|| format!("timestep {t} out of range 0..{n}"))
            })
            .collect()
    }

    /// ᾱ_t and ᾱ_prev of the update at `timestep` in a run of `steps` steps.
    pub fn alphas(&self, timestep: usize, steps: usize) -> StepAlphas {
        let prev = timestep as i64 - (self.config.num_train_timesteps / steps.max(1)) as i64;
        let alpha_prod_t_prev = if prev >= 0 {
            self.alphas_cumprod[prev as usize]
        } else {
            self.final_alpha_cumprod
        };
        StepAlphas {
            timestep,
            alpha_prod_t: self.alphas_cumprod[timestep],
            alpha_prod_t_prev,
        }
    }

    /// One deterministic DDIM step (η = 0): the sample at the previous timestep.
    pub fn step(&self, model_output: &Tensor, timestep: usize, sample: &Tensor, steps: usize) -> CResult<Tensor> {
        let a = self.alphas(timestep, steps);
        let (at, ap) = (a.alpha_prod_t, a.alpha_prod_t_prev);
        let beta_t = 1.0 - at;
        let (sa, sb) = (at.sqrt() as f64, beta_t.sqrt() as f64);
        let (x0, eps) = match self.config.prediction_type {
            PredictionType::VPrediction => (
                ((sample * sa)? - (model_output * sb)?)?,
                ((model_output * sa)? + (sample * sb)?)?,
            ),
            PredictionType::Epsilon => {
                let x0 = ((sample - (model_output * sb)?)? / sa)?;
                (x0, model_output.clone())
            }
            PredictionType::Sample => {
                let eps = ((sample - (model_output * sa)?)? / sb)?;
                (model_output.clone(), eps)
            }
        };
        let dir = (eps * ((1.0 - ap).sqrt() as f64))?;
        (x0 * (ap.sqrt() as f64))? + dir
    }
}

/// `torch.cumprod` of f32 values: PyTorch's CPU kernel accumulates in f64 and rounds each
/// partial product to f32.
fn cumprod(xs: impl Iterator<Item = f32>) -> Vec<f32> {
    let mut acc = 1.0f64;
    xs.map(|x| {
        acc *= x as f64;
        acc as f32
    })
    .collect()
}

/// numpy's `round` (half to even).
fn round_half_even(x: f64) -> f64 {
    let r = x.round();
    if (x - x.trunc()).abs() == 0.5 {
        2.0 * (x / 2.0).round()
    } else {
        r
    }
}

/// diffusers' `rescale_zero_terminal_snr` (Lin et al. 2024, Alg. 1) in f32: shift and scale √ᾱ so
/// that ᾱ at the last timestep is 0 while ᾱ₀ is unchanged, then back to betas.
fn rescale_zero_terminal_snr(betas: &[f32]) -> Vec<f32> {
    let mut sqrt_bar: Vec<f32> = cumprod(betas.iter().map(|b| 1.0 - b))
        .into_iter()
        .map(f32::sqrt)
        .collect();
    let (first, last) = (sqrt_bar[0], sqrt_bar[sqrt_bar.len() - 1]);
    for s in sqrt_bar.iter_mut() {
        *s -= last;
    }
    let scale = first / (first - last);
    for s in sqrt_bar.iter_mut() {
        *s *= scale;
    }
    let bar: Vec<f32> = sqrt_bar.iter().map(|s| s * s).collect();
    let mut out = Vec::with_capacity(bar.len());
    out.push(1.0 - bar[0]);
    for i in 1..bar.len() {
        out.push(1.0 - bar[i] / bar[i - 1]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn marigold() -> SchedulerConfig {
        SchedulerConfig::from_json(
            r#"{"_class_name":"DDIMScheduler","num_train_timesteps":1000,"beta_start":0.00085,
            "beta_end":0.012,"beta_schedule":"scaled_linear","clip_sample":false,"prediction_type":"v_prediction",
            "set_alpha_to_one":false,"steps_offset":1,"timestep_spacing":"trailing","rescale_betas_zero_snr":true,
            "thresholding":false}"#,
        )
        .unwrap()
    }

    #[test]
    fn trailing_rounds_the_real_ratio() {
        let d = Ddim::new(marigold());
        assert_eq!(d.timesteps(1).unwrap(), vec![999]);
        assert_eq!(d.timesteps(3).unwrap(), vec![999, 666, 332]);
        assert_eq!(d.timesteps(4).unwrap(), vec![999, 749, 499, 249]);
        assert!(d.timesteps(0).is_err() && d.timesteps(1001).is_err());
    }

    #[test]
    fn zero_snr_keeps_the_first_alpha_and_ends_at_zero() {
        let d = Ddim::new(marigold());
        assert_eq!(d.alphas_cumprod[999], 0.0);
        // ᾱ₀ = 1 − β₀ with β₀ = 0.00085 before and after the rescale (f64 by hand).
        assert!((d.alphas_cumprod[0] as f64 - (1.0 - 0.00085)).abs() < 1e-6);
        assert!(d.alphas_cumprod.windows(2).all(|w| w[1] <= w[0]));
        assert_eq!(d.final_alpha_cumprod, d.alphas_cumprod[0]);
    }

    #[test]
    fn v_prediction_step_at_zero_snr_returns_minus_v_scaled() {
        // At t = 999, ᾱ_t = 0: x0 = −v, ε = x; the step is √ᾱ_prev·(−v) + √(1−ᾱ_prev)·x.
        let d = Ddim::new(marigold());
        let dev = candle_core::Device::Cpu;
        let x = Tensor::new(&[1.0f32, -2.0], &dev).unwrap();
        let v = Tensor::new(&[0.5f32, 0.25], &dev).unwrap();
        let out = d.step(&v, 999, &x, 4).unwrap().to_vec1::<f32>().unwrap();
        let ap = d.alphas_cumprod[749] as f64;
        for i in 0..2 {
            let (xi, vi) = ([1.0, -2.0][i], [0.5, 0.25][i]);
            let want = ap.sqrt() * -vi + (1.0 - ap).sqrt() * xi;
            assert!((out[i] as f64 - want).abs() < 1e-6, "{} vs {want}", out[i]);
        }
    }

    #[test]
    fn unsupported_settings_are_named() {
        let bad = r#"{"_class_name":"DDIMScheduler","prediction_type":"flow","clip_sample":false}"#;
        assert!(SchedulerConfig::from_json(bad).unwrap_err().contains("prediction_type"));
        let bad = r#"{"_class_name":"LCMScheduler"}"#;
        assert!(SchedulerConfig::from_json(bad).unwrap_err().contains("DDIMScheduler"));
        let bad = r#"{"_class_name":"DDIMScheduler","clip_sample":false,"beta_schedule":"squaredcos_cap_v2"}"#;
        assert!(SchedulerConfig::from_json(bad).unwrap_err().contains("beta_schedule"));
    }
}
