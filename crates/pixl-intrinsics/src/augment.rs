//! The conditioning corruption pipeline (paper App. C, Table 4): artifacts of coarse
//! reconstructions, applied to C_T during training.
//!
//! Input and output: a batch of C_T tensors `(B, 9, H, W)` f32 (channel order of
//! [`crate::ct::Ct::to_chw`]), one `u64` seed per sample; [`corrupt_where`] corrupts only the
//! chosen samples (training can leave those on a coarse reconstruction's C_T as they are). Every
//! random decision and every random number of a sample comes from its seed alone (CPU-side
//! [`Rng`] streams, one per augmentation, so changing one probability does not shift the draws of
//! the others); the image arithmetic is candle tensor ops on the input's device, so training can
//! run it on the GPU.
//!
//! Per sample, with the [`AugmentConfig`] defaults being Table 4:
//! 1. **gate**: the whole pipeline fires with `p_apply` (0.70); otherwise the sample is returned
//!    bit-for-bit unchanged.
//! 2. **photometric**, per intrinsic group (albedo, shading, residual), each group deciding on
//!    its own: colour cast (p 0.50; per-channel `x·scale + bias`, scale ∈ [0.85, 1.15], bias ∈
//!    [−0.06, 0.06]); gamma (p 0.30; per-channel `max(x,0)^γ`, γ ∈ [0.75, 1.35]).
//! 3. **structural**: holes (p 0.50; fraction f ∈ [0.005, 0.040]; a low-resolution uniform noise
//!    grid, one value per `holes_cell` pixels, bilinearly upsampled, plus — with probability
//!    `holes_edge_bias_p` — `holes_edge_weight ×` the normalised Sobel edge map; the top f of
//!    pixels, all nine channels, become the channel minimum plus a uniform noise floor in
//!    [0, `holes_noise_floor`)); edge cracks (p 0.50; pixels whose Sobel magnitude exceeds its
//!    q-quantile, q ∈ [0.92, 0.99], dilated by a `(2·cracks_dilate+1)²` max filter, are
//!    multiplied by `1 − strength` (flat pixels, magnitude ≤ 1e-3 of the strongest edge, never crack), strength ∈ [0.4, 1.0]). The Sobel map is taken on the mean
//!    of the nine channels, with edge-replicated borders.
//! 4. **noise**: salt-and-pepper (p 0.25; a fraction ∈ [0, 0.003] of pixels, all channels, set
//!    to the channel's input maximum or minimum, 50/50); Gaussian (p 0.50; `+σ·N(0,1)` per
//!    sample, σ ∈ [0, 0.04]).
//! 5. **frequency**: separable Gaussian blur (p 0.25; σ ∈ [0.4, 1.2], radius ⌈3σ⌉,
//!    edge-replicated borders); posterisation (p 0.25; L ∈ [12, 64] integer levels spread
//!    evenly over the channel's input range, so at most L distinct values per channel).
//! 6. the output is clipped, **per channel**, to that channel's input `[min, max]`.
//!
//! Strengths are uniform in their ranges (levels uniform over the integers of the range).
use crate::ct::Ct;
use crate::error::Result;
use candle_core::{DType, Device, Tensor};
use pixl_core::Rng;
use serde::{Deserialize, Serialize};

