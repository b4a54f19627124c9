//! Watertightness of every triangle test: rays aimed exactly at the shared edges and vertices
//! of closed convex meshes, from outside and from inside, must hit the surface there — through
//! the scalar test, the BVH's single-ray traversal (four triangles at a time) and the packet
//! kernels of every instruction set this CPU has.
use super::*;
use pixl_core::Rng;

thread_local! {
    /// Calls of the f64 last stage (`refine`), to check that the tests reach it.
    pub(super) static REFINES: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

fn refines() -> usize {
    REFINES.with(|c| c.get())
}

/// A closed convex mesh: shared vertices, faces, outward unit normals (f64), for each vertex
/// its incident faces, and the centroid of the vertices.
struct Closed {
    name: &'static str,
    v: Vec<V3>,
    f: Vec<[u32; 3]>,
    n: Vec<[f64; 3]>,
    vfaces: Vec<Vec<usize>>,
    centre: [f64; 3],
}

fn d3(p: V3) -> [f64; 3] {
    [p.x as f64, p.y as f64, p.z as f64]
}
fn sub3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot3(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross3(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn unit3(a: [f64; 3]) -> [f64; 3] {
    let l = dot3(a, a).sqrt();
    [a[0] / l, a[1] / l, a[2] / l]
}

impl Closed {
    fn new(name: &'static str, v: Vec<V3>, f: Vec<[u32; 3]>) -> Closed {
        let mut c = [0.0; 3];
        for p in &v {
            for a in 0..3 {
                c[a] += d3(*p)[a] / v.len() as f64;
            }
        }
        let mut vfaces = vec![Vec::new(); v.len()];
        let mut edges: std::collections::BTreeMap<(u32, u32), Vec<usize>> = Default::default();
        let mut n = Vec::new();
        for (k, t) in f.iter().enumerate() {
            let [a, b, cc] = t.map(|i| d3(v[i as usize]));
            let mut nn = unit3(cross3(sub3(b, a), sub3(cc, a)));
            if dot3(nn, sub3(a, c)) < 0.0 {
                nn = nn.map(|x| -x);
            }
            n.push(nn);
            for j in 0..3 {
                vfaces[t[j] as usize].push(k);
                let (p, q) = (t[j], t[(j + 1) % 3]);
                edges.entry((p.min(q), p.max(q))).or_default().push(k);
            }
        }
        assert!(edges.values().all(|fs| fs.len() == 2), "{name}: not closed");
        Closed {
            name,
            v,
            f,
            n,
            vfaces,
            centre: c,
        }
    }

    fn tris(&self) -> Vec<Tri> {
        self.f
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| self.v[i as usize]);
                tri_of(a, b, c)
            })
            .collect()
    }

    /// Whether `p` lies inside every face plane by at least `margin`.
    fn inside(&self, p: [f64; 3], margin: f64) -> bool {
        self.f
            .iter()
            .zip(&self.n)
            .all(|(t, n)| dot3(*n, sub3(p, d3(self.v[t[0] as usize]))) < -margin)
    }

    /// Neighbours of vertex `v` (through its faces).
    fn neighbours(&self, v: usize) -> Vec<u32> {
        let mut out: Vec<u32> = self.vfaces[v]
            .iter()
            .flat_map(|&k| self.f[k])
            .filter(|&w| w as usize != v)
            .collect();
        out.sort_unstable();
        out.dedup();
        out
    }
}

/// The triangle with vertices `a`, `b`, `c` (barycentrics `b1`, `b2` of `b` and `c`).
fn tri_of(a: V3, b: V3, c: V3) -> Tri {
    Tri { p0: a, p1: b, p2: c }
}

