//! `pixl-render`: the scene description, a native path tracer that writes Cycles-equivalent
//! render passes, the paper's lighting presets (§4.2), depth→mesh reconstruction and the
//! Blender bridge (issue 4).
//!
//! - [`scene`]: the serde scene description (TOML / JSON), Blender units and conventions.
//! - [`color`]: blackbody temperature → linear RGB.
//! - [`mesh`]: triangle meshes.
//! - [`integrator::render`]: path-trace a scene into a [`Film`] of Cycles passes (`scene` →
//!   [`geometry`] + [`bvh`] + [`light`] + [`material`] → [`integrator`] → [`film`]), its
//!   uniform numbers from [`sampler`] (padded Owen-scrambled Sobol by default).
//! - [`placement`]: lights placed at a pixel of the photo or from a named side of the scene.
//! - [`reconstruct::coarse_scene`]: the coarse scene of the paper's inference from a source render.
// Index loops over fixed-size RGB / axis arrays read like the math; `!(x > 0.0)` is the
// deliberate NaN-rejecting form.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]
pub mod blender;
pub mod bvh;
pub mod camera;
pub mod color;
pub mod denoise;
pub mod depth;
pub mod error;
pub mod export;
pub mod film;
pub mod geometry;
pub mod integrator;
pub mod light;
pub mod material;
pub mod math;
pub mod mesh;
pub mod placement;
pub mod presets;
pub mod reconstruct;
pub mod sampler;
pub mod sampling;
pub mod scene;
pub mod texture;

pub use error::{RenderError, Result};
pub use film::Film;
pub use integrator::{render, RenderOptions};
pub use mesh::Mesh;
pub use sampler::Sampler;
pub use scene::{Camera, Color, Light, Material, Object, Scene, Shape, Transform, World};
