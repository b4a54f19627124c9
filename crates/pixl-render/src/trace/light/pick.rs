//! The light picker: at a shading point ([`ShadingPoint`]) one light is chosen with a
//! probability in proportion to an estimate of what it brings there, a share [`PICK_FLOOR`]
//! following the scene-wide power among the lights that can reach the point (the estimates:
//! the module docs of [`super`]). [`Lights::pick_at`] computes the weights once per point
//! ([`LightPick`]); [`Lights::pick_pmf_at`] gives the probability of a light for MIS.
//!
//! Contract: at every point the lights' pick probabilities sum to one, and every light that can
//! reach the point has a positive one, so the estimator stays unbiased (tested).
use super::kinds::LightKind;
use super::lights::Lights;
use crate::math::V3;
use std::f32::consts::PI;

/// Share of a light's pick probability that follows the scene-wide power estimate (among the
/// lights that can reach the shading point) rather than the per-point one.
pub const PICK_FLOOR: f32 = 0.1;

/// Pick items (analytic lights, then the group of emissive triangles) whose weights a
/// [`LightPick`] keeps; further ones are recomputed when asked.
pub(super) const CACHED: usize = 8;

/// What the light choice knows of a shading point.
#[derive(Clone, Copy, Debug)]
pub struct ShadingPoint {
    pub p: V3,
    /// Shading normal on the side light is scattered to (unit).
    pub n: V3,
    /// Light from both sides of `n` can scatter (a transmission lobe): no cosine bound.
    pub two_sided: bool,
    /// Sample rectangular area lights by solid angle ([`RectView`](super::rect::RectView); costlier per sample,
    /// worth it where the light is seen directly: the integrator asks it at the camera vertex).
    pub solid_angle: bool,
}

/// The light choice at one shading point: the per-point weights of the pick items, their sum,
/// and the summed power weights of the items that can reach the point.
#[derive(Clone, Copy, Debug)]
pub struct LightPick {
    pub sp: ShadingPoint,
    pub(super) total: f32,
    pub(super) base_total: f32,
    /// Weight per item (the first [`CACHED`]); negative: the item cannot reach the point.
    pub(super) w: [f32; CACHED],
    /// The rectangle the light sample at this point sampled by solid angle, and that solid
    /// angle (so that the MIS of a BSDF sample hitting it need not compute it again).
    pub(super) rect: Option<(usize, f32)>,
}

/// `max cos` between `n` and the directions within angle `α` of a direction at cosine `cos_t`
/// from `n` (`cos(max(0, θ − α))`, clamped at 0).
#[inline(always)]
fn cos_bound(cos_t: f32, sin_a: f32, cos_a: f32) -> f32 {
    if cos_t >= cos_a {
        return 1.0;
    }
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    (cos_t * cos_a + sin_t * sin_a).max(0.0)
}

impl Lights {
    /// Number of pick items: the analytic lights, then one for all emissive triangles.
    #[inline(always)]
    pub(super) fn items(&self) -> usize {
        self.analytic + (self.lights.len() > self.analytic) as usize
    }

    #[inline(always)]
    fn item_base(&self, k: usize) -> f32 {
        if k < self.analytic {
            self.base.pmf(k)
        } else {
            self.tri_base
        }
    }

    /// Whether pick item `k` can reach `sp` at all (`item_weight` is `Some`), without the weight.
    #[inline(always)]
    pub(super) fn item_reaches(&self, k: usize, sp: &ShadingPoint) -> bool {
        match self.lights.get(k) {
            Some(LightKind::Area { c, n, .. }) if k < self.analytic => (sp.p - *c).dot(*n) > 0.0,
            Some(LightKind::Env) if k < self.analytic => self.env_peaked > 0.0,
            Some(l @ LightKind::Spot { p, .. }) if k < self.analytic => l.spot_mask(sp.p - *p) > 0.0,
            _ => true,
        }
    }