/// An icosphere: the icosahedron subdivided `levels` times, radius `r`, centred at `c`.
fn icosphere(levels: usize, r: f64, c: [f64; 3]) -> Closed {
    let t = (1.0 + 5f64.sqrt()) / 2.0;
    let mut v: Vec<[f64; 3]> = vec![
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .into_iter()
    .map(unit3)
    .collect();
    let mut f: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut mid = std::collections::HashMap::new();
        let mut nf = Vec::new();
        for t in &f {
            let mut m = [0u32; 3];
            for j in 0..3 {
                let (a, b) = (t[j], t[(j + 1) % 3]);
                m[j] = *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                    let (pa, pb) = (v[a as usize], v[b as usize]);
                    v.push(unit3([pa[0] + pb[0], pa[1] + pb[1], pa[2] + pb[2]]));
                    v.len() as u32 - 1
                });
            }
            nf.extend([[t[0], m[0], m[2]], [t[1], m[1], m[0]], [t[2], m[2], m[1]], m]);
        }
        f = nf;
    }
    let v = v
        .iter()
        .map(|p| {
            V3::new(
                (c[0] + r * p[0]) as f32,
                (c[1] + r * p[1]) as f32,
                (c[2] + r * p[2]) as f32,
            )
        })
        .collect();
    Closed::new("icosphere", v, f)
}

/// An axis-aligned box of half size `h` centred at `c`, each face an `n`×`n` grid of quads
/// split into two triangles (diagonals alternating), grid vertices shared along the seams.
fn grid_cube(n: u32, h: [f64; 3], c: [f64; 3]) -> Closed {
    let mut index = std::collections::HashMap::new();
    let mut v = Vec::new();
    let mut vert = |p: [u32; 3]| -> u32 {
        *index.entry(p).or_insert_with(|| {
            let x = |a: usize| (c[a] + h[a] * (2.0 * p[a] as f64 / n as f64 - 1.0)) as f32;
            v.push(V3::new(x(0), x(1), x(2)));
            v.len() as u32 - 1
        })
    };
    let mut f = Vec::new();
    for axis in 0..3 {
        for side in [0, n] {
            let (u, w) = ((axis + 1) % 3, (axis + 2) % 3);
            for i in 0..n {
                for j in 0..n {
                    let at = |di: u32, dj: u32| {
                        let mut p = [0u32; 3];
                        p[axis] = side;
                        p[u] = i + di;
                        p[w] = j + dj;
                        p
                    };
                    let (a, b, cc, d) = (vert(at(0, 0)), vert(at(1, 0)), vert(at(0, 1)), vert(at(1, 1)));
                    if (i + j) % 2 == 0 {
                        f.extend([[a, b, d], [a, d, cc]]);
                    } else {
                        f.extend([[a, b, cc], [b, d, cc]]);
                    }
                }
            }
        }
    }
    Closed::new("grid cube", v, f)
}

/// A closed prism of `segs` sides (radius `r`, height `h`) in a tilted frame at `c`: long
/// thin side triangles, and caps as fans of `segs` slivers around a centre vertex.
fn sliver_prism(segs: usize, r: f64, h: f64, c: [f64; 3]) -> Closed {
    // An orthonormal frame tilted off every axis.
    let ax = unit3([0.3, 1.0, 0.2]);
    let bx = unit3(cross3(ax, [1.0, 0.0, 0.0]));
    let cx = cross3(ax, bx);
    let at = |x: f64, y: f64, z: f64| {
        V3::new(
            (c[0] + x * bx[0] + y * ax[0] + z * cx[0]) as f32,
            (c[1] + x * bx[1] + y * ax[1] + z * cx[1]) as f32,
            (c[2] + x * bx[2] + y * ax[2] + z * cx[2]) as f32,
        )
    };
    let mut v = Vec::new();
    for ring in 0..2 {
        let y = if ring == 0 { -h / 2.0 } else { h / 2.0 };
        for i in 0..segs {
            let phi = 2.0 * std::f64::consts::PI * i as f64 / segs as f64;
            v.push(at(r * phi.cos(), y, r * phi.sin()));
        }
    }
    let (bot, top) = (v.len() as u32, v.len() as u32 + 1);
    v.push(at(0.0, -h / 2.0, 0.0));
    v.push(at(0.0, h / 2.0, 0.0));
    let s = segs as u32;
    let mut f = Vec::new();
    for i in 0..s {
        let j = (i + 1) % s;
        f.extend([[i, j, s + j], [i, s + j, s + i], [bot, j, i], [top, s + i, s + j]]);
    }
    Closed::new("sliver prism", v, f)
}

