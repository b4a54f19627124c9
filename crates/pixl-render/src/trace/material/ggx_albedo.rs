//! Albedo tables of this crate's GGX reflection lobe: the quantities Blender Cycles (4+) reads
//! from its precomputed tables for the Principled BSDF's energy compensation, layering and colour
//! passes. Computed by integrating our own GGX (nothing is copied from Cycles' tables): a
//! stratified midpoint rule over the distribution of visible normals (VNDF, [`ggx_sample_vndf`]),
//! so each entry is a deterministic quadrature. The values are baked into `ggx_tables.rs`
//! (regenerate with `cargo test -p pixl-render --release -- --ignored regenerate_ggx_tables`,
//! about a minute); tests recompute entries and check them against an independent
//! hemispherical integral.
//!
//! For roughness `r` (`α = r²`) and view cosine `μ` (view `wo = (√(1−μ²), 0, μ)`), with `h`
//! drawn from the VNDF of `wo`, `wi = reflect(wo, h)` and `V = [wi.z > 0]`:
//! - `E(r, μ) = E_h[V · G2(wo, wi) / G1(wo)]`: directional albedo of single-scattering GGX with
//!   Fresnel 1 (so `1/E` is the multiple-scattering energy compensation factor).
//! - `Ē(r) = ∫₀¹ 2μ E(r, μ) dμ`: its cosine-weighted hemispherical average.
//! - `S(r, μ, η) = E_h[V · s_η(h·wo)]` with `s_η(c) = (F_η(c) − F0(η)) / (1 − F0(η))`, the exact
//!   dielectric Fresnel written as an interpolation weight between `F0` and 1. The Fresnel-weighted
//!   albedo of the energy-compensated lobe is then `mix(F0, 1, S)` for any `F0` (Cycles' definition
//!   of a microfacet closure's albedo: the per-sample Fresnel weight averaged over the VNDF).
//! - `S5(r, μ) = E_h[V · (1 − h·wo)⁵]`, the same for Schlick's Fresnel (metals).
//!
//! Grids (as Cycles' tables, linearly interpolated, clamped at the ends): `E` 32 × 32 over
//! `(r, μ)` in `[0, 1]²`; `Ē` 32 over `r`; `S` 16 × 16 × 16 over `(r, μ, z)` with
//! `z = √((η−1)/(η+1))` (so `F0 = z⁴`; `z ≤ 0.99`); `S5` 16 × 16. Node values: `r, μ ≥ 1e-4`.
//! Quadrature: 256 × 256 VNDF strata per entry, `Ē` from 64 midpoints in `μ`; the visibility
//! rule uses a substitution that refines the disk rim (converged to ~1e-5 at 256², ≲ 2e-4 at 128²).
//! Accuracy against an independent hemispherical integral: tested to 1e-3.
use super::fresnel_dielectric;
use super::ggx_tables;
use crate::math::V3;
use crate::trace::sampling::{ggx_lambda, ggx_sample_vndf};
use rayon::prelude::*;

const NE: usize = 32;
const NS: usize = 16;
/// VNDF strata per axis used to bake the tables.
pub const STRATA_BAKE: usize = 256;
/// `μ` midpoints for `Ē`.
const MU_AVG: usize = 64;

/// The tables (see the module docs): `E`, `Ē`, `S` (slices of `NS × NS` per `z`, roughness
/// fastest) and `S5`.
pub struct GgxAlbedo<'a> {
    e: &'a [f32],
    e_avg: &'a [f32],
    s: &'a [f32],
    s5: &'a [f32],
}

/// The baked tables.
#[inline]
pub fn tables() -> &'static GgxAlbedo<'static> {
    static T: GgxAlbedo<'static> = GgxAlbedo {
        e: &ggx_tables::E,
        e_avg: &ggx_tables::E_AVG,
        s: &ggx_tables::S,
        s5: &ggx_tables::S5,
    };
    &T
}

/// Grid node `i` of `n` over `[0, 1]`, clamped like Cycles' table nodes.
fn node(i: usize, n: usize, lo: f32, hi: f32) -> f32 {
    (i as f32 / (n - 1) as f32).clamp(lo, hi)
}

/// `F0` of a dielectric of relative IOR `eta`.
pub fn f0_from_ior(eta: f32) -> f32 {
    ((eta - 1.0) / (eta + 1.0)).powi(2)
}

