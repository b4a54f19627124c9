//! Mesh files in and out: glTF 2.0 binary ([`glb`]), Wavefront OBJ + MTL ([`obj`]) and binary
//! PLY ([`ply`]), and [`load_mesh`], which the scene loader calls for mesh objects.
//!
//! # UV conventions
//! [`Mesh`] UVs have `v = 0` at the **top** of the texture (glTF's convention too). OBJ and PLY
//! put `v = 0` at the bottom (Blender, MeshLab and every OBJ reader do), so their writers store
//! `1 − v` and their readers flip back; an OBJ/PLY round trip reproduces `v` to within one ulp.
//!
//! All writes are atomic ([`pixl_core::io::atomic_write`]).
use crate::scene::mesh::Mesh;
use std::path::{Path, PathBuf};

pub mod glb;
pub mod obj;
pub mod ply;

#[derive(Debug, thiserror::Error)]
pub enum MeshIoError {
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    /// A mesh file that does not parse; `line` is 1-based where the format has lines.
    #[error("{path}{}: {reason}", line.map(|l| format!(":{l}")).unwrap_or_default())]
    Parse {
        path: PathBuf,
        line: Option<usize>,
        reason: String,
    },
    /// A mesh that cannot be written as asked (index out of range, mismatched attribute counts).
    #[error("{path}: cannot write mesh: {reason}")]
    Invalid { path: PathBuf, reason: String },
}

pub type Result<T, E = MeshIoError> = std::result::Result<T, E>;

pub(crate) fn parse_err(path: &Path, line: Option<usize>, reason: impl Into<String>) -> MeshIoError {
    MeshIoError::Parse {
        path: path.to_owned(),
        line,
        reason: reason.into(),
    }
}

/// Reads a triangle mesh by extension: `.obj`, `.ply` or `.glb`.
pub fn load_mesh(path: &Path) -> Result<Mesh> {
    if !path.exists() {
        return Err(pixl_core::CoreError::NotFound { path: path.to_owned() }.into());
    }
    let mesh = match pixl_core::io::extension(path).as_str() {
        "obj" => obj::read_obj(path)?,
        "ply" => ply::read_ply(path)?,
        "glb" => glb::read_glb(path)?,
        _ => {
            return Err(pixl_core::CoreError::UnknownExtension {
                path: path.to_owned(),
                expected: "obj, ply, glb",
            }
            .into())
        }
    };
    check_mesh(&mesh).map_err(|reason| parse_err(path, None, reason))?;
    Ok(mesh)
}

/// Checks attribute counts, index ranges and finiteness; the reason names the first problem.
pub fn check_mesh(mesh: &Mesh) -> std::result::Result<(), String> {
    let n = mesh.positions.len();
    if !mesh.normals.is_empty() && mesh.normals.len() != n {
        return Err(format!("{} normals for {n} positions", mesh.normals.len()));
    }
    if !mesh.uvs.is_empty() && mesh.uvs.len() != n {
        return Err(format!("{} UVs for {n} positions", mesh.uvs.len()));
    }
    if let Some((t, i)) = mesh
        .indices
        .iter()
        .enumerate()
        .find_map(|(t, tri)| tri.iter().find(|i| **i as usize >= n).map(|i| (t, *i)))
    {
        return Err(format!("triangle {t} uses vertex {i} but there are only {n} vertices"));
    }
    let bad = |v: &[f32]| v.iter().any(|c| !c.is_finite());
    if let Some(i) = mesh.positions.iter().position(|p| bad(p)) {
        return Err(format!("vertex {i} has a non-finite position"));
    }
    if let Some(i) = mesh.normals.iter().position(|p| bad(p)) {
        return Err(format!("vertex {i} has a non-finite normal"));
    }
    if let Some(i) = mesh.uvs.iter().position(|p| bad(p)) {
        return Err(format!("vertex {i} has a non-finite UV"));
    }
    Ok(())
}

/// [`check_mesh`] for writers.
pub(crate) fn check_writable(path: &Path, mesh: &Mesh) -> Result<()> {
    check_mesh(mesh).map_err(|reason| MeshIoError::Invalid {
        path: path.to_owned(),
        reason,
    })
}