/// Probabilities and strength ranges of the pipeline; `Default` is the paper's Table 4 (plus the
/// few implementation constants the table does not fix, documented per field).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AugmentConfig {
    /// Probability that the pipeline fires at all (0.70).
    pub p_apply: f32,
    /// Colour cast probability per intrinsic group (0.50).
    pub cast_p: f32,
    /// Per-channel multiplicative scale range ([0.85, 1.15]).
    pub cast_scale: [f32; 2],
    /// Per-channel additive bias range ([−0.06, 0.06]).
    pub cast_bias: [f32; 2],
    /// Gamma probability per intrinsic group (0.30).
    pub gamma_p: f32,
    /// Per-channel gamma range ([0.75, 1.35]).
    pub gamma: [f32; 2],
    /// Holes probability (0.50).
    pub holes_p: f32,
    /// Fraction of pixels turned into holes ([0.005, 0.040]).
    pub holes_fraction: [f32; 2],
    /// Probability that the hole mask is biased toward Sobel edges (not in Table 4: 0.5).
    pub holes_edge_bias_p: f32,
    /// Weight of the normalised edge map added to the noise when biased (not in Table 4: 1.0).
    pub holes_edge_weight: f32,
    /// Pixels per cell of the low-resolution noise grid (not in Table 4: 16).
    pub holes_cell: usize,
    /// Width of the uniform noise floor added to the channel minimum (not in Table 4: 0.02).
    pub holes_noise_floor: f32,
    /// Edge-crack probability (0.50).
    pub cracks_p: f32,
    /// Sobel-magnitude quantile range ([0.92, 0.99]).
    pub cracks_quantile: [f32; 2],
    /// Darkening strength range ([0.4, 1.0]).
    pub cracks_strength: [f32; 2],
    /// Dilation radius of the crack mask in pixels (not in Table 4: 1, a 3×3 max filter).
    pub cracks_dilate: usize,
    /// Salt-and-pepper probability (0.25).
    pub salt_pepper_p: f32,
    /// Fraction of pixels replaced ([0, 0.003]).
    pub salt_pepper_fraction: [f32; 2],
    /// Gaussian noise probability (0.50).
    pub noise_p: f32,
    /// Noise standard deviation range ([0, 0.04]).
    pub noise_sigma: [f32; 2],
    /// Gaussian blur probability (0.25).
    pub blur_p: f32,
    /// Blur σ range in pixels ([0.4, 1.2]).
    pub blur_sigma: [f32; 2],
    /// Posterisation probability (0.25).
    pub posterize_p: f32,
    /// Number of levels range, inclusive ([12, 64]).
    pub posterize_levels: [u32; 2],
}

impl Default for AugmentConfig {
    fn default() -> Self {
        AugmentConfig::paper()
    }
}

impl AugmentConfig {
    /// Table 4 of the paper.
    pub fn paper() -> Self {
        AugmentConfig {
            p_apply: 0.70,
            cast_p: 0.50,
            cast_scale: [0.85, 1.15],
            cast_bias: [-0.06, 0.06],
            gamma_p: 0.30,
            gamma: [0.75, 1.35],
            holes_p: 0.50,
            holes_fraction: [0.005, 0.040],
            holes_edge_bias_p: 0.5,
            holes_edge_weight: 1.0,
            holes_cell: 16,
            holes_noise_floor: 0.02,
            cracks_p: 0.50,
            cracks_quantile: [0.92, 0.99],
            cracks_strength: [0.4, 1.0],
            cracks_dilate: 1,
            salt_pepper_p: 0.25,
            salt_pepper_fraction: [0.0, 0.003],
            noise_p: 0.50,
            noise_sigma: [0.0, 0.04],
            blur_p: 0.25,
            blur_sigma: [0.4, 1.2],
            posterize_p: 0.25,
            posterize_levels: [12, 64],
        }
    }

    /// The same ranges with every probability (gate included) set to 0: the identity.
    pub fn disabled() -> Self {
        AugmentConfig {
            p_apply: 0.0,
            ..AugmentConfig::paper().only(Aug::None)
        }
    }

    /// The gate forced to 1 and every augmentation but `aug` off, `aug` with probability 1
    /// (for looking at, or testing, one augmentation at a time).
    pub fn only(self, aug: Aug) -> Self {
        let p = |a: Aug| if a == aug { 1.0 } else { 0.0 };
        AugmentConfig {
            p_apply: 1.0,
            cast_p: p(Aug::ColorCast),
            gamma_p: p(Aug::Gamma),
            holes_p: p(Aug::Holes),
            cracks_p: p(Aug::EdgeCracks),
            salt_pepper_p: p(Aug::SaltPepper),
            noise_p: p(Aug::GaussianNoise),
            blur_p: p(Aug::Blur),
            posterize_p: p(Aug::Posterize),
            ..self
        }
    }

