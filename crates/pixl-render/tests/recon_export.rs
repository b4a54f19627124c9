//! Mesh exporters: OBJ and PLY round trips, GLB checked structurally by parsing its container
//! by hand (independently of the crate's reader), then read back through `load_mesh`.
use pixl_render::export::glb::{encode_glb, write_glb, GlbMaterial};
use pixl_render::export::obj::{write_obj, ObjMaterial};
use pixl_render::export::ply::write_ply;
use pixl_render::export::{load_mesh, MeshIoError};
use pixl_render::Mesh;

/// A small irregular mesh: a 4×3 grid with awkward float values and one missing triangle.
fn sample_mesh() -> Mesh {
    let mut m = Mesh::default();
    for y in 0..3 {
        for x in 0..4 {
            let (fx, fy) = (x as f32, y as f32);
            m.positions.push([fx * 0.1 + 1e-7, -fy / 3.0, -2.0 - 0.01 * fx * fy]);
            let n = [0.1 * fx, 0.2, 1.0];
            let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            m.normals.push(n.map(|v| v / l));
            m.uvs.push([(fx + 0.5) / 4.0, (fy + 0.5) / 3.0]);
        }
    }
    for y in 0..2u32 {
        for x in 0..3u32 {
            let a = y * 4 + x;
            if (x, y) != (1, 1) {
                m.indices.push([a, a + 4, a + 5]);
            }
            m.indices.push([a, a + 5, a + 1]);
        }
    }
    m
}

fn assert_same(a: &Mesh, b: &Mesh, what: &str) {
    assert_eq!(a.positions, b.positions, "{what}: positions");
    assert_eq!(a.normals, b.normals, "{what}: normals");
    assert_eq!(a.indices, b.indices, "{what}: indices");
    assert_eq!(a.uvs.len(), b.uvs.len(), "{what}: uv count");
    for (p, q) in a.uvs.iter().zip(&b.uvs) {
        // OBJ/PLY store 1 − v; flipping twice may move v by one ulp.
        assert!(
            (p[0] - q[0]).abs() <= 1e-7 && (p[1] - q[1]).abs() <= 1.2e-7,
            "{what}: uv {p:?} vs {q:?}"
        );
    }
}

#[test]
fn obj_round_trip_is_identical() {
    let dir = tempfile::tempdir().unwrap();
    let m = sample_mesh();
    let p = dir.path().join("m.obj");
    let mat = ObjMaterial {
        texture: Some("albedo.png".into()),
        ..Default::default()
    };
    write_obj(&p, &m, Some(&mat)).unwrap();
    assert_same(&load_mesh(&p).unwrap(), &m, "obj");
    let mtl = std::fs::read_to_string(dir.path().join("m.mtl")).unwrap();
    assert!(mtl.contains("map_Kd albedo.png"), "{mtl}");
    // Without normals and UVs.
    let bare = Mesh {
        normals: vec![],
        uvs: vec![],
        ..m.clone()
    };
    write_obj(&p, &bare, None).unwrap();
    assert_same(&load_mesh(&p).unwrap(), &bare, "obj bare");
}

#[test]
fn obj_reader_welds_mixed_indices_and_fans_polygons() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("q.obj");
    // A quad with separate vt indices (v=1 at the top in OBJ → our v=0) and negative indices.
    let text = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 1\nvn 0 0 1\n\
                f 1/1/1 2/1/1 3/2/1 -1/2/-1\n";
    std::fs::write(&p, text).unwrap();
    let m = load_mesh(&p).unwrap();
    assert_eq!(m.indices, vec![[0, 1, 2], [0, 2, 3]]);
    assert_eq!(
        m.positions,
        vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]
    );
    assert_eq!(m.uvs, vec![[0.0, 1.0], [0.0, 1.0], [1.0, 0.0], [1.0, 0.0]]);
    // Errors carry the line number.
    std::fs::write(&p, "v 0 0 0\nv 1 0 0\nf 1 2 7\n").unwrap();
    let e = load_mesh(&p).unwrap_err().to_string();
    assert!(e.contains("q.obj:3") && e.contains("out of range"), "{e}");
    std::fs::write(&p, "v 0 zero 0\n").unwrap();
    assert!(load_mesh(&p).unwrap_err().to_string().contains("q.obj:1"));
}

#[test]
fn ply_round_trip_is_identical_and_reads_ascii() {
    let dir = tempfile::tempdir().unwrap();
    let m = sample_mesh();
    let p = dir.path().join("m.ply");
    write_ply(&p, &m).unwrap();
    assert_same(&load_mesh(&p).unwrap(), &m, "ply");
    let bare = Mesh {
        normals: vec![],
        uvs: vec![],
        ..m.clone()
    };
    write_ply(&p, &bare).unwrap();
    assert_same(&load_mesh(&p).unwrap(), &bare, "ply bare");
    // ASCII with an extra colour property and a quad.
    let text = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
                property uchar red\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
                0 0 0 255\n1 0 0 0\n1 1 0 0\n0 1 0 9\n4 0 1 2 3\n";
    std::fs::write(&p, text).unwrap();
    let q = load_mesh(&p).unwrap();
    assert_eq!(q.indices, vec![[0, 1, 2], [0, 2, 3]]);
    assert_eq!(q.positions[2], [1.0, 1.0, 0.0]);
    // Truncated binary body.
    write_ply(&p, &m).unwrap();
    let mut bytes = std::fs::read(&p).unwrap();
    bytes.truncate(bytes.len() - 5);
    std::fs::write(&p, bytes).unwrap();
    assert!(matches!(load_mesh(&p), Err(MeshIoError::Parse { .. })));
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes(b[i..i + 4].try_into().unwrap())
}

