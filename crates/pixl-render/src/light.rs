//! Lights for the tracer, in Cycles' units (see [`crate::scene`]): point, spot, area
//! (rectangle / disk), sun, the world, and emissive triangles. One light is picked per shading
//! point ([`LightPick`]) in proportion to an estimate of what it brings *there* — its
//! unoccluded irradiance bounded over the light's extent: intensity or radiance × a bound of the
//! emitter's and the receiver's cosines (and a spot's cone mask) / distance², capped at `π L`
//! for area lights; a sun's irradiance × the receiver's cosine bound; the world's irradiance on
//! the normal from its first spherical harmonics, times the share of its light above its mean
//! radiance (what BSDF samples find poorly; a constant world is never light-sampled: BSDF
//! samples find it as well as light samples would); the emissive triangles as one group (by power,
//! over the distance to their bounds), inside which a triangle is picked by power. A share
//! [`PICK_FLOOR`] of the probability follows the lights' scene-wide power among the lights that
//! can reach the point at all (not behind a one-sided area light, not outside a spot's cone),
//! so no light that can contribute has probability 0 (the estimator stays unbiased whatever the
//! estimate). BSDF-sampled hits of a light are MIS-weighted with the pick probability of the
//! vertex the ray left ([`Lights::pick_pmf_at`]). The sample returns the incident radiance
//! (or, for delta lights, the radiance-equivalent `I/d²` or irradiance) and the pdf including
//! the pick probability.
//!
//! - Point: intensity `I = P·color / 4π`. With a radius `r` it is a sphere, as in Cycles: seen as
//!   a disk of radiance `I / (π r²)` (the same irradiance `I cos θ / d²` wherever the sphere is
//!   wholly above the horizon), light-sampled uniformly in the cone it subtends and hit by BSDF
//!   rays; when that cone is too narrow for f32 (`1 − cos θmax < 1e-5`) or the shading point is
//!   inside, the sample point is jittered on a facing disk of the radius (light sampling only).
//! - Spot: point intensity (a sphere with a radius, as above) masked by
//!   `smoothstep(0, 1, (cos θ − cos(size/2)) / ((1 − cos(size/2))·blend))`
//!   (hard edge for `blend = 0`), not renormalised to the cone.
//! - Area: one-sided Lambertian, radiance `P·color / (π A)`, emitting along its direction; its
//!   local X (`size`) is `normalize(d × Y)` (or +X when `d ∥ Y`), local Y is `(−d) × X`.
//!   Sampled by area, except rectangles seen from a camera vertex (unless they subtend under
//!   1e-3 sr), sampled uniformly in the solid angle they subtend ([`RectView`]).
//! - Sun: irradiance `strength·color` on a surface facing it; with an angular diameter of at
//!   least ~0.16° (Blender's default is 0.526°) a cone of uniform radiance `E / Ω` (`Ω = 2π(1 −
//!   cos(angle/2))`, directions sampled uniformly in it), below that a delta light of
//!   irradiance `E` (directions still spread over the cone).
//! - World: radiance `strength·color` (× texel). An image world is sampled in proportion to
//!   the mean luminance of each texel's cell of the bilinear lookup × `sin θ` (a piecewise-constant
//!   2-D distribution over the equirectangular image, pdf per solid angle `p(u, v) / (2π² sin θ)`).
//!   A constant world is found by BSDF samples only (its direction sampler, cosine-weighted about
//!   the shading normal or uniform at points that transmit, is kept for completeness).
//! - Emissive triangles: two-sided, radiance = the material's emission, sampled by area.
//!
//! Point and spot lights without a radius, and a sun below ~0.16°, are invisible to camera and BSDF
//! rays (delta lights, sampled only by next-event estimation). Area lights, sphere (point / spot
//! with a radius) lights, emissive triangles, the world and a wider sun are hit by BSDF
//! rays (the sun only by rays that escape the scene, as
//! in Cycles — so smooth glass and mirrors show its glint) and combined with light sampling by
//! MIS (power heuristic). No light is seen by camera rays except emissive triangles, the
//! world, and area and sphere (point / spot with a radius) lights marked `visible_to_camera`
//! (sphere lights then show their radiance `I / (π r²)`, spot-masked, wherever a camera ray
//! hits the sphere, as in Cycles). Lights do not occlude.
use crate::bvh::Ray;
use crate::error::Result;
use crate::geometry::Geometry;
use crate::math::{sin_cos_poly, Frame, V3};
use crate::sampling::{
    concentric_disk, cosine_hemisphere, uniform_cone, uniform_sphere, uniform_triangle, Distribution1D, Distribution2D,
};
use crate::scene::{AreaShape, Light, Scene};
use crate::texture::Texture;
use std::f32::consts::PI;

#[derive(Clone, Debug)]
pub enum LightKind {
    Point {
        p: V3,
        intensity: V3,
        radius: f32,
        /// The sphere is seen by camera rays (needs a radius).
        camera: bool,
    },
    Spot {
        p: V3,
        dir: V3,
        intensity: V3,
        radius: f32,
        cos_half: f32,
        smooth: f32,
        camera: bool,
    },
    Area {
        c: V3,
        ex: V3,
        ey: V3,
        n: V3,
        disk: bool,
        /// Unit edge directions and full edge lengths (for [`RectView`]).
        frame: RectFrame,
        radiance: V3,
        area: f32,
        /// Seen by camera rays (else only by rays that scattered).
        camera: bool,
    },
    Sun {
        dir: V3,
        irradiance: V3,
        cos_max: f32,
        /// Solid angle of the cone (0: a delta light).
        omega: f32,
    },
    Env,
    Tri {
        prim: u32,
        radiance: V3,
    },
}

/// The world: constant radiance or an equirectangular image times a strength.
#[derive(Clone, Debug)]
pub struct Environment {
    pub radiance: V3,
    pub image: Option<Texture>,
    pub rotation: f32,
}

impl Environment {
    /// Radiance arriving from direction `-d` (i.e. seen looking along `d`).
    pub fn eval(&self, d: V3) -> V3 {
        match &self.image {
            None => self.radiance,
            Some(tex) => {
                let (s, c) = (-self.rotation).sin_cos();
                let d = V3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z);
                let u = 0.5 - (-d.z).atan2(d.x) / (2.0 * PI);
                let v = 0.5 + d.y.atan2((d.x * d.x + d.z * d.z).sqrt()) / PI;
                self.radiance * tex.sample(u, 1.0 - v)
            }
        }
    }
}

/// A light sample at a shading point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Incident radiance (delta lights: `I/d²` or irradiance), before the BSDF.
    pub li: V3,
    pub wi: V3,
    /// Distance to the sampled point (`INFINITY` for sun and world).
    pub dist: f32,
    /// Solid-angle pdf including the pick probability (delta lights: the pick probability).
    pub pdf: f32,
    pub delta: bool,
}

/// Share of a light's pick probability that follows the scene-wide power estimate (among the
/// lights that can reach the shading point) rather than the per-point one.
pub const PICK_FLOOR: f32 = 0.1;

/// Pick items (analytic lights, then the group of emissive triangles) whose weights a
/// [`LightPick`] keeps; further ones are recomputed when asked.
const CACHED: usize = 8;

/// What the light choice knows of a shading point.
#[derive(Clone, Copy, Debug)]
pub struct ShadingPoint {
    pub p: V3,
    /// Shading normal on the side light is scattered to (unit).
    pub n: V3,
    /// Light from both sides of `n` can scatter (a transmission lobe): no cosine bound.
    pub two_sided: bool,
    /// Sample rectangular area lights by solid angle ([`RectView`]; costlier per sample,
    /// worth it where the light is seen directly: the integrator asks it at the camera vertex).
    pub solid_angle: bool,
}

/// The light choice at one shading point: the per-point weights of the pick items, their sum,
/// and the summed power weights of the items that can reach the point.
#[derive(Clone, Copy, Debug)]
pub struct LightPick {
    pub sp: ShadingPoint,
    total: f32,
    base_total: f32,
    /// Weight per item (the first [`CACHED`]); negative: the item cannot reach the point.
    w: [f32; CACHED],
    /// The rectangle the light sample at this point sampled by solid angle, and that solid
    /// angle (so that the MIS of a BSDF sample hitting it need not compute it again).
    rect: Option<(usize, f32)>,
}

/// The world image's sampling distribution (see the module docs).
#[derive(Clone, Debug)]
struct EnvSampler {
    dist: Distribution2D,
    /// `sin, cos` of minus the world's rotation about +Y (as [`Environment::eval`]).
    sin_cos: (f32, f32),
}