    /// Checks probabilities in [0, 1] and ranges ordered and sensible.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str| Err(crate::IntrinsicsError::Invalid(format!("augment config: {what}")));
        let probs = [
            ("p_apply", self.p_apply),
            ("cast_p", self.cast_p),
            ("gamma_p", self.gamma_p),
            ("holes_p", self.holes_p),
            ("holes_edge_bias_p", self.holes_edge_bias_p),
            ("cracks_p", self.cracks_p),
            ("salt_pepper_p", self.salt_pepper_p),
            ("noise_p", self.noise_p),
            ("blur_p", self.blur_p),
            ("posterize_p", self.posterize_p),
        ];
        for (n, p) in probs {
            if !(0.0..=1.0).contains(&p) {
                return bad(&format!("{n} = {p} is not a probability in [0, 1]"));
            }
        }
        let ranges = [
            ("cast_scale", self.cast_scale),
            ("cast_bias", self.cast_bias),
            ("gamma", self.gamma),
            ("holes_fraction", self.holes_fraction),
            ("cracks_quantile", self.cracks_quantile),
            ("cracks_strength", self.cracks_strength),
            ("salt_pepper_fraction", self.salt_pepper_fraction),
            ("noise_sigma", self.noise_sigma),
            ("blur_sigma", self.blur_sigma),
        ];
        for (n, [lo, hi]) in ranges {
            if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                return bad(&format!("{n} = [{lo}, {hi}] is not an ordered finite range"));
            }
        }
        if self.gamma[0] <= 0.0 || self.blur_sigma[0] < 0.0 || self.noise_sigma[0] < 0.0 {
            return bad("gamma must be > 0, blur and noise sigma ≥ 0");
        }
        if !(0.0..=1.0).contains(&self.holes_fraction[0]) || !(0.0..=1.0).contains(&self.holes_fraction[1]) {
            return bad("holes_fraction must lie in [0, 1]");
        }
        if !(0.0..=1.0).contains(&self.salt_pepper_fraction[1]) || self.salt_pepper_fraction[0] < 0.0 {
            return bad("salt_pepper_fraction must lie in [0, 1]");
        }
        if !(0.0..=1.0).contains(&self.cracks_quantile[0]) || !(0.0..=1.0).contains(&self.cracks_quantile[1]) {
            return bad("cracks_quantile must lie in [0, 1]");
        }
        let [l0, l1] = self.posterize_levels;
        if l0 < 2 || l0 > l1 {
            return bad(&format!("posterize_levels = [{l0}, {l1}] must be ordered and ≥ 2"));
        }
        if self.holes_cell == 0 {
            return bad("holes_cell must be ≥ 1");
        }
        Ok(())
    }
}

/// The augmentations, for [`AugmentConfig::only`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Aug {
    None,
    ColorCast,
    Gamma,
    Holes,
    EdgeCracks,
    SaltPepper,
    GaussianNoise,
    Blur,
    Posterize,
}

/// Random-stream ids: one per decision group, one per per-pixel field.
mod stream {
    pub const GATE: u64 = 0x6761_7465;
    pub const CAST: u64 = 1;
    pub const GAMMA: u64 = 2;
    pub const HOLES: u64 = 3;
    pub const CRACKS: u64 = 4;
    pub const SALT: u64 = 5;
    pub const NOISE: u64 = 6;
    pub const BLUR: u64 = 7;
    pub const POSTER: u64 = 8;
    pub const PIXELS: u64 = 100;
}

/// Hole parameters of one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HolesPlan {
    pub fraction: f32,
    /// Edge-map weight when the mask is edge-biased.
    pub edge_weight: Option<f32>,
}

/// Edge-crack parameters of one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CracksPlan {
    pub quantile: f32,
    pub strength: f32,
}

/// Everything decided for one sample before touching pixels: which augmentations fire and
/// their strengths. `None` = does not fire.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Plan {
    pub applied: bool,
    /// Per group (albedo, shading, residual): per-channel (scale, bias).
    pub cast: [Option<([f32; 3], [f32; 3])>; 3],
    /// Per group: per-channel γ.
    pub gamma: [Option<[f32; 3]>; 3],
    pub holes: Option<HolesPlan>,
    pub cracks: Option<CracksPlan>,
    /// Fraction of pixels.
    pub salt_pepper: Option<f32>,
    /// σ.
    pub noise: Option<f32>,
    /// σ in pixels.
    pub blur: Option<f32>,
    /// Levels.
    pub posterize: Option<u32>,
}

