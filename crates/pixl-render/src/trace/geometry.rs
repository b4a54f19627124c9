//! Scene geometry for the tracer: every object (mesh file or primitive) turned into world-space
//! triangles with shading normals, UVs and a material, in one BVH.
//!
//! Primitives (before the object transform): `sphere` is a UV sphere of 96 × 48 segments with
//! analytic smooth normals; `cuboid` has flat faces and outward normals; `quad` lies in the XY
//! plane facing +Z with UV `(0, 0)` at its `(−x, +y)` corner. Normals are transformed by the
//! inverse transpose of the object matrix.
use crate::error::{RenderError, Result};
use crate::math::V3;
use crate::scene::mesh::Mesh;
use crate::scene::{Scene, Shape};
use crate::trace::bvh::{Bvh, Hit, Ray, RayPack, Tri};
use crate::trace::material::glass_albedo::GlassTables;
use crate::trace::material::Coat;
use crate::trace::texture::Texture;
use rayon::prelude::*;
use std::f32::consts::PI;

/// Per-triangle shading data, in BVH order.
#[derive(Clone, Copy, Debug)]
pub struct TriAttr {
    pub n: [V3; 3],
    pub uv: [[f32; 2]; 3],
    /// Unit geometric normal (`e1 × e2`).
    pub ng: V3,
    pub area: f32,
    pub material: u32,
    /// Index into the light list if the triangle is emissive, else `u32::MAX`.
    pub light: u32,
}

/// A material resolved for rendering: constants plus optional textures.
#[derive(Clone, Debug)]
pub struct MaterialData {
    pub base: V3,
    pub base_tex: Option<Texture>,
    pub roughness: f32,
    pub roughness_tex: Option<Texture>,
    pub metallic: f32,
    pub metallic_tex: Option<Texture>,
    /// Tangent-space normal map ([`Geometry::mapped_normal`]).
    pub normal_tex: Option<Texture>,
    pub transmission: f32,
    pub ior: f32,
    pub emission: V3,
    /// The dielectric specular coat, from the scene material's IOR and specular IOR level: must
    /// be `Coat::new(ior, level)` ([`resolve_material`] builds it; rebuild it if `ior` changes).
    pub coat: Coat,
    /// Albedo tables of the rough glass's energy compensation, for materials that can have
    /// rough glass (transmission, roughness and an IOR above 1): [`GlassTables::new`] of `ior`.
    pub glass: Option<std::sync::Arc<GlassTables>>,
}

pub struct Geometry {
    pub tris: Vec<Tri>,
    pub attrs: Vec<TriAttr>,
    pub materials: Vec<MaterialData>,
    pub bvh: Bvh,
    pub lo: V3,
    pub hi: V3,
}

/// The surface at a hit point.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceHit {
    pub p: V3,
    /// Geometric normal (unit, not flipped).
    pub ng: V3,
    /// Interpolated shading normal (unit, not flipped).
    pub ns: V3,
    pub uv: [f32; 2],
    pub prim: u32,
    pub t: f32,
}

/// The tessellated mesh of one object shape, in object space.
pub fn shape_mesh(scene: &Scene, shape: &Shape) -> Result<Mesh> {
    Ok(match shape {
        // A mesh the scene holds in memory first, else the file.
        Shape::Mesh { path } => match scene.assets.meshes.get(path) {
            Some(m) => (**m).clone(),
            None => {
                let full = scene.resolve(path);
                crate::io::export::load_mesh(&full).map_err(|e| RenderError::Invalid {
                    path: full.clone(),
                    message: e.to_string(),
                })?
            }
        },
        Shape::Sphere { radius } => uv_sphere(*radius, 96, 48),
        Shape::Cuboid { size } => cuboid(*size),
        Shape::Quad { size } => quad(*size),
        Shape::Cylinder { radius, height } => cylinder(*radius, *height, 96),
    })
}