impl EnvSampler {
    /// Built from the luminance of `tex` (times nothing: the strength scales every cell alike).
    fn new(tex: &Texture, rotation: f32) -> Option<EnvSampler> {
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
    fn sample(&self, u1: f32, u2: f32) -> Option<(V3, f32)> {
        let ([u, v], pdf) = self.dist.sample(u1, u2)?;
        let (d, sin_t) = self.direction(u, v);
        if !(sin_t > 0.0 && pdf > 0.0) {
            return None;
        }
        Some((d, pdf / (2.0 * PI * PI * sin_t)))
    }

    /// Solid-angle density of [`EnvSampler::sample`] along `d` (unit).
    #[inline]
    fn pdf(&self, d: V3) -> f32 {
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

/// A rectangle's unit edge directions `x`, `y`, its normal `z = x × y` and its full edge
/// lengths (zero lengths: a degenerate rectangle, never sampled by solid angle).
#[derive(Clone, Copy, Debug)]
pub struct RectFrame {
    x: V3,
    y: V3,
    z: V3,
    lx: f32,
    ly: f32,
}

impl RectFrame {
    /// The frame of full edges `ex`, `ey` (orthogonal).
    fn new(ex: V3, ey: V3) -> RectFrame {
        let (lx, ly) = (ex.length(), ey.length());
        let (x, y) = if lx > 0.0 && ly > 0.0 {
            (ex / lx, ey / ly)
        } else {
            (V3::ZERO, V3::ZERO)
        };
        RectFrame {
            x,
            y,
            z: x.cross(y),
            lx,
            ly,
        }
    }
}

/// Smallest solid angle (sr) at which a rectangle is sampled by solid angle ([`RectView`]);
/// smaller ones, which sampling by area serves as well, are sampled by area.
const MIN_RECT_OMEGA: f32 = 1e-3;

/// A rectangular area light seen from a point, for sampling it uniformly in the solid angle it
/// subtends: the area-preserving parametrisation of Ureña, Fajardo and King, "An
/// Area-Preserving Parametrization for Spherical Rectangles" (EGSR 2013). In the rectangle's
/// frame (`x`, `y` along its edges, `z` its normal turned away from the point `o`, which sits
/// at the origin), the rectangle spans `[x0, x1] × [y0, y1]` at height `z0 < 0`
/// ([`RectCoords`]); [`rect_solid_angle`] gives its solid angle, [`rect_point`] the sample of
/// `(u, v)`: `u` picks the `x` of a sample by solid angle (the area of the spherical rectangle
/// left of it grows linearly in `u`), `v` its `y` uniformly in the sine of the elevation along
/// that line, which is uniform in solid angle too.
///
/// The two functions are a long chain of square roots, divisions and polynomials with no
/// branch, so that [`Lights::sample_lanes`] computes them for a packet's shading points in one
/// vectorised loop: one at a time they cost 12–15 % of a whole render at 32 spp.
#[derive(Clone, Copy, Debug)]
struct RectView {
    /// The rectangle's normal turned away from the point.
    z: V3,
    r: RectCoords,
}

/// A rectangle's extent in the frame of the point it is seen from (see [`RectView`]).
#[derive(Clone, Copy, Debug)]
struct RectCoords {
    x0: f32,
    x1: f32,
    y0: f32,
    y1: f32,
    z0: f32,
}

impl RectCoords {
    /// A unit square at unit distance: the input of lanes that sample no rectangle (finite
    /// results, nothing slow).
    const PLACEHOLDER: RectCoords = RectCoords {
        x0: -1.0,
        x1: 1.0,
        y0: -1.0,
        y1: 1.0,
        z0: -1.0,
    };
}

/// What sampling a [`RectCoords`] needs beside it: the solid angle `omega`, `k` (2π minus two
/// of the corner angles) and the sines `b0`, `b1` of the elevations of the edges `y = y0`,
/// `y = y1`.
#[derive(Clone, Copy, Debug)]
struct RectSolidAngle {
    omega: f32,
    k: f32,
    b0: f32,
    b1: f32,
}

impl RectView {
    /// Area light `(c, ex, ey)` seen from `o`, when it is sampled by solid angle there: a
    /// rectangle (not a disk) whose solid angle f32 resolves (≥ [`MIN_RECT_OMEGA`]: smaller
    /// ones are screened first by a cheap bound, then by [`RectView::solid_angle`]), at any
    /// distance, as Cycles does. On the depth-mesh scene of the noise benchmark, sampling by
    /// area beyond four half-diagonals left the 1-spp Diffuse Direct RMSE 13 % above this
    /// rule's (7 % at 4 spp). The same rule decides the pdf of light and BSDF samples.
    #[inline(always)]
    fn for_light(c: V3, ex: V3, ey: V3, frame: &RectFrame, o: V3) -> Option<RectView> {
        // Ω ≤ area / (d − r)² for a point at distance d from the centre of a rectangle whose
        // corners lie within r of it: screened when that bound is under the smallest Ω.
        let to = c - o;
        let (d, r) = (to.dot(to).sqrt(), (ex.dot(ex) + ey.dot(ey)).sqrt());
        let area = 4.0 * (ex.dot(ex) * ey.dot(ey)).sqrt();
        if d > r && area < MIN_RECT_OMEGA * (d - r) * (d - r) {
            return None;
        }
        RectView::with_frame(o, c - ex - ey, frame)
    }

    /// The rectangle with corner `corner` and the edges of `f`, seen from `o` (`None` when `o`
    /// is in its plane or the rectangle is degenerate). Inlined: so it is compiled with the
    /// vector features of the integrator's dispatched kernels.
    #[inline(always)]
    fn with_frame(o: V3, corner: V3, f: &RectFrame) -> Option<RectView> {
        let RectFrame { x, y, lx, ly, .. } = *f;
        if !(lx > 0.0 && ly > 0.0) {
            return None;
        }
        let mut z = f.z;
        let d = corner - o;
        let mut z0 = d.dot(z);
        if z0 > 0.0 {
            z0 = -z0;
            z = -z;
        }
        if !(z0 < 0.0) {
            return None;
        }
        let (x0, y0) = (d.dot(x), d.dot(y));
        Some(RectView {
            z,
            r: RectCoords {
                x0,
                x1: x0 + lx,
                y0,
                y1: y0 + ly,
                z0,
            },
        })
    }

    /// The solid angle and the sampling constants, when it is large enough to be sampled
    /// by solid angle.
    #[inline(always)]
    fn solid_angle(&self) -> Option<RectSolidAngle> {
        Some(rect_solid_angle(&self.r)).filter(|s| s.omega >= MIN_RECT_OMEGA)
    }

    /// The point of local coordinates `(x, y)` on the rectangle of frame `f` seen from `o`.
    #[inline(always)]
    fn point(&self, o: V3, f: &RectFrame, x: f32, y: f32) -> V3 {
        o + f.x * x + f.y * y + self.z * self.r.z0
    }
}

/// The solid angle of `r` and the constants [`rect_point`] needs (no branch; `omega` is ≤ 0
/// or NaN for a rectangle f32 cannot resolve).
#[inline(always)]
fn rect_solid_angle(r: &RectCoords) -> RectSolidAngle {
    let RectCoords { x0, x1, y0, y1, z0 } = *r;
    // The planes through the origin and the edges y = y0, x = x1, y = y1, x = x0 have the unit
    // normals n0 = (0, z0, −y0)/r0, n1 = (−z0, 0, x1)/r1, n2 = (0, −z0, y1)/r2,
    // n3 = (z0, 0, −x0)/r3 with r = √(z0² + e²) for the edge's coordinate e. The interior
    // angle at a corner is acos(−nᵢ·nᵢ₊₁), and those dot products reduce to one product of
    // edge coordinates each; the solid angle is the angles' sum minus 2π. The four corners'
    // square roots, divisions and arccosines are independent of one another.
    let z2 = z0 * z0;
    let inv_r = [y0, x1, y1, x0].map(|e| 1.0 / (z2 + e * e).sqrt());
    let num = [y0 * x1, -x1 * y1, x0 * y1, -x0 * y0];
    let g: [f32; 4] = std::array::from_fn(|i| acos_poly((num[i] * inv_r[i] * inv_r[(i + 1) % 4]).clamp(-1.0, 1.0)));
    let k = 2.0 * PI - g[2] - g[3];
    RectSolidAngle {
        omega: g[0] + g[1] - k,
        k,
        b0: -y0 * inv_r[0],
        b1: y1 * inv_r[2],
    }
}

/// The local `(x, y)` on `r` of the direction `(u, v)` maps to (uniform in solid angle; no
/// branch).
#[inline(always)]
fn rect_point(r: &RectCoords, s: &RectSolidAngle, u: f32, v: f32) -> (f32, f32) {
    let RectCoords { x0, x1, y0, y1, z0 } = *r;
    // x: the spherical rectangle's area left of the line through x is u·Ω.
    let (sa, ca) = sin_cos_poly(u * s.omega + s.k);
    let fu = (ca * s.b0 - s.b1) / sa;
    let cu = (1.0 / (fu * fu + s.b0 * s.b0).sqrt()).copysign(fu).clamp(-1.0, 1.0);
    let xu = (-(cu * z0) / (1.0 - cu * cu).max(1e-12).sqrt()).max(x0).min(x1);
    // y: uniform in the sine of the elevation along that line.
    let dist = (xu * xu + z0 * z0).sqrt();
    let h0 = y0 / (dist * dist + y0 * y0).sqrt();
    let h1 = y1 / (dist * dist + y1 * y1).sqrt();
    let hv = h0 + v * (h1 - h0);
    let hv2 = hv * hv;
    let yv = (hv * dist / (1.0 - hv2).sqrt()).max(y0).min(y1);
    (xu, if hv2 < 1.0 - 1e-6 { yv } else { y1 })
}

/// `acos(x)` for `x` in `[−1, 1]` as `√(1 − |x|)·P(|x|)` (mirrored for `x < 0`), `P` the
/// degree-7 polynomial of Abramowitz & Stegun 4.4.46 (error ≤ 2e-8 in exact arithmetic; in
/// `f32` within 5e-7 of the true value, tested; libm's `acosf` is within 2.2e-7). Inline, with
/// no call and no branch on the argument's range: libm's `acosf` was the largest part of the
/// spherical rectangle's setup.
#[inline(always)]
fn acos_poly(x: f32) -> f32 {
    #[allow(clippy::excessive_precision)] // the published coefficients, as printed
    const A: [f32; 8] = [
        1.570_796_305,
        -0.214_598_801_6,
        0.088_978_987_4,
        -0.050_174_304_6,
        0.030_891_881_0,
        -0.017_088_125_6,
        0.006_670_090_1,
        -0.001_262_491_1,
    ];
    let a = x.abs();
    let mut p = A[7];
    for c in A[..7].iter().rev() {
        p = p * a + *c; // not mul_add: without FMA in the build's target it is a libm call
    }
    let r = (1.0 - a).max(0.0).sqrt() * p;
    if x < 0.0 {
        PI - r
    } else {
        r
    }
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

/// The point of area light `(c, ex, ey)` (a disk of semi-axes `ex`, `ey` if `disk`) for the
/// uniforms `(u1, u2)`, uniform in area.
#[inline(always)]
fn area_point(c: V3, ex: V3, ey: V3, disk: bool, u1: f32, u2: f32) -> V3 {
    let (a, b) = if disk {
        concentric_disk(u1, u2)
    } else {
        (2.0 * u1 - 1.0, 2.0 * u2 - 1.0)
    };
    c + ex * a + ey * b
}

/// The light sample of point `q` of an area light (normal `n`) seen from `p`, picked with
/// probability `pick`: the pdf is `pick / Ω` when it was sampled uniformly in the solid angle
/// `Ω` (`omega`), else that of sampling by area.
#[inline(always)]
fn area_sample(p: V3, q: V3, n: V3, radiance: V3, area: f32, pick: f32, omega: Option<f32>) -> Option<LightSample> {
    let d = q - p;
    let dist = d.length();
    let wi = d / dist;
    let cos_l = -wi.dot(n);
    if !(cos_l > 0.0 && dist > 0.0) {
        return None;
    }
    let pdf = match omega {
        Some(omega) => pick / omega,
        None => pick * dist * dist / (cos_l * area),
    };
    Some(LightSample {
        li: radiance,
        wi,
        dist,
        pdf,
        delta: false,
    })
}

pub struct Lights {
    pub lights: Vec<LightKind>,
    /// Scene-wide power estimate of every light (the floor of the per-point choice).
    base: Distribution1D,
    /// Lights `0..analytic` are the scene's lights and the world; the rest emissive triangles.
    analytic: usize,
    /// Luminance per light (for the per-point weights): point / spot intensity, area radiance,
    /// sun irradiance; unused for the world and triangles.
    lum: Vec<f32>,
    /// Emissive triangles: power distribution among them, their summed power weight, their
    /// bounding sphere and total power (luminance).
    tri_dist: Distribution1D,
    tri_base: f32,
    tri_bounds: (V3, f32),
    tri_power: f32,
    pub env: Option<Environment>,
    env_index: Option<usize>,
    env_sampler: Option<EnvSampler>,
    /// The world's luminance to first order: mean radiance `a` and `b` of `L(ω) ≈ a + b·ω`.
    env_sh: (f32, V3),
    /// Share of the world's light above its mean radiance, `∫ max(0, L − L̄) / ∫ L` (0 for a
    /// constant world): the part light sampling is needed for (see [`Lights::item_weight`]).
    env_peaked: f32,
    area_indices: Vec<usize>,
    /// Suns with an angular size (hit by rays that escape).
    sun_indices: Vec<usize>,
    /// Point and spot lights with a radius (spheres, hit by BSDF rays).
    sphere_indices: Vec<usize>,
    /// The one pick item besides a constant world, if there is only one
    /// ([`Lights::single_item`]).
    single: Option<usize>,
}

fn smoothstep(x: f32) -> f32 {
    let x = x.clamp(0.0, 1.0);
    x * x * (3.0 - 2.0 * x)
}

/// The cone a sphere light of centre `c` and radius `r` subtends from `x`, when it is worth
/// sampling as one: `x` outside the sphere and the cone not so narrow that `1 − cos θmax` is
/// lost in f32 (then the light is treated as a point, by light sampling alone).
struct SphereCone {
    /// Unit direction from `x` to the centre, and the distance.
    axis: V3,
    dist: f32,
    cos_max: f32,
    /// Solid angle `2π (1 − cos θmax)`.
    omega: f32,
}

impl SphereCone {
    fn new(c: V3, r: f32, x: V3) -> Option<SphereCone> {
        if !(r > 0.0) {
            return None;
        }
        let to = c - x;
        let dist = to.length();
        if !(dist > r * 1.0001) {
            return None;
        }
        let sin2 = (r / dist) * (r / dist);
        let cos_max = (1.0 - sin2).max(0.0).sqrt();
        // 1 − cos θmax = sin² / (1 + cos), without cancellation.
        let one_minus = sin2 / (1.0 + cos_max);
        if one_minus < 1e-5 {
            return None;
        }
        Some(SphereCone {
            axis: to / dist,
            dist,
            cos_max,
            omega: 2.0 * PI * one_minus,
        })
    }
}

/// The first-order spherical-harmonic fit `L(ω) ≈ a + b·ω` of an image world's luminance
/// (times `scale`): `a = ∫L / 4π`, `b = 3 ∫L ω / 4π`, summed over the texels' solid angles.
fn env_harmonics(tex: &Texture, rotation: f32, scale: f32) -> (f32, V3) {
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
fn env_peak_share(tex: &Texture) -> f32 {
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

impl LightKind {
    /// A spot light's cone mask for the direction `from_light` (light → shading point,
    /// any length); 1 for every other light.
    fn spot_mask(&self, from_light: V3) -> f32 {
        match self {
            LightKind::Spot {
                dir, cos_half, smooth, ..
            } => {
                let cos_a = dir.dot(from_light.normalize());
                if *smooth > 0.0 {
                    smoothstep((cos_a - cos_half) / smooth)
                } else if cos_a > *cos_half {
                    1.0
                } else {
                    0.0
                }
            }
            _ => 1.0,
        }
    }
}

/// The local X axis of an area light travelling along `d` (see module docs).
pub fn area_axes(d: V3) -> (V3, V3) {
    let x = d.cross(V3::new(0.0, 1.0, 0.0));
    let x = if x.length() < 1e-6 {
        V3::new(1.0, 0.0, 0.0)
    } else {
        x.normalize()
    };
    let y = (-d).cross(x).normalize();
    (x, y)
}

impl Lights {
    /// Collects the scene's lights and marks emissive triangles in `geom`.
    pub fn build(scene: &Scene, geom: &mut Geometry) -> Result<Lights> {
        let (_, radius) = geom.bounding_sphere();
        let mut lights = Vec::new();
        let mut power = Vec::new();
        let mut area_indices = Vec::new();
        let mut sun_indices = Vec::new();
        let mut sphere_indices = Vec::new();
        let mut lum = Vec::new();
        for l in &scene.lights {
            let color = V3::from_arr(l.color().rgb());
            let dir = l
                .direction()
                .map(V3::from_arr)
                .unwrap_or(V3::new(0.0, -1.0, 0.0))
                .normalize();
            match l {
                Light::Point {
                    position,
                    power: p,
                    radius,
                    visible_to_camera,
                    ..
                } => {
                    let intensity = color * (*p / (4.0 * PI));
                    if *radius > 0.0 {
                        sphere_indices.push(lights.len());
                    }
                    lights.push(LightKind::Point {
                        p: V3::from_arr(*position),
                        intensity,
                        radius: *radius,
                        camera: *visible_to_camera && *radius > 0.0,
                    });
                    power.push(p * color.luminance());
                    lum.push(intensity.luminance());
                }
                Light::Spot {
                    position,
                    power: p,
                    spot_size_deg,
                    blend,
                    radius,
                    visible_to_camera,
                    ..
                } => {
                    let intensity = color * (*p / (4.0 * PI));
                    let cos_half = (0.5 * spot_size_deg.to_radians()).cos();
                    let smooth = (1.0 - cos_half) * blend;
                    if *radius > 0.0 {
                        sphere_indices.push(lights.len());
                    }
                    lights.push(LightKind::Spot {
                        p: V3::from_arr(*position),
                        dir,
                        intensity,
                        radius: *radius,
                        cos_half,
                        smooth,
                        camera: *visible_to_camera && *radius > 0.0,
                    });
                    power.push(p * color.luminance());
                    lum.push(intensity.luminance());
                }
                Light::Area {
                    position,
                    shape,
                    power: p,
                    visible_to_camera,
                    ..
                } => {
                    let (sx, sy) = l.area_size().unwrap_or((1.0, 1.0));
                    let disk = matches!(shape, AreaShape::Disk | AreaShape::Ellipse);
                    let area = if disk { PI * 0.25 * sx * sy } else { sx * sy };
                    let (x, y) = area_axes(dir);
                    area_indices.push(lights.len());
                    lights.push(LightKind::Area {
                        c: V3::from_arr(*position),
                        ex: x * (0.5 * sx),
                        ey: y * (0.5 * sy),
                        n: dir,
                        disk,
                        frame: RectFrame::new(x * sx, y * sy),
                        radiance: color * (*p / (PI * area)),
                        area,
                        camera: *visible_to_camera,
                    });
                    power.push(p * color.luminance());
                    lum.push((color * (*p / (PI * area))).luminance());
                }
                Light::Sun {
                    strength, angle_deg, ..
                } => {
                    let cos_max = (0.5 * angle_deg.to_radians()).cos().min(1.0 - 1e-7);
                    // Ω of exactly the cone that is sampled and hit-tested (`cos ≥ cos_max`, in
                    // f32). Below ~0.16° (1 − cos_max < 4e-6) a direction's rounding (~1e-7) is
                    // no longer small against the cone, so such a sun stays a delta light.
                    let one_minus = 1.0 - cos_max as f64;
                    let omega = if one_minus >= 4e-6 {
                        sun_indices.push(lights.len());
                        (2.0 * std::f64::consts::PI * one_minus) as f32
                    } else {
                        0.0
                    };
                    lights.push(LightKind::Sun {
                        dir,
                        irradiance: color * *strength,
                        cos_max,
                        omega,
                    });
                    power.push(strength * color.luminance() * PI * radius * radius);
                    lum.push((color * *strength).luminance());
                }
            }
        }
        let mut env = None;
        let mut env_index = None;
        let mut env_sampler = None;
        let mut env_sh = (0.0, V3::ZERO);
        let mut env_peaked = 0.0;
        if let Some(w) = &scene.world {
            let image = match &w.image {
                Some(p) => Some(Texture::load_color(&scene.resolve(p))?),
                None => None,
            };
            let radiance = match image {
                Some(_) => V3::splat(w.strength),
                None => V3::from_arr(w.color.rgb()) * w.strength,
            };
            let mean = match &image {
                Some(t) => {
                    let img = t.image();
                    let n = (img.width * img.height).max(1) as f32;
                    img.data
                        .chunks_exact(3)
                        .fold(V3::ZERO, |a, p| a + V3::new(p[0], p[1], p[2]))
                        / n
                }
                None => V3::ONE,
            };
            let e = Environment {
                radiance,
                image,
                rotation: w.rotation_deg.to_radians(),
            };
            let lum_mean = (radiance * mean).luminance();
            if lum_mean > 0.0 {
                env_index = Some(lights.len());
                lights.push(LightKind::Env);
                power.push(2.0 * PI * PI * radius * radius * lum_mean);
                lum.push(lum_mean);
                match &e.image {
                    Some(tex) => {
                        env_sampler = EnvSampler::new(tex, e.rotation);
                        env_sh = env_harmonics(tex, e.rotation, radiance.luminance());
                        env_peaked = env_peak_share(tex);
                    }
                    None => env_sh = (lum_mean, V3::ZERO),
                }
            }
            env = Some(e);
        }
        let analytic = lights.len();
        let mut tri_power = Vec::new();
        let (mut lo, mut hi) = (V3::splat(f32::INFINITY), V3::splat(f32::NEG_INFINITY));
        for (prim, a) in geom.attrs.iter_mut().enumerate() {
            let em = geom.materials[a.material as usize].emission;
            if em.max_comp() > 0.0 {
                a.light = lights.len() as u32;
                lights.push(LightKind::Tri {
                    prim: prim as u32,
                    radiance: em,
                });
                let tri = &geom.tris[prim];
                for q in [tri.point(0.0, 0.0), tri.point(1.0, 0.0), tri.point(0.0, 1.0)] {
                    lo = lo.min(q);
                    hi = hi.max(q);
                }
                let w = 2.0 * PI * a.area * em.luminance();
                power.push(w);
                tri_power.push(w);
            }
        }
        let base = Distribution1D::new(&power);
        let tri_dist = Distribution1D::new(&tri_power);
        let tri_base = (analytic..lights.len()).map(|i| base.pmf(i)).sum();
        let tri_bounds = if tri_power.is_empty() {
            (V3::ZERO, 0.0)
        } else {
            ((lo + hi) * 0.5, (hi - lo).length() * 0.5)
        };
        let mut lights = Lights {
            lights,
            base,
            analytic,
            lum,
            tri_base,
            tri_bounds,
            tri_power: tri_dist.total,
            tri_dist,
            env,
            env_index,
            env_sampler,
            env_sh,
            env_peaked,
            area_indices,
            sun_indices,
            sphere_indices,
            single: None,
        };
        lights.single = lights.find_single_item();
        Ok(lights)
    }

    pub fn is_empty(&self) -> bool {
        self.base.is_empty()
    }

    /// Number of pick items: the analytic lights, then one for all emissive triangles.
    #[inline(always)]
    fn items(&self) -> usize {
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
    fn item_reaches(&self, k: usize, sp: &ShadingPoint) -> bool {
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
    fn item_weight(&self, k: usize, sp: &ShadingPoint) -> Option<f32> {
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
    fn single_item(&self) -> Option<usize> {
        self.single
    }

    fn find_single_item(&self) -> Option<usize> {
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
    fn choose(&self, pick: &LightPick, u: f32) -> Option<(usize, f32)> {
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

    /// Solid-angle density with which [`Lights::sample`] at `sp` samples the world along `d`
    /// (before the pick probability).
    #[inline(always)]
    fn env_dir_pdf(&self, sp: &ShadingPoint, d: V3) -> f32 {
        match &self.env_sampler {
            Some(s) => s.pdf(d),
            None if sp.two_sided => 1.0 / (4.0 * PI),
            None => (d.dot(sp.n) / PI).max(0.0),
        }
    }

    /// Samples one light for the shading point of `pick` ([`Lights::sample_lanes`] for one
    /// lane).
    pub fn sample(&self, geom: &Geometry, pick: &LightPick, u_pick: f32, u1: f32, u2: f32) -> Option<LightSample> {
        let mut pick = *pick;
        let mut out = [None];
        self.sample_lanes(geom, [Some((&mut pick, [u_pick, u1, u2]))], &mut out);
        out[0]
    }

    /// Light samples for up to `L` shading points at once: lane `l` samples one light for the
    /// shading point of `lanes[l]`'s pick with the uniforms `[u_pick, u1, u2]` (`None`: no
    /// sample). Each lane's result depends on its own input only; the rectangles sampled by
    /// solid angle ([`RectView`]) are computed for all lanes in one loop, which the compiler
    /// vectorises (the same operations, so the same values, whatever `L`), and their solid
    /// angles kept in the picks for [`Lights::area_dir_pdf`].
    #[inline(always)]
    pub fn sample_lanes<const L: usize>(
        &self,
        geom: &Geometry,
        mut lanes: [Option<(&mut LightPick, [f32; 3])>; L],
        out: &mut [Option<LightSample>; L],
    ) {
        *out = [None; L];
        // Lanes sampling a rectangle by solid angle: its light, pick probability and the
        // rectangle seen from the lane's point; and its coordinates and uniforms by lane.
        let mut rects: [Option<(usize, f32, RectView)>; L] = [None; L];
        let mut coords = [RectCoords::PLACEHOLDER; L];
        let mut uv = [[0.5f32; 2]; L];
        for l in 0..L {
            let Some((pick, [u_pick, u1, u2])) = &lanes[l] else {
                continue;
            };
            let [u_pick, u1, u2] = [*u_pick, *u1, *u2];
            let Some((i, pick_p)) = self.choose(pick, u_pick) else {
                continue;
            };
            if !(pick_p > 0.0) {
                continue;
            }
            match self.rect_view(i, &pick.sp) {
                Some(view) => {
                    rects[l] = Some((i, pick_p, view));
                    coords[l] = view.r;
                    uv[l] = [u1, u2];
                }
                None => out[l] = self.sample_chosen(geom, &pick.sp, i, pick_p, u1, u2),
            }
        }
        // Only up to the last such lane (a 1-spp render's packets have one lane): the loop is
        // vectorised in blocks of lanes, the rest computed one by one, with the same values.
        let Some(end) = rects.iter().rposition(Option::is_some).map(|l| l + 1) else {
            return;
        };
        let mut solid = [(0f32, 0f32, 0f32); L];
        for l in 0..end {
            let s = rect_solid_angle(&coords[l]);
            let (x, y) = rect_point(&coords[l], &s, uv[l][0], uv[l][1]);
            solid[l] = (s.omega, x, y);
        }
        for l in 0..end {
            let (Some((i, pick_p, view)), Some((pick, _))) = (rects[l], &mut lanes[l]) else {
                continue;
            };
            let LightKind::Area {
                c,
                ex,
                ey,
                n,
                frame,
                radiance,
                area,
                ..
            } = &self.lights[i]
            else {
                continue;
            };
            let o = pick.sp.p;
            let (omega, x, y) = solid[l];
            // A solid angle too small to sample by: sampled by area.
            let by_angle = omega >= MIN_RECT_OMEGA;
            let q = if by_angle {
                view.point(o, frame, x, y)
            } else {
                area_point(*c, *ex, *ey, false, uv[l][0], uv[l][1])
            };
            out[l] = area_sample(o, q, *n, *radiance, *area, pick_p, by_angle.then_some(omega));
            if by_angle {
                pick.rect = Some((i, omega));
            }
        }
    }

    /// The rectangle of light `i` seen from `sp`, when it is sampled by solid angle there (an
    /// area light, not a disk, at a point that asks for it, see [`RectView::for_light`]).
    #[inline(always)]
    fn rect_view(&self, i: usize, sp: &ShadingPoint) -> Option<RectView> {
        match (sp.solid_angle, self.lights.get(i)) {
            (
                true,
                Some(LightKind::Area {
                    c,
                    ex,
                    ey,
                    frame,
                    disk: false,
                    ..
                }),
            ) => RectView::for_light(*c, *ex, *ey, frame, sp.p),
            _ => None,
        }
    }

    /// A sample of light `i`, chosen with probability `pick` at `sp`, other than a rectangle
    /// sampled by solid angle.
    #[inline(always)]
    fn sample_chosen(
        &self,
        geom: &Geometry,
        sp: &ShadingPoint,
        i: usize,
        pick: f32,
        u1: f32,
        u2: f32,
    ) -> Option<LightSample> {
        let p = sp.p;
        let towards = |q: V3| {
            let d = q - p;
            let dist = d.length();
            (d / dist, dist)
        };
        match &self.lights[i] {
            LightKind::Point {
                p: lp,
                intensity,
                radius,
                ..
            }
            | LightKind::Spot {
                p: lp,
                intensity,
                radius,
                ..
            } => {
                let light = &self.lights[i];
                let mask = light.spot_mask(p - *lp);
                if mask <= 0.0 {
                    return None;
                }
                if let Some(cone) = SphereCone::new(*lp, *radius, p) {
                    // A sphere light: a direction uniform in the cone it subtends.
                    let wi = Frame::new(cone.axis).to_world(uniform_cone(u1, u2, cone.cos_max));
                    let b = cone.dist * wi.dot(cone.axis);
                    let dist = b - (radius * radius - (cone.dist * cone.dist - b * b)).max(0.0).sqrt();
                    return Some(LightSample {
                        li: *intensity / (PI * radius * radius) * mask,
                        wi,
                        dist,
                        pdf: pick / cone.omega,
                        delta: false,
                    });
                }
                // A point (or a sphere too small or too close to sample as one): the position
                // jittered on a disk of the radius facing the shading point.
                let mut q = *lp;
                if *radius > 0.0 {
                    let f = Frame::new((p - *lp).normalize());
                    let (dx, dy) = concentric_disk(u1, u2);
                    q = q + f.t * (dx * radius) + f.b * (dy * radius);
                }
                let (wi, dist) = towards(q);
                if !(dist > 0.0) {
                    return None;
                }
                Some(LightSample {
                    li: *intensity / (dist * dist) * mask,
                    wi,
                    dist,
                    pdf: pick,
                    delta: true,
                })
            }
            LightKind::Area {
                c,
                ex,
                ey,
                n,
                disk,
                radiance,
                area,
                ..
            } => area_sample(
                p,
                area_point(*c, *ex, *ey, *disk, u1, u2),
                *n,
                *radiance,
                *area,
                pick,
                None,
            ),
            LightKind::Sun {
                dir,
                irradiance,
                cos_max,
                omega,
            } => {
                let f = Frame::new(-*dir);
                let wi = f.to_world(uniform_cone(u1, u2, *cos_max));
                let (li, pdf, delta) = if *omega > 0.0 {
                    (*irradiance / *omega, pick / *omega, false)
                } else {
                    (*irradiance, pick, true)
                };
                Some(LightSample {
                    li,
                    wi,
                    dist: f32::INFINITY,
                    pdf,
                    delta,
                })
            }
            LightKind::Env => {
                let env = self.env.as_ref()?;
                let (wi, pdf) = match &self.env_sampler {
                    Some(s) => s.sample(u1, u2)?,
                    None if sp.two_sided => (uniform_sphere(u1, u2), 1.0 / (4.0 * PI)),
                    None => {
                        let wi = Frame::new(sp.n).to_world(cosine_hemisphere(u1, u2));
                        (wi, wi.dot(sp.n) / PI)
                    }
                };
                if !(pdf > 0.0) {
                    return None;
                }
                Some(LightSample {
                    li: env.eval(wi),
                    wi,
                    dist: f32::INFINITY,
                    pdf: pick * pdf,
                    delta: false,
                })
            }
            LightKind::Tri { prim, radiance } => {
                let tri = &geom.tris[*prim as usize];
                let (b1, b2) = uniform_triangle(u1, u2);
                let q = tri.point(b1, b2);
                let a = &geom.attrs[*prim as usize];
                let (wi, dist) = towards(q);
                let cos_l = wi.dot(a.ng).abs();
                if !(cos_l > 0.0 && dist > 0.0) {
                    return None;
                }
                Some(LightSample {
                    li: *radiance,
                    wi,
                    dist,
                    pdf: pick * dist * dist / (cos_l * a.area),
                    delta: false,
                })
            }
        }
    }

    /// The world's radiance along `d`.
    #[inline]
    pub fn env_hit(&self, d: V3) -> Option<V3> {
        Some(self.env.as_ref()?.eval(d))
    }

    /// The light-sampling pdf (solid angle, with the pick probability) of the world along `d`
    /// at the shading point of `pick`.
    #[inline]
    pub fn env_pdf(&self, pick: &LightPick, d: V3) -> f32 {
        match self.env_index {
            Some(i) => self.pick_pmf_at(pick, i) * self.env_dir_pdf(&pick.sp, d),
            None => 0.0,
        }
    }

    /// Suns with a cone (see the module docs) a ray escaping the scene along `d` sees: calls
    /// `f(radiance, light, direction_pdf)` for each (the pdf without the pick probability).
    #[inline(always)]
    pub fn sun_hits(&self, d: V3, mut f: impl FnMut(V3, usize, f32)) {
        for &i in &self.sun_indices {
            if let LightKind::Sun {
                dir,
                irradiance,
                cos_max,
                omega,
            } = &self.lights[i]
            {
                if -d.dot(*dir) >= *cos_max {
                    f(*irradiance / *omega, i, 1.0 / *omega);
                }
            }
        }
    }

    /// The direction pdf with which light `i` is sampled at the shading point of `pick`, given
    /// `pdf` from [`Lights::area_hits`]: `1 / Ω` for a rectangle sampled by solid angle there,
    /// else `pdf` itself.
    #[inline(always)]
    pub fn area_dir_pdf(&self, pick: &LightPick, i: usize, pdf: f32) -> f32 {
        if let Some((k, omega)) = pick.rect {
            if k == i {
                return 1.0 / omega;
            }
        }
        match self.rect_view(i, &pick.sp).and_then(|v| v.solid_angle()) {
            Some(s) => 1.0 / s.omega,
            None => pdf,
        }
    }

    /// Light-sampling pdf (solid angle, with the pick probability of `pick`) of an emissive
    /// triangle hit at distance `t` with `|cos|` between the ray and its normal.
    pub fn tri_pdf(&self, geom: &Geometry, pick: &LightPick, prim: u32, t: f32, cos_l: f32) -> f32 {
        let a = &geom.attrs[prim as usize];
        if a.light == u32::MAX || cos_l <= 0.0 {
            return 0.0;
        }
        self.pick_pmf_at(pick, a.light as usize) * t * t / (cos_l * a.area)
    }

    /// Area and sphere lights hit by `ray` before `tmax`: calls `f(radiance, light,
    /// direction_pdf, t)` for each, the pdf without the pick probability, for area lights the
    /// pdf of sampling by area (see [`Lights::area_dir_pdf`]) (lights do not occlude, so every
    /// one on the way counts).
    #[inline(always)]
    pub fn area_hits(&self, ray: &Ray, tmax: f32, f: impl FnMut(V3, usize, f32, f32)) {
        self.area_hits_if(ray, tmax, false, f)
    }

    /// [`Lights::area_hits`] for a camera ray: only the area and sphere lights visible to the
    /// camera (the pdf passed to `f` is then meaningless: no MIS at the camera).
    #[inline(always)]
    pub fn camera_area_hits(&self, ray: &Ray, tmax: f32, f: impl FnMut(V3, usize, f32, f32)) {
        self.area_hits_if(ray, tmax, true, f)
    }

    #[inline(always)]
    fn area_hits_if(&self, ray: &Ray, tmax: f32, camera_ray: bool, mut f: impl FnMut(V3, usize, f32, f32)) {
        for &i in &self.area_indices {
            if let LightKind::Area {
                c,
                ex,
                ey,
                n,
                disk,
                radiance,
                area,
                camera,
                ..
            } = &self.lights[i]
            {
                if camera_ray && !camera {
                    continue;
                }
                let denom = ray.d.dot(*n);
                if denom >= 0.0 {
                    continue; // back side or parallel: one-sided emitter
                }
                let t = (*c - ray.o).dot(*n) / denom;
                if !(t > 1e-5 && t < tmax) {
                    continue;
                }
                let q = ray.o + ray.d * t - *c;
                let a = q.dot(*ex) / ex.dot(*ex);
                let b = q.dot(*ey) / ey.dot(*ey);
                let inside = if *disk {
                    a * a + b * b <= 1.0
                } else {
                    a.abs() <= 1.0 && b.abs() <= 1.0
                };
                if inside {
                    f(*radiance, i, t * t / (-denom * area), t);
                }
            }
        }
        for &i in &self.sphere_indices {
            let light = &self.lights[i];
            let (LightKind::Point {
                p: c,
                intensity,
                radius,
                camera,
            }
            | LightKind::Spot {
                p: c,
                intensity,
                radius,
                camera,
                ..
            }) = light
            else {
                continue;
            };
            if camera_ray && !camera {
                continue;
            }
            let oc = ray.o - *c;
            let b = oc.dot(ray.d);
            let disc = b * b - (oc.dot(oc) - radius * radius);
            if disc < 0.0 {
                continue;
            }
            let t = -b - disc.sqrt();
            if !(t > 1e-5 && t < tmax) {
                continue;
            }
            let mask = light.spot_mask(oc);
            if !(mask > 0.0) {
                continue;
            }
            let radiance = *intensity / (PI * radius * radius) * mask;
            if camera_ray {
                // The camera sees the sphere wherever its rays hit it (no MIS to match).
                f(radiance, i, 0.0, t);
                continue;
            }
            // Only where light sampling samples the sphere as a cone (else it is a point).
            let Some(cone) = SphereCone::new(*c, *radius, ray.o) else {
                continue;
            };
            f(radiance, i, 1.0 / cone.omega, t);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_core::{Image, Rng};

    fn lights_of(src: &str) -> (Geometry, Lights) {
        let scene = Scene::from_toml_str(src).expect("scene");
        let mut geom = Geometry::build(&scene).expect("geometry");
        let lights = Lights::build(&scene, &mut geom).expect("lights");
        (geom, lights)
    }

    /// Eleven analytic lights (more than a pick caches) of every kind, some of which cannot reach
    /// part of the space (a one-sided area light facing up, a narrow spot), and an emissive panel.
    const MANY: &str = r#"
        [camera]
        width = 8
        height = 8
        fov_y_deg = 50.0
        position = [0.0, 1.0, 4.0]
        look_at = [0.0, 0.5, 0.0]

        [[objects]]
        name = "floor"
        shape = { type = "quad", size = [6.0, 6.0] }
        transform = { rotate_deg = [-90.0, 0.0, 0.0] }
        material = { base_color = [0.7, 0.6, 0.5] }

        [[objects]]
        name = "panel"
        shape = { type = "quad", size = [0.5, 0.5] }
        transform = { translate = [0.0, 1.2, -1.5] }
        material = { base_color = [0.1, 0.1, 0.1], emission_color = [1.0, 0.8, 0.6], emission_strength = 3.0 }

        [[lights]]
        type = "point"
        position = [-1.5, 1.5, 1.5]
        power = 80.0
        radius = 0.2

        [[lights]]
        type = "point"
        position = [1.5, 0.3, 0.5]
        power = 5.0

        [[lights]]
        type = "point"
        position = [0.0, 3.0, -2.0]
        power = 300.0
        radius = 0.05

        [[lights]]
        type = "spot"
        position = [0.0, 2.0, 0.0]
        direction = [0.0, -1.0, 0.0]
        spot_size_deg = 20.0
        blend = 0.0
        power = 200.0

        [[lights]]
        type = "spot"
        position = [1.0, 2.0, 1.0]
        direction = [0.0, -1.0, 0.0]
        spot_size_deg = 60.0
        blend = 0.5
        power = 100.0
        radius = 0.1

        [[lights]]
        type = "area"
        position = [1.0, 2.5, 1.0]
        look_at = [0.0, 0.0, 0.0]
        size = 1.0
        power = 150.0

        [[lights]]
        type = "area"
        position = [0.0, 0.5, 0.0]
        direction = [0.0, 1.0, 0.0]
        shape = "disk"
        size = 0.4
        power = 40.0

        [[lights]]
        type = "area"
        position = [-2.0, 1.0, 0.0]
        direction = [1.0, 0.0, 0.0]
        size = 0.5
        power = 20.0

        [[lights]]
        type = "sun"
        direction = [0.3, -1.0, -0.4]
        strength = 2.0
        angle_deg = 5.0

        [[lights]]
        type = "sun"
        direction = [-0.5, -0.2, 0.1]
        strength = 0.5

        [world]
        color = [0.2, 0.25, 0.3]
    "#;

    /// Whether light `i` can send any light to `p` (by any sampling technique).
    fn can_reach(lights: &Lights, i: usize, p: V3) -> bool {
        match &lights.lights[i] {
            LightKind::Area { c, n, .. } => (p - *c).dot(*n) > 0.0,
            l @ LightKind::Spot { p: lp, .. } => l.spot_mask(p - *lp) > 0.0,
            // A constant world is left to BSDF samples.
            LightKind::Env => lights.env_peaked > 0.0,
            _ => true,
        }
    }

    fn random_point(rng: &mut Rng) -> ShadingPoint {
        ShadingPoint {
            p: V3::new(6.0 * rng.f32() - 3.0, 3.0 * rng.f32() - 0.2, 6.0 * rng.f32() - 3.0),
            n: uniform_sphere(rng.f32(), rng.f32()),
            two_sided: rng.f32() < 0.25,
            solid_angle: rng.f32() < 0.5,
        }
    }

    #[test]
    fn pick_probabilities_sum_to_one_and_are_positive_wherever_a_light_can_reach() {
        let (_, lights) = lights_of(MANY);
        assert!(
            lights.analytic == 11 && lights.items() > CACHED,
            "{} analytic lights",
            lights.analytic
        );
        assert!(lights.lights.len() > lights.analytic, "emissive triangles are lights");
        let mut rng = Rng::new(5);
        let (mut unreachable, mut floor_only) = (0, 0);
        for _ in 0..2000 {
            let sp = random_point(&mut rng);
            let pick = lights.pick_at(sp);
            let mut sum = 0.0f64;
            for i in 0..lights.lights.len() {
                let pmf = lights.pick_pmf_at(&pick, i);
                sum += pmf as f64;
                let reach = can_reach(&lights, i, sp.p);
                assert_eq!(
                    pmf > 0.0,
                    reach,
                    "light {i} at {:?}: pmf {pmf}, reachable {reach}",
                    sp.p
                );
                unreachable += !reach as usize;
                if i < lights.analytic && reach {
                    // Every reachable light keeps at least its share of the power floor.
                    assert!(pmf >= PICK_FLOOR * lights.base.pmf(i) * 0.999);
                    floor_only += (lights.item_weight(i, &sp) == Some(0.0)) as usize;
                }
            }
            assert!(
                (sum - 1.0).abs() < 1e-5,
                "pick probabilities at {:?} sum to {sum}",
                sp.p
            );
        }
        // The scene exercises lights that cannot reach a point and ones whose estimate is 0
        // (facing away) but that still get the floor.
        assert!(
            unreachable > 500 && floor_only > 500,
            "{unreachable} unreachable, {floor_only} floor only"
        );
    }

    /// With one light (and a constant world, which is never light-sampled) the choice skips the
    /// weights: the light is picked wherever it can reach the point, as the weights would say.
    #[test]
    fn a_single_light_is_picked_wherever_it_can_reach() {
        let src = MANY.split("[[lights]]").next().expect("head").to_string()
            + "[[lights]]\ntype = \"area\"\nposition = [1.0, 2.5, 1.0]\nlook_at = [0.0, 0.0, 0.0]\nsize = 1.0\npower = 150.0\n"
            + "[world]\ncolor = [0.2, 0.25, 0.3]\n";
        let (_, lights) = lights_of(&src.replace("emission_strength = 3.0", "emission_strength = 0.0"));
        assert_eq!((lights.items(), lights.single_item()), (2, Some(0)));
        // The pick probability the general formula gives a lone item, exactly.
        assert_eq!((1.0 - PICK_FLOOR) * (1.0 / 1.0) + PICK_FLOOR * (0.7 / 0.7), 1.0);
        let mut rng = Rng::new(2);
        for _ in 0..1000 {
            let sp = random_point(&mut rng);
            let pick = lights.pick_at(sp);
            let p = lights.pick_pmf_at(&pick, 0);
            assert_eq!(p, if can_reach(&lights, 0, sp.p) { 1.0 } else { 0.0 });
            assert_eq!(lights.item_weight(0, &sp).is_some(), lights.item_reaches(0, &sp));
            assert_eq!(lights.pick_pmf_at(&pick, 1), 0.0);
        }
    }

    #[test]
    fn lights_are_chosen_with_their_pick_probabilities() {
        let (_, lights) = lights_of(MANY);
        let mut rng = Rng::new(9);
        for _ in 0..5 {
            let pick = lights.pick_at(random_point(&mut rng));
            let mut counts = vec![0usize; lights.lights.len()];
            let n = 200_000;
            for k in 0..n {
                let u = (k as f32 + 0.5) / n as f32;
                let (i, p) = lights.choose(&pick, u).expect("a light");
                assert_eq!(p, lights.pick_pmf_at(&pick, i));
                counts[i] += 1;
            }
            for (i, c) in counts.iter().enumerate() {
                let (f, p) = (*c as f64 / n as f64, lights.pick_pmf_at(&pick, i) as f64);
                assert!((f - p).abs() < 2e-4, "light {i}: frequency {f} vs pmf {p}");
            }
        }
    }

    /// Light sampling at a point under a strong disk light, a weak point light off to the
    /// side, a sun and a dim constant sky: the mean of `Li cos / pdf` is the analytic irradiance
    /// of the lights (the sky is left to BSDF samples), and most picks go to the strong light.
    #[test]
    fn light_sampling_with_per_point_choice_gives_the_analytic_irradiance() {
        let (r, h, power) = (0.5f64, 1.5f64, 300.0f64);
        let (pp, pl) = ([2.0f64, 0.5, 1.0], 10.0f64);
        let (sun, sun_dir) = (0.4f64, [0.2f64, -1.0, 0.3]);
        let sky = 0.05f64;
        let src = format!(
            r#"
            [camera]
            width = 4
            height = 4
            fov_y_deg = 50.0
            position = [0.0, 5.0, 5.0]
            look_at = [0.0, 0.0, 0.0]

            [[objects]]
            name = "far"
            shape = {{ type = "quad", size = [1.0, 1.0] }}
            transform = {{ translate = [20.0, -5.0, 0.0] }}
            material = {{ base_color = [0.5, 0.5, 0.5] }}

            [[lights]]
            type = "area"
            shape = "disk"
            position = [0.0, {h}, 0.0]
            direction = [0.0, -1.0, 0.0]
            size = {d}
            power = {power}

            [[lights]]
            type = "point"
            position = [{}, {}, {}]
            power = {pl}

            [[lights]]
            type = "sun"
            direction = [{}, {}, {}]
            strength = {sun}

            [world]
            color = [{sky}, {sky}, {sky}]
            "#,
            pp[0],
            pp[1],
            pp[2],
            sun_dir[0],
            sun_dir[1],
            sun_dir[2],
            d = 2.0 * r,
        );
        let (geom, lights) = lights_of(&src);
        // At the origin, normal +Y. Disk of radiance L = P / (π · πr²) on the axis at height h:
        // E = π L r² / (h² + r²). Point: E = P/(4π) · cos / d². Sun: E = strength · cos. Sky
        // over the upper hemisphere: E = π L.
        let l_disk = power / (PI as f64 * PI as f64 * r * r);
        let e_disk = PI as f64 * l_disk * r * r / (h * h + r * r);
        let d2 = pp.iter().map(|v| v * v).sum::<f64>();
        let e_point = pl / (4.0 * PI as f64) * (pp[1] / d2.sqrt()) / d2;
        let sl = sun_dir.iter().map(|v| v * v).sum::<f64>().sqrt();
        let e_sun = sun * (-sun_dir[1] / sl);
        // The constant sky is left to BSDF samples (never light-sampled).
        let e_sky = 0.0;
        let expect = e_disk + e_point + e_sun + e_sky;
        let n = V3::new(0.0, 1.0, 0.0);
        let pick = lights.pick_at(ShadingPoint {
            p: V3::ZERO,
            n,
            two_sided: false,
            solid_angle: false,
        });
        assert!(lights.pick_pmf_at(&pick, 0) > 0.8, "the strong light gets most picks");
        let mut rng = Rng::new(11);
        let samples = 1_000_000;
        let mut sum = 0.0f64;
        for _ in 0..samples {
            if let Some(ls) = lights.sample(&geom, &pick, rng.f32(), rng.f32(), rng.f32()) {
                let cos = ls.wi.dot(n).max(0.0) as f64;
                sum += ls.li.x as f64 * cos / ls.pdf as f64;
            }
        }
        let mean = sum / samples as f64;
        assert!(
            (mean - expect).abs() < 0.005 * expect,
            "estimate {mean} vs analytic {expect} (disk {e_disk}, point {e_point}, sun {e_sun}, sky {e_sky})"
        );
    }

    /// The pdf a light sample reports is the one the BSDF side computes for the same direction
    /// (pick probability × direction pdf), for every light hit by rays.
    #[test]
    fn light_sample_pdfs_match_the_pdfs_of_bsdf_hits() {
        // With an image world (a constant one is not light-sampled).
        let dir = tempfile::tempdir().expect("temp dir");
        let sky = dir.path().join("sky.exr");
        pixl_core::io::write_image(&sky, spot_image().image()).expect("sky image");
        let src = MANY.replace(
            "color = [0.2, 0.25, 0.3]",
            &format!("image = {:?}\nstrength = 0.2", sky),
        );
        let (geom, lights) = lights_of(&src);
        assert!(lights.env_sampler.is_some() && lights.env_peaked > 0.0);
        let mut rng = Rng::new(3);
        let mut checked = [0usize; 4];
        for _ in 0..20_000 {
            let sp = random_point(&mut rng);
            let pick = lights.pick_at(sp);
            let Some(ls) = lights.sample(&geom, &pick, rng.f32(), rng.f32(), rng.f32()) else {
                continue;
            };
            if ls.delta {
                continue;
            }
            let ray = Ray::new(sp.p, ls.wi);
            let clear = if ls.dist.is_finite() {
                ls.dist * (1.0 - 1e-3)
            } else {
                f32::INFINITY
            };
            if geom.occluded(&ray, 0.0, clear) {
                continue;
            }
            let mut found = Vec::new();
            let tmax = if ls.dist.is_finite() {
                ls.dist * 1.001
            } else {
                f32::INFINITY
            };
            lights.area_hits(&ray, tmax, |_, i, pdf, t| {
                found.push((lights.pick_pmf_at(&pick, i) * lights.area_dir_pdf(&pick, i, pdf), t, 0))
            });
            if !ls.dist.is_finite() {
                found.push((lights.env_pdf(&pick, ls.wi), f32::INFINITY, 1));
                lights.sun_hits(ls.wi, |_, i, pdf| {
                    found.push((lights.pick_pmf_at(&pick, i) * pdf, f32::INFINITY, 2))
                });
            }
            let tri = geom
                .intersect(&ray, 0.0, tmax)
                .filter(|h| geom.attrs[h.prim as usize].light != u32::MAX);
            if let Some(h) = tri {
                found.push((lights.tri_pdf(&geom, &pick, h.prim, h.t, ls.wi.dot(h.ng).abs()), h.t, 3));
            }
            // The sampled light is the one at the sampled distance; its pdf must agree.
            let same = found.iter().find(|(pdf, t, _)| {
                ((t - ls.dist).abs() <= 1e-3 * ls.dist.max(1.0) || (t.is_infinite() && ls.dist.is_infinite()))
                    && (pdf - ls.pdf).abs() <= 2e-3 * ls.pdf
            });
            let Some((_, _, kind)) = same else {
                panic!(
                    "no BSDF-side pdf matches the light sample's {} at {:?}: {found:?}",
                    ls.pdf, sp.p
                );
            };
            checked[*kind] += 1;
        }
        assert!(
            checked.iter().all(|&c| c > 100),
            "area/sphere, world, sun, triangle: {checked:?}"
        );
    }

    /// Spherical-rectangle sampling: the solid angle is the area integral `∫ cos_l / d² dA`,
    /// sampled points lie on the rectangle, and the mean of `cos θ / pdf` over samples is the
    /// irradiance integral `∫ cos θ cos_l / d² dA` (uniform in solid angle), for points near
    /// the rectangle, far off its axis and nearly in its plane.
    #[test]
    fn spherical_rectangle_samples_its_solid_angle_uniformly() {
        let (c, ex, ey) = (V3::new(0.2, 1.0, -0.3), V3::new(0.6, 0.0, 0.0), V3::new(0.0, 0.3, 0.4));
        let n = ex.cross(ey).normalize();
        let recv = V3::new(0.1, 0.2, 1.0).normalize();
        for o in [
            V3::new(0.0, 0.0, 1.0),
            V3::new(1.5, 1.2, 0.8),
            V3::new(-0.3, 0.9, -0.2),
            V3::new(0.2, 1.0, 0.05),
        ] {
            let view = RectView::with_frame(o, c - ex - ey, &RectFrame::new(ex * 2.0, ey * 2.0)).expect("in front");
            let r = view.solid_angle().expect("large enough");
            let (mut omega, mut irr) = (0.0f64, 0.0f64);
            let m = 400;
            let da = (4.0 * ex.length() * ey.length()) as f64 / (m * m) as f64;
            for i in 0..m {
                for j in 0..m {
                    let q = c
                        + ex * (2.0 * (i as f32 + 0.5) / m as f32 - 1.0)
                        + ey * (2.0 * (j as f32 + 0.5) / m as f32 - 1.0);
                    let d = q - o;
                    let d2 = d.dot(d) as f64;
                    let w = d / d.length();
                    let cos_l = w.dot(n).abs() as f64;
                    omega += cos_l / d2 * da;
                    irr += cos_l / d2 * da * w.dot(recv).abs() as f64;
                }
            }
            assert!(
                (r.omega as f64 - omega).abs() < 2e-3 * omega,
                "Ω {} vs {omega} at {o:?}",
                r.omega
            );
            let mut rng = Rng::new(4);
            let samples = 200_000;
            let mut est = 0.0f64;
            for _ in 0..samples {
                let (x, y) = rect_point(&view.r, &r, rng.f32(), rng.f32());
                let q = view.point(o, &RectFrame::new(ex * 2.0, ey * 2.0), x, y);
                let local = q - c;
                let (a, b) = (local.dot(ex) / ex.dot(ex), local.dot(ey) / ey.dot(ey));
                assert!(
                    a.abs() <= 1.0 + 1e-4 && b.abs() <= 1.0 + 1e-4 && local.dot(n).abs() < 1e-4,
                    "{q:?} off the rectangle"
                );
                let w = (q - o).normalize();
                est += w.dot(recv).abs() as f64 * r.omega as f64;
            }
            let est = est / samples as f64;
            assert!((est - irr).abs() < 5e-3 * irr, "irradiance {est} vs {irr} at {o:?}");
        }
    }

    /// The packet form of the light sampling gives each lane what sampling it alone gives
    /// (bit for bit), whatever the other lanes hold: lights of every kind, rectangles sampled
    /// by solid angle (near) and by area (screened: far), and lanes without a sample.
    #[test]
    fn light_samples_of_a_packet_are_those_of_each_lane_alone() {
        // MANY's camera and objects, with a near rectangle and a far one instead of its lights.
        let far = MANY.split("[[lights]]").next().expect("head").to_string()
            + r#"
            [[lights]]
            type = "area"
            shape = "rectangle"
            position = [0.0, 2.0, 0.0]
            direction = [0.0, -1.0, 0.0]
            size = 1.0
            size_y = 0.5
            power = 100.0
            [[lights]]
            type = "area"
            position = [400.0, 3.0, 0.0]
            direction = [-1.0, 0.0, 0.0]
            size = 0.1
            power = 100.0
            "#;
        const L: usize = 16;
        for src in [MANY, far.as_str()] {
            let (geom, lights) = lights_of(src);
            let mut rng = Rng::new(11);
            for _ in 0..200 {
                let picks: Vec<LightPick> = (0..L).map(|_| lights.pick_at(random_point(&mut rng))).collect();
                let mut sampled = picks.clone();
                let us: Vec<[f32; 3]> = (0..L).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
                let live: Vec<bool> = (0..L).map(|_| rng.f32() < 0.8).collect();
                let mut it = sampled.iter_mut().enumerate();
                let lanes: [Option<(&mut LightPick, [f32; 3])>; L] = std::array::from_fn(|_| {
                    let (l, pick) = it.next().expect("L picks");
                    live[l].then_some((pick, us[l]))
                });
                let mut packet = [None; L];
                lights.sample_lanes(&geom, lanes, &mut packet);
                for l in 0..L {
                    let alone = live[l]
                        .then(|| lights.sample(&geom, &picks[l], us[l][0], us[l][1], us[l][2]))
                        .flatten();
                    let key = |s: &Option<LightSample>| {
                        s.map(|s| (s.wi.to_arr().map(f32::to_bits), s.dist.to_bits(), s.pdf.to_bits()))
                    };
                    assert_eq!(key(&packet[l]), key(&alone), "lane {l}");
                    // The solid angle kept in the pick is the one computed afresh.
                    for i in 0..lights.lights.len() {
                        assert_eq!(
                            lights.area_dir_pdf(&sampled[l], i, 0.5).to_bits(),
                            lights.area_dir_pdf(&picks[l], i, 0.5).to_bits()
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn polynomial_arccos_is_within_5e7_of_f64() {
        // Every 2^-20 step over [−1, 1], the ends and their neighbours included.
        let mut worst = 0.0f64;
        let n = 1i32 << 20;
        for i in -n..=n {
            let x = i as f32 / n as f32;
            let err = (acos_poly(x) as f64 - (x as f64).acos()).abs();
            worst = worst.max(err);
        }
        for x in [1.0f32, -1.0, 1.0 - f32::EPSILON, -1.0 + f32::EPSILON, 0.0, -0.0] {
            worst = worst.max((acos_poly(x) as f64 - (x as f64).acos()).abs());
        }
        assert!(worst < 5e-7, "max error {worst}");
    }

    fn spot_image() -> Texture {
        // A dim gradient, a black band and a bright 2×2 spot.
        Texture::from_image(Image::from_fn(32, 16, 3, |x, y, c| {
            if (20..22).contains(&x) && (4..6).contains(&y) {
                [50.0, 40.0, 30.0][c]
            } else if (8..12).contains(&x) {
                0.0
            } else {
                0.05 + 0.01 * y as f32
            }
        }))
    }

    #[test]
    fn only_the_light_of_a_world_above_its_mean_draws_light_samples() {
        let flat = Texture::from_image(Image::from_fn(16, 8, 3, |_, _, _| 0.3));
        assert!(env_peak_share(&flat).abs() < 1e-6);
        let peaked = env_peak_share(&spot_image());
        assert!(peaked > 0.5 && peaked < 1.0, "{peaked}");
        // A constant world is never light-sampled (BSDF samples find it).
        let (_, lights) = lights_of(MANY);
        let env = lights.env_index.expect("a world");
        let sp = ShadingPoint {
            p: V3::new(0.0, 0.01, 0.0),
            n: V3::new(0.0, 1.0, 0.0),
            two_sided: false,
            solid_angle: true,
        };
        let pick = lights.pick_at(sp);
        assert_eq!(lights.item_weight(env, &sp), None);
        assert_eq!(lights.pick_pmf_at(&pick, env), 0.0);
        assert_eq!(lights.env_pdf(&pick, V3::new(0.0, 1.0, 0.0)), 0.0);
    }

    #[test]
    fn world_image_sampling_pdf_integrates_to_one_matches_a_histogram_and_covers_every_lit_direction() {
        let tex = spot_image();
        let rot = 30f32.to_radians();
        let s = EnvSampler::new(&tex, rot).expect("sampler");
        let env = Environment {
            radiance: V3::ONE,
            image: Some(tex),
            rotation: rot,
        };
        // ∫ pdf dω over the sphere, midpoint rule on a fine (θ, φ) grid.
        let (nt, np) = (400, 800);
        let mut integral = 0.0f64;
        for i in 0..nt {
            let theta = PI as f64 * (i as f64 + 0.5) / nt as f64;
            for j in 0..np {
                let phi = 2.0 * PI as f64 * (j as f64 + 0.5) / np as f64;
                let d = V3::new(
                    (theta.sin() * phi.cos()) as f32,
                    theta.cos() as f32,
                    (theta.sin() * phi.sin()) as f32,
                );
                integral += s.pdf(d) as f64 * theta.sin() * (PI as f64 / nt as f64) * (2.0 * PI as f64 / np as f64);
            }
        }
        assert!((integral - 1.0).abs() < 2e-3, "∫ pdf = {integral}");
        // Samples: the reported pdf is the pdf of the direction, every sampled direction sees
        // light, and the sample counts per image cell follow the pdf.
        let mut rng = Rng::new(1);
        let n = 400_000;
        let (mut counts, mut lit, mut agree) = (vec![0usize; 32 * 16], 0, 0);
        let mut mc = 0.0f64;
        for _ in 0..n {
            let (d, pdf) = s.sample(rng.f32(), rng.f32()).expect("a direction");
            agree += ((s.pdf(d) - pdf).abs() <= 1e-3 * pdf) as usize;
            lit += (env.eval(d).luminance() > 0.0) as usize;
            mc += env.eval(d).luminance() as f64 / pdf as f64;
            let (sn, cs) = (-rot).sin_cos();
            let r = V3::new(cs * d.x + sn * d.z, d.y, -sn * d.x + cs * d.z);
            let u = 0.5 - (-r.z).atan2(r.x) / (2.0 * PI);
            let v = 0.5 - r.y.atan2((r.x * r.x + r.z * r.z).sqrt()) / PI;
            let (x, y) = (((u * 32.0) as usize).min(31), ((v * 16.0) as usize).min(15));
            counts[y * 32 + x] += 1;
        }
        assert!(agree as f64 > 0.999 * n as f64, "{agree} of {n} pdfs agree");
        // (Half of each cell next to the black band lies in the dark: a few samples are wasted.)
        assert!(
            lit as f64 > 0.995 * n as f64,
            "{lit} of {n} sampled directions see light"
        );
        for y in 0..16 {
            for x in 0..32 {
                let p = s.dist.pdf((x as f32 + 0.5) / 32.0, (y as f32 + 0.5) / 16.0) as f64 / (32.0 * 16.0);
                let f = counts[y * 32 + x] as f64 / n as f64;
                let sigma = (p * (1.0 - p) / n as f64).sqrt();
                assert!((f - p).abs() < 5.0 * sigma + 1e-5, "cell ({x}, {y}): {f} vs {p}");
                if (9..11).contains(&x) {
                    assert_eq!(counts[y * 32 + x], 0, "the black band is never sampled");
                }
            }
        }
        // ∫ L dω: the importance-sampled estimate against the midpoint rule.
        let mut exact = 0.0f64;
        for i in 0..nt {
            let theta = PI as f64 * (i as f64 + 0.5) / nt as f64;
            for j in 0..np {
                let phi = 2.0 * PI as f64 * (j as f64 + 0.5) / np as f64;
                let d = V3::new(
                    (theta.sin() * phi.cos()) as f32,
                    theta.cos() as f32,
                    (theta.sin() * phi.sin()) as f32,
                );
                let l = env.eval(d).luminance();
                // Wherever the world sends light, the sampler can sample it.
                assert!(!(l > 0.0) || s.pdf(d) > 0.0, "radiance {l} but pdf 0 along {d:?}");
                exact += l as f64 * theta.sin() * (PI as f64 / nt as f64) * (2.0 * PI as f64 / np as f64);
            }
        }
        let mc = mc / n as f64;
        assert!((mc - exact).abs() < 0.01 * exact, "{mc} vs {exact}");
    }
}
