//! The path tracer: a [`Scene`](crate::scene::Scene) in, a [`Film`](film::Film) of Cycles'
//! render passes out ([`integrator::render`]).
//!
//! - [`integrator`]: the path loop (next-event estimation, MIS, the passes of the first hit),
//!   pixels in parallel, camera paths of a pixel traced as packets.
//! - [`camera`]: camera rays (pinhole or thin lens).
//! - [`geometry`]: the scene's objects as world-space triangles in one [`bvh`], with their
//!   shading data and [`texture`]s.
//! - [`bvh`]: the 4-wide BVH and its single-ray and packet kernels (portable, AVX2, AVX-512).
//! - [`material`]: the Principled BSDF and its baked albedo tables.
//! - [`light`]: the light kinds, their samplers and the per-point light picker.
//! - [`sampler`]: where a path's uniform numbers come from (Sobol or independent);
//!   [`sampling`]: the warps that turn them into directions and points.
//! - [`film`]: per-pixel pass sums and their Cycles names; [`denoise`]: the guided median
//!   clean-up of `Combined`.
//!
//! Contract: a render is a function of the scene, the options and the seed alone — bit-identical
//! whatever the thread count, the scheduling or the instruction set the BVH kernels use.
pub mod bvh;
pub mod camera;
pub mod denoise;
pub mod film;
pub mod geometry;
pub mod integrator;
pub mod light;
pub mod material;
pub mod sampler;
pub mod sampling;
pub mod texture;