/// A ray aimed at a point of the surface, with the distance at which it must hit, the
/// tolerance, and the faces around the point (those of its vertex, or of its edge's two
/// vertices), one of which it must hit.
#[derive(Clone, Debug)]
struct Aim {
    ray: Ray,
    t: f64,
    tol: f64,
    near: Vec<usize>,
}

/// `n` rays in groups of [`PACKET`] (coherent, as one packet) aimed at vertices of `m`, points
/// of their edges and of their faces' opposite edges. Kinds by group: 0 from outside in a
/// random direction, 1 from outside along an axis, 2 from outside nearly parallel to the faces
/// at the target, each as a parallel beam or from one point; 3 from inside from one point, 4
/// from inside along an axis, 5 from inside nearly parallel to the faces.
fn aims(m: &Closed, n: usize, seed: u64) -> Vec<Aim> {
    let mut rng = Rng::new(seed);
    let mut out = Vec::new();
    let mut group = 0usize;
    while out.len() < n {
        let kind = group % 6;
        group += 1;
        let outside = kind < 3;
        let v0 = rng.below(m.v.len());
        // The group's direction (beams) or origin (point sources).
        let dir = |rng: &mut Rng| -> [f64; 3] {
            let random = |rng: &mut Rng| unit3([rng.f64() - 0.5, rng.f64() - 0.5, rng.f64() - 0.5]);
            match kind % 3 {
                1 => {
                    let mut d = [0.0; 3];
                    d[rng.below(3)] = if rng.f32() < 0.5 { -1.0 } else { 1.0 };
                    d
                }
                2 => {
                    // At a small angle to one of the faces at the vertex.
                    let n = m.n[m.vfaces[v0][rng.below(m.vfaces[v0].len())]];
                    let c = 0.002 + 0.028 * rng.f64();
                    let t = unit3(cross3(n, random(rng)));
                    let (s, sg) = ((1.0 - c * c).sqrt(), if outside { -1.0 } else { 1.0 });
                    std::array::from_fn(|a| sg * c * n[a] + s * t[a])
                }
                _ => random(rng),
            }
        };
        // Cosine bounds between the direction and the faces at a target (signed so that the
        // ray enters them from outside, leaves them from inside).
        let (lo, hi) = if kind % 3 == 2 { (0.002, 0.03) } else { (0.05, 1.01) };
        let faces_ok = |faces: &[usize], d: [f64; 3]| -> Option<f64> {
            let mut worst = f64::INFINITY;
            for &k in faces {
                let c = dot3(d, m.n[k]) * if outside { -1.0 } else { 1.0 };
                if c < lo {
                    return None;
                }
                worst = worst.min(c);
            }
            // Nearly parallel: to one face at least.
            (kind % 3 != 2 || worst <= hi).then_some(worst)
        };
        let Some(d0) = (0..200)
            .map(|_| dir(&mut rng))
            .find(|&d| faces_ok(&m.vfaces[v0], d).is_some())
        else {
            continue;
        };
        let beam = !kind.is_multiple_of(3) || rng.f32() < 0.5;
        let scale = 1.0 + dot3(m.centre, m.centre).sqrt();
        let src = if outside {
            let p = d3(m.v[v0]);
            let l = rng.f64() * 3.0 + 0.5;
            [p[0] - d0[0] * l, p[1] - d0[1] * l, p[2] - d0[2] * l]
        } else {
            // A point well inside (some of the way from the centre to the target vertex).
            let p = d3(m.v[v0]);
            let s = 0.2 + 0.6 * rng.f64();
            [
                m.centre[0] + (p[0] - m.centre[0]) * s,
                m.centre[1] + (p[1] - m.centre[1]) * s,
                m.centre[2] + (p[2] - m.centre[2]) * s,
            ]
        };
        let nb = m.neighbours(v0);
        let mut tries = 0;
        let mut made = 0;
        while made < PACKET && tries < 40 * PACKET {
            tries += 1;
            // Target: the vertex, a neighbour, a point of an edge at the vertex, or of the
            // edge opposite it in one of its faces.
            let w = nb[rng.below(nb.len())];
            let (target, near): (V3, Vec<usize>) = match rng.below(4) {
                0 => (m.v[v0], m.vfaces[v0].clone()),
                1 => (m.v[w as usize], m.vfaces[w as usize].clone()),
                k => {
                    let (a, b) = if k == 2 {
                        (v0 as u32, w)
                    } else {
                        let t = m.f[m.vfaces[v0][rng.below(m.vfaces[v0].len())]];
                        let o: Vec<u32> = t.into_iter().filter(|&x| x as usize != v0).collect();
                        (o[0], o[1])
                    };
                    let s = match rng.below(3) {
                        0 => 0.5,
                        _ => rng.f32(),
                    };
                    let (pa, pb) = (m.v[a as usize], m.v[b as usize]);
                    let p = pa * (1.0 - s) + pb * s;
                    let mut near = m.vfaces[a as usize].clone();
                    near.extend(&m.vfaces[b as usize]);
                    (p, near)
                }
            };
            let p = d3(target);
            let (o, d) = if beam {
                let l = if outside {
                    rng.f64() * 3.0 + 0.5
                } else {
                    // Inside along a direction nearly parallel to the surface, the body is
                    // thin behind the target: stay close.
                    (0.02 + 0.3 * rng.f64()) * if kind == 5 { 0.3 } else { 1.0 }
                };
                let o = V3::new(
                    (p[0] - d0[0] * l) as f32,
                    (p[1] - d0[1] * l) as f32,
                    (p[2] - d0[2] * l) as f32,
                );
                (o, V3::new(d0[0] as f32, d0[1] as f32, d0[2] as f32))
            } else {
                let o = V3::new(src[0] as f32, src[1] as f32, src[2] as f32);
                (o, (target - o).normalize())
            };
            let od = d3(o);
            if !outside && !m.inside(od, 1e-5 * scale) {
                continue;
            }
            let dd = d3(d);
            // All faces around the target facing the ray (from outside: so that the target is
            // not near the silhouette, where a ray may rightly pass by; from inside: so that
            // the origin lies inside).
            let Some(cos) = faces_ok(&near, dd) else {
                continue;
            };
            // Outside: the origin must be outside the body (beyond a face at the target).
            let t = dot3(sub3(p, od), dd);
            if !(t > 1e-3) {
                continue;
            }
            // The f32 distance's error grows with the distance to the vertices, the faces'
            // aspect (longest edge² / twice the area) and 1 / cos.
            let (mut long, mut aspect) = (0f64, 0f64);
            for &k in &near {
                let [a, b, c] = m.f[k].map(|i| d3(m.v[i as usize]));
                let l2 = [sub3(b, a), sub3(c, b), sub3(a, c)]
                    .map(|e| dot3(e, e))
                    .into_iter()
                    .fold(0.0, f64::max);
                let cr = cross3(sub3(b, a), sub3(c, a));
                long = long.max(l2.sqrt());
                aspect = aspect.max(l2 / dot3(cr, cr).sqrt());
            }
            let tol = 4e-6 * ((t + long) * aspect.max(1.0) / cos + t);
            out.push(Aim {
                ray: Ray::new(o, d),
                t,
                tol,
                near,
            });
            made += 1;
        }
    }
    out
}

