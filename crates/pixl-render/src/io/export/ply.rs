//! Binary little-endian PLY: a writer (`x y z [nx ny nz] [s t]` as float, faces as
//! `list uchar uint vertex_indices`) and a reader.
//!
//! The reader accepts `binary_little_endian` and `ascii` PLY 1.0 with any vertex properties of
//! the scalar types (`char uchar short ushort int uint float double` and their `int8 … float64`
//! aliases; unknown ones such as colours are skipped), takes `x y z`, `nx ny nz` and `s t` (or
//! `u v`, `texture_u texture_v`) if present, and fan-triangulates polygons of the `face` element
//! (`vertex_indices` or `vertex_index`). Other elements are skipped if they precede nothing we
//! need or have only scalar properties. `t` is flipped (`v ← 1 − t`), see [`super`].
use super::{check_writable, parse_err, MeshIoError, Result};
use crate::scene::mesh::Mesh;
use pixl_core::CoreError;
use std::path::Path;

/// Writes `mesh` as binary little-endian PLY.
pub fn write_ply(path: &Path, mesh: &Mesh) -> Result<()> {
    check_writable(path, mesh)?;
    let (has_n, has_t) = (!mesh.normals.is_empty(), !mesh.uvs.is_empty());
    let mut header = String::from("ply\nformat binary_little_endian 1.0\ncomment written by pixlrelight\n");
    header.push_str(&format!("element vertex {}\n", mesh.positions.len()));
    header.push_str("property float x\nproperty float y\nproperty float z\n");
    if has_n {
        header.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if has_t {
        header.push_str("property float s\nproperty float t\n");
    }
    header.push_str(&format!(
        "element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        mesh.indices.len()
    ));
    let per_vertex = 4 * (3 + 3 * has_n as usize + 2 * has_t as usize);
    let mut out = Vec::with_capacity(header.len() + mesh.positions.len() * per_vertex + mesh.indices.len() * 13);
    out.extend_from_slice(header.as_bytes());
    for i in 0..mesh.positions.len() {
        let mut put = |v: f32| out.extend_from_slice(&v.to_le_bytes());
        mesh.positions[i].iter().for_each(|v| put(*v));
        if has_n {
            mesh.normals[i].iter().for_each(|v| put(*v));
        }
        if has_t {
            put(mesh.uvs[i][0]);
            put(1.0 - mesh.uvs[i][1]);
        }
    }
    for tri in &mesh.indices {
        out.push(3);
        for i in tri {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    pixl_core::io::atomic_write_bytes(path, &out)?;
    Ok(())
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "char" | "int8" => Self::I8,
            "uchar" | "uint8" => Self::U8,
            "short" | "int16" => Self::I16,
            "ushort" | "uint16" => Self::U16,
            "int" | "int32" => Self::I32,
            "uint" | "uint32" => Self::U32,
            "float" | "float32" => Self::F32,
            "double" | "float64" => Self::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Self::I8 | Self::U8 => 1,
            Self::I16 | Self::U16 => 2,
            Self::I32 | Self::U32 | Self::F32 => 4,
            Self::F64 => 8,
        }
    }
    fn decode(self, b: &[u8]) -> f64 {
        match self {
            Self::I8 => b[0] as i8 as f64,
            Self::U8 => b[0] as f64,
            Self::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Self::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Self::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Self::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Self::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Self::F64 => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
        }
    }
}

#[derive(Clone, Debug)]
enum Prop {
    Scalar(String, Scalar),
    List(String, Scalar, Scalar),
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Prop>,
}

/// Pulls values from the body, binary or ASCII.
enum Body<'a> {
    Binary { b: &'a [u8], i: usize },
    Ascii { tokens: std::str::SplitAsciiWhitespace<'a> },
}

impl Body<'_> {
    fn next(&mut self, t: Scalar) -> std::result::Result<f64, String> {
        match self {
            Body::Binary { b, i } => {
                let n = t.size();
                let bytes = b.get(*i..*i + n).ok_or("file ends early")?;
                *i += n;
                Ok(t.decode(bytes))
            }
            Body::Ascii { tokens } => {
                let tok = tokens.next().ok_or("file ends early")?;
                tok.parse::<f64>().map_err(|_| format!("{tok:?} is not a number"))
            }
        }
    }
}

/// Reads a PLY mesh (see the module docs).
pub fn read_ply(path: &Path) -> Result<Mesh> {
    let bytes = std::fs::read(path).map_err(|e| CoreError::io(path, e))?;
    let err = |line: Option<usize>, r: String| parse_err(path, line, r);
    let end = find(&bytes, b"end_header").ok_or_else(|| err(None, "no end_header".into()))?;
    let body_start = bytes[end..]
        .iter()
        .position(|&c| c == b'\n')
        .map(|p| end + p + 1)
        .unwrap_or(bytes.len());
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| err(None, "header is not text".into()))?;
    let mut lines = header.lines().enumerate();
    if lines.next().map(|(_, l)| l.trim()) != Some("ply") {
        return Err(err(Some(1), "missing the 'ply' magic line".into()));
    }
    let mut ascii = None;
    let mut elements: Vec<Element> = Vec::new();
    for (ln, line) in lines {
        let w: Vec<&str> = line.split_ascii_whitespace().collect();
        let e = |r: &str| err(Some(ln + 1), r.to_string());
        match w.as_slice() {
            [] | ["comment", ..] | ["obj_info", ..] => {}
            ["format", "binary_little_endian", _] => ascii = Some(false),
            ["format", "ascii", _] => ascii = Some(true),
            ["format", f, ..] => {
                return Err(e(&format!(
                    "format {f} is not supported (binary_little_endian or ascii)"
                )))
            }
            ["element", name, count] => {
                let count = count
                    .parse()
                    .map_err(|_| e(&format!("element count {count:?} is not an integer")))?;
                elements.push(Element {
                    name: name.to_string(),
                    count,
                    props: Vec::new(),
                });
            }
            ["property", "list", ct, it, name] => {
                let (Some(ct), Some(it)) = (Scalar::parse(ct), Scalar::parse(it)) else {
                    return Err(e(&format!("unknown list types {ct} {it}")));
                };
                let el = elements.last_mut().ok_or_else(|| e("property before any element"))?;
                el.props.push(Prop::List(name.to_string(), ct, it));
            }
            ["property", t, name] => {
                let t = Scalar::parse(t).ok_or_else(|| e(&format!("unknown property type {t}")))?;
                let el = elements.last_mut().ok_or_else(|| e("property before any element"))?;
                el.props.push(Prop::Scalar(name.to_string(), t));
            }
            _ => return Err(e(&format!("unrecognised header line {line:?}"))),
        }
    }
    let ascii = ascii.ok_or_else(|| err(None, "no format line".into()))?;
    let mut body = if ascii {
        let text = std::str::from_utf8(&bytes[body_start..]).map_err(|_| err(None, "ASCII body is not text".into()))?;
        Body::Ascii {
            tokens: text.split_ascii_whitespace(),
        }
    } else {
        Body::Binary {
            b: &bytes[body_start..],
            i: 0,
        }
    };
    let mut mesh = Mesh::default();
    let mut saw_faces = false;
    for el in &elements {
        let body_err = |r: String| err(None, format!("element {}: {r}", el.name));
        match el.name.as_str() {
            "vertex" => read_vertices(el, &mut body, &mut mesh).map_err(body_err)?,
            "face" => {
                saw_faces = true;
                read_faces(el, &mut body, &mut mesh).map_err(body_err)?
            }
            _ => skip_element(el, &mut body).map_err(body_err)?,
        }
    }
    if !saw_faces || mesh.indices.is_empty() {
        return Err(err(None, "no faces".into()));
    }
    let n = mesh.positions.len();
    if let Some(i) = mesh.indices.iter().flatten().find(|i| **i as usize >= n) {
        return Err(MeshIoError::Parse {
            path: path.to_owned(),
            line: None,
            reason: format!("a face uses vertex {i} but there are only {n} vertices"),
        });
    }
    Ok(mesh)
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

fn read_vertices(el: &Element, body: &mut Body, mesh: &mut Mesh) -> std::result::Result<(), String> {
    let names: Vec<&str> = el
        .props
        .iter()
        .map(|p| match p {
            Prop::Scalar(n, _) | Prop::List(n, _, _) => n.as_str(),
        })
        .collect();
    let pos = |n: &str| names.iter().position(|x| *x == n);
    let (Some(ix), Some(iy), Some(iz)) = (pos("x"), pos("y"), pos("z")) else {
        return Err("vertices need x, y and z".into());
    };
    let normal = match (pos("nx"), pos("ny"), pos("nz")) {
        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
        _ => None,
    };
    let uv = [("s", "t"), ("u", "v"), ("texture_u", "texture_v")]
        .iter()
        .find_map(|(a, b)| Some([pos(a)?, pos(b)?]));
    let mut vals = vec![0.0f64; el.props.len()];
    for _ in 0..el.count {
        for (k, p) in el.props.iter().enumerate() {
            match p {
                Prop::Scalar(_, t) => vals[k] = body.next(*t)?,
                Prop::List(_, ct, it) => {
                    let n = body.next(*ct)? as usize;
                    for _ in 0..n {
                        body.next(*it)?;
                    }
                }
            }
        }
        let f = |i: usize| vals[i] as f32;
        mesh.positions.push([f(ix), f(iy), f(iz)]);
        if let Some([a, b, c]) = normal {
            mesh.normals.push([f(a), f(b), f(c)]);
        }
        if let Some([a, b]) = uv {
            mesh.uvs.push([f(a), 1.0 - f(b)]);
        }
    }
    Ok(())
}

fn read_faces(el: &Element, body: &mut Body, mesh: &mut Mesh) -> std::result::Result<(), String> {
    let target = el
        .props
        .iter()
        .position(|p| matches!(p, Prop::List(n, _, _) if n == "vertex_indices" || n == "vertex_index"));
    let Some(target) = target else {
        return Err("faces need a vertex_indices list".into());
    };
    let mut poly: Vec<u32> = Vec::new();
    for _ in 0..el.count {
        for (k, p) in el.props.iter().enumerate() {
            match p {
                Prop::Scalar(_, t) => {
                    body.next(*t)?;
                }
                Prop::List(_, ct, it) => {
                    let n = body.next(*ct)?;
                    if !(0.0..=1e6).contains(&n) {
                        return Err(format!("face with {n} corners"));
                    }
                    poly.clear();
                    for _ in 0..n as usize {
                        let i = body.next(*it)?;
                        if !(0.0..=u32::MAX as f64).contains(&i) || i.fract() != 0.0 {
                            return Err(format!("vertex index {i} is not a valid index"));
                        }
                        poly.push(i as u32);
                    }
                    if k == target {
                        if poly.len() < 3 {
                            return Err(format!("face with {} corners", poly.len()));
                        }
                        for j in 1..poly.len() - 1 {
                            mesh.indices.push([poly[0], poly[j], poly[j + 1]]);
                        }
                    }
                }
            }
        }
    }
    Ok(())
}

fn skip_element(el: &Element, body: &mut Body) -> std::result::Result<(), String> {
    for _ in 0..el.count {
        for p in &el.props {
            match p {
                Prop::Scalar(_, t) => {
                    body.next(*t)?;
                }
                Prop::List(_, ct, it) => {
                    let n = body.next(*ct)? as usize;
                    for _ in 0..n {
                        body.next(*it)?;
                    }
                }
            }
        }
    }
    Ok(())
}