impl Plan {
    /// The plan of the sample with this seed (pure CPU; see the module docs for the draws).
    pub fn draw(seed: u64, cfg: &AugmentConfig) -> Plan {
        let mut gate = Rng::for_stream(seed, &[stream::GATE]);
        if !gate.bernoulli(cfg.p_apply) {
            return Plan::default();
        }
        let u = |r: &mut Rng, [lo, hi]: [f32; 2]| r.uniform(lo, hi);
        let mut plan = Plan {
            applied: true,
            ..Plan::default()
        };
        let mut r = Rng::for_stream(seed, &[stream::CAST]);
        for g in plan.cast.iter_mut() {
            if r.bernoulli(cfg.cast_p) {
                let scale = [(); 3].map(|_| u(&mut r, cfg.cast_scale));
                let bias = [(); 3].map(|_| u(&mut r, cfg.cast_bias));
                *g = Some((scale, bias));
            }
        }
        let mut r = Rng::for_stream(seed, &[stream::GAMMA]);
        for g in plan.gamma.iter_mut() {
            if r.bernoulli(cfg.gamma_p) {
                *g = Some([(); 3].map(|_| u(&mut r, cfg.gamma)));
            }
        }
        let mut r = Rng::for_stream(seed, &[stream::HOLES]);
        if r.bernoulli(cfg.holes_p) {
            let fraction = u(&mut r, cfg.holes_fraction);
            let edge_weight = r.bernoulli(cfg.holes_edge_bias_p).then_some(cfg.holes_edge_weight);
            plan.holes = Some(HolesPlan { fraction, edge_weight });
        }
        let mut r = Rng::for_stream(seed, &[stream::CRACKS]);
        if r.bernoulli(cfg.cracks_p) {
            let quantile = u(&mut r, cfg.cracks_quantile);
            let strength = u(&mut r, cfg.cracks_strength);
            plan.cracks = Some(CracksPlan { quantile, strength });
        }
        let mut r = Rng::for_stream(seed, &[stream::SALT]);
        plan.salt_pepper = r
            .bernoulli(cfg.salt_pepper_p)
            .then(|| u(&mut r, cfg.salt_pepper_fraction));
        let mut r = Rng::for_stream(seed, &[stream::NOISE]);
        plan.noise = r.bernoulli(cfg.noise_p).then(|| u(&mut r, cfg.noise_sigma));
        let mut r = Rng::for_stream(seed, &[stream::BLUR]);
        plan.blur = r.bernoulli(cfg.blur_p).then(|| u(&mut r, cfg.blur_sigma));
        let mut r = Rng::for_stream(seed, &[stream::POSTER]);
        plan.posterize = r.bernoulli(cfg.posterize_p).then(|| {
            let [lo, hi] = cfg.posterize_levels;
            lo + r.below((hi - lo) as usize + 1) as u32
        });
        plan
    }
}

fn msg(s: String) -> candle_core::Error {
    candle_core::Error::Msg(s)
}

/// Corrupts a batch `(B, 9, H, W)` f32, sample `b` with `seeds[b]` (see the module docs).
pub fn corrupt(ct: &Tensor, seeds: &[u64], cfg: &AugmentConfig) -> candle_core::Result<Tensor> {
    corrupt_masked(ct, seeds, &|_| true, cfg)
}

/// [`corrupt`] for the samples `b` with `which[b]`; the others are returned unchanged. Each
/// corrupted sample gets exactly the values [`corrupt`] gives it (its draws come from its seed alone).
pub fn corrupt_where(ct: &Tensor, seeds: &[u64], which: &[bool], cfg: &AugmentConfig) -> candle_core::Result<Tensor> {
    if which.len() != seeds.len() {
        return Err(msg(format!(
            "corrupt: {} choices for {} seeds",
            which.len(),
            seeds.len()
        )));
    }
    corrupt_masked(ct, seeds, &|i| which[i], cfg)
}

fn corrupt_masked(
    ct: &Tensor,
    seeds: &[u64],
    chosen: &dyn Fn(usize) -> bool,
    cfg: &AugmentConfig,
) -> candle_core::Result<Tensor> {
    let (b, c, _, _) = ct.dims4()?;
    if c != 9 {
        return Err(msg(format!(
            "corrupt: C_T batch has {c} channels, expected 9 (B, 9, H, W)"
        )));
    }
    if ct.dtype() != DType::F32 {
        return Err(msg(format!("corrupt: C_T batch is {:?}, expected f32", ct.dtype())));
    }
    if seeds.len() != b {
        return Err(msg(format!("corrupt: {} seeds for a batch of {b}", seeds.len())));
    }
    cfg.validate().map_err(|e| msg(e.to_string()))?;
    let plans: Vec<Plan> = seeds.iter().map(|&s| Plan::draw(s, cfg)).collect();
    let applied = |i: usize| plans[i].applied && chosen(i);
    if !(0..b).any(applied) {
        return Ok(ct.clone());
    }
    let mut out = Vec::with_capacity(b);
    for (i, (plan, &seed)) in plans.iter().zip(seeds).enumerate() {
        let x = ct.get(i)?;
        out.push(if applied(i) { apply(&x, plan, seed, cfg)? } else { x });
    }
    Tensor::stack(&out, 0)
}

