//! Wavefront OBJ + MTL: a writer (`v`/`vt`/`vn`/`f i/i/i`, one material with `map_Kd`) and a
//! reader for the subset scenes need.
//!
//! The reader takes `v`, `vt`, `vn` and `f` lines (corners `v`, `v/vt`, `v//vn`, `v/vt/vn`,
//! 1-based or negative indices); polygons with more than three corners are fan-triangulated;
//! `o`, `g`, `s`, `usemtl`, `mtllib`, `l`, `p` and comments are ignored (one mesh, no materials).
//! Corners are welded by their `(v, vt, vn)` triple; a file whose corners all use the same
//! index for `v`, `vt` and `vn` (what [`write_obj`] writes) keeps its vertex order exactly.
//! If any corner lacks a normal, the mesh gets none (face normals are used); if any lacks a
//! texture coordinate, UVs are dropped as well. `vt` is flipped (`v ← 1 − v`), see [`super`].
use super::{check_writable, parse_err, Result};
use crate::scene::mesh::Mesh;
use pixl_core::CoreError;
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

/// The one material written to the `.mtl` beside an `.obj`.
#[derive(Clone, Debug, PartialEq)]
pub struct ObjMaterial {
    pub name: String,
    /// Linear diffuse colour (`Kd`); multiplies the texture in most readers — keep it white
    /// when a texture is given.
    pub diffuse: [f32; 3],
    /// Texture file name, relative to the `.mtl` (`map_Kd`).
    pub texture: Option<String>,
    /// PBR extension (`Pr`, `Pm`) understood by Blender's importer.
    pub roughness: f32,
    pub metallic: f32,
}

impl Default for ObjMaterial {
    fn default() -> Self {
        Self {
            name: "material".into(),
            diffuse: [0.8; 3],
            texture: None,
            roughness: 0.5,
            metallic: 0.0,
        }
    }
}

/// Writes `mesh` to `path` (`.obj`); with a material, also `path.with_extension("mtl")`.
pub fn write_obj(path: &Path, mesh: &Mesh, material: Option<&ObjMaterial>) -> Result<()> {
    check_writable(path, mesh)?;
    let mut s = String::with_capacity(mesh.positions.len() * 64 + mesh.indices.len() * 32);
    s.push_str("# written by pixlrelight\n");
    if let Some(m) = material {
        let mtl_path = path.with_extension("mtl");
        let mtl_name = mtl_path.file_name().and_then(|n| n.to_str()).unwrap_or("material.mtl");
        let _ = writeln!(s, "mtllib {mtl_name}");
        write_mtl(&mtl_path, m)?;
    }
    for p in &mesh.positions {
        let _ = writeln!(s, "v {} {} {}", p[0], p[1], p[2]);
    }
    for t in &mesh.uvs {
        let _ = writeln!(s, "vt {} {}", t[0], 1.0 - t[1]);
    }
    for n in &mesh.normals {
        let _ = writeln!(s, "vn {} {} {}", n[0], n[1], n[2]);
    }
    if let Some(m) = material {
        let _ = writeln!(s, "usemtl {}", m.name);
    }
    let (has_t, has_n) = (!mesh.uvs.is_empty(), !mesh.normals.is_empty());
    for tri in &mesh.indices {
        s.push('f');
        for &i in tri {
            let i = i + 1;
            let _ = match (has_t, has_n) {
                (true, true) => write!(s, " {i}/{i}/{i}"),
                (true, false) => write!(s, " {i}/{i}"),
                (false, true) => write!(s, " {i}//{i}"),
                (false, false) => write!(s, " {i}"),
            };
        }
        s.push('\n');
    }
    pixl_core::io::atomic_write_bytes(path, s.as_bytes())?;
    Ok(())
}

fn write_mtl(path: &Path, m: &ObjMaterial) -> Result<()> {
    let mut s = String::new();
    let _ = writeln!(s, "# written by pixlrelight\nnewmtl {}", m.name);
    let _ = writeln!(s, "Kd {} {} {}", m.diffuse[0], m.diffuse[1], m.diffuse[2]);
    let _ = writeln!(s, "Ks 0 0 0\nillum 1\nPr {}\nPm {}", m.roughness, m.metallic);
    if let Some(t) = &m.texture {
        let _ = writeln!(s, "map_Kd {t}");
    }
    pixl_core::io::atomic_write_bytes(path, s.as_bytes())?;
    Ok(())
}

/// One face corner: 0-based indices into `v`, `vt`, `vn`.
type Corner = (usize, Option<usize>, Option<usize>);