/// Whether a closest hit (distance, face) or none is wrong for `a`.
fn missed(a: &Aim, hit: Option<(f32, usize)>) -> bool {
    match hit {
        Some((t, face)) => (t as f64 - a.t).abs() > a.tol || !a.near.contains(&face),
        None => true,
    }
}

/// Misses of every query path on `m`'s rays: brute force with the scalar test, with the
/// four-triangle test and with each instruction set's packet kernel (every triangle tested),
/// then per instruction set the BVH's single-ray (closest and any hit) and packet (closest and
/// any hit) traversals. Returns `(path, misses, calls of the f64 stage)`.
fn misses(m: &Closed, aims: &[Aim]) -> Vec<(String, usize, usize)> {
    let tris = m.tris();
    let (bvh, perm) = Bvh::build(&tris);
    let face = |h: &Hit| (h.t, perm[h.prim as usize] as usize);
    let mut out = Vec::new();
    let mut bad = 0;
    let r0 = refines();
    for a in aims {
        let mut best: Option<(f32, usize)> = None;
        for (k, t) in tris.iter().enumerate() {
            if let Some((th, _, _)) = intersect_tri(t, &a.ray, 0.0, f32::INFINITY) {
                if best.is_none_or(|b| th < b.0) {
                    best = Some((th, k));
                }
            }
        }
        bad += missed(a, best) as usize;
    }
    out.push(("scalar".to_string(), bad, refines() - r0));
    // The BVH's leaf packets, every triangle once (lane `prim` = BVH order).
    let packets = &bvh.packets;
    let (mut bad, r0) = (0, refines());
    for a in aims {
        let r = RayTri::new(&a.ray);
        let mut best: Option<Hit> = None;
        for pk in packets {
            let tmax = best.map_or(f32::INFINITY, |h| h.t);
            if let Some(h) = intersect_tri4(pk, &r, 0.0, tmax) {
                best = Some(h);
            }
        }
        bad += missed(a, best.as_ref().map(face)) as usize;
    }
    out.push(("four-triangle test".to_string(), bad, refines() - r0));
    for isa in Isa::available() {
        let (mut bad, r0) = (0, refines());
        for chunk in aims.chunks(PACKET) {
            let rays: Vec<Ray> = chunk.iter().map(|a| a.ray).collect();
            let (mut p, act) = RayPack::new(&rays, &vec![f32::INFINITY; rays.len()]);
            for pk in packets {
                for l in 0..4 {
                    let m = tri_lanes_isa(isa, pk, l, &mut p, 0.0, act);
                    p.record(m, pk, l);
                }
            }
            for (r, a) in chunk.iter().enumerate() {
                bad += missed(a, p.hit(r).as_ref().map(face)) as usize;
            }
        }
        out.push((format!("{isa:?} packet kernel"), bad, refines() - r0));
    }
    for isa in Isa::available() {
        let r0 = refines();
        let (mut single, mut single_any) = (0, 0);
        for a in aims {
            let h = bvh.intersect_isa(isa, &a.ray, 0.0, f32::INFINITY);
            single += missed(a, h.as_ref().map(face)) as usize;
            single_any += !bvh.occluded_isa(isa, &a.ray, 0.0, f32::INFINITY) as usize;
        }
        let r1 = refines();
        let (mut packet, mut packet_any) = (0, 0);
        for chunk in aims.chunks(PACKET) {
            let rays: Vec<Ray> = chunk.iter().map(|a| a.ray).collect();
            let tmax = vec![f32::INFINITY; rays.len()];
            let mut got = vec![None; rays.len()];
            bvh.intersect_packet_isa(isa, &rays, 0.0, &tmax, &mut got);
            let mut occ = vec![false; rays.len()];
            bvh.occluded_packet_isa(isa, &rays, 0.0, &tmax, &mut occ);
            for ((a, h), o) in chunk.iter().zip(&got).zip(&occ) {
                packet += missed(a, h.as_ref().map(face)) as usize;
                packet_any += !o as usize;
            }
        }
        let r2 = refines();
        out.push((format!("{isa:?} single"), single, r1 - r0));
        out.push((format!("{isa:?} single any-hit"), single_any, r1 - r0));
        out.push((format!("{isa:?} packet"), packet, r2 - r1));
        out.push((format!("{isa:?} packet any-hit"), packet_any, r2 - r1));
    }
    out
}