    /// The per-point weight of pick item `k` at `sp` (an estimate of its unoccluded irradiance
    /// there, see the module docs), or `None` when it cannot light the point at all.
    #[inline(always)]
    pub(super) fn item_weight(&self, k: usize, sp: &ShadingPoint) -> Option<f32> {
        let facing = |cos_t: f32, sin_a: f32, cos_a: f32| {
            if sp.two_sided {
                cos_bound(cos_t.abs(), sin_a, cos_a)
            } else {
                cos_bound(cos_t, sin_a, cos_a)
            }
        };
        if k >= self.analytic {
            let (c, r) = self.tri_bounds;
            let d2 = (c - sp.p).dot(c - sp.p).max(r * r);
            return Some(self.tri_power / (2.0 * PI * d2.max(1e-12)));
        }
        let lum = self.lum[k];
        match &self.lights[k] {
            LightKind::Point { p, radius, .. } | LightKind::Spot { p, radius, .. } => {
                let to = *p - sp.p;
                let d2 = to.dot(to);
                let mask = self.lights[k].spot_mask(-to);
                if !(mask > 0.0) {
                    return None;
                }
                let d = d2.sqrt();
                let r = *radius;
                let cos_t = sp.n.dot(to) / d;
                let f = if r > 0.0 && d > r {
                    let sin_a = r / d;
                    facing(cos_t, sin_a, (1.0 - sin_a * sin_a).sqrt())
                } else if r > 0.0 {
                    1.0
                } else {
                    facing(cos_t, 0.0, 1.0)
                };
                let w = lum * mask * f / d2.max(r * r);
                Some(if w.is_finite() { w } else { 0.0 })
            }
            LightKind::Area {
                c,
                ex,
                ey,
                n,
                disk,
                area,
                ..
            } => {
                let to = sp.p - *c;
                let h = to.dot(*n);
                if !(h > 0.0) {
                    return None; // behind the one-sided emitter (or in its plane)
                }
                let d2 = to.dot(to);
                let d = d2.sqrt();
                let r2 = if *disk {
                    ex.dot(*ex).max(ey.dot(*ey))
                } else {
                    ex.dot(*ex) + ey.dot(*ey)
                };
                let (sin_a, cos_a) = if d2 > r2 {
                    let s2 = r2 / d2;
                    (s2.sqrt(), (1.0 - s2).sqrt())
                } else {
                    (1.0, 0.0)
                };
                let emit = cos_bound(h / d, sin_a, cos_a);
                let recv = facing(-sp.n.dot(to) / d, sin_a, cos_a);
                Some(lum * (area * emit / d2).min(PI) * recv)
            }
            LightKind::Sun { dir, cos_max, .. } => {
                let cos_a = *cos_max;
                let sin_a = (1.0 - cos_a * cos_a).max(0.0).sqrt();
                Some(lum * facing(-sp.n.dot(*dir), sin_a, cos_a))
            }
            LightKind::Env => {
                // Only the world's light above its mean is worth light samples: BSDF samples
                // (MIS-weighted) already find a constant sky as well as light sampling could
                // (for a Lambertian surface and a cosine-sampled sky, with the same density),
                // so a constant world is left to them entirely (every non-delta lobe samples
                // all the directions it scatters to, so nothing is missed) and its picks go to
                // the lights that need them. (A floor share of picks for it cost the depth-mesh
                // bench scene most of its Diffuse Direct noise: 0.8 % of samples without the key
                // light.)
                if !(self.env_peaked > 0.0) {
                    return None;
                }
                let (a, b) = self.env_sh;
                let e = if sp.two_sided {
                    2.0 * PI * a
                } else {
                    // ∫ (a + b·ω) cos over the hemisphere = π a + (2π/3) b·n; the first-order
                    // fit can dip below the true (non-negative) value, hence the clamp.
                    (PI * a + (2.0 * PI / 3.0) * b.dot(sp.n)).max(0.1 * PI * a)
                };
                Some(e * self.env_peaked)
            }
            LightKind::Tri { .. } => Some(0.0),
        }
    }

