//! glTF 2.0 binary (`.glb`): a writer for one textured mesh and a reader for triangle meshes.
//!
//! # Writer
//! One scene → one node → one mesh → one primitive (`mode` 4, triangles) with `POSITION`,
//! `NORMAL` (if any), `TEXCOORD_0` (if any) as `FLOAT` accessors and `u32` indices, and one
//! metallic-roughness material whose base colour texture (if any) is embedded as PNG in the
//! binary chunk. Layout: 12-byte header (`glTF`, version 2, total length), a `JSON` chunk padded
//! with spaces and a `BIN` chunk padded with zeros to 4 bytes; every buffer view starts on a
//! 4-byte boundary. `POSITION` carries `min`/`max` as the spec requires. glTF UVs put `v = 0` at
//! the top of the image, as [`Mesh`] does, so UVs are written as they are.
//!
//! # Reader
//! Reads the embedded `BIN` buffer only (no external `uri`s, no sparse accessors, no Draco).
//! Walks the default scene's node tree, applies each node's `matrix` or TRS to positions and its
//! rotation/scale part to normals (renormalised; exact for rotations and uniform scales), and
//! merges every triangle primitive into one [`Mesh`]. Without scenes, meshes are read as they are.
//! Attributes: `FLOAT` positions/normals; `FLOAT` or normalised `UNSIGNED_BYTE/SHORT` UVs;
//! `u8/u16/u32` indices (or none: consecutive triples). If some primitive lacks normals or UVs,
//! the merged mesh drops them.
use super::{check_writable, parse_err, Result};
use crate::scene::mesh::Mesh;
use pixl_core::CoreError;
use serde_json::{json, Value};
use std::path::Path;

const MAGIC: u32 = 0x4654_6C67; // "glTF"
const CHUNK_JSON: u32 = 0x4E4F_534A; // "JSON"
const CHUNK_BIN: u32 = 0x004E_4942; // "BIN\0"
const FLOAT: u64 = 5126;
const U8: u64 = 5121;
const U16: u64 = 5123;
const U32: u64 = 5125;

/// The one material of a written `.glb` (glTF metallic-roughness).
#[derive(Clone, Debug, PartialEq)]
pub struct GlbMaterial {
    pub name: String,
    /// Linear RGBA factor; multiplies the texture.
    pub base_color: [f32; 4],
    /// An encoded PNG to embed as the base colour texture (sRGB, as glTF specifies).
    pub base_color_png: Option<Vec<u8>>,
    pub metallic: f32,
    pub roughness: f32,
}

impl Default for GlbMaterial {
    fn default() -> Self {
        Self {
            name: "material".into(),
            base_color: [1.0; 4],
            base_color_png: None,
            metallic: 0.0,
            roughness: 0.5,
        }
    }
}

fn pad4(v: &mut Vec<u8>, byte: u8) {
    while !v.len().is_multiple_of(4) {
        v.push(byte);
    }
}