/// Every ray aimed at a shared edge or vertex of a closed mesh hits it, from outside and from
/// inside, whichever path answers the query.
#[test]
fn rays_at_shared_edges_and_vertices_never_slip_through() {
    let meshes = [
        icosphere(3, 1.3, [0.37, -0.21, 0.55]),
        grid_cube(12, [1.0, 0.7, 1.3], [0.1, 0.27, -0.33]),
        sliver_prism(500, 1.1, 2.5, [-0.4, 0.15, 0.3]),
    ];
    let mut total = 0;
    let mut report = Vec::new();
    let mut missed = 0;
    let mut refined = std::collections::BTreeMap::<String, usize>::new();
    for (k, m) in meshes.iter().enumerate() {
        let aims = aims(m, 24_000, 100 + k as u64);
        total += aims.len();
        for (path, n, r) in misses(m, &aims) {
            report.push(format!(
                "{}: {path}: {n} of {} rays missed ({r} f64 stages)",
                m.name,
                aims.len()
            ));
            missed += n;
            *refined.entry(path).or_default() += r;
        }
    }
    println!("{}", report.join("\n"));
    assert!(total >= 70_000, "only {total} rays");
    assert!(missed == 0, "rays slipped through:\n{}", report.join("\n"));
    // Rays through vertices and along axes make edge functions of exactly 0: every path must
    // have gone through its f64 stage, or the test does not exercise it.
    for (path, r) in refined {
        assert!(r > 0, "{path}: the f64 stage was never reached");
    }
}

