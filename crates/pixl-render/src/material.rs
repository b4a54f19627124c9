//! The surface BSDF: a metallic/roughness Principled-like model with three lobes.
//!
//! - **Diffuse** (Lambertian): albedo `kd = base · (1 − metallic) · (1 − transmission)`.
//! - **Glossy** (GGX microfacet, `α = roughness²`, height-correlated Smith G2, Schlick Fresnel):
//!   `F0 = lerp(F0_dielectric, base, metallic)`, `F0_dielectric = ((ior−1)/(ior+1))² · 2 ·
//!   specular_ior_level`, scaled by `metallic + (1 − metallic)(1 − transmission)`. Sampled with
//!   GGX visible normals (Heitz 2018).
//! - **Transmission** (weight `(1 − metallic) · transmission`): a *smooth* dielectric of the
//!   given IOR (Fresnel-weighted specular reflection + refraction tinted by the base colour),
//!   whatever the roughness — rough glass is rendered as smooth glass (known approximation).
//!   Radiance is not scaled by `η²` at refraction, as Cycles does not for camera paths.
//!
//! Simplifications against Blender's Principled BSDF v2: no energy-compensation between the
//! specular layer and the diffuse base (the diffuse lobe is not darkened by `1 − F`, ≤ 4 % more
//! energy at F0 = 0.04), no multiple-scattering GGX, no sheen / coat / subsurface / anisotropy.
//!
//! Lobes are picked for sampling in proportion to a luminance weight; MIS uses the combined pdf
//! of the non-delta lobes. Evaluations are returned per lobe (diffuse / glossy / transmission) so
//! the film can split light into Cycles' passes.
use crate::geometry::{MaterialData, SurfaceHit};
use crate::math::{Frame, V3};
use crate::sampling::{cosine_hemisphere, ggx_d, ggx_g1, ggx_g2, ggx_sample_vndf};
use std::f32::consts::FRAC_1_PI;

/// Which pass family a lobe belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lobe {
    Diffuse,
    Glossy,
    Transmission,
}

/// `f · |cos θi|` per lobe, and the pdf (solid angle) of sampling `wi` with [`Bsdf::sample`].
#[derive(Clone, Copy, Debug, Default)]
pub struct BsdfEval {
    pub diffuse: V3,
    pub glossy: V3,
    pub transmission: V3,
    pub pdf: f32,
}

impl BsdfEval {
    pub fn total(&self) -> V3 {
        self.diffuse + self.glossy + self.transmission
    }
}

/// A sampled direction with per-lobe weights `f · |cos θi| / pdf`.
#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    pub wi: V3,
    pub weight: BsdfEval,
    /// The pdf for MIS (meaningless when `delta`).
    pub pdf: f32,
    pub delta: bool,
    /// Whether `wi` leaves on the other side of the surface (refraction).
    pub transmitted: bool,
}

/// The BSDF at one shading point, for one outgoing direction.
#[derive(Clone, Debug)]
pub struct Bsdf {
    frame: Frame,
    /// Geometric normal, flipped to the side of `wo`.
    ng: V3,
    wo_local: V3,
    kd: V3,
    f0: V3,
    spec_scale: f32,
    alpha: f32,
    trans_w: f32,
    tint: V3,
    /// Relative IOR across the interface in the direction of travel into the surface.
    eta: f32,
    p_diff: f32,
    p_spec: f32,
    p_trans: f32,
    /// The albedo-like colour weights that Cycles stores as DiffCol / GlossCol / TransCol.
    pub colors: [V3; 3],
}

#[inline]
fn schlick(f0: V3, cos: f32) -> V3 {
    let m = (1.0 - cos.clamp(0.0, 1.0)).powi(5);
    f0 + (V3::ONE - f0) * m
}