/// Encodes `mesh` with `material` as GLB bytes.
pub fn encode_glb(mesh: &Mesh, material: &GlbMaterial) -> std::result::Result<Vec<u8>, String> {
    super::check_mesh(mesh)?;
    if mesh.positions.is_empty() || mesh.indices.is_empty() {
        return Err("a glTF mesh needs at least one triangle".into());
    }
    let mut bin: Vec<u8> = Vec::new();
    let mut views: Vec<Value> = Vec::new();
    let mut push_view = |bin: &mut Vec<u8>, data: &[u8], target: Option<u32>| -> usize {
        pad4(bin, 0);
        let mut v = json!({ "buffer": 0, "byteOffset": bin.len(), "byteLength": data.len() });
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        bin.extend_from_slice(data);
        views.push(v);
        views.len() - 1
    };
    let f32s = |vals: &mut dyn Iterator<Item = f32>| -> Vec<u8> { vals.flat_map(f32::to_le_bytes).collect() };
    let n = mesh.positions.len();
    let mut accessors: Vec<Value> = Vec::new();
    let mut attributes = serde_json::Map::new();

    let (lo, hi) = mesh.bounds().ok_or("empty mesh")?;
    let v = push_view(
        &mut bin,
        &f32s(&mut mesh.positions.iter().flatten().copied()),
        Some(34962),
    );
    accessors
        .push(json!({ "bufferView": v, "componentType": FLOAT, "count": n, "type": "VEC3", "min": lo, "max": hi }));
    attributes.insert("POSITION".into(), json!(accessors.len() - 1));
    if !mesh.normals.is_empty() {
        let v = push_view(
            &mut bin,
            &f32s(&mut mesh.normals.iter().flatten().copied()),
            Some(34962),
        );
        accessors.push(json!({ "bufferView": v, "componentType": FLOAT, "count": n, "type": "VEC3" }));
        attributes.insert("NORMAL".into(), json!(accessors.len() - 1));
    }
    if !mesh.uvs.is_empty() {
        let v = push_view(&mut bin, &f32s(&mut mesh.uvs.iter().flatten().copied()), Some(34962));
        accessors.push(json!({ "bufferView": v, "componentType": FLOAT, "count": n, "type": "VEC2" }));
        attributes.insert("TEXCOORD_0".into(), json!(accessors.len() - 1));
    }
    let idx: Vec<u8> = mesh.indices.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
    let v = push_view(&mut bin, &idx, Some(34963));
    accessors.push(json!({ "bufferView": v, "componentType": U32, "count": mesh.indices.len() * 3, "type": "SCALAR" }));
    let indices = accessors.len() - 1;

    let mut pbr = json!({
        "baseColorFactor": material.base_color,
        "metallicFactor": material.metallic,
        "roughnessFactor": material.roughness,
    });
    let mut doc = json!({
        "asset": { "version": "2.0", "generator": "pixlrelight" },
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "mesh": 0, "name": "mesh" }],
        "meshes": [{ "name": "mesh", "primitives": [{ "attributes": attributes, "indices": indices, "material": 0, "mode": 4 }] }],
    });
    if let Some(png) = &material.base_color_png {
        let v = push_view(&mut bin, png, None);
        pbr["baseColorTexture"] = json!({ "index": 0, "texCoord": 0 });
        doc["images"] = json!([{ "bufferView": v, "mimeType": "image/png" }]);
        // LINEAR filters, CLAMP_TO_EDGE wrapping: the texture is the photo, not a tile.
        doc["samplers"] = json!([{ "magFilter": 9729, "minFilter": 9729, "wrapS": 33071, "wrapT": 33071 }]);
        doc["textures"] = json!([{ "source": 0, "sampler": 0 }]);
    }
    pad4(&mut bin, 0);
    doc["materials"] = json!([{ "name": material.name, "pbrMetallicRoughness": pbr, "doubleSided": true }]);
    doc["accessors"] = json!(accessors);
    doc["bufferViews"] = json!(views);
    doc["buffers"] = json!([{ "byteLength": bin.len() }]);

    let mut text = serde_json::to_vec(&doc).map_err(|e| e.to_string())?;
    pad4(&mut text, b' ');
    let total = 12 + 8 + text.len() + 8 + bin.len();
    let total32 = u32::try_from(total).map_err(|_| format!("GLB would be {total} bytes, over the 4 GiB limit"))?;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(&MAGIC.to_le_bytes());
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&total32.to_le_bytes());
    out.extend_from_slice(&(text.len() as u32).to_le_bytes());
    out.extend_from_slice(&CHUNK_JSON.to_le_bytes());
    out.extend_from_slice(&text);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(&CHUNK_BIN.to_le_bytes());
    out.extend_from_slice(&bin);
    Ok(out)
}

/// Writes `mesh` with `material` to a `.glb` file.
pub fn write_glb(path: &Path, mesh: &Mesh, material: &GlbMaterial) -> Result<()> {
    check_writable(path, mesh)?;
    let bytes = encode_glb(mesh, material).map_err(|reason| super::MeshIoError::Invalid {
        path: path.to_owned(),
        reason,
    })?;
    pixl_core::io::atomic_write_bytes(path, &bytes)?;
    Ok(())
}

