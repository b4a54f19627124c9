//! `pixl-render`: the scene description, a native path tracer that writes Cycles-equivalent
//! render passes, the paper's lighting presets (§4.2), depth→mesh reconstruction and the
//! Blender bridge (issue 4).
//!
//! - [`scene`]: the serde scene description (TOML / JSON), Blender units and conventions.
//! - [`color`]: blackbody temperature → linear RGB.
//! - [`mesh`]: triangle meshes.
pub mod color;
pub mod error;
pub mod mesh;
pub mod depth;
pub mod export;
pub mod scene;

pub use error::{RenderError, Result};
pub use mesh::Mesh;
pub use scene::{Camera, Color, Light, Material, Object, Scene, Shape, Transform, World};