/// The IOR whose `F0` is `f0` (`f0 < 1`).
pub fn ior_from_f0(f0: f32) -> f32 {
    let s = f0.clamp(0.0, 0.9999).sqrt();
    (1.0 + s) / (1.0 - s)
}

/// `η` from the table coordinate `z` (`F0 = z⁴`).
fn ior_from_z(z: f32) -> f32 {
    ior_from_f0(z * z * z * z)
}

/// Averages of `f(h·wo, G2/G1)` over the VNDF (0 where `wi` is below the horizon): a midpoint
/// rule on `strata²` cells of `(t, u2)` with `u1 = 1 − (1 − t)³`, which packs samples towards
/// the rim of the projected disk (`u1 → 1`), where GGX's heavy tail and the horizon cut live.
fn vndf_mean<const K: usize>(rough: f32, mu: f32, strata: usize, f: impl Fn(f32, f32) -> [f32; K]) -> [f32; K] {
    let alpha = rough * rough;
    let wo = V3::new((1.0 - mu * mu).max(0.0).sqrt(), 0.0, mu);
    let lo = ggx_lambda(wo, alpha);
    let mut acc = [0f64; K];
    let inv = 1.0 / strata as f64;
    for i in 0..strata {
        let t = (i as f64 + 0.5) * inv;
        let u1 = (1.0 - (1.0 - t).powi(3)) as f32;
        let jac = 3.0 * (1.0 - t).powi(2);
        for j in 0..strata {
            let h = ggx_sample_vndf(wo, alpha, u1, ((j as f64 + 0.5) * inv) as f32);
            let c = wo.dot(h);
            let wi = h * (2.0 * c) - wo;
            if wi.z <= 0.0 {
                continue;
            }
            let g2_over_g1 = (1.0 + lo) / (1.0 + lo + ggx_lambda(wi, alpha));
            let v = f(c.clamp(0.0, 1.0), g2_over_g1);
            for k in 0..K {
                acc[k] += v[k] as f64 * jac;
            }
        }
    }
    let n = (strata * strata) as f64;
    acc.map(|a| (a / n) as f32)
}

/// `E(r, μ)` by quadrature with `strata²` VNDF samples (no table).
pub fn e_direct(rough: f32, mu: f32, strata: usize) -> f32 {
    vndf_mean(rough, mu, strata, |_, g| [g])[0]
}

/// `[S(r, μ, η_z) for the 16 table IORs, S5(r, μ)]` by quadrature with `strata²` samples.
pub fn s_direct(rough: f32, mu: f32, strata: usize) -> [f32; NS + 1] {
    let etas: Vec<(f32, f32)> = (0..NS)
        .map(|z| {
            let eta = ior_from_z(node(z, NS, 1e-4, 0.99));
            (eta, f0_from_ior(eta))
        })
        .collect();
    vndf_mean::<{ NS + 1 }>(rough, mu, strata, |c, _| {
        let mut out = [0f32; NS + 1];
        for (z, (eta, f0)) in etas.iter().enumerate() {
            out[z] = ((fresnel_dielectric(c, *eta) - f0) / (1.0 - f0)).clamp(0.0, 1.0);
        }
        out[NS] = (1.0 - c).powi(5);
        out
    })
}

/// `Ē(r)` by quadrature (64 midpoints in `μ`, `strata²` VNDF samples each).
pub fn e_avg_direct(rough: f32, strata: usize) -> f32 {
    (0..MU_AVG)
        .map(|j| {
            let mu = (j as f32 + 0.5) / MU_AVG as f32;
            2.0 * mu * e_direct(rough, mu, strata)
        })
        .sum::<f32>()
        / MU_AVG as f32
}