/// A closed cylinder along Y, centred on the origin: `segs` side quads with smooth normals
/// (u around, v down the side), and two flat caps with their own vertices (planar UVs).
fn cylinder(r: f32, h: f32, segs: usize) -> Mesh {
    let mut m = Mesh::default();
    let hy = 0.5 * h;
    let ring = |i: usize| {
        // The seam's last column repeats the first one's positions bit for bit (no crack).
        let phi = 2.0 * PI * (i % segs) as f32 / segs as f32;
        (phi.cos(), phi.sin())
    };
    for i in 0..=segs {
        let (c, s) = ring(i);
        let n = [c, 0.0, -s];
        for (y, v) in [(hy, 0.0), (-hy, 1.0)] {
            m.positions.push([r * n[0], y, r * n[2]]);
            m.normals.push(n);
            m.uvs.push([i as f32 / segs as f32, v]);
        }
    }
    for i in 0..segs as u32 {
        let (top, bot) = (2 * i, 2 * i + 1);
        // Counter-clockwise seen from outside: φ grows counter-clockwise seen from +Y.
        m.indices.push([top, bot, bot + 2]);
        m.indices.push([top, bot + 2, top + 2]);
    }
    for (y, ny) in [(hy, 1.0f32), (-hy, -1.0)] {
        let centre = m.positions.len() as u32;
        m.positions.push([0.0, y, 0.0]);
        m.normals.push([0.0, ny, 0.0]);
        m.uvs.push([0.5, 0.5]);
        for i in 0..segs {
            let (c, s) = ring(i);
            m.positions.push([r * c, y, -r * s]);
            m.normals.push([0.0, ny, 0.0]);
            m.uvs.push([0.5 + 0.5 * c, 0.5 - 0.5 * ny * s]);
        }
        for i in 0..segs as u32 {
            let (a, b) = (centre + 1 + i, centre + 1 + (i + 1) % segs as u32);
            m.indices.push(if ny > 0.0 { [centre, a, b] } else { [centre, b, a] });
        }
    }
    m
}

fn uv_sphere(r: f32, segs: usize, rings: usize) -> Mesh {
    let mut m = Mesh::default();
    for j in 0..=rings {
        let theta = PI * j as f32 / rings as f32;
        for i in 0..=segs {
            let phi = 2.0 * PI * i as f32 / segs as f32;
            let n = [theta.sin() * phi.cos(), theta.cos(), -theta.sin() * phi.sin()];
            m.positions.push([n[0] * r, n[1] * r, n[2] * r]);
            m.normals.push(n);
            m.uvs.push([i as f32 / segs as f32, j as f32 / rings as f32]);
        }
    }
    let row = segs as u32 + 1;
    for j in 0..rings as u32 {
        for i in 0..segs as u32 {
            let a = j * row + i;
            let b = a + row;
            if j != 0 {
                m.indices.push([a, b, a + 1]);
            }
            if j != rings as u32 - 1 {
                m.indices.push([a + 1, b, b + 1]);
            }
        }
    }
    m
}

fn cuboid(size: [f32; 3]) -> Mesh {
    let h = size.map(|s| 0.5 * s);
    let mut m = Mesh::default();
    // (normal axis, sign): each face as 4 corners counter-clockwise seen from outside.
    for axis in 0..3 {
        for sign in [1.0f32, -1.0] {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let base = m.positions.len() as u32;
            let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)];
            for (cu, cv) in corners {
                let mut p = [0.0; 3];
                p[axis] = sign * h[axis];
                p[u] = cu * h[u];
                p[v] = cv * h[v] * sign;
                let mut n = [0.0; 3];
                n[axis] = sign;
                m.positions.push(p);
                m.normals.push(n);
                m.uvs.push([0.5 * (cu + 1.0), 0.5 * (1.0 - cv)]);
            }
            m.indices.push([base, base + 1, base + 2]);
            m.indices.push([base, base + 2, base + 3]);
        }
    }
    m
}

fn quad(size: [f32; 2]) -> Mesh {
    let (hx, hy) = (0.5 * size[0], 0.5 * size[1]);
    Mesh {
        positions: vec![[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]],
        normals: vec![[0.0, 0.0, 1.0]; 4],
        uvs: vec![[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]],
        indices: vec![[0, 1, 2], [0, 2, 3]],
    }
}

fn mat_apply(m: &[[f32; 4]; 4], p: [f32; 3]) -> V3 {
    V3::new(
        m[0][0] * p[0] + m[0][1] * p[1] + m[0][2] * p[2] + m[0][3],
        m[1][0] * p[0] + m[1][1] * p[1] + m[1][2] * p[2] + m[1][3],
        m[2][0] * p[0] + m[2][1] * p[1] + m[2][2] * p[2] + m[2][3],
    )
}

