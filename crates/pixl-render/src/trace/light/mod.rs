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
//!   1e-3 sr), sampled uniformly in the solid angle they subtend ([`RectView`](rect::RectView)).
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
//!
//! # Layout
//! - `kinds.rs`: the light kinds ([`LightKind`], [`Environment`]) and what they emit;
//! - `lights.rs`: [`Lights`], a scene's lights built for a render, and what the rays that leave
//!   the camera or a surface find of them;
//! - `pick.rs`: the light picker ([`ShadingPoint`], [`LightPick`], [`PICK_FLOOR`]);
//! - `sample.rs`: sampling the picked light ([`LightSample`]) and the pdfs MIS needs;
//! - `env.rs`: the world image's sampling distribution and the summaries the picker uses;
//! - `rect.rs`: sampling rectangles by solid angle ([`RectFrame`]).
mod env;
mod kinds;
mod lights;
mod pick;
mod rect;
mod sample;
#[cfg(test)]
mod tests;

pub use kinds::{area_axes, Environment, LightKind};
pub use lights::Lights;
pub use pick::{LightPick, ShadingPoint, PICK_FLOOR};
pub use rect::RectFrame;
pub use sample::LightSample;
