//! Sampling the picked light: a direction towards it, its incident radiance and its solid-angle
//! pdf with the pick probability ([`LightSample`]), for one shading point
//! ([`Lights::sample`]) or a packet's lanes at once ([`Lights::sample_lanes`]); and the pdfs
//! light sampling gives the directions that BSDF samples find, for MIS ([`Lights::env_pdf`],
//! [`Lights::area_dir_pdf`], [`Lights::tri_pdf`]).
//!
//! Contract: a lane of a packet gets bit for bit the sample it gets alone, and the pdf of a
//! light sample is the one its direction gets when a BSDF sample finds the light (tested).
use super::kinds::LightKind;
use super::lights::Lights;
use super::pick::{LightPick, ShadingPoint};
use super::rect::{rect_point, rect_solid_angle, RectCoords, RectView, MIN_RECT_OMEGA};
use crate::math::{Frame, V3};
use crate::trace::geometry::Geometry;
use crate::trace::sampling::{concentric_disk, cosine_hemisphere, uniform_cone, uniform_sphere, uniform_triangle};
use std::f32::consts::PI;

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

/// The cone a sphere light of centre `c` and radius `r` subtends from `x`, when it is worth
/// sampling as one: `x` outside the sphere and the cone not so narrow that `1 − cos θmax` is
/// lost in f32 (then the light is treated as a point, by light sampling alone).
pub(super) struct SphereCone {
    /// Unit direction from `x` to the centre, and the distance.
    pub(super) axis: V3,
    pub(super) dist: f32,
    pub(super) cos_max: f32,
    /// Solid angle `2π (1 − cos θmax)`.
    pub(super) omega: f32,
}

impl SphereCone {
    pub(super) fn new(c: V3, r: f32, x: V3) -> Option<SphereCone> {
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

impl Lights {
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

    /// The light-sampling pdf (solid angle, with the pick probability) of the world along `d`
    /// at the shading point of `pick`.
    #[inline]
    pub fn env_pdf(&self, pick: &LightPick, d: V3) -> f32 {
        match self.env_index {
            Some(i) => self.pick_pmf_at(pick, i) * self.env_dir_pdf(&pick.sp, d),
            None => 0.0,
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
}