/// [`corrupt`] on one [`Ct`] (CPU).
pub fn corrupt_ct(ct: &Ct, seed: u64, cfg: &AugmentConfig) -> Result<Ct> {
    let (w, h) = (ct.width(), ct.height());
    let x = Tensor::from_vec(ct.to_chw(), (1, 9, h, w), &Device::Cpu)?;
    let y = corrupt(&x, &[seed], cfg)?;
    Ct::from_chw(w, h, &y.flatten_all()?.to_vec1::<f32>()?)
}

/// Per-channel statistic of `(9, H, W)` as `(9, 1, 1)`.
fn channel_min(x: &Tensor) -> candle_core::Result<Tensor> {
    x.flatten_from(1)?.min_keepdim(1)?.unsqueeze(2)
}

fn channel_max(x: &Tensor) -> candle_core::Result<Tensor> {
    x.flatten_from(1)?.max_keepdim(1)?.unsqueeze(2)
}

/// A `(9, 1, 1)` tensor from per-channel values.
fn per_channel(v: [f32; 9], dev: &Device) -> candle_core::Result<Tensor> {
    Tensor::from_vec(v.to_vec(), (9, 1, 1), dev)
}

/// One sample `(9, H, W)` through the pipeline.
fn apply(x: &Tensor, plan: &Plan, seed: u64, cfg: &AugmentConfig) -> candle_core::Result<Tensor> {
    let (_, h, w) = x.dims3()?;
    let dev = x.device().clone();
    let lo = channel_min(x)?;
    let hi = channel_max(x)?;
    let mut px = Rng::for_stream(seed, &[stream::PIXELS]);
    let mut x = x.clone();

    // Photometric, per intrinsic group.
    if plan.cast.iter().any(Option::is_some) {
        let (mut scale, mut bias) = ([1f32; 9], [0f32; 9]);
        for (g, cast) in plan.cast.iter().enumerate() {
            if let Some((s, b)) = cast {
                scale[3 * g..3 * g + 3].copy_from_slice(s);
                bias[3 * g..3 * g + 3].copy_from_slice(b);
            }
        }
        x = x
            .broadcast_mul(&per_channel(scale, &dev)?)?
            .broadcast_add(&per_channel(bias, &dev)?)?;
    }
    if plan.gamma.iter().any(Option::is_some) {
        let mut groups = Vec::with_capacity(3);
        for (g, gamma) in plan.gamma.iter().enumerate() {
            let xg = x.narrow(0, 3 * g, 3)?;
            groups.push(match gamma {
                Some(gm) => xg
                    .relu()?
                    .broadcast_pow(&Tensor::from_vec(gm.to_vec(), (3, 1, 1), &dev)?)?,
                None => xg,
            });
        }
        x = Tensor::cat(&groups, 0)?;
    }

    // Structural.
    let needs_edges = plan.holes.is_some_and(|hp| hp.edge_weight.is_some()) || plan.cracks.is_some();
    let edges = if needs_edges { Some(sobel_magnitude(&x)?) } else { None };
    if let Some(holes) = plan.holes {
        let cell = cfg.holes_cell.max(1);
        let (gh, gw) = (h.div_ceil(cell) + 1, w.div_ceil(cell) + 1);
        let grid: Vec<f32> = (0..gh * gw).map(|_| px.f32()).collect();
        let mut score = Tensor::from_vec(grid, (1, 1, gh, gw), &dev)?
            .upsample_bilinear2d(h, w, true)?
            .reshape((h, w))?;
        if let (Some(wt), Some(e)) = (holes.edge_weight, &edges) {
            let emax = e.max_keepdim(0)?.max_keepdim(1)?.to_vec2::<f32>()?[0][0];
            if emax > 0.0 {
                score = (score + (e * (wt as f64 / emax as f64))?)?;
            }
        }
        let k = ((holes.fraction as f64 * (h * w) as f64).round() as usize).min(h * w);
        if k > 0 {
            let mut s = score.flatten_all()?.to_vec1::<f32>()?;
            let (_, &mut thr, _) = s.select_nth_unstable_by(h * w - k, f32::total_cmp);
            let mask = score.ge(thr as f64)?.unsqueeze(0)?.broadcast_as((9, h, w))?;
            let floor: Vec<f32> = (0..h * w).map(|_| px.f32() * cfg.holes_noise_floor).collect();
            let fill = Tensor::from_vec(floor, (1, h, w), &dev)?.broadcast_add(&channel_min(&x)?)?;
            x = mask.where_cond(&fill, &x)?;
        }
    }
    if let (Some(cracks), Some(e)) = (plan.cracks, &edges) {
        let mut vals = e.flatten_all()?.to_vec1::<f32>()?;
        // "Flat" = magnitude at most 1e-3 of the strongest edge (the convolution leaves ~1e-8
        // rounding noise on constant regions).
        let flat = 1e-3 * vals.iter().copied().fold(0f32, f32::max);
        let thr = crate::compose::percentile(&mut vals, cracks.quantile as f64 * 100.0);
        // At or above the quantile, but never where the image is flat (a flat image gets no
        // cracks, and a quantile falling on the flat plateau selects only actual edges).
        let mask = if thr > flat {
            e.ge(thr as f64)?
        } else {
            e.gt(flat as f64)?
        };
        let mask = mask.to_dtype(DType::F32)?.reshape((1, 1, h, w))?;
        let r = cfg.cracks_dilate;
        let mask = if r > 0 {
            mask.pad_with_zeros(2, r, r)?
                .pad_with_zeros(3, r, r)?
                .max_pool2d_with_stride(2 * r + 1, 1)?
        } else {
            mask
        };
        let factor = (1.0 - (mask.reshape((1, h, w))? * cracks.strength as f64)?)?;
        x = x.broadcast_mul(&factor)?;
    }

    // Noise.
    if let Some(fraction) = plan.salt_pepper {
        let k = (fraction as f64 * (h * w) as f64).round() as usize;
        if k > 0 {
            let (mut salt, mut pepper) = (vec![0u8; h * w], vec![0u8; h * w]);
            for _ in 0..k {
                let p = px.below(h * w);
                if px.bernoulli(0.5) {
                    (salt[p], pepper[p]) = (1, 0);
                } else {
                    (salt[p], pepper[p]) = (0, 1);
                }
            }
            let salt = Tensor::from_vec(salt, (1, h, w), &dev)?.broadcast_as((9, h, w))?;
            let pepper = Tensor::from_vec(pepper, (1, h, w), &dev)?.broadcast_as((9, h, w))?;
            x = salt.where_cond(&hi.broadcast_as((9, h, w))?, &x)?;
            x = pepper.where_cond(&lo.broadcast_as((9, h, w))?, &x)?;
        }
    }
    if let Some(sigma) = plan.noise {
        let n: Vec<f32> = (0..9 * h * w).map(|_| px.normal() * sigma).collect();
        x = (x + Tensor::from_vec(n, (9, h, w), &dev)?)?;
    }

    // Frequency.
    if let Some(sigma) = plan.blur {
        x = gaussian_blur(&x, sigma)?;
    }
    if let Some(levels) = plan.posterize {
        let steps = (levels - 1) as f64;
        let span = (&hi - &lo)?.clamp(1e-12f32, f32::MAX)?;
        let t = x
            .broadcast_maximum(&lo)?
            .broadcast_minimum(&hi)?
            .broadcast_sub(&lo)?
            .broadcast_div(&span)?;
        let q = ((t * steps)?.round()? / steps)?;
        x = q.broadcast_mul(&span)?.broadcast_add(&lo)?;
    }
    x.broadcast_maximum(&lo)?.broadcast_minimum(&hi)
}