/// The four tables by quadrature, `[E, Ē, S, S5]` in the layout of `ggx_tables.rs`, with
/// `strata²` VNDF samples per entry (the baked ones use [`STRATA_BAKE`]; rayon-parallel).
pub fn compute(strata: usize) -> [Vec<f32>; 4] {
    let e: Vec<f32> = (0..NE * NE)
        .into_par_iter()
        .map(|k| e_direct(node(k % NE, NE, 1e-4, 1.0), node(k / NE, NE, 1e-4, 1.0), strata))
        .collect();
    let e_avg: Vec<f32> = (0..NE)
        .into_par_iter()
        .map(|x| e_avg_direct(node(x, NE, 1e-4, 1.0), strata))
        .collect();
    let rows: Vec<[f32; NS + 1]> = (0..NS * NS)
        .into_par_iter()
        .map(|k| s_direct(node(k % NS, NS, 1e-4, 1.0), node(k / NS, NS, 1e-4, 1.0), strata))
        .collect();
    let mut s = vec![0f32; NS * NS * NS];
    let mut s5 = vec![0f32; NS * NS];
    for (k, row) in rows.iter().enumerate() {
        for z in 0..NS {
            s[z * NS * NS + k] = row[z];
        }
        s5[k] = row[NS];
    }
    [e, e_avg, s, s5]
}

impl GgxAlbedo<'_> {
    /// `E(r, μ)` (interpolated).
    #[inline]
    pub fn e(&self, rough: f32, mu: f32) -> f32 {
        lerp2(self.e, NE, rough, mu)
    }

    /// `Ē(r)` (interpolated).
    #[inline]
    pub fn e_avg(&self, rough: f32) -> f32 {
        let (i0, i1, t) = cell(rough, NE);
        self.e_avg[i0] * (1.0 - t) + self.e_avg[i1] * t
    }

    /// `S(r, μ, η)` for a dielectric `η > 1` (interpolated; `η < 1` is read as `1/η`).
    pub fn s_dielectric(&self, rough: f32, mu: f32, eta: f32) -> f32 {
        self.s_dielectric_at(rough, mu, EtaCell::new(eta))
    }

    /// [`GgxAlbedo::s_dielectric`] with the `η` slice located beforehand (per material).
    /// Always inlined: called from `Bsdf::new` in the pixel kernel, which an out-of-line call
    /// would leave for the baseline build (LLVM stopped inlining it once the kernel held more
    /// than one packet width).
    #[inline(always)]
    pub fn s_dielectric_at(&self, rough: f32, mu: f32, eta: EtaCell) -> f32 {
        let (z0, z1, t) = eta.0;
        let n2 = NS * NS;
        // The (r, μ) cell is shared by both `z` slices: locate it once.
        let (cx, cy) = (cell(rough, NS), cell(mu, NS));
        let a = lerp2_at(&self.s[z0 * n2..(z0 + 1) * n2], NS, cx, cy);
        let b = lerp2_at(&self.s[z1 * n2..(z1 + 1) * n2], NS, cx, cy);
        a * (1.0 - t) + b * t
    }

    /// `S5(r, μ)` (interpolated).
    #[inline]
    pub fn s_schlick(&self, rough: f32, mu: f32) -> f32 {
        lerp2(self.s5, NS, rough, mu)
    }
}

/// Where a dielectric's `η` falls in the `S` table's `η` axis (see
/// [`GgxAlbedo::s_dielectric_at`]); depends on the material only, so it is found once.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EtaCell((usize, usize, f32));

impl EtaCell {
    /// `η < 1` is read as `1/η`.
    pub fn new(eta: f32) -> EtaCell {
        let eta = if eta < 1.0 { 1.0 / eta.max(1e-6) } else { eta };
        let z = ((eta - 1.0) / (eta + 1.0)).max(0.0).sqrt();
        EtaCell(cell(z, NS))
    }
}

/// The two nodes around `x ∈ [0, 1]` on an `n`-node grid and the weight of the upper one.
#[inline]
fn cell(x: f32, n: usize) -> (usize, usize, f32) {
    let f = if x.is_finite() { x.clamp(0.0, 1.0) } else { 0.0 } * (n - 1) as f32;
    // `0 ≤ f < 2³²`, so truncation is the floor (no libm call on baseline x86-64), and the
    // conversion to `u32` is cheaper than a saturating one to `usize`.
    let i0 = (f as u32 as usize).min(n - 2);
    (i0, i0 + 1, f - i0 as f32)
}

/// Bilinear lookup in an `n × n` table stored row-major with `x` (roughness) fastest.
#[inline]
fn lerp2(t: &[f32], n: usize, x: f32, y: f32) -> f32 {
    lerp2_at(t, n, cell(x, n), cell(y, n))
}

