//! pixl-render
pub mod mesh;
pub use mesh::Mesh;