/// An f64 reference for a ray and a triangle, independent of the tests under test: the
/// distance to the triangle's plane, the barycentrics `[b0, b1, b2]` of the point there, and
/// the bounds of the f32 test's errors (barycentrics, distance) from its error model: vertex
/// coordinates relative to the ray rounded in proportion to their distance `R` from the origin,
/// edge functions in proportion to `R · S` (`S` the vertices' largest distance from the ray's
/// line), over twice the area seen along the ray; the distance further in proportion to the
/// spread `Z` of the vertices along the ray. `None` for a ray parallel to the plane.
fn reference(tri: &Tri, ray: &Ray) -> Option<(f64, [f64; 3], f64, f64)> {
    let (o, d) = (d3(ray.o), d3(ray.d));
    let dn = unit3(d);
    let [a, b, c] = [tri.p0, tri.p1, tri.p2].map(d3);
    let (e1, e2) = (sub3(b, a), sub3(c, a));
    let n = cross3(e1, e2);
    let nn = dot3(n, n);
    let denom = dot3(n, d);
    if denom == 0.0 || nn == 0.0 {
        return None;
    }
    let t = dot3(n, sub3(a, o)) / denom;
    let x: [f64; 3] = std::array::from_fn(|k| o[k] + t * d[k]);
    let xa = sub3(x, a);
    let b1 = dot3(cross3(xa, e2), n) / nn;
    let b2 = dot3(cross3(e1, xa), n) / nn;
    let bary = [1.0 - b1 - b2, b1, b2];
    let rel = [a, b, c].map(|v| sub3(v, o));
    let r = rel.iter().map(|v| dot3(*v, *v).sqrt()).fold(0.0, f64::max);
    let along = rel.map(|v| dot3(v, dn));
    let s = rel
        .iter()
        .zip(along)
        .map(|(v, z)| (dot3(*v, *v) - z * z).max(0.0).sqrt())
        .fold(0.0, f64::max);
    let z = along.iter().fold(f64::MIN, |m, &x| m.max(x)) - along.iter().fold(f64::MAX, |m, &x| m.min(x));
    let area2_seen = nn.sqrt() * (denom / (nn.sqrt() * dot3(d, d).sqrt())).abs();
    let eps = f32::EPSILON as f64 / 2.0;
    // Constants 8× and 5× the largest errors seen over the pairs of the test below.
    let db = 16.0 * eps * r * s / area2_seen;
    let dt = 64.0 * eps * (r * s * z / area2_seen + r + t.abs());
    Some((t, bary, db, dt))
}

