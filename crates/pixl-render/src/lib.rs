//! `pixl-render`: the scene description, a native path tracer that writes Cycles-equivalent
//! render passes, the paper's lighting presets (§4.2), depth→mesh reconstruction and the
//! Blender bridge. The crate has four parts, a folder each (`crates/pixl-render/README.md`
//! draws them):
//!
//! - [`scene`]: the serde scene description (TOML / JSON, Blender units and conventions), with
//!   [`scene::color`] (blackbody temperature → linear RGB) and [`scene::mesh`] (triangle meshes).
//!   Uses nothing else of the crate but its error type.
//! - [`trace`]: the path tracer. [`trace::integrator::render`] path-traces a scene into a
//!   [`Film`] of Cycles passes (`scene` → [`trace::geometry`] + [`trace::bvh`] +
//!   [`trace::light`] + [`trace::material`] → [`trace::integrator`] → [`trace::film`]), its
//!   uniform numbers from [`trace::sampler`] (padded Owen-scrambled Sobol by default).
//! - [`reconstruct`]: scenes made from a photo and lights placed in them: depth map → mesh
//!   ([`reconstruct::depth`]) with normal-map files ([`reconstruct::normals`]), the coarse scene
//!   of the paper's inference ([`reconstruct::coarse_scene`]), lights at a pixel or from a side
//!   ([`reconstruct::placement`]) and the paper's presets ([`reconstruct::presets`]).
//! - [`io`]: files other tools read and write: mesh files ([`io::export`]) and the Blender
//!   bridge ([`io::blender`]).
//!
//! [`error`] and [`math`] serve them all. Every module is also re-exported at the crate root
//! under its own name (`pixl_render::depth`, `pixl_render::light`, …), the paths callers use.
// Index loops over fixed-size RGB / axis arrays read like the math; `!(x > 0.0)` is the
// deliberate NaN-rejecting form.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]
pub mod error;
pub mod io;
pub mod math;
pub mod reconstruct;
pub mod scene;
pub mod trace;

// Every module at the crate root under its own name (`pixl_render::film`, `pixl_render::blender`, …).
pub use io::{blender, export};
pub use reconstruct::{depth, normals, placement, presets};
pub use scene::{color, mesh};
pub use trace::{bvh, camera, denoise, film, geometry, integrator, light, material, sampler, sampling, texture};

pub use error::{RenderError, Result};
pub use film::Film;
pub use integrator::{render, RenderOptions};
pub use mesh::Mesh;
pub use sampler::Sampler;
pub use scene::{Camera, Color, Light, Material, Object, Scene, Shape, Transform, World};