/// Sobel gradient magnitude of the channel mean, `(H, W)`, edge-replicated borders.
fn sobel_magnitude(x: &Tensor) -> candle_core::Result<Tensor> {
    let (_, h, w) = x.dims3()?;
    let m = x.mean_keepdim(0)?.reshape((1, 1, h, w))?;
    let m = m.pad_with_same(2, 1, 1)?.pad_with_same(3, 1, 1)?;
    #[rustfmt::skip]
    let k: [f32; 18] = [
        -1.0, 0.0, 1.0, -2.0, 0.0, 2.0, -1.0, 0.0, 1.0, // d/dx
        -1.0, -2.0, -1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 1.0, // d/dy
    ];
    let kernel = Tensor::from_vec(k.to_vec(), (2, 1, 3, 3), x.device())?;
    let g = m.conv2d(&kernel, 0, 1, 1, 1)?;
    g.sqr()?.sum(1)?.sqrt()?.reshape((h, w))
}

/// Separable Gaussian blur of `(C, H, W)` with σ in pixels, radius ⌈3σ⌉, replicated borders.
fn gaussian_blur(x: &Tensor, sigma: f32) -> candle_core::Result<Tensor> {
    let (c, h, w) = x.dims3()?;
    if sigma <= 0.0 {
        return Ok(x.clone());
    }
    let r = (3.0 * sigma).ceil() as usize;
    let weights: Vec<f64> = (0..=2 * r)
        .map(|i| (-((i as f64 - r as f64).powi(2)) / (2.0 * (sigma as f64).powi(2))).exp())
        .collect();
    let total: f64 = weights.iter().sum();
    let k: Vec<f32> = weights.iter().map(|v| (v / total) as f32).collect();
    let kx = Tensor::from_vec(k.clone(), (1, 1, 1, 2 * r + 1), x.device())?;
    let ky = Tensor::from_vec(k, (1, 1, 2 * r + 1, 1), x.device())?;
    let y = x.reshape((c, 1, h, w))?;
    let y = y.pad_with_same(3, r, r)?.conv2d(&kx, 0, 1, 1, 1)?;
    let y = y.pad_with_same(2, r, r)?.conv2d(&ky, 0, 1, 1, 1)?;
    y.reshape((c, h, w))
}