/// Unpolarised Fresnel reflectance of a dielectric interface; `eta = n_t / n_i`.
pub fn fresnel_dielectric(cos_i: f32, eta: f32) -> f32 {
    let cos_i = cos_i.clamp(0.0, 1.0);
    let sin2_t = (1.0 - cos_i * cos_i) / (eta * eta);
    if sin2_t >= 1.0 {
        return 1.0;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    let rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    let rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    0.5 * (rs * rs + rp * rp)
}

impl Bsdf {
    /// The BSDF of material `m` at `hit` for the outgoing direction `wo` (unit, pointing away).
    pub fn new(m: &MaterialData, hit: &SurfaceHit, wo: V3) -> Bsdf {
        let mut base = m.base;
        if let Some(t) = &m.base_tex {
            base *= t.sample(hit.uv[0], hit.uv[1]);
        }
        let mut roughness = m.roughness;
        if let Some(t) = &m.roughness_tex {
            roughness *= t.sample(hit.uv[0], hit.uv[1]).x;
        }
        let mut metallic = m.metallic;
        if let Some(t) = &m.metallic_tex {
            metallic *= t.sample(hit.uv[0], hit.uv[1]).x;
        }
        let roughness = roughness.clamp(0.0, 1.0);
        let metallic = metallic.clamp(0.0, 1.0);
        let base = base.max(V3::ZERO);
        // Outward orientation from the shading normal; entering if wo is on the outside.
        let ng_out = if hit.ng.dot(hit.ns) < 0.0 { -hit.ng } else { hit.ng };
        let entering = wo.dot(ng_out) >= 0.0;
        let ng = if entering { ng_out } else { -ng_out };
        let mut ns = if entering { hit.ns } else { -hit.ns };
        if ns.dot(wo) <= 1e-4 {
            // Shading normal facing away from the viewer: fall back to the geometric normal.
            ns = ng;
        }
        let frame = Frame::new(ns);
        let wo_local = frame.to_local(wo);
        let trans = m.transmission.clamp(0.0, 1.0);
        let kd = base * ((1.0 - metallic) * (1.0 - trans));
        let f0d = (((m.ior - 1.0) / (m.ior + 1.0)).powi(2) * 2.0 * m.specular_level).clamp(0.0, 1.0);
        let f0 = V3::lerp(V3::splat(f0d), base, metallic);
        let spec_scale = if f0d == 0.0 && metallic == 0.0 {
            0.0
        } else {
            metallic + (1.0 - metallic) * (1.0 - trans)
        };
        let trans_w = (1.0 - metallic) * trans;
        let eta = if entering { m.ior } else { 1.0 / m.ior };
        let cos_o = wo_local.z.max(0.0);
        let gloss_col = schlick(f0, cos_o) * spec_scale;
        let fr = fresnel_dielectric(cos_o, eta);
        let w_d = kd.luminance();
        let w_s = gloss_col.luminance();
        let w_t = if trans_w > 0.0 {
            trans_w * (fr + (1.0 - fr) * base.luminance()).max(1e-3)
        } else {
            0.0
        };
        let sum = w_d + w_s + w_t;
        let (p_diff, p_spec, p_trans) = if sum > 0.0 {
            (w_d / sum, w_s / sum, w_t / sum)
        } else {
            (0.0, 0.0, 0.0)
        };
        let colors = [kd, gloss_col + V3::splat(trans_w * fr), base * (trans_w * (1.0 - fr))];
        Bsdf {
            frame,
            ng,
            wo_local,
            kd,
            f0,
            spec_scale,
            alpha: (roughness * roughness).max(1e-3),
            trans_w,
            tint: base,
            eta,
            p_diff,
            p_spec,
            p_trans,
            colors,
        }
    }

    /// Whether the BSDF can scatter at all.
    pub fn is_black(&self) -> bool {
        self.p_diff + self.p_spec + self.p_trans <= 0.0
    }

    /// Whether the BSDF has a non-delta lobe (worth light sampling).
    pub fn has_smooth(&self) -> bool {
        self.p_diff + self.p_spec > 0.0
    }

    /// The geometric normal on the side of `wo`.
    pub fn ng(&self) -> V3 {
        self.ng
    }

    /// Evaluates the non-delta lobes for the incident direction `wi` (world, unit).
    pub fn eval(&self, wi_world: V3) -> BsdfEval {
        let wi = self.frame.to_local(wi_world);
        let wo = self.wo_local;
        let mut out = BsdfEval::default();
        if wi.z <= 0.0 || wo.z <= 0.0 || wi_world.dot(self.ng) <= 0.0 {
            return out;
        }
        if self.p_diff > 0.0 {
            out.diffuse = self.kd * (FRAC_1_PI * wi.z);
            out.pdf += self.p_diff * wi.z * FRAC_1_PI;
        }
        if self.p_spec > 0.0 {
            let h = (wo + wi).normalize();
            let d = ggx_d(h, self.alpha);
            let f = schlick(self.f0, wi.dot(h));
            let g2 = ggx_g2(wo, wi, self.alpha);
            out.glossy = f * (self.spec_scale * d * g2 / (4.0 * wo.z));
            out.pdf += self.p_spec * ggx_g1(wo, self.alpha) * d / (4.0 * wo.z);
        }
        out
    }

    /// Samples an incident direction with uniforms `(u_lobe, u1, u2)`.
    pub fn sample(&self, u_lobe: f32, u1: f32, u2: f32) -> Option<BsdfSample> {
        let wo = self.wo_local;
        if self.is_black() || wo.z <= 0.0 {
            return None;
        }
        if u_lobe < self.p_trans {
            // Smooth dielectric: reflect with probability F, else refract.
            let u = u_lobe / self.p_trans;
            let fr = fresnel_dielectric(wo.z, self.eta);
            let scale = self.trans_w / self.p_trans;
            let mut weight = BsdfEval::default();
            let (wi, transmitted) = if u < fr {
                weight.glossy = V3::splat(scale);
                (V3::new(-wo.x, -wo.y, wo.z), false)
            } else {
                weight.transmission = self.tint * scale;
                let eta = self.eta;
                let cos_t = (1.0 - (1.0 - wo.z * wo.z) / (eta * eta)).max(0.0).sqrt();
                (V3::new(-wo.x / eta, -wo.y / eta, -cos_t).normalize(), true)
            };
            let wi_world = self.frame.to_world(wi);
            // Keep the sample on the geometric side it claims to be on.
            if (wi_world.dot(self.ng) > 0.0) == transmitted {
                return None;
            }
            return Some(BsdfSample {
                wi: wi_world,
                weight,
                pdf: 0.0,
                delta: true,
                transmitted,
            });
        }
        let u = u_lobe - self.p_trans;
        let wi = if u < self.p_diff {
            cosine_hemisphere(u1, u2)
        } else {
            let h = ggx_sample_vndf(wo, self.alpha, u1, u2);
            let wi = h * (2.0 * wo.dot(h)) - wo;
            if wi.z <= 0.0 {
                return None;
            }
            wi
        };
        let wi_world = self.frame.to_world(wi);
        let e = self.eval(wi_world);
        let pdf = e.pdf;
        if !(pdf > 0.0) {
            return None;
        }
        let inv = 1.0 / pdf;
        let weight = BsdfEval {
            diffuse: e.diffuse * inv,
            glossy: e.glossy * inv,
            transmission: V3::ZERO,
            pdf,
        };
        Some(BsdfSample {
            wi: wi_world,
            weight,
            pdf,
            delta: false,
            transmitted: false,
        })
    }
}
