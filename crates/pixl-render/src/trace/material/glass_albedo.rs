//! Directional albedo of this crate's single-scattering rough glass, for its energy compensation
//! (Cycles' Principled glass carries the same compensation: the lobe is scaled by `1 / E`, so a
//! clear glass reflects plus transmits all the light that reaches it, as the smooth glass does).
//!
//! For roughness `r` (`α = max(r², 1e-3)`, as the BSDF), view cosine `μ` (`wo = (√(1−μ²), 0, μ)`)
//! and relative IOR `η` across the interface, with `h` drawn from the visible normals of `wo`:
//! `E(r, μ) = E_h[F·V_r + (1 − F)·V_t] · G2 / G1(wo)`, where `F = F_η(wo·h)`, `V_r` says the
//! mirror direction about `h` is above the surface and `V_t` that the refracted one is below
//! (`G2` at that direction) — the mean sample weight of [`super::Bsdf`]'s rough glass with base
//! 1 and no compensation. Computed per material when it is loaded (both sides: `η = ior` and
//! `1/ior`), by a stratified midpoint rule of 32 × 32 visible normals per entry on a 16 × 16
//! grid over `(r, μ)` (nodes `r = i/15`, `μ = (j + ½)/16`), bilinearly interpolated and clamped
//! at the ends: 2 × 256 entries × 1024 visible normals per material. Accuracy: tested against the
//! BSDF's own quadrature.
use super::fresnel_dielectric;
use crate::math::V3;
use crate::trace::sampling::{ggx_lambda, ggx_sample_vndf};

const N_R: usize = 16;
const N_MU: usize = 16;
const STRATA: usize = 32;

/// `E(r, μ)` of one side of an interface (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct GlassAlbedo {
    e: [[f32; N_MU]; N_R],
}

/// The glass albedo tables of a material: light arriving from outside (`η = ior`) and from
/// inside (`η = 1/ior`).
#[derive(Clone, Debug, PartialEq)]
pub struct GlassTables {
    pub entering: GlassAlbedo,
    pub leaving: GlassAlbedo,
}

impl GlassTables {
    pub fn new(ior: f32) -> GlassTables {
        GlassTables {
            entering: GlassAlbedo::new(ior),
            leaving: GlassAlbedo::new(1.0 / ior),
        }
    }
}

/// `E` at one `(r, μ, η)` by the stratified midpoint rule.
pub fn glass_albedo(r: f32, mu: f32, eta: f32) -> f32 {
    let alpha = (r * r).max(1e-3);
    let mu = mu.clamp(1e-4, 1.0);
    let wo = V3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let g1_o = 1.0 / (1.0 + ggx_lambda(wo, alpha));
    let mut sum = 0.0f64;
    for i in 0..STRATA {
        for j in 0..STRATA {
            let (u1, u2) = ((i as f32 + 0.5) / STRATA as f32, (j as f32 + 0.5) / STRATA as f32);
            let h = ggx_sample_vndf(wo, alpha, u1, u2);
            let c = wo.dot(h);
            if !(c > 0.0) {
                continue;
            }
            let f = fresnel_dielectric(c, eta);
            let weight = |wi: V3| (1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha))) / g1_o;
            let wr = h * (2.0 * c) - wo;
            if wr.z > 0.0 {
                sum += (f * weight(wr)) as f64;
            }
            if f < 1.0 {
                let cos_t = (1.0 - (1.0 - c * c) / (eta * eta)).max(0.0).sqrt();
                let wt = (h * (c / eta - cos_t) - wo / eta).normalize();
                if wt.z < 0.0 {
                    sum += ((1.0 - f) * weight(wt)) as f64;
                }
            }
        }
    }
    (sum / (STRATA * STRATA) as f64) as f32
}

impl GlassAlbedo {
    pub fn new(eta: f32) -> GlassAlbedo {
        let mut e = [[0.0; N_MU]; N_R];
        for (i, row) in e.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = glass_albedo(i as f32 / (N_R - 1) as f32, (j as f32 + 0.5) / N_MU as f32, eta);
            }
        }
        GlassAlbedo { e }
    }

    /// `E(r, μ)`, bilinear between the nodes.
    pub fn eval(&self, r: f32, mu: f32) -> f32 {
        let x = (r.clamp(0.0, 1.0) * (N_R - 1) as f32).min((N_R - 1) as f32);
        let y = (mu * N_MU as f32 - 0.5).clamp(0.0, (N_MU - 1) as f32);
        let (i, j) = ((x as usize).min(N_R - 2), (y as usize).min(N_MU - 2));
        let (fx, fy) = (x - i as f32, y - j as f32);
        let row = |i: usize| self.e[i][j] * (1.0 - fy) + self.e[i][j + 1] * fy;
        row(i) * (1.0 - fx) + row(i + 1) * fx
    }
}