/// Inverse transpose of the upper 3×3 (cofactor matrix; the scale does not matter for normals).
fn normal_matrix(m: &[[f32; 4]; 4]) -> [[f32; 3]; 3] {
    let a = |i: usize, j: usize| m[i][j];
    let mut c = [[0.0; 3]; 3];
    for (i, row) in c.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let (i1, i2) = ((i + 1) % 3, (i + 2) % 3);
            let (j1, j2) = ((j + 1) % 3, (j + 2) % 3);
            *v = a(i1, j1) * a(i2, j2) - a(i1, j2) * a(i2, j1);
        }
    }
    c
}

/// The resolved material of an object (textures loaded).
pub fn resolve_material(scene: &Scene, m: &crate::scene::Material) -> Result<MaterialData> {
    // An image the scene holds in memory first, else the file.
    let load = |p: &Option<std::path::PathBuf>, color: bool| -> Result<Option<Texture>> {
        let Some(p) = p else { return Ok(None) };
        if let Some(img) = scene.assets.images.get(p) {
            return Ok(Some(if color {
                Texture::color(img, pixl_core::io::extension(p) != "exr")
            } else {
                Texture::scalar(img)
            }));
        }
        let full = scene.resolve(p);
        Ok(Some(if color {
            Texture::load_color(&full)?
        } else {
            Texture::load_scalar(&full)?
        }))
    };
    Ok(MaterialData {
        base: V3::from_arr(m.base_color.rgb()),
        base_tex: load(&m.base_color_texture, true)?,
        roughness: m.roughness,
        roughness_tex: load(&m.roughness_texture, false)?,
        metallic: m.metallic,
        metallic_tex: load(&m.metallic_texture, false)?,
        normal_tex: match &m.normal_texture {
            Some(p) => Some(match scene.assets.images.get(p) {
                Some(img) => Texture::data(img),
                None => Texture::load_data(&scene.resolve(p))?,
            }),
            None => None,
        },
        transmission: m.transmission,
        ior: m.ior,
        emission: V3::from_arr(m.emission_color.rgb()) * m.emission_strength,
        coat: Coat::new(m.ior, m.specular_ior_level),
        glass: (m.transmission > 0.0 && m.metallic < 1.0 && m.roughness > 0.0 && m.ior > 1.001)
            .then(|| std::sync::Arc::new(GlassTables::new(m.ior))),
    })
}

impl Geometry {
    /// Builds world-space triangles and the BVH for every object in the scene.
    pub fn build(scene: &Scene) -> Result<Geometry> {
        let mut tris = Vec::new();
        let mut attrs = Vec::new();
        let mut materials = Vec::new();
        for obj in &scene.objects {
            let mesh = shape_mesh(scene, &obj.shape)?;
            let mi = materials.len() as u32;
            materials.push(resolve_material(scene, &obj.material)?);
            let m = obj.transform.to_matrix();
            let nm = normal_matrix(&m);
            let pos: Vec<V3> = mesh.positions.iter().map(|p| mat_apply(&m, *p)).collect();
            let nrm: Vec<V3> = mesh
                .normals
                .iter()
                .map(|n| {
                    V3::new(
                        nm[0][0] * n[0] + nm[0][1] * n[1] + nm[0][2] * n[2],
                        nm[1][0] * n[0] + nm[1][1] * n[1] + nm[1][2] * n[2],
                        nm[2][0] * n[0] + nm[2][1] * n[1] + nm[2][2] * n[2],
                    )
                    .normalize()
                })
                .collect();
            let nv = pos.len();
            for (k, ix) in mesh.indices.iter().enumerate() {
                if ix.iter().any(|&i| i as usize >= nv) {
                    return Err(RenderError::Options(format!(
                        "object {:?}: triangle {k} indexes vertex {:?} of {nv}",
                        obj.name, ix
                    )));
                }
                let [a, b, c] = ix.map(|i| pos[i as usize]);
                let (e1, e2) = (b - a, c - a);
                let cr = e1.cross(e2);
                let area = 0.5 * cr.length();
                if !(area > 0.0 && area.is_finite()) {
                    continue; // degenerate triangle: invisible, skip
                }
                let ng = cr.normalize();
                let n = if nrm.len() == nv {
                    ix.map(|i| nrm[i as usize])
                } else {
                    [ng; 3]
                };
                let uv = if mesh.uvs.len() == nv {
                    ix.map(|i| mesh.uvs[i as usize])
                } else {
                    [[0.0, 0.0]; 3]
                };
                tris.push(Tri { p0: a, p1: b, p2: c });
                attrs.push(TriAttr {
                    n,
                    uv,
                    ng,
                    area,
                    material: mi,
                    light: u32::MAX,
                });
            }
        }
        let (bvh, perm) = Bvh::build(&tris);
        let tris: Vec<Tri> = perm.par_iter().map(|&i| tris[i as usize]).collect();
        let attrs: Vec<TriAttr> = perm.par_iter().map(|&i| attrs[i as usize]).collect();
        let mut lo = V3::splat(f32::INFINITY);
        let mut hi = V3::splat(f32::NEG_INFINITY);
        for t in &tris {
            for p in [t.p0, t.p1, t.p2] {
                lo = lo.min(p);
                hi = hi.max(p);
            }
        }
        if tris.is_empty() {
            lo = V3::ZERO;
            hi = V3::ZERO;
        }
        Ok(Geometry {
            tris,
            attrs,
            materials,
            bvh,
            lo,
            hi,
        })
    }