/// The JSON document and binary chunk of a GLB file, after checking the container.
pub fn split_glb(bytes: &[u8]) -> std::result::Result<(Value, &[u8]), String> {
    let u32_at = |i: usize| -> std::result::Result<u32, String> {
        let b = bytes.get(i..i + 4).ok_or("file ends inside a header")?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    };
    if u32_at(0)? != MAGIC {
        return Err("not a GLB file (magic is not 'glTF')".into());
    }
    let version = u32_at(4)?;
    if version != 2 {
        return Err(format!("glTF container version {version} is not supported (2)"));
    }
    let total = u32_at(8)? as usize;
    if total != bytes.len() {
        return Err(format!("header says {total} bytes, file has {}", bytes.len()));
    }
    let json_len = u32_at(12)? as usize;
    if u32_at(16)? != CHUNK_JSON {
        return Err("first chunk is not JSON".into());
    }
    let json_bytes = bytes.get(20..20 + json_len).ok_or("JSON chunk runs past the end")?;
    let doc: Value = serde_json::from_slice(json_bytes).map_err(|e| format!("JSON chunk: {e}"))?;
    let mut bin: &[u8] = &[];
    let next = 20 + json_len;
    if next < bytes.len() {
        let bin_len = u32_at(next)? as usize;
        if u32_at(next + 4)? != CHUNK_BIN {
            return Err("second chunk is not BIN".into());
        }
        bin = bytes
            .get(next + 8..next + 8 + bin_len)
            .ok_or("BIN chunk runs past the end")?;
    }
    Ok((doc, bin))
}

type Mat4 = [[f64; 4]; 4];
const IDENTITY: Mat4 = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
    [0.0, 0.0, 0.0, 1.0],
];

fn mat_mul(a: &Mat4, b: &Mat4) -> Mat4 {
    let mut m = [[0.0; 4]; 4];
    for (r, row) in m.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = (0..4).map(|k| a[r][k] * b[k][c]).sum();
        }
    }
    m
}

/// A node's local matrix (`m[row][col]`) from `matrix` (column-major) or T·R·S.
fn node_matrix(node: &Value) -> Mat4 {
    let nums = |key: &str| -> Option<Vec<f64>> { node.get(key)?.as_array()?.iter().map(Value::as_f64).collect() };
    if let Some(m) = nums("matrix").filter(|m| m.len() == 16) {
        let mut out = [[0.0; 4]; 4];
        for (c, col) in m.chunks_exact(4).enumerate() {
            for (r, v) in col.iter().enumerate() {
                out[r][c] = *v;
            }
        }
        return out;
    }
    let t = nums("translation").filter(|v| v.len() == 3).unwrap_or(vec![0.0; 3]);
    let q = nums("rotation")
        .filter(|v| v.len() == 4)
        .unwrap_or(vec![0.0, 0.0, 0.0, 1.0]);
    let s = nums("scale").filter(|v| v.len() == 3).unwrap_or(vec![1.0; 3]);
    let (x, y, z, w) = (q[0], q[1], q[2], q[3]);
    let r = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    let mut m = IDENTITY;
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = r[i][j] * s[j];
        }
        m[i][3] = t[i];
    }
    m
}

struct Reader<'a> {
    doc: &'a Value,
    bin: &'a [u8],
}