#[test]
fn glb_is_structurally_valid() {
    let m = sample_mesh();
    let png = {
        let mut buf = std::io::Cursor::new(Vec::new());
        image::RgbImage::from_pixel(3, 2, image::Rgb([200, 100, 50]))
            .write_to(&mut buf, image::ImageFormat::Png)
            .unwrap();
        buf.into_inner()
    };
    let mat = GlbMaterial {
        base_color_png: Some(png.clone()),
        ..Default::default()
    };
    let b = encode_glb(&m, &mat).unwrap();
    // Header.
    assert_eq!(&b[0..4], b"glTF");
    assert_eq!(u32_at(&b, 4), 2);
    assert_eq!(u32_at(&b, 8) as usize, b.len());
    // JSON chunk, 4-aligned, space-padded.
    let jl = u32_at(&b, 12) as usize;
    assert_eq!(jl % 4, 0);
    assert_eq!(&b[16..20], b"JSON");
    let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jl]).unwrap();
    // BIN chunk follows, 4-aligned.
    let bl = u32_at(&b, 20 + jl) as usize;
    assert_eq!(bl % 4, 0);
    assert_eq!(&b[24 + jl..28 + jl], b"BIN\0");
    assert_eq!(28 + jl + bl, b.len());
    let bin = &b[28 + jl..];
    assert_eq!(doc["asset"]["version"], "2.0");
    assert_eq!(doc["buffers"][0]["byteLength"].as_u64().unwrap() as usize, bl);
    let prim = &doc["meshes"][0]["primitives"][0];
    let acc = |name: &str| &doc["accessors"][prim["attributes"][name].as_u64().unwrap() as usize];
    let n = m.positions.len() as u64;
    assert_eq!(acc("POSITION")["count"], n);
    assert_eq!(acc("NORMAL")["count"], n);
    assert_eq!(acc("TEXCOORD_0")["count"], n);
    let idx = &doc["accessors"][prim["indices"].as_u64().unwrap() as usize];
    assert_eq!(idx["count"].as_u64().unwrap() as usize, 3 * m.indices.len());
    assert_eq!(idx["componentType"], 5125);
    // min/max equal the bounds computed here.
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in &m.positions {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let arr = |v: &serde_json::Value| -> Vec<f32> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap() as f32)
            .collect()
    };
    assert_eq!(arr(&acc("POSITION")["min"]), lo.to_vec());
    assert_eq!(arr(&acc("POSITION")["max"]), hi.to_vec());
    // Every buffer view is 4-aligned and inside the chunk; the image view holds our PNG.
    for v in doc["bufferViews"].as_array().unwrap() {
        let off = v["byteOffset"].as_u64().unwrap() as usize;
        let len = v["byteLength"].as_u64().unwrap() as usize;
        assert_eq!(off % 4, 0);
        assert!(off + len <= bl);
    }
    let img_view = &doc["bufferViews"][doc["images"][0]["bufferView"].as_u64().unwrap() as usize];
    let off = img_view["byteOffset"].as_u64().unwrap() as usize;
    assert_eq!(&bin[off..off + png.len()], &png[..]);
    assert_eq!(
        doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"],
        0
    );
    // The position buffer holds the positions as little-endian f32.
    let pv = &doc["bufferViews"][acc("POSITION")["bufferView"].as_u64().unwrap() as usize];
    let off = pv["byteOffset"].as_u64().unwrap() as usize;
    assert_eq!(
        f32::from_le_bytes(bin[off + 4..off + 8].try_into().unwrap()),
        m.positions[0][1]
    );

    // And through the reader (UVs are stored as they are, so the round trip is exact).
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("m.glb");
    write_glb(&p, &m, &mat).unwrap();
    assert_eq!(load_mesh(&p).unwrap(), m);
    // A corrupted length is refused.
    let mut bad = b.clone();
    bad[8] ^= 1;
    std::fs::write(&p, bad).unwrap();
    assert!(load_mesh(&p).unwrap_err().to_string().contains("m.glb"));
}

#[test]
fn writers_refuse_broken_meshes() {
    let dir = tempfile::tempdir().unwrap();
    let mut m = sample_mesh();
    m.indices.push([0, 1, 99]);
    for name in ["a.obj", "a.ply", "a.glb"] {
        let p = dir.path().join(name);
        let r = match name {
            "a.obj" => write_obj(&p, &m, None),
            "a.ply" => write_ply(&p, &m),
            _ => write_glb(&p, &m, &GlbMaterial::default()),
        };
        let e = r.unwrap_err().to_string();
        assert!(e.contains(name) && e.contains("99"), "{e}");
        assert!(!p.exists());
    }
    assert!(load_mesh(&dir.path().join("x.stl")).is_err());
}