    /// Closest surface along `ray` in `(tmin, tmax)`.
    pub fn intersect(&self, ray: &Ray, tmin: f32, tmax: f32) -> Option<SurfaceHit> {
        self.bvh.intersect(ray, tmin, tmax).map(|h| self.surface(h))
    }

    /// [`Geometry::intersect`] for each of `rays` (far limits `tmax`), into `out`, sharing BVH
    /// traversals between the rays (see [`Bvh::intersect_packet`]): for coherent rays such as
    /// the samples of one pixel. Pairs beyond the shortest slice are not traced.
    pub fn intersect_packet(&self, rays: &[Ray], tmin: f32, tmax: &[f32], out: &mut [Option<SurfaceHit>]) {
        for ((rays, tmax), out) in rays
            .chunks(crate::trace::bvh::PACKET)
            .zip(tmax.chunks(crate::trace::bvh::PACKET))
            .zip(out.chunks_mut(crate::trace::bvh::PACKET))
        {
            let mut p = RayPack::empty();
            let mut act = 0u32;
            for (r, ((ray, &tm), _)) in rays.iter().zip(tmax).zip(out.iter()).enumerate() {
                p.set(r, ray, tm);
                act |= 1 << r;
            }
            self.intersect_pack(&mut p, act, tmin, |r, h| out[r] = h);
        }
    }

    /// The closest hits of the lanes of `p` in `act` (see [`Bvh::intersect_pack`]), each
    /// passed with its lane to `out` as a [`SurfaceHit`] (lanes without a hit: `None`).
    #[inline(always)]
    #[allow(clippy::manual_map)] // see below
    pub fn intersect_pack(&self, p: &mut RayPack, act: u32, tmin: f32, mut out: impl FnMut(usize, Option<SurfaceHit>)) {
        self.bvh.intersect_pack(p, act, tmin);
        // Start loading every hit's attributes before using the first (they are scattered over
        // a large array: each is a likely cache miss).
        for r in 0..crate::trace::bvh::PACKET {
            if act >> r & 1 != 0 {
                if let Some(h) = p.hit(r) {
                    self.prefetch_attrs(h.prim);
                }
            }
        }
        for r in 0..crate::trace::bvh::PACKET {
            if act >> r & 1 != 0 {
                // A `match`, not `map` with a closure: the closure was compiled out of line,
                // outside the integrator's vector-feature kernels.
                out(
                    r,
                    match p.hit(r) {
                        Some(h) => Some(self.surface(h)),
                        None => None,
                    },
                );
            }
        }
    }

    /// Hints the CPU to load the attributes of triangle `prim` (no effect if out of range):
    /// the cache lines of its first and last byte.
    #[inline(always)]
    fn prefetch_attrs(&self, prim: u32) {
        if let Some(a) = self.attrs.get(prim as usize) {
            let p: *const u8 = (a as *const TriAttr).cast();
            crate::math::prefetch(p);
            crate::math::prefetch(p.wrapping_add(std::mem::size_of::<TriAttr>() - 1));
        }
    }

    /// The shading data at a BVH hit.
    #[inline(always)]
    fn surface(&self, hit: Hit) -> SurfaceHit {
        let Hit { t, b1, b2, prim, p } = hit;
        let a = &self.attrs[prim as usize];
        let b0 = 1.0 - b1 - b2;
        let mut ns = (a.n[0] * b0 + a.n[1] * b1 + a.n[2] * b2).normalize();
        if !ns.is_finite() || ns.is_zero() {
            ns = a.ng;
        }
        let uv = [
            a.uv[0][0] * b0 + a.uv[1][0] * b1 + a.uv[2][0] * b2,
            a.uv[0][1] * b0 + a.uv[1][1] * b1 + a.uv[2][1] * b2,
        ];
        SurfaceHit {
            p,
            ng: a.ng,
            ns,
            uv,
            prim,
            t,
        }
    }