    /// The one pick item that is not a constant world, when there is only one (then its
    /// per-point weight does not matter, only whether it can reach the point: it is picked with
    /// probability 1 wherever it can).
    #[inline(always)]
    pub(super) fn single_item(&self) -> Option<usize> {
        self.single
    }

    pub(super) fn find_single_item(&self) -> Option<usize> {
        let constant_env = self.env_index.filter(|_| !(self.env_peaked > 0.0));
        match (self.items(), constant_env) {
            (1, None) => Some(0),
            (2, Some(e)) => Some(1 - e),
            _ => None,
        }
    }

    /// The light choice at `sp` (computes the per-point weights).
    #[inline(always)]
    pub fn pick_at(&self, sp: ShadingPoint) -> LightPick {
        let mut pick = LightPick {
            sp,
            total: 0.0,
            base_total: 0.0,
            w: [-1.0; CACHED],
            rect: None,
        };
        if let Some(k) = self.single_item() {
            // Picked whenever it can reach the point (any weight gives it probability 1).
            if self.item_reaches(k, &sp) {
                pick.w[k] = 1.0;
                pick.total = 1.0;
                pick.base_total = self.item_base(k);
            }
            return pick;
        }
        for k in 0..self.items() {
            let w = self.item_weight(k, &sp);
            if let Some(w) = w {
                pick.total += w;
                pick.base_total += self.item_base(k);
            }
            if k < CACHED {
                pick.w[k] = w.unwrap_or(-1.0);
            }
        }
        pick
    }

    /// Probability that `pick` chooses item `k`.
    #[inline(always)]
    fn item_pmf(&self, pick: &LightPick, k: usize) -> f32 {
        if let Some(s) = self.single_item() {
            // What the general case below gives, exactly: (1 − floor)·1 + floor·1 = 1 in f32.
            return if k == s && pick.w[s] >= 0.0 { 1.0 } else { 0.0 };
        }
        let w = if k < CACHED {
            pick.w[k]
        } else {
            self.item_weight(k, &pick.sp).unwrap_or(-1.0)
        };
        if w < 0.0 {
            return 0.0;
        }
        let base = if pick.base_total > 0.0 {
            self.item_base(k) / pick.base_total
        } else {
            0.0
        };
        match (pick.total > 0.0, pick.base_total > 0.0) {
            (true, true) => (1.0 - PICK_FLOOR) * (w / pick.total) + PICK_FLOOR * base,
            (true, false) => w / pick.total,
            (false, _) => base,
        }
    }

    /// Probability that the light choice `pick` picks light `i`.
    #[inline(always)]
    pub fn pick_pmf_at(&self, pick: &LightPick, i: usize) -> f32 {
        if i < self.analytic {
            self.item_pmf(pick, i)
        } else {
            self.item_pmf(pick, self.analytic) * self.tri_dist.pmf(i - self.analytic)
        }
    }

    /// Light `i` and its pick probability, chosen by `pick` with the uniform number `u`.
    #[inline(always)]
    pub(super) fn choose(&self, pick: &LightPick, u: f32) -> Option<(usize, f32)> {
        let (k, p, lo) = match self.single_item() {
            // The walk below would find it with probability 1 (or nothing where it cannot reach).
            Some(s) if pick.w[s] >= 0.0 => (s, 1.0, 0.0),
            Some(_) => return None,
            None => {
                let mut acc = 0.0;
                let mut chosen = None;
                for k in 0..self.items() {
                    let p = self.item_pmf(pick, k);
                    if p > 0.0 {
                        chosen = Some((k, p, acc));
                        acc += p;
                        if u < acc {
                            break;
                        }
                    }
                }
                chosen?
            }
        };
        if k < self.analytic {
            return Some((k, p));
        }
        let (t, _) = self.tri_dist.sample(((u - lo) / p).clamp(0.0, 0.999_999_94));
        Some((self.analytic + t, p * self.tri_dist.pmf(t)))
    }
}