impl Reader<'_> {
    fn get<'v>(&self, v: &'v Value, key: &str) -> std::result::Result<&'v Value, String> {
        v.get(key).ok_or_else(|| format!("missing '{key}'"))
    }

    fn index(&self, v: &Value, key: &str) -> std::result::Result<usize, String> {
        self.get(v, key)?
            .as_u64()
            .map(|i| i as usize)
            .ok_or_else(|| format!("'{key}' is not an index"))
    }

    /// Reads accessor `a` as rows of `width` `f64`s.
    fn accessor(&self, a: usize) -> std::result::Result<Vec<Vec<f64>>, String> {
        let acc = self.doc["accessors"]
            .get(a)
            .ok_or_else(|| format!("accessor {a} does not exist"))?;
        if acc.get("sparse").is_some() {
            return Err(format!("accessor {a} is sparse (not supported)"));
        }
        let count = self.index(acc, "count")?;
        let ct = self.get(acc, "componentType")?.as_u64().unwrap_or(0);
        let width = match self.get(acc, "type")?.as_str().unwrap_or("") {
            "SCALAR" => 1,
            "VEC2" => 2,
            "VEC3" => 3,
            "VEC4" => 4,
            t => return Err(format!("accessor {a} has type {t:?} (expected SCALAR or VEC2-4)")),
        };
        let normalized = acc.get("normalized").and_then(Value::as_bool).unwrap_or(false);
        let size = match ct {
            FLOAT | U32 => 4,
            U16 => 2,
            U8 => 1,
            c => return Err(format!("accessor {a} has component type {c} (not supported)")),
        };
        let view_id = self.index(acc, "bufferView")?;
        let view = self.doc["bufferViews"]
            .get(view_id)
            .ok_or_else(|| format!("bufferView {view_id} does not exist"))?;
        if self.index(view, "buffer")? != 0 {
            return Err("only the GLB's own buffer 0 is supported".into());
        }
        if self.doc["buffers"].get(0).and_then(|b| b.get("uri")).is_some() {
            return Err("buffer 0 refers to an external file (not supported)".into());
        }
        let view_off = view.get("byteOffset").and_then(Value::as_u64).unwrap_or(0) as usize;
        let view_len = self.index(view, "byteLength")?;
        let acc_off = acc.get("byteOffset").and_then(Value::as_u64).unwrap_or(0) as usize;
        let stride = view
            .get("byteStride")
            .and_then(Value::as_u64)
            .map(|s| s as usize)
            .unwrap_or(size * width);
        let data = self
            .bin
            .get(view_off..view_off.saturating_add(view_len))
            .ok_or_else(|| format!("bufferView {view_id} runs past the binary chunk"))?;
        let mut rows = Vec::with_capacity(count);
        for i in 0..count {
            let start = acc_off + i * stride;
            let b = data
                .get(start..start + size * width)
                .ok_or_else(|| format!("accessor {a} runs past its bufferView"))?;
            let row = b
                .chunks_exact(size)
                .map(|c| match ct {
                    FLOAT => f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
                    U32 => u32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64,
                    U16 => {
                        let v = u16::from_le_bytes([c[0], c[1]]) as f64;
                        if normalized {
                            v / 65535.0
                        } else {
                            v
                        }
                    }
                    _ => {
                        if normalized {
                            c[0] as f64 / 255.0
                        } else {
                            c[0] as f64
                        }
                    }
                })
                .collect();
            rows.push(row);
        }
        Ok(rows)
    }

    fn append_mesh(&self, mesh_id: usize, m: &Mat4, parts: &mut Vec<Mesh>) -> std::result::Result<(), String> {
        let mesh = self.doc["meshes"]
            .get(mesh_id)
            .ok_or_else(|| format!("mesh {mesh_id} does not exist"))?;
        let prims = self
            .get(mesh, "primitives")?
            .as_array()
            .ok_or("'primitives' is not a list")?;
        for prim in prims {
            if prim.get("mode").and_then(Value::as_u64).unwrap_or(4) != 4 {
                continue;
            }
            let attrs = self.get(prim, "attributes")?;
            let pos = self.accessor(self.index(attrs, "POSITION")?)?;
            let mut part = Mesh::default();
            // Identity transforms copy values bit-exactly (no −0.0, no renormalisation drift).
            let identity = *m == IDENTITY;
            for p in &pos {
                let p3 = [p[0], p.get(1).copied().unwrap_or(0.0), p.get(2).copied().unwrap_or(0.0)];
                part.positions.push(std::array::from_fn(|r| {
                    if identity {
                        p3[r] as f32
                    } else {
                        (m[r][0] * p3[0] + m[r][1] * p3[1] + m[r][2] * p3[2] + m[r][3]) as f32
                    }
                }));
            }
            if let Some(i) = attrs.get("NORMAL").and_then(Value::as_u64) {
                for n in self.accessor(i as usize)? {
                    if identity {
                        part.normals
                            .push(std::array::from_fn(|r| n.get(r).copied().unwrap_or(0.0) as f32));
                        continue;
                    }
                    let v: [f64; 3] = std::array::from_fn(|r| {
                        m[r][0] * n[0]
                            + m[r][1] * n.get(1).copied().unwrap_or(0.0)
                            + m[r][2] * n.get(2).copied().unwrap_or(0.0)
                    });
                    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-30);
                    part.normals.push(v.map(|c| (c / l) as f32));
                }
            }
            if let Some(i) = attrs.get("TEXCOORD_0").and_then(Value::as_u64) {
                part.uvs = self
                    .accessor(i as usize)?
                    .iter()
                    .map(|t| [t[0] as f32, t.get(1).copied().unwrap_or(0.0) as f32])
                    .collect();
            }
            let flat: Vec<u32> = match prim.get("indices").and_then(Value::as_u64) {
                Some(i) => self.accessor(i as usize)?.iter().map(|r| r[0] as u32).collect(),
                None => (0..pos.len() as u32).collect(),
            };
            if !flat.len().is_multiple_of(3) {
                return Err(format!("mesh {mesh_id}: {} indices is not a multiple of 3", flat.len()));
            }
            part.indices = flat.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            super::check_mesh(&part).map_err(|e| format!("mesh {mesh_id}: {e}"))?;
            parts.push(part);
        }
        Ok(())
    }

    fn walk(
        &self,
        node_id: usize,
        parent: &Mat4,
        depth: usize,
        parts: &mut Vec<Mesh>,
    ) -> std::result::Result<(), String> {
        if depth > 64 {
            return Err("node hierarchy deeper than 64 (a cycle?)".into());
        }
        let node = self.doc["nodes"]
            .get(node_id)
            .ok_or_else(|| format!("node {node_id} does not exist"))?;
        let m = mat_mul(parent, &node_matrix(node));
        if let Some(mesh) = node.get("mesh").and_then(Value::as_u64) {
            self.append_mesh(mesh as usize, &m, parts)?;
        }
        for c in node.get("children").and_then(Value::as_array).into_iter().flatten() {
            self.walk(
                c.as_u64().ok_or("child is not an index")? as usize,
                &m,
                depth + 1,
                parts,
            )?;
        }
        Ok(())
    }
}