/// Wraps a candle error from [`corrupt`] for callers using this crate's `Result`.
pub fn corrupt_batch(ct: &Tensor, seeds: &[u64], cfg: &AugmentConfig) -> Result<Tensor> {
    Ok(corrupt(ct, seeds, cfg)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_table_4() {
        let c = AugmentConfig::default();
        assert_eq!(c.p_apply, 0.70);
        assert_eq!(
            (c.cast_p, c.cast_scale, c.cast_bias),
            (0.50, [0.85, 1.15], [-0.06, 0.06])
        );
        assert_eq!((c.gamma_p, c.gamma), (0.30, [0.75, 1.35]));
        assert_eq!((c.holes_p, c.holes_fraction), (0.50, [0.005, 0.040]));
        assert_eq!(
            (c.cracks_p, c.cracks_quantile, c.cracks_strength),
            (0.50, [0.92, 0.99], [0.4, 1.0])
        );
        assert_eq!((c.salt_pepper_p, c.salt_pepper_fraction), (0.25, [0.0, 0.003]));
        assert_eq!((c.noise_p, c.noise_sigma), (0.50, [0.0, 0.04]));
        assert_eq!((c.blur_p, c.blur_sigma), (0.25, [0.4, 1.2]));
        assert_eq!((c.posterize_p, c.posterize_levels), (0.25, [12, 64]));
        c.validate().unwrap();
        let toml_like: AugmentConfig = serde_json::from_str(r#"{"p_apply": 0.5}"#).unwrap();
        assert_eq!(toml_like.p_apply, 0.5);
        assert_eq!(toml_like.gamma, [0.75, 1.35]);
        assert!(serde_json::from_str::<AugmentConfig>(r#"{"p_aply": 0.5}"#).is_err());
    }

    #[test]
    fn blur_kernel_preserves_constants_and_mass() {
        let x = Tensor::full(0.37f32, (2, 5, 6), &Device::Cpu).unwrap();
        let y = gaussian_blur(&x, 1.1)
            .unwrap()
            .flatten_all()
            .unwrap()
            .to_vec1::<f32>()
            .unwrap();
        assert!(y.iter().all(|v| (v - 0.37).abs() < 1e-6));
    }
}
