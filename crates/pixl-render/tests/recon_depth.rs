//! Depth → mesh: unprojection against hand-derived values, a plane stays a plane with nothing
//! cut, a step is cut exactly along the step, and the `.npy` parser on hand-built bytes.
use pixl_render::depth::{
    depth_to_mesh, parse_npy, read_depth, DepthError, DepthMap, Intrinsics, MeshOptions, NpyDtype,
};

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * (1.0 + b.abs())
}

#[test]
fn unprojects_centre_and_corner_by_hand() {
    // 4x2 image, vertical FOV 90°: f = (H/2)/tan(45°) = 1 px.
    let k = Intrinsics::from_vfov_deg(4, 2, 90.0).unwrap();
    assert!(close(k.focal_px, 1.0, 1e-12));
    assert!(close(k.vfov_deg(), 90.0, 1e-12));
    // The image centre (2, 1) is on the optical axis.
    assert_eq!(k.unproject(2.0, 1.0, 3.0), [0.0, 0.0, -3.0]);
    // Pixel (0, 0)'s centre is (0.5, 0.5): 1.5 px left of and 0.5 px above the centre.
    // At depth 2: X = -1.5 * 2 / 1 = -3, Y = +0.5 * 2 / 1 = +1, Z = -2.
    let p = k.unproject(0.5, 0.5, 2.0);
    assert!(
        close(p[0], -3.0, 1e-12) && close(p[1], 1.0, 1e-12) && close(p[2], -2.0, 1e-12),
        "{p:?}"
    );
    // Focal-length form: f = 10 px, pixel (9, 0) of 10x4 at depth 5 → ((9.5-5)*5/10, (2-0.5)*5/10, -5).
    let k = Intrinsics::from_focal_px(10, 4, 10.0).unwrap();
    let p = k.unproject(9.5, 0.5, 5.0);
    assert!(
        close(p[0], 2.25, 1e-12) && close(p[1], 0.75, 1e-12) && p[2] == -5.0,
        "{p:?}"
    );
    assert!(Intrinsics::from_vfov_deg(4, 4, 0.0).is_err());
    assert!(Intrinsics::from_vfov_deg(4, 4, f64::NAN).is_err());
    assert!(Intrinsics::from_focal_px(4, 4, -1.0).is_err());
}

/// A tilted plane `n·p = c` rendered as z-depth: d(x, y) = c / (n · ray(x, y)) with ray(z) = -1.
fn plane_depth(w: usize, h: usize, k: &Intrinsics, n: [f64; 3], c: f64) -> DepthMap {
    let mut data = Vec::new();
    for y in 0..h {
        for x in 0..w {
            let r = k.unproject(x as f64 + 0.5, y as f64 + 0.5, 1.0);
            data.push((c / (n[0] * r[0] + n[1] * r[1] + n[2] * r[2])) as f32);
        }
    }
    DepthMap::new(w, h, data).unwrap()
}

