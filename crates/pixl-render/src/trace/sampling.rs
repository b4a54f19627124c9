//! Sampling routines: hemispheres, spheres, disks, cones, triangles, GGX visible normals, a
//! discrete distribution, and the power heuristic for MIS. Every routine takes its uniforms as
//! arguments, so a path is reproducible from its random stream.
use crate::math::V3;
use std::f32::consts::{FRAC_PI_4, PI};

/// Cosine-weighted direction on the +Z hemisphere; pdf `cos θ / π`.
#[inline]
pub fn cosine_hemisphere(u1: f32, u2: f32) -> V3 {
    let (dx, dy) = concentric_disk(u1, u2);
    let z = (1.0 - dx * dx - dy * dy).max(0.0).sqrt();
    V3::new(dx, dy, z)
}

/// Uniform point on the unit disk (Shirley–Chiu concentric map).
#[inline]
pub fn concentric_disk(u1: f32, u2: f32) -> (f32, f32) {
    let a = 2.0 * u1 - 1.0;
    let b = 2.0 * u2 - 1.0;
    if a == 0.0 && b == 0.0 {
        return (0.0, 0.0);
    }
    let (r, phi) = if a.abs() > b.abs() {
        (a, FRAC_PI_4 * (b / a))
    } else {
        (b, PI / 2.0 - FRAC_PI_4 * (a / b))
    };
    (r * phi.cos(), r * phi.sin())
}

/// Uniform direction on the unit sphere; pdf `1 / 4π`.
#[inline]
pub fn uniform_sphere(u1: f32, u2: f32) -> V3 {
    let z = 1.0 - 2.0 * u1;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u2;
    V3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Uniform direction in the cone of half-angle with cosine `cos_max` around +Z.
#[inline]
pub fn uniform_cone(u1: f32, u2: f32, cos_max: f32) -> V3 {
    let z = 1.0 - u1 * (1.0 - cos_max);
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u2;
    V3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Uniform barycentrics `(b1, b2)` on a triangle.
#[inline]
pub fn uniform_triangle(u1: f32, u2: f32) -> (f32, f32) {
    let s = u1.sqrt();
    (1.0 - s, u2 * s)
}

/// Power heuristic (β = 2) weight of the strategy with pdf `a` against one with pdf `b`.
#[inline]
pub fn power_heuristic(a: f32, b: f32) -> f32 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 && a2.is_finite() {
        a2 / (a2 + b2)
    } else if a.is_infinite() {
        1.0
    } else {
        0.0
    }
}

/// GGX (Trowbridge–Reitz) normal distribution `D(h)` in the local frame (+Z normal).
#[inline]
pub fn ggx_d(h: V3, alpha: f32) -> f32 {
    let a2 = alpha * alpha;
    let c2 = h.z * h.z;
    let d = c2 * (a2 - 1.0) + 1.0;
    a2 / (PI * d * d)
}

/// Smith `Λ(w)` for GGX.
#[inline]
pub fn ggx_lambda(w: V3, alpha: f32) -> f32 {
    let c2 = w.z * w.z;
    if c2 <= 0.0 {
        return f32::INFINITY;
    }
    let t2 = (1.0 - c2).max(0.0) / c2;
    0.5 * ((1.0 + alpha * alpha * t2).sqrt() - 1.0)
}

#[inline]
pub fn ggx_g1(w: V3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(w, alpha))
}

/// Height-correlated Smith masking–shadowing.
#[inline]
pub fn ggx_g2(wo: V3, wi: V3, alpha: f32) -> f32 {
    1.0 / (1.0 + ggx_lambda(wo, alpha) + ggx_lambda(wi, alpha))
}

