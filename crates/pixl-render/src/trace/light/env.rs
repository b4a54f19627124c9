//! The world image as a light: its sampling distribution ([`EnvSampler`]: in proportion to the
//! mean luminance of each texel's cell × `sin θ`, pdf per solid angle `p(u, v) / (2π² sin θ)`),
//! and the two summaries the light picker weighs the world by — its first spherical harmonics
//! ([`env_harmonics`]) and the share of its light above its mean ([`env_peak_share`]).
//!
//! Contract: the pdf integrates to one over the sphere, matches the histogram of the samples,
//! and is positive wherever the world sends light (tested).
use crate::math::V3;
use crate::trace::sampling::Distribution2D;
use crate::trace::texture::Texture;
use std::f32::consts::PI;

/// The world image's sampling distribution (see the module docs).
#[derive(Clone, Debug)]
pub(super) struct EnvSampler {
    pub(super) dist: Distribution2D,
    /// `sin, cos` of minus the world's rotation about +Y (as [`Environment::eval`]).
    sin_cos: (f32, f32),
}

impl EnvSampler {
    /// Built from the luminance of `tex` (times nothing: the strength scales every cell alike).
    pub(super) fn new(tex: &Texture, rotation: f32) -> Option<EnvSampler> {
        let (w, h) = (tex.width(), tex.height());
        if w == 0 || h == 0 {
            return None;
        }
        let lum: Vec<f32> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| tex.texel(x as isize, y as isize).max(V3::ZERO).luminance())
            .collect();
        let at = |x: isize, y: isize| {
            let (xi, yi) = (x.rem_euclid(w as isize) as usize, y.clamp(0, h as isize - 1) as usize);
            lum[yi * w + xi]
        };
        // The mean of the bilinear lookup over cell (x, y) is the [1, 6, 1] / 8 filter of the
        // texels in each axis (u wraps, v clamps, as `Texture::sample`): positive wherever the
        // lookup is positive somewhere in the cell.
        let k = [0.125f32, 0.75, 0.125];
        let mut weights = vec![0f32; w * h];
        for y in 0..h {
            let sin_t = (PI * (y as f32 + 0.5) / h as f32).sin();
            for x in 0..w {
                let mut m = 0.0;
                for (dy, ky) in k.iter().enumerate() {
                    for (dx, kx) in k.iter().enumerate() {
                        m += ky * kx * at(x as isize + dx as isize - 1, y as isize + dy as isize - 1);
                    }
                }
                weights[y * w + x] = m * sin_t;
            }
        }
        let dist = Distribution2D::new(&weights, w, h)?;
        if dist.is_empty() {
            return None;
        }
        Some(EnvSampler {
            dist,
            sin_cos: (-rotation).sin_cos(),
        })
    }

    /// The direction (looking along it) of image coordinates `(u, v)` (`v = 0` the top row),
    /// and `sin θ`.
    fn direction(&self, u: f32, v: f32) -> (V3, f32) {
        let theta = PI * v;
        let phi = 2.0 * PI * (0.5 - u);
        let (st, ct) = theta.sin_cos();
        let (sp, cp) = phi.sin_cos();
        let d = V3::new(st * cp, ct, -st * sp);
        // Undo the rotation `Environment::eval` applies (its transpose).
        let (s, c) = self.sin_cos;
        (V3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z), st)
    }

    #[inline]
    pub(super) fn sample(&self, u1: f32, u2: f32) -> Option<(V3, f32)> {
        let ([u, v], pdf) = self.dist.sample(u1, u2)?;
        let (d, sin_t) = self.direction(u, v);
        if !(sin_t > 0.0 && pdf > 0.0) {
            return None;
        }
        Some((d, pdf / (2.0 * PI * PI * sin_t)))
    }

    /// Solid-angle density of [`EnvSampler::sample`] along `d` (unit).
    #[inline]
    pub(super) fn pdf(&self, d: V3) -> f32 {
        let (s, c) = self.sin_cos;
        let d = V3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z);
        let sin_t = (d.x * d.x + d.z * d.z).sqrt();
        if !(sin_t > 0.0) {
            return 0.0;
        }
        let u = 0.5 - (-d.z).atan2(d.x) / (2.0 * PI);
        let v = 0.5 - d.y.atan2(sin_t) / PI;
        self.dist.pdf(u, v) / (2.0 * PI * PI * sin_t)
    }
}

/// The first-order spherical-harmonic fit `L(ω) ≈ a + b·ω` of an image world's luminance
/// (times `scale`): `a = ∫L / 4π`, `b = 3 ∫L ω / 4π`, summed over the texels' solid angles.
pub(super) fn env_harmonics(tex: &Texture, rotation: f32, scale: f32) -> (f32, V3) {
    let (w, h) = (tex.width(), tex.height());
    let (s, c) = (-rotation).sin_cos();
    let (mut a, mut b) = (0f64, [0f64; 3]);
    for y in 0..h {
        let theta = PI * (y as f32 + 0.5) / h as f32;
        let (st, ct) = theta.sin_cos();
        let d_omega = st as f64 * (PI as f64 / h as f64) * (2.0 * PI as f64 / w as f64);
        for x in 0..w {
            let phi = 2.0 * PI * (0.5 - (x as f32 + 0.5) / w as f32);
            let (sp, cp) = phi.sin_cos();
            let d = V3::new(st * cp, ct, -st * sp);
            let d = V3::new(c * d.x - s * d.z, d.y, s * d.x + c * d.z);
            let l = tex.texel(x as isize, y as isize).max(V3::ZERO).luminance() as f64 * d_omega;
            a += l;
            b[0] += l * d.x as f64;
            b[1] += l * d.y as f64;
            b[2] += l * d.z as f64;
        }
    }
    let k = scale as f64 / (4.0 * std::f64::consts::PI);
    (
        (a * k) as f32,
        V3::new(
            (3.0 * b[0] * k) as f32,
            (3.0 * b[1] * k) as f32,
            (3.0 * b[2] * k) as f32,
        ),
    )
}

/// `∫ max(0, L − L̄) dω / ∫ L dω` of an image world's luminance `L` (`L̄` its mean over the
/// sphere), by texel solid angles: 0 for a constant image, near 1 for a small bright sun.
pub(super) fn env_peak_share(tex: &Texture) -> f32 {
    let (w, h) = (tex.width(), tex.height());
    let mut texels = Vec::with_capacity(w * h);
    let (mut sum, mut area) = (0f64, 0f64);
    for y in 0..h {
        let d_omega = (PI * (y as f32 + 0.5) / h as f32).sin() as f64;
        for x in 0..w {
            let l = tex.texel(x as isize, y as isize).max(V3::ZERO).luminance() as f64;
            texels.push((l, d_omega));
            sum += l * d_omega;
            area += d_omega;
        }
    }
    if !(sum > 0.0) {
        return 0.0;
    }
    let mean = sum / area;
    let above: f64 = texels.iter().map(|(l, d)| (l - mean).max(0.0) * d).sum();
    (above / sum) as f32
}