/// Random rays against random triangles (compact and thin ones; rays from anywhere, along
/// axes, with zero components, nearly parallel to the triangle; random distance windows):
/// the scalar test, the four-triangle test and every packet kernel give the same hits, bit for
/// bit, and those agree with the f64 reference [`reference`] — hit or miss, distance and
/// barycentrics — except within its error bounds of an edge or a window end.
#[test]
fn triangle_tests_agree_with_each_other_and_an_f64_reference() {
    let mut rng = Rng::new(2024);
    let isas = Isa::available();
    let (mut pairs, mut hits, mut banded) = (0usize, 0usize, 0usize);
    for round in 0..12_000 {
        // Four triangles: compact, thin, tiny or large.
        let tris: Vec<Tri> = (0..4)
            .map(|k| {
                let c = V3::new(rng.uniform(-4.0, 4.0), rng.uniform(-4.0, 4.0), rng.uniform(-4.0, 4.0));
                let size = [1.0, 1.0, 0.01, 6.0][(round + k) % 4];
                let mut v = || V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)) * size;
                let (p0, mut p1, p2) = (c + v(), c + v(), c + v());
                if (round + k) % 5 == 1 {
                    // A sliver: p1 close to the line p0–p2.
                    p1 = p0 * 0.3 + p2 * 0.7 + v() * 0.01;
                }
                Tri { p0, p1, p2 }
            })
            .collect();
        let pk = {
            let mut pk = Tri4 {
                p0: [[0.0; 4]; 3],
                p1: [[0.0; 4]; 3],
                p2: [[0.0; 4]; 3],
                prim: [0, 1, 2, 3],
            };
            for (l, t) in tris.iter().enumerate() {
                for a in 0..3 {
                    (pk.p0[a][l], pk.p1[a][l], pk.p2[a][l]) = (t.p0[a], t.p1[a], t.p2[a]);
                }
            }
            pk
        };
        // Sixteen rays, each aimed near one of the triangles.
        let tmin = if round % 3 == 0 { rng.uniform(0.0, 2.0) } else { 0.0 };
        let mut rays = Vec::new();
        let mut tmax = Vec::new();
        for j in 0..PACKET {
            let t = &tris[j % 4];
            let (u, v) = (rng.uniform(-0.2, 1.2), rng.uniform(-0.2, 1.2));
            let aim = t.p0 + (t.p1 - t.p0) * u + (t.p2 - t.p0) * v * (1.0 - u).max(0.0);
            let mut d = match j % 8 {
                0 => {
                    let mut d = V3::ZERO;
                    let a = rng.below(3);
                    let sign = if rng.f32() < 0.5 { -1.0 } else { 1.0 };
                    (d.x, d.y, d.z) = [(sign, 0.0, 0.0), (0.0, sign, 0.0), (0.0, 0.0, sign)][a];
                    d
                }
                1 => {
                    // Nearly parallel to the triangle's plane.
                    let n = t.e1().cross(t.e2()).normalize();
                    let w = V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0));
                    (n.cross(w).normalize() + n * rng.uniform(-0.01, 0.01)).normalize()
                }
                _ => V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)).normalize(),
            };
            if j % 8 == 2 {
                d.y = 0.0;
                d = d.normalize();
            }
            let o = aim - d * rng.uniform(-2.0, 9.0);
            rays.push(Ray::new(o, d));
            tmax.push(if j % 3 == 1 {
                rng.uniform(0.5, 10.0)
            } else {
                f32::INFINITY
            });
        }
        for (j, ray) in rays.iter().enumerate() {
            // Scalar test per triangle against the reference; the closest hit as the
            // four-triangle test must give it (lowest lane among equal distances).
            let mut best: Option<(f32, f32, f32, u32)> = None;
            for (k, t) in tris.iter().enumerate() {
                pairs += 1;
                let got = intersect_tri(t, ray, tmin, tmax[j]);
                if let Some((th, b1, b2)) = got {
                    hits += 1;
                    if best.is_none_or(|b| th < b.0) {
                        best = Some((th, b1, b2, k as u32));
                    }
                }
                let Some((t64, bary, db, dt)) = reference(t, ray) else {
                    assert!(
                        got.is_none(),
                        "round {round} ray {j} tri {k}: hit parallel to the plane"
                    );
                    continue;
                };
                // Inside where the smallest barycentric is positive.
                let inside = bary.iter().fold(f64::MAX, |m, &b| m.min(b));
                let near_end = (t64 - tmin as f64).abs() <= dt || (t64 - tmax[j] as f64).abs() <= dt;
                if inside.abs() <= db || (inside > 0.0 && near_end) {
                    banded += 1;
                    continue;
                }
                let want = inside > 0.0 && t64 > tmin as f64 && t64 < tmax[j] as f64;
                match got {
                    None => assert!(!want, "round {round} ray {j} tri {k}: missed, reference {t64} {bary:?}"),
                    Some((th, b1, b2)) => {
                        assert!(
                            want,
                            "round {round} ray {j} tri {k}: hit {th}, reference {t64} {bary:?}"
                        );
                        assert!(
                            (th as f64 - t64).abs() <= dt,
                            "round {round} ray {j} tri {k}: t {th} vs {t64} ± {dt}"
                        );
                        assert!(
                            (b1 as f64 - bary[1]).abs() <= db && (b2 as f64 - bary[2]).abs() <= db,
                            "round {round} ray {j} tri {k}: ({b1}, {b2}) vs {bary:?} ± {db}"
                        );
                    }
                }
            }
            let bits = |h: Option<Hit>| h.map(|h| (h.t.to_bits(), h.b1.to_bits(), h.b2.to_bits(), h.prim));
            let want = best.map(|(t, b1, b2, k)| (t.to_bits(), b1.to_bits(), b2.to_bits(), k));
            let tri4 = intersect_tri4(&pk, &RayTri::new(ray), tmin, tmax[j]);
            assert_eq!(bits(tri4), want, "round {round} ray {j}: four-triangle test");
            if let Some(h) = tri4 {
                assert_eq!(h.p, tris[h.prim as usize].point(h.b1, h.b2));
            }
        }
        // Each packet kernel, the four triangles in turn as a leaf is tested, on a random
        // subset of the lanes.
        let act = if round % 4 == 0 {
            rng.next_u64() as u32 & PACK_LANES
        } else {
            PACK_LANES
        };
        for &isa in &isas {
            let (mut p, _) = RayPack::new(&rays, &tmax);
            for l in 0..4 {
                let m = tri_lanes_isa(isa, &pk, l, &mut p, tmin, act);
                p.record(m, &pk, l);
            }
            for (j, ray) in rays.iter().enumerate() {
                let tri4 = if act >> j & 1 != 0 {
                    intersect_tri4(&pk, &RayTri::new(ray), tmin, tmax[j])
                } else {
                    None
                };
                let bits = |h: Option<Hit>| h.map(|h| (h.t.to_bits(), h.b1.to_bits(), h.b2.to_bits(), h.prim, h.p));
                assert_eq!(bits(p.hit(j)), bits(tri4), "{isa:?} round {round} ray {j}");
            }
        }
    }
    // Enough hits and few enough pairs near an edge that the comparison means something.
    println!("{pairs} pairs, {hits} hits, {banded} within the error bounds of an edge or a window end");
    assert!(hits > pairs / 16, "{hits} hits of {pairs}");
    assert!(banded < pairs / 50, "{banded} of {pairs} near an edge");
}