/// Merges parts into one mesh; attributes some part lacks are dropped.
fn merge(parts: Vec<Mesh>) -> Mesh {
    let keep_n = parts.iter().all(|p| !p.normals.is_empty());
    let keep_t = parts.iter().all(|p| !p.uvs.is_empty());
    let mut out = Mesh::default();
    for p in parts {
        let base = out.positions.len() as u32;
        out.positions.extend(p.positions);
        if keep_n {
            out.normals.extend(p.normals);
        }
        if keep_t {
            out.uvs.extend(p.uvs);
        }
        out.indices.extend(p.indices.iter().map(|t| t.map(|i| i + base)));
    }
    out
}

/// Decodes GLB bytes into one triangle mesh (see the module docs).
pub fn decode_glb(bytes: &[u8]) -> std::result::Result<Mesh, String> {
    let (doc, bin) = split_glb(bytes)?;
    let r = Reader { doc: &doc, bin };
    let mut parts = Vec::new();
    let scene = doc.get("scene").and_then(Value::as_u64).unwrap_or(0) as usize;
    match doc.get("scenes").and_then(|s| s.get(scene)) {
        Some(s) => {
            for n in s.get("nodes").and_then(Value::as_array).into_iter().flatten() {
                r.walk(
                    n.as_u64().ok_or("scene node is not an index")? as usize,
                    &IDENTITY,
                    0,
                    &mut parts,
                )?;
            }
        }
        None => {
            let count = doc.get("meshes").and_then(Value::as_array).map_or(0, Vec::len);
            for m in 0..count {
                r.append_mesh(m, &IDENTITY, &mut parts)?;
            }
        }
    }
    let mesh = merge(parts);
    if mesh.indices.is_empty() {
        return Err("no triangles".into());
    }
    Ok(mesh)
}

/// Reads a `.glb` file into one triangle mesh.
pub fn read_glb(path: &Path) -> Result<Mesh> {
    let bytes = std::fs::read(path).map_err(|e| CoreError::io(path, e))?;
    decode_glb(&bytes).map_err(|r| parse_err(path, None, r))
}