    /// `hit` with its shading normal bent by the material's normal map (Blender's Normal Map
    /// node, tangent space, strength 1; see [`crate::scene::Material::normal_texture`]): the
    /// tangent is the triangle's `∂p/∂u` and the bitangent `±N × T`, its sign that of Blender's
    /// `∂p/∂v` (our `−∂p/∂v`, as `v` is flipped), as MikkTSpace gives for a triangle on its
    /// own. Unchanged without a map, or where the triangle's UVs are degenerate.
    #[inline(always)]
    pub fn mapped_normal(&self, m: &MaterialData, hit: SurfaceHit) -> SurfaceHit {
        match &m.normal_tex {
            None => hit,
            Some(tex) => self.bend_normal(tex, hit),
        }
    }

    #[inline(never)]
    fn bend_normal(&self, tex: &Texture, hit: SurfaceHit) -> SurfaceHit {
        let (tri, a) = (&self.tris[hit.prim as usize], &self.attrs[hit.prim as usize]);
        let (dp1, dp2) = (tri.p1 - tri.p0, tri.p2 - tri.p0);
        let (du1, dv1) = (a.uv[1][0] - a.uv[0][0], a.uv[1][1] - a.uv[0][1]);
        let (du2, dv2) = (a.uv[2][0] - a.uv[0][0], a.uv[2][1] - a.uv[0][1]);
        let det = du1 * dv2 - du2 * dv1;
        if !(det.abs() > 1e-12) {
            return hit;
        }
        let dpdu = (dp1 * dv2 - dp2 * dv1) / det;
        let dpdv = (dp2 * du1 - dp1 * du2) / det;
        let n = hit.ns;
        let t = (dpdu - n * n.dot(dpdu)).normalize();
        let b = n.cross(t);
        if !(t.is_finite() && b.is_finite()) {
            return hit;
        }
        // Blender's v grows towards the texture's top row: along −∂p/∂v here.
        let b = if b.dot(dpdv) > 0.0 { -b } else { b };
        let c = tex.sample(hit.uv[0], hit.uv[1]) * 2.0 - V3::ONE;
        let mapped = (t * c.x + b * c.y + n * c.z).normalize();
        if !mapped.is_finite() || mapped.is_zero() {
            return hit;
        }
        SurfaceHit { ns: mapped, ..hit }
    }

    pub fn occluded(&self, ray: &Ray, tmin: f32, tmax: f32) -> bool {
        self.bvh.occluded(ray, tmin, tmax)
    }

