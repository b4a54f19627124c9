//! Triangle meshes: positions, per-vertex normals and UVs, and triangle indices.
//!
//! Coordinates are right-handed, metres, with the camera convention of [`crate`]'s scene
//! (see [`crate::scene`]). UVs are in [0, 1] with `v = 0` at the *top* row of the texture image.

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    /// Per-vertex normals (unit length), or empty to use face normals.
    pub normals: Vec<[f32; 3]>,
    /// Per-vertex texture coordinates, or empty.
    pub uvs: Vec<[f32; 2]>,
    /// Triangles as vertex indices, counter-clockwise seen from the front.
    pub indices: Vec<[u32; 3]>,
}

impl Mesh {
    pub fn num_triangles(&self) -> usize {
        self.indices.len()
    }

    /// Axis-aligned bounds `(min, max)`; `None` for an empty mesh.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let first = *self.positions.first()?;
        let mut lo = first;
        let mut hi = first;
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        Some((lo, hi))
    }
}