/// [`lerp2`] with the cells of `x` and `y` given.
#[inline]
fn lerp2_at(t: &[f32], n: usize, (x0, x1, tx): (usize, usize, f32), (y0, y1, ty): (usize, usize, f32)) -> f32 {
    let row = |y: usize| t[y * n + x0] * (1.0 - tx) + t[y * n + x1] * tx;
    row(y0) * (1.0 - ty) + row(y1) * ty
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// Independent f64 reference: ∫ over the upper hemisphere of `wi` (θ, φ midpoint grid) of
    /// `D(h) · G / (4 μo) · weight(h·wo)`, GGX written out here. With `G = G2(wo, wi)` this is
    /// the directional albedo `E`; with `G = G1(wo)` it is the VNDF expectation `E_h[V · weight]`
    /// (the VNDF density of `wi = reflect(wo, h)` is `G1(wo) D(h) / (4 μo)`).
    fn hemisphere(rough: f64, mu: f64, g2: bool, weight: impl Fn(f64) -> f64) -> f64 {
        let a2 = rough.powi(4);
        let wo = [(1.0 - mu * mu).sqrt(), 0.0, mu];
        let lambda = |c: f64| {
            let t2 = (1.0 - c * c).max(0.0) / (c * c);
            0.5 * ((1.0 + a2 * t2).sqrt() - 1.0)
        };
        let (nt, np) = (1500, 600);
        let mut sum = 0.0;
        for i in 0..nt {
            let th = (i as f64 + 0.5) / nt as f64 * PI / 2.0;
            let (st, ct) = th.sin_cos();
            for j in 0..np {
                let ph = (j as f64 + 0.5) / np as f64 * 2.0 * PI;
                let wi = [st * ph.cos(), st * ph.sin(), ct];
                let h = [wi[0] + wo[0], wi[1] + wo[1], wi[2] + wo[2]];
                let l = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
                let hz = h[2] / l;
                let c = (wo[0] * h[0] + wo[2] * h[2]) / l;
                let d = a2 / (PI * (hz * hz * (a2 - 1.0) + 1.0).powi(2));
                let g = if g2 {
                    1.0 / (1.0 + lambda(mu) + lambda(ct))
                } else {
                    1.0 / (1.0 + lambda(mu))
                };
                sum += d * g / (4.0 * mu) * weight(c) * st * (PI / 2.0 / nt as f64) * (2.0 * PI / np as f64);
            }
        }
        sum
    }

    #[test]
    fn albedo_tables_match_a_hemispherical_integral() {
        let t = tables();
        // Grid nodes (no interpolation error): r = 10/31 ≈ 0.32, 20/31, 1; μ = 8/31, 20/31, 1.
        for &(xi, yi) in &[(10usize, 8usize), (20, 20), (31, 31), (31, 8)] {
            let (r, mu) = (node(xi, NE, 1e-4, 1.0), node(yi, NE, 1e-4, 1.0));
            let want = hemisphere(r as f64, mu as f64, true, |_| 1.0);
            let got = t.e(r, mu) as f64;
            assert!((got - want).abs() < 1e-3, "E({r}, {mu}) = {got}, integral {want}");
            // Single scattering loses energy; at r = 1, μ = 1 only half of the normals reflect
            // into the upper hemisphere (E ≈ 0.307).
            assert!(want < 1.0 && want > 0.25, "E = {want}");
        }
        // S at nodes of the S grid (z = 6/15, i.e. η ≈ 1.38).
        let eta = ior_from_z(6.0 / 15.0);
        let f0 = f0_from_ior(eta) as f64;
        let s_of = |c: f64| {
            let f = fresnel_dielectric(c as f32, eta) as f64;
            ((f - f0) / (1.0 - f0)).clamp(0.0, 1.0)
        };
        for &(xi, yi) in &[(5usize, 9usize), (15, 3), (10, 15)] {
            let (r, mu) = (node(xi, NS, 1e-4, 1.0), node(yi, NS, 1e-4, 1.0));
            let want = hemisphere(r as f64, mu as f64, false, s_of);
            let got = t.s_dielectric(r, mu, eta) as f64;
            assert!(
                (got - want).abs() < 2e-3,
                "S({r}, {mu}, {eta}) = {got}, integral {want}"
            );
            let want5 = hemisphere(r as f64, mu as f64, false, |c| (1.0 - c).powi(5));
            let got5 = t.s_schlick(r, mu) as f64;
            assert!((got5 - want5).abs() < 1e-3, "S5({r}, {mu}) = {got5}, integral {want5}");
        }
        // A near-mirror sees one microfacet orientation: S5 = (1 − μ)⁵.
        let mu = 9.0 / 15.0;
        let got = t.s_schlick(0.0, mu);
        assert!((got - (1.0f32 - mu).powi(5)).abs() < 1e-4, "{got}");
        // Ē at r = 1 equals ∫ 2μE by a separate trapezoid over the E table.
        let trap: f32 = (0..NE - 1)
            .map(|j| {
                let (m0, m1) = (j as f32 / 31.0, (j + 1) as f32 / 31.0);
                (2.0 * m0 * t.e(1.0, m0) + 2.0 * m1 * t.e(1.0, m1)) * 0.5 / 31.0
            })
            .sum();
        assert!((t.e_avg(1.0) - trap).abs() < 3e-3, "Eavg {} vs {trap}", t.e_avg(1.0));
    }

    #[test]
    fn baked_entries_match_a_fresh_quadrature() {
        // A spread of entries of each table, recomputed with 128² strata (error ≲ 3e-4).
        let t = tables();
        for k in (0..NE * NE).step_by(97) {
            let got = e_direct(node(k % NE, NE, 1e-4, 1.0), node(k / NE, NE, 1e-4, 1.0), 128);
            assert!((t.e[k] - got).abs() < 1e-3, "E[{k}] {} vs {got}", t.e[k]);
        }
        for x in [0, 7, 20, 31] {
            let got = e_avg_direct(node(x, NE, 1e-4, 1.0), 64);
            assert!((t.e_avg[x] - got).abs() < 1e-3, "Eavg[{x}] {} vs {got}", t.e_avg[x]);
        }
        for k in (0..NS * NS).step_by(37) {
            let got = s_direct(node(k % NS, NS, 1e-4, 1.0), node(k / NS, NS, 1e-4, 1.0), 128);
            for z in 0..NS {
                let baked = t.s[z * NS * NS + k];
                assert!((baked - got[z]).abs() < 1e-3, "S[{z}][{k}] {baked} vs {}", got[z]);
            }
            assert!((t.s5[k] - got[NS]).abs() < 1e-3, "S5[{k}] {} vs {}", t.s5[k], got[NS]);
        }
    }

    /// Rewrites `ggx_tables.rs` (run explicitly; about a minute in release).
    #[test]
    #[ignore]
    fn regenerate_ggx_tables() {
        use std::fmt::Write;
        let [e, e_avg, s, s5] = compute(STRATA_BAKE);
        let mut out = String::from(
            "//! Baked GGX albedo tables, see `ggx_albedo.rs` for their definitions. Generated by\n\
             //! `cargo test -p pixl-render --release -- --ignored regenerate_ggx_tables`; do not edit.\n",
        );
        for (name, v, doc) in [
            ("E", &e, "`E(r, μ)`: 32 × 32, index `μ_i · 32 + r_i`."),
            ("E_AVG", &e_avg, "`Ē(r)`: 32."),
            (
                "S",
                &s,
                "`S(r, μ, z)`: 16 × 16 × 16, index `(z_i · 16 + μ_i) · 16 + r_i`.",
            ),
            ("S5", &s5, "`S5(r, μ)`: 16 × 16, index `μ_i · 16 + r_i`."),
        ] {
            writeln!(
                out,
                "\n/// {doc}\n#[rustfmt::skip]\npub const {name}: [f32; {}] = [",
                v.len()
            )
            .unwrap();
            for row in v.chunks(8) {
                let items: Vec<String> = row.iter().map(|x| format!("{x:?}")).collect();
                writeln!(out, "    {},", items.join(", ")).unwrap();
            }
            out.push_str("];\n");
        }
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/src/trace/material/ggx_tables.rs");
        std::fs::write(path, out).unwrap();
    }

    #[test]
    fn ior_f0_roundtrip() {
        for eta in [1.05f32, 1.33, 1.5, 2.4] {
            assert!((ior_from_f0(f0_from_ior(eta)) - eta).abs() < 1e-4 * eta);
        }
        assert!((f0_from_ior(1.5) - 0.04).abs() < 1e-7);
    }
}