    /// Centre and radius of a sphere bounding the geometry.
    pub fn bounding_sphere(&self) -> (V3, f32) {
        let c = (self.lo + self.hi) * 0.5;
        (c, ((self.hi - self.lo) * 0.5).length().max(1e-3))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_core::Rng;

    /// The cylinder is closed and outward-facing: every directed edge (by position) is met by
    /// its reverse exactly once, and the divergence-theorem volume equals the prism's
    /// `h · (n/2) r² sin(2π/n)` computed here in f64; the side normals are radial, caps ±Y.
    #[test]
    fn cylinder_is_closed_and_has_the_prism_volume() {
        let (r, h, n) = (0.7f32, 1.3f32, 24usize);
        let m = cylinder(r, h, n);
        let key = |i: u32| m.positions[i as usize].map(f32::to_bits);
        let mut edges = std::collections::HashMap::new();
        for t in &m.indices {
            for k in 0..3 {
                *edges.entry((key(t[k]), key(t[(k + 1) % 3]))).or_insert(0) += 1;
            }
        }
        for (&(a, b), &count) in &edges {
            assert_eq!(count, 1, "edge used twice in one direction");
            assert_eq!(
                edges.get(&(b, a)),
                Some(&1),
                "edge without its reverse: the mesh has a crack"
            );
        }
        let p = |i: u32| m.positions[i as usize].map(f64::from);
        let volume: f64 = m
            .indices
            .iter()
            .map(|t| {
                let (a, b, c) = (p(t[0]), p(t[1]), p(t[2]));
                let cross = [
                    b[1] * c[2] - b[2] * c[1],
                    b[2] * c[0] - b[0] * c[2],
                    b[0] * c[1] - b[1] * c[0],
                ];
                (a[0] * cross[0] + a[1] * cross[1] + a[2] * cross[2]) / 6.0
            })
            .sum();
        let (rf, hf, nf) = (r as f64, h as f64, n as f64);
        let want = hf * nf / 2.0 * rf * rf * (2.0 * std::f64::consts::PI / nf).sin();
        assert!((volume - want).abs() < 1e-5 * want, "volume {volume} vs {want}");
        for (q, nrm) in m.positions.iter().zip(&m.normals) {
            if nrm[1] == 0.0 {
                assert!((q[0] / r - nrm[0]).abs() < 1e-6 && (q[2] / r - nrm[2]).abs() < 1e-6);
            } else {
                assert_eq!(q[1], 0.5 * h * nrm[1], "cap normal ±Y on its own cap");
            }
        }
    }

    /// Packet queries (`intersect_packet`, through a `RayPack`) give each ray exactly the
    /// single-ray query's surface, for full and partial packets of coherent and random rays,
    /// rays leaving a triangle, and finite far limits.
    #[test]
    fn packet_surfaces_equal_single_ray_surfaces() {
        let scene = Scene::from_toml_str(
            r#"
            [camera]
            width = 8
            height = 8
            fov_y_deg = 40.0
            [[objects]]
            name = "ball"
            shape = { type = "sphere", radius = 0.7 }
            [[objects]]
            name = "floor"
            shape = { type = "quad", size = [6.0, 6.0] }
            transform = { rotate_deg = [-90.0, 0.0, 0.0], translate = [0.0, -0.7, 0.0] }
            "#,
        )
        .expect("scene");
        let g = Geometry::build(&scene).expect("geometry");
        let mut rng = Rng::new(5);
        let mut hits = 0;
        for k in 0..60 {
            let len: usize = [16, 1, 7, 16 + 5, 40][k % 5];
            let o0 = V3::new(rng.uniform(-2.0, 2.0), rng.uniform(0.5, 2.0), rng.uniform(1.5, 3.0));
            let mut rays = Vec::new();
            let mut tmax = Vec::new();
            for j in 0..len {
                let target = V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 0.5), rng.uniform(-1.0, 1.0));
                let ray = if k % 2 == 0 {
                    Ray::new(o0, (target - o0).normalize())
                } else if j % 3 == 0 && !g.tris.is_empty() {
                    // Leaving a random triangle.
                    let prim = rng.below(g.tris.len()) as u32;
                    let t = &g.tris[prim as usize];
                    let p = t.point(0.25, 0.25);
                    Ray::leaving(prim, p, (target - p).normalize())
                } else {
                    let o = V3::new(rng.uniform(-3.0, 3.0), rng.uniform(-0.5, 3.0), rng.uniform(-3.0, 3.0));
                    Ray::new(o, (target - o).normalize())
                };
                rays.push(ray);
                tmax.push(if j % 4 == 1 {
                    rng.uniform(0.5, 3.0)
                } else {
                    f32::INFINITY
                });
            }
            // `out` one shorter than `rays` (only that many are traced), pre-filled so a miss
            // must overwrite its entry.
            let mut out = vec![None; len.saturating_sub(1)];
            let marker = SurfaceHit {
                p: V3::ZERO,
                ng: V3::ZERO,
                ns: V3::ZERO,
                uv: [9.0, 9.0],
                prim: u32::MAX,
                t: -1.0,
            };
            out.iter_mut().for_each(|o| *o = Some(marker));
            g.intersect_packet(&rays, 0.0, &tmax, &mut out);
            for (j, got) in out.iter().enumerate() {
                let want = g.intersect(&rays[j], 0.0, tmax[j]);
                match (want, got) {
                    (None, None) => {}
                    (Some(w), Some(h)) => {
                        hits += 1;
                        assert_eq!(
                            (w.prim, w.t.to_bits(), w.p, w.ns, w.uv),
                            (h.prim, h.t.to_bits(), h.p, h.ns, h.uv),
                            "packet {k} ray {j}"
                        );
                    }
                    (w, h) => panic!("packet {k} ray {j}: single {w:?} vs packet {h:?}"),
                }
            }
        }
        assert!(hits > 200, "only {hits} hits: the test rays miss the scene");
    }
}