/// Reads a triangle (or polygon) mesh from an OBJ file (see the module docs).
pub fn read_obj(path: &Path) -> Result<Mesh> {
    let text = std::fs::read_to_string(path).map_err(|e| CoreError::io(path, e))?;
    let mut v: Vec<[f32; 3]> = Vec::new();
    let mut vt: Vec<[f32; 2]> = Vec::new();
    let mut vn: Vec<[f32; 3]> = Vec::new();
    let mut faces: Vec<[Corner; 3]> = Vec::new();
    for (ln, raw) in text.lines().enumerate() {
        let line = raw.split('#').next().unwrap_or("").trim();
        let mut it = line.split_ascii_whitespace();
        let Some(tag) = it.next() else { continue };
        let err = |reason: String| parse_err(path, Some(ln + 1), reason);
        let floats = |it: std::str::SplitAsciiWhitespace, min: usize, max: usize| -> Result<Vec<f32>> {
            let vals: Vec<f32> = it
                .map(|t| {
                    t.parse::<f32>()
                        .map_err(|_| err(format!("{tag}: {t:?} is not a number")))
                })
                .collect::<Result<_>>()?;
            if vals.len() < min || vals.len() > max {
                return Err(err(format!("{tag} needs {min} to {max} numbers, found {}", vals.len())));
            }
            if vals.iter().any(|x| !x.is_finite()) {
                return Err(err(format!("{tag} has a non-finite value")));
            }
            Ok(vals)
        };
        match tag {
            "v" => {
                let f = floats(it, 3, 4)?;
                v.push([f[0], f[1], f[2]]);
            }
            "vt" => {
                let f = floats(it, 1, 3)?;
                vt.push([f[0], 1.0 - f.get(1).copied().unwrap_or(0.0)]);
            }
            "vn" => {
                let f = floats(it, 3, 3)?;
                vn.push([f[0], f[1], f[2]]);
            }
            "f" => {
                let corners: Vec<Corner> = it
                    .map(|c| {
                        parse_corner(c, v.len(), vt.len(), vn.len()).map_err(|r| err(format!("face corner {c:?}: {r}")))
                    })
                    .collect::<Result<_>>()?;
                if corners.len() < 3 {
                    return Err(err(format!("a face needs at least 3 corners, found {}", corners.len())));
                }
                for k in 1..corners.len() - 1 {
                    faces.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            "o" | "g" | "s" | "usemtl" | "mtllib" | "l" | "p" | "vp" => {}
            other => return Err(err(format!("unknown statement {other:?}"))),
        }
    }
    if faces.is_empty() {
        return Err(parse_err(path, None, "no faces"));
    }
    let all = |f: &dyn Fn(&Corner) -> bool| faces.iter().flatten().all(f);
    let keep_t = all(&|c| c.1.is_some());
    let keep_n = all(&|c| c.2.is_some());
    let aligned = all(&|c| c.1.is_none_or(|t| t == c.0) && c.2.is_none_or(|n| n == c.0))
        && (!keep_t || vt.len() == v.len())
        && (!keep_n || vn.len() == v.len());
    let mut mesh = Mesh::default();
    if aligned {
        mesh.positions = v;
        mesh.uvs = if keep_t { vt } else { Vec::new() };
        mesh.normals = if keep_n { vn } else { Vec::new() };
        mesh.indices = faces.iter().map(|f| f.map(|c| c.0 as u32)).collect();
    } else {
        let mut weld: HashMap<(usize, Option<usize>, Option<usize>), u32> = HashMap::new();
        for f in &faces {
            let mut tri = [0u32; 3];
            for (k, &(pi, ti, ni)) in f.iter().enumerate() {
                let key = (pi, ti.filter(|_| keep_t), ni.filter(|_| keep_n));
                let next = mesh.positions.len() as u32;
                let id = *weld.entry(key).or_insert_with(|| {
                    mesh.positions.push(v[pi]);
                    if let Some(t) = key.1 {
                        mesh.uvs.push(vt[t]);
                    }
                    if let Some(n) = key.2 {
                        mesh.normals.push(vn[n]);
                    }
                    next
                });
                tri[k] = id;
            }
            mesh.indices.push(tri);
        }
    }
    Ok(mesh)
}

/// `v`, `v/vt`, `v//vn` or `v/vt/vn`, 1-based or negative (relative to the end).
fn parse_corner(c: &str, nv: usize, nt: usize, nn: usize) -> std::result::Result<Corner, String> {
    let mut parts = c.split('/');
    let idx = |s: &str, n: usize, what: &str| -> std::result::Result<usize, String> {
        let i: i64 = s.parse().map_err(|_| format!("{what} index {s:?} is not an integer"))?;
        let z = if i > 0 { i - 1 } else { n as i64 + i };
        if i == 0 || z < 0 || z >= n as i64 {
            return Err(format!("{what} index {i} is out of range (only {n} defined so far)"));
        }
        Ok(z as usize)
    };
    let p = idx(parts.next().unwrap_or(""), nv, "vertex")?;
    let t = match parts.next() {
        Some("") | None => None,
        Some(s) => Some(idx(s, nt, "texture")?),
    };
    let n = match parts.next() {
        Some("") | None => None,
        Some(s) => Some(idx(s, nn, "normal")?),
    };
    if parts.next().is_some() {
        return Err("too many '/'".into());
    }
    Ok((p, t, n))
}