/// Samples a GGX visible normal for `wo` (local, `wo.z > 0`) (Heitz 2018); its pdf is
/// `G1(wo) · max(0, wo·h) · D(h) / wo.z`.
#[inline]
pub fn ggx_sample_vndf(wo: V3, alpha: f32, u1: f32, u2: f32) -> V3 {
    let vh = V3::new(alpha * wo.x, alpha * wo.y, wo.z).normalize();
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 0.0 {
        V3::new(-vh.y, vh.x, 0.0) / lensq.sqrt()
    } else {
        V3::new(1.0, 0.0, 0.0)
    };
    let t2 = vh.cross(t1);
    let r = u1.sqrt();
    let phi = 2.0 * PI * u2;
    let p1 = r * phi.cos();
    let s = 0.5 * (1.0 + vh.z);
    let p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * r * phi.sin();
    let nh = t1 * p1 + t2 * p2 + vh * (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt();
    V3::new(alpha * nh.x, alpha * nh.y, nh.z.max(1e-6)).normalize()
}

/// A discrete distribution over non-negative weights, sampled by inverting its CDF.
#[derive(Clone, Debug, Default)]
pub struct Distribution1D {
    cdf: Vec<f32>,
    pmf: Vec<f32>,
    pub total: f32,
}

impl Distribution1D {
    pub fn new(weights: &[f32]) -> Self {
        let total: f64 = weights.iter().map(|w| w.max(0.0) as f64).sum();
        let mut cdf = Vec::with_capacity(weights.len());
        let mut acc = 0.0f64;
        let pmf = weights
            .iter()
            .map(|w| {
                if total > 0.0 {
                    (w.max(0.0) as f64 / total) as f32
                } else {
                    0.0
                }
            })
            .collect();
        for w in weights {
            acc += w.max(0.0) as f64;
            cdf.push(if total > 0.0 { (acc / total) as f32 } else { 0.0 });
        }
        Distribution1D {
            cdf,
            pmf,
            total: total as f32,
        }
    }

    pub fn is_empty(&self) -> bool {
        self.total <= 0.0
    }

    pub fn len(&self) -> usize {
        self.pmf.len()
    }

    pub fn pmf(&self, i: usize) -> f32 {
        self.pmf.get(i).copied().unwrap_or(0.0)
    }

    /// Index with probability `pmf(i)`, and `u` remapped to [0, 1) within that bin.
    #[inline]
    pub fn sample(&self, u: f32) -> (usize, f32) {
        let i = self
            .cdf
            .partition_point(|&c| c <= u)
            .min(self.cdf.len().saturating_sub(1));
        // Skip zero-probability bins a rounding edge could land on.
        let mut i = i;
        while i > 0 && self.pmf[i] == 0.0 {
            i -= 1;
        }
        let lo = if i == 0 { 0.0 } else { self.cdf[i - 1] };
        let p = self.pmf[i];
        let ur = if p > 0.0 {
            ((u - lo) / p).clamp(0.0, 0.999_999_94)
        } else {
            0.0
        };
        (i, ur)
    }
}

/// A piecewise-constant density on `[0, 1)²` over a `width × height` grid of non-negative
/// cell weights (row-major, row `y` covering `[y/h, (y+1)/h)` of the second coordinate): a
/// marginal distribution over rows and one conditional distribution over the cells of each row.
#[derive(Clone, Debug)]
pub struct Distribution2D {
    rows: Vec<Distribution1D>,
    marginal: Distribution1D,
    width: usize,
    height: usize,
}

impl Distribution2D {
    /// `weights` has `width × height` entries (row-major); `None` when the sizes disagree or a
    /// size is 0.
    pub fn new(weights: &[f32], width: usize, height: usize) -> Option<Self> {
        if width == 0 || height == 0 || weights.len() != width.checked_mul(height)? {
            return None;
        }
        let rows: Vec<Distribution1D> = weights.chunks_exact(width).map(Distribution1D::new).collect();
        let marginal = Distribution1D::new(&rows.iter().map(|r| r.total).collect::<Vec<_>>());
        Some(Distribution2D {
            rows,
            marginal,
            width,
            height,
        })
    }

    pub fn is_empty(&self) -> bool {
        self.marginal.is_empty()
    }

    /// A point `(x, y)` in `[0, 1)²` with the density of [`Distribution2D::pdf`] (`None` when
    /// every weight is 0).
    #[inline]
    pub fn sample(&self, u1: f32, u2: f32) -> Option<([f32; 2], f32)> {
        if self.is_empty() {
            return None;
        }
        let (y, ry) = self.marginal.sample(u1);
        let row = &self.rows[y];
        let (x, rx) = row.sample(u2);
        let pdf = self.marginal.pmf(y) * row.pmf(x) * (self.width * self.height) as f32;
        let px = ((x as f32 + rx) / self.width as f32).min(1.0 - f32::EPSILON);
        let py = ((y as f32 + ry) / self.height as f32).min(1.0 - f32::EPSILON);
        Some(([px, py], pdf))
    }

    /// The density at `(x, y)` in `[0, 1]²` (coordinates outside are clamped to the edge cells).
    #[inline]
    pub fn pdf(&self, x: f32, y: f32) -> f32 {
        if self.is_empty() {
            return 0.0;
        }
        let cell = |t: f32, n: usize| {
            let i = (t * n as f32) as isize;
            i.clamp(0, n as isize - 1) as usize
        };
        let (ix, iy) = (cell(x, self.width), cell(y, self.height));
        self.marginal.pmf(iy) * self.rows[iy].pmf(ix) * (self.width * self.height) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_core::Rng;

    #[test]
    fn vndf_pdf_integrates_to_one() {
        // ∫ pdf(wi) dwi over the sphere, estimated by uniform sphere sampling, must be ≈ 1 when
        // the reflected directions stay above the horizon mass (alpha moderate, wo near normal).
        let alpha = 0.5f32;
        let wo = V3::new(0.3, 0.0, 1.0).normalize();
        let mut rng = Rng::new(3);
        let n = 400_000;
        let mut sum = 0.0f64;
        for _ in 0..n {
            let wi = uniform_sphere(rng.f32(), rng.f32());
            let h = (wo + wi).normalize();
            if h.z <= 0.0 {
                continue;
            }
            let pdf = ggx_g1(wo, alpha) * wo.dot(h).max(0.0) * ggx_d(h, alpha) / wo.z / (4.0 * wo.dot(h));
            sum += pdf as f64 * 4.0 * std::f64::consts::PI;
        }
        let est = sum / n as f64;
        assert!((est - 1.0).abs() < 0.03, "∫pdf = {est}");
    }

    #[test]
    fn distribution_matches_weights() {
        let d = Distribution1D::new(&[1.0, 0.0, 3.0]);
        let mut counts = [0usize; 3];
        let mut rng = Rng::new(1);
        for _ in 0..40_000 {
            counts[d.sample(rng.f32()).0] += 1;
        }
        assert_eq!(counts[1], 0);
        let f = counts[2] as f32 / 40_000.0;
        assert!((f - 0.75).abs() < 0.01, "{f}");
        assert!((d.pmf(0) - 0.25).abs() < 1e-6);
    }
}