#[test]
fn plane_gives_a_planar_uncut_mesh() {
    let (w, h) = (13, 9);
    let k = Intrinsics::from_vfov_deg(w, h, 50.0).unwrap();
    // Plane facing the camera, tilted: normal (0.2, 0.3, 1) normalised, at distance 2.
    let n0 = [0.2f64, 0.3, 1.0];
    let l = (n0[0] * n0[0] + n0[1] * n0[1] + n0[2] * n0[2]).sqrt();
    let n = n0.map(|v| v / l);
    let c = -2.0;
    let depth = plane_depth(w, h, &k, n, c);
    // The tilt makes depth vary by a few percent per pixel at most; allow it.
    let mesh = depth_to_mesh(
        &depth,
        &k,
        None,
        &MeshOptions {
            max_jump: 0.2,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(mesh.num_triangles(), 2 * (w - 1) * (h - 1));
    assert_eq!(mesh.positions.len(), w * h);
    for p in &mesh.positions {
        let d = n[0] * p[0] as f64 + n[1] * p[1] as f64 + n[2] * p[2] as f64;
        assert!(((d - c) / c).abs() < 1e-5, "point {p:?} off the plane: {d} vs {c}");
    }
    // Every triangle faces the camera (its normal has n·(-p) > 0) and agrees with the plane normal.
    for t in &mesh.indices {
        let [a, b, cc] = t.map(|i| mesh.positions[i as usize].map(f64::from));
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [cc[0] - a[0], cc[1] - a[1], cc[2] - a[2]];
        let fnrm = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let facing = -(fnrm[0] * a[0] + fnrm[1] * a[1] + fnrm[2] * a[2]);
        assert!(facing > 0.0, "triangle {t:?} faces away from the camera");
        let cos = (fnrm[0] * n[0] + fnrm[1] * n[1] + fnrm[2] * n[2])
            / (fnrm[0] * fnrm[0] + fnrm[1] * fnrm[1] + fnrm[2] * fnrm[2]).sqrt();
        assert!(cos > 0.9999, "face normal off the plane normal: cos {cos}");
    }
    // Vertex normals (computed) equal the plane normal.
    for v in &mesh.normals {
        let cos = v[0] as f64 * n[0] + v[1] as f64 * n[1] + v[2] as f64 * n[2];
        assert!(cos > 0.9999, "{v:?}");
    }
    // UVs: pixel (x, y) ↦ ((x+½)/W, (y+½)/H), v = 0 at the top. Vertices are in row-major order.
    for (i, uv) in mesh.uvs.iter().enumerate() {
        let (x, y) = (i % w, i / w);
        assert!(close(uv[0] as f64, (x as f64 + 0.5) / w as f64, 1e-6));
        assert!(close(uv[1] as f64, (y as f64 + 0.5) / h as f64, 1e-6));
    }
}

#[test]
fn step_is_cut_exactly_along_the_step() {
    // Fronto-parallel: left half (x < 5) at 2 m, right half at 3 m (a 50 % jump).
    let (w, h) = (10, 6);
    let k = Intrinsics::from_vfov_deg(w, h, 60.0).unwrap();
    let data: Vec<f32> = (0..w * h).map(|i| if i % w < 5 { 2.0 } else { 3.0 }).collect();
    let depth = DepthMap::new(w, h, data).unwrap();
    let mesh = depth_to_mesh(&depth, &k, None, &MeshOptions::default()).unwrap();
    // Quads between columns 4 and 5 straddle the step: 2 triangles × (h−1) rows are cut.
    assert_eq!(mesh.num_triangles(), 2 * (w - 1) * (h - 1) - 2 * (h - 1));
    for t in &mesh.indices {
        let z = t.map(|i| mesh.positions[i as usize][2]);
        assert!(
            z.iter().all(|v| *v == z[0]),
            "a kept triangle straddles the step: {z:?}"
        );
    }
    // A threshold above the jump keeps everything.
    let all = depth_to_mesh(
        &depth,
        &k,
        None,
        &MeshOptions {
            max_jump: 0.6,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(all.num_triangles(), 2 * (w - 1) * (h - 1));
}

#[test]
fn invalid_depth_drops_its_triangles_and_stride_keeps_the_border() {
    let (w, h) = (5, 5);
    let k = Intrinsics::from_vfov_deg(w, h, 40.0).unwrap();
    let mut data = vec![1.0f32; w * h];
    data[2 * w + 2] = f32::NAN; // the centre pixel: its 6 adjacent triangles go
    data[0] = -1.0; // corner: 1 triangle (a-c-d of quad 0) plus (a-d-b) uses it too → 2
    let depth = DepthMap::new(w, h, data).unwrap();
    let mesh = depth_to_mesh(&depth, &k, None, &MeshOptions::default()).unwrap();
    assert_eq!(mesh.num_triangles(), 2 * 4 * 4 - 6 - 2);
    assert!(mesh.positions.iter().all(|p| p.iter().all(|c| c.is_finite())));
    // Stride 2 on 5×5 samples columns/rows 0, 2, 4 → 3×3 grid → 8 triangles.
    let depth = DepthMap::new(w, h, vec![1.0; w * h]).unwrap();
    let m2 = depth_to_mesh(
        &depth,
        &k,
        None,
        &MeshOptions {
            stride: 2,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(m2.num_triangles(), 8);
    let (lo, hi) = m2.bounds().unwrap();
    let full = depth_to_mesh(&depth, &k, None, &MeshOptions::default())
        .unwrap()
        .bounds()
        .unwrap();
    assert_eq!((lo, hi), full, "stride must keep the outermost pixel centres");
}

fn npy(descr: &str, fortran: bool, shape: &str, body: &[u8], version: u8) -> Vec<u8> {
    let mut header = format!(
        "{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}",
        if fortran { "True" } else { "False" }
    );
    let pre = if version == 1 { 10 } else { 12 };
    while (pre + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY".to_vec();
    out.push(version);
    out.push(0);
    if version == 1 {
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(body);
    out
}

#[test]
fn npy_parser_reads_hand_built_arrays() {
    let vals = [1.5f32, -2.0, 0.25, 7.0, 8.0, 9.0];
    let body: Vec<u8> = vals.iter().flat_map(|v| v.to_le_bytes()).collect();
    let a = parse_npy(&npy("<f4", false, "(2, 3)", &body, 1)).unwrap();
    assert_eq!((a.dtype, a.shape), (NpyDtype::F32, (2, 3)));
    assert_eq!(a.data, vals.map(f64::from).to_vec());
    let body: Vec<u8> = [0.1f64, 0.2].iter().flat_map(|v| v.to_le_bytes()).collect();
    let a = parse_npy(&npy("<f8", false, "(1, 2, 1)", &body, 2)).unwrap();
    assert_eq!((a.dtype, a.shape, a.data), (NpyDtype::F64, (1, 2), vec![0.1, 0.2]));
    let body: Vec<u8> = [1000u16, 0, 65535, 3].iter().flat_map(|v| v.to_le_bytes()).collect();
    let a = parse_npy(&npy("<u2", false, "(2,2)", &body, 3)).unwrap();
    assert_eq!((a.dtype, a.data), (NpyDtype::U16, vec![1000.0, 0.0, 65535.0, 3.0]));
}

#[test]
fn npy_parser_rejects_malformed_input() {
    let body = vec![0u8; 24];
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (b"NUMPY\x01\x00\x00\x00".to_vec(), "magic"),
        (npy(">f4", false, "(2, 3)", &body, 1), "big-endian"),
        (npy("<i8", false, "(3,)", &body, 1), "not supported"),
        (npy("<f4", true, "(2, 3)", &body, 1), "Fortran"),
        (npy("<f4", false, "(24,)", &body, 1), "not 2-D"),
        (npy("<f4", false, "(2, 2)", &body, 1), "needs 16 data bytes"),
        (npy("<f4", false, "(2, x)", &body, 1), "malformed"),
        (npy("<f4", false, "(2, 3", &body, 1), "malformed"),
    ];
    for (bytes, want) in cases {
        let e = parse_npy(&bytes).unwrap_err();
        assert!(e.contains(want), "expected {want:?} in {e:?}");
    }
    // Header length pointing past the end of the file.
    let mut b = npy("<f4", false, "(2, 3)", &body, 1);
    b[8] = 0xff;
    b[9] = 0xff;
    b.truncate(40);
    assert!(parse_npy(&b).unwrap_err().contains("header announces"));
    // Unknown key.
    let bad = b"\x93NUMPY\x01\x00\x10\x00{'descrx': 1}  \n".to_vec();
    assert!(parse_npy(&bad).is_err());
}

#[test]
fn depth_files_read_in_metres() {
    let dir = tempfile::tempdir().unwrap();
    // npy uint16 uses the depth scale; 0 means missing.
    let body: Vec<u8> = [1500u16, 0, 2000, 2500].iter().flat_map(|v| v.to_le_bytes()).collect();
    let p = dir.path().join("d.npy");
    std::fs::write(&p, npy("<u2", false, "(2, 2)", &body, 1)).unwrap();
    let d = read_depth(&p, 0.001).unwrap();
    assert_eq!((d.width, d.height), (2, 2));
    assert!(close(d.data[0] as f64, 1.5, 1e-6) && d.data[1] == 0.0 && close(d.data[3] as f64, 2.5, 1e-6));
    // 16-bit PNG: raw × scale.
    let p = dir.path().join("d.png");
    let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(2, 1, vec![1234, 40000]).unwrap();
    img.save(&p).unwrap();
    let d = read_depth(&p, 0.0005).unwrap();
    assert!(
        close(d.data[0] as f64, 0.617, 1e-6) && close(d.data[1] as f64, 20.0, 1e-6),
        "{:?}",
        d.data
    );
    // 8-bit PNG refused.
    let p8 = dir.path().join("d8.png");
    image::GrayImage::from_raw(2, 1, vec![1, 2]).unwrap().save(&p8).unwrap();
    assert!(matches!(read_depth(&p8, 0.001), Err(DepthError::Format { .. })));
    // EXR: a Blender-style depth channel among others.
    let p = dir.path().join("d.exr");
    let mut ch = pixl_core::exrio::ExrChannels::new(2, 1);
    ch.push("ViewLayer.Combined.R", vec![9.0, 9.0]).unwrap();
    ch.push("ViewLayer.Depth.Z", vec![4.0, 1e10]).unwrap();
    pixl_core::exrio::write_exr_channels(&p, &ch).unwrap();
    let d = read_depth(&p, 1.0).unwrap();
    assert_eq!(d.data, vec![4.0, 1e10]);
    assert_eq!(d.count_valid(MeshOptions::default().max_depth), 1);
    // Missing file and unknown extension name the file.
    let e = read_depth(&dir.path().join("nope.exr"), 1.0).unwrap_err().to_string();
    assert!(e.contains("nope.exr"), "{e}");
    let e = read_depth(&dir.path().join("d.npy").with_extension("txt"), 1.0)
        .unwrap_err()
        .to_string();
    assert!(e.contains("d.txt"), "{e}");
}

/// `full_frame` moves the outermost vertices from the border pixels' centres to the image
/// edges: a constant-depth map then spans exactly the frustum's cross-section at that depth.
#[test]
fn full_frame_mesh_reaches_the_image_edges() {
    let (w, h, d) = (4usize, 3usize, 2.0f32);
    let k = Intrinsics::from_focal_px(w, h, 5.0).unwrap();
    let depth = DepthMap::new(w, h, vec![d; w * h]).unwrap();
    let extent = |full_frame: bool| {
        let m = depth_to_mesh(
            &depth,
            &k,
            None,
            &MeshOptions {
                full_frame,
                ..Default::default()
            },
        )
        .unwrap();
        let xs = m.positions.iter().map(|p| p[0]);
        let ys = m.positions.iter().map(|p| p[1]);
        (
            xs.clone().fold(f32::INFINITY, f32::min),
            xs.fold(f32::NEG_INFINITY, f32::max),
            ys.clone().fold(f32::INFINITY, f32::min),
            ys.fold(f32::NEG_INFINITY, f32::max),
            m.num_triangles(),
        )
    };
    // Half-width at depth d: (w/2)·d/f; with pixel centres, half a pixel less.
    let (hx, hy) = (w as f32 / 2.0 * d / 5.0, h as f32 / 2.0 * d / 5.0);
    let (px, py) = ((w as f32 / 2.0 - 0.5) * d / 5.0, (h as f32 / 2.0 - 0.5) * d / 5.0);
    let close = |a: f32, b: f32| (a - b).abs() < 1e-6;
    let (x0, x1, y0, y1, n) = extent(true);
    assert!(
        close(x0, -hx) && close(x1, hx) && close(y0, -hy) && close(y1, hy),
        "{x0} {x1} {y0} {y1}"
    );
    let (x0, x1, y0, y1, n_centres) = extent(false);
    assert!(
        close(x0, -px) && close(x1, px) && close(y0, -py) && close(y1, py),
        "{x0} {x1} {y0} {y1}"
    );
    assert_eq!(n, n_centres);
    assert_eq!(n, 2 * (w - 1) * (h - 1));
}
