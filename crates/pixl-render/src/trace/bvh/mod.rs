//! A bounding-volume hierarchy over triangles for the tracer: a binary binned-SAH build
//! collapsed into a 4-wide tree, with triangles stored in leaf order as 4-wide packets.
//!
//! Contract: [`Bvh::intersect`] returns the closest hit in `(tmin, tmax)` and
//! [`Bvh::occluded`] whether any hit lies there, both as the watertight test [`intersect_tri`]
//! (two-sided) over every triangle but the ray's [`Ray::skip`] would — the four-triangle test
//! and every packet kernel perform the same floating-point operations in the same order per
//! lane, so hit distances and barycentrics are bit-identical to [`intersect_tri`]'s; among
//! triangles hit at exactly the same distance the one reported may differ. [`Hit::prim`]
//! indexes the input slice given to [`Bvh::build`] after reordering with the permutation it
//! returns.
//!
//! The triangle test is watertight (Woop, Benthin and Wald, "Watertight Ray/Triangle
//! Intersection", JCGT 2013): a ray never passes between triangles that share an edge or a
//! vertex — through a shared edge or vertex it hits at least one of them (possibly several, at
//! the same distance up to rounding). Per ray, once per query ([`RayTri`], or a [`RayPack`]'s
//! shear rows): the axis `kz` of the direction's largest component, `kx`, `ky` the next two
//! (cyclically), and the shear `(d[kx] / d[kz], d[ky] / d[kz], 1 / d[kz])`. Per triangle:
//! - the vertices relative to the origin, axes permuted to `(kx, ky, kz)`, x and y sheared so
//!   that the ray becomes the z axis ([`sheared`]);
//! - the 2-D edge functions `U, V, W` (for edges BC, CA, AB; [`edge_fns`]) — a shared edge gives
//!   its two triangles the same value with opposite signs, bit for bit;
//! - a hit needs `U, V, W` all ≥ 0 or all ≤ 0 (two-sided), `det = U + V + W ≠ 0` and
//!   `t = (U·A_z + V·B_z + W·C_z) · S_z / det` in `(tmin, tmax)`; barycentrics `b1 = V / det`
//!   and `b2 = W / det` weight vertices [`Tri::p1`] and [`Tri::p2`], as before;
//! - a hit with an edge function exactly 0 (the ray through an edge or a vertex, or a product
//!   rounded so) is decided again with the edge functions in f64 from the same f32 inputs
//!   ([`refine`]): the products are then exact, so the signs are exact, and they agree with
//!   every non-zero f32 result (rounding is monotonic), which keeps the test watertight on the
//!   edge itself. This stage is rare and out of line.
//!
//! Triangles are stored by their vertices ([`Tri`], [`Tri4`]), not as a vertex and two edges:
//! a vertex rebuilt as `p0 + e1` in f32 differs from the one its neighbour stores, which opens
//! cracks whatever the test. Rays that leave a surface skip the triangle they start on
//! ([`Ray::skip`]) and start exactly there; `tmin` is only the lower end of the window.
//!
//! Layout, chosen by measurement on the ~500 k-triangle depth-mesh benchmark (see
//! BENCHMARKS.md): the tree is shallow and wide (a render is bound by traversal instructions).
//! - Build: binned SAH (12 bins × 3 axes) with a packet-aware cost (`ceil(n/4)` per side),
//!   leaves of at most 4 triangles (one packet); deterministic (ties broken by index, subtrees
//!   built in parallel but laid out in a fixed order), so a scene always gives the same tree.
//!   The build partitions primitive records (box, centroid, index) in place and bins all three
//!   axes in one pass, each side's bounds coming from its parent; large nodes are binned by
//!   parallel chunks and the root's large children collapsed in parallel (the same tree, node
//!   for node, as on one thread: tested).
//! - Nodes: 128-byte, 64-byte-aligned, structure-of-arrays boxes of 4 children, so the four
//!   slab tests are plain lane loops the compiler turns into SIMD on stable Rust (SSE2).
//!   (8-wide nodes, `NW = 8`, measured: 43 % fewer nodes but no faster — shadow
//!   packets 6.4 → 4.3 Mrays/s, single rays unchanged.)
//! - Leaves: [`Tri4`] packets (three vertices per lane, lanes padded with NaN vertices, which
//!   never hit), tested 4 at a time the same way ([`simd4`]: SSE on x86-64).
//! - Traversal: children hit by the ray are visited nearest first (sorted by entry distance)
//!   for closest-hit queries, with entries farther than the current hit skipped when popped;
//!   any-hit queries stop at the first hit and do not sort.
//! - Packets of up to [`PACKET`] rays ([`Bvh::intersect_packet`], [`Bvh::occluded_packet`])
//!   share one traversal: a node is visited while any live lane enters it. On AVX2 CPUs the
//!   kernel is written with intrinsics (`packet_avx2.rs`: a child box or a triangle against 16
//!   lanes in two 8-wide vectors), on AVX-512 CPUs in one 16-wide vector with mask registers
//!   (`packet_avx512.rs`: packets 25–45 % faster, the benchmark render ~4 % on a Zen 5);
//!   elsewhere portable lane loops. Once a node is reached by at
//!   most `FINISH_ALONE` (3) live lanes, each finishes that subtree by single-ray traversal
//!   (cheaper per node than a nearly empty packet). Per lane, results equal the single-ray
//!   query's (same triangle test), up to ties.
//! - `PIXL_ISA=base` in the environment forces the portable code, `PIXL_ISA=avx2` the AVX2
//!   kernels (for A/B measurements; `base` also caps the renderer's pixel loop,
//!   [`crate::trace::integrator::Renderer::render_pixel`]).
//!
//! Why our own rather than a crate: the renderer needs a few hundred lines of BVH, must be
//! deterministic and is tuned to this triangle layout; the crates we looked at (`bvh`, `obvhs`)
//! bring their own vector types or their own ray/primitive traits.
use crate::math::V3;

#[cfg(target_arch = "x86_64")]
mod packet_avx2;
#[cfg(target_arch = "x86_64")]
mod packet_avx512;
#[cfg(target_arch = "x86_64")]
mod packet_simd;
mod simd4;

/// A triangle as stored for intersection: its three vertices (a hit's barycentrics `b1`, `b2`
/// weight `p1` and `p2`). Triangles sharing a vertex must hold it bit for bit (as they do when
/// made from one vertex array): the watertight test relies on it.
#[derive(Clone, Copy, Debug)]
pub struct Tri {
    pub p0: V3,
    pub p1: V3,
    pub p2: V3,
}

impl Tri {
    /// The edge `p1 − p0`.
    #[inline]
    pub fn e1(&self) -> V3 {
        self.p1 - self.p0
    }

    /// The edge `p2 − p0`.
    #[inline]
    pub fn e2(&self) -> V3 {
        self.p2 - self.p0
    }

    /// The point with barycentrics `b1`, `b2`: `p0 + e1·b1 + e2·b2`, as [`Hit::p`] is computed.
    #[inline]
    pub fn point(&self, b1: f32, b2: f32) -> V3 {
        self.p0 + self.e1() * b1 + self.e2() * b2
    }
}

/// A ray with precomputed reciprocal direction, and the primitive it leaves (never hit).
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub o: V3,
    pub d: V3,
    pub inv_d: V3,
    /// The primitive (index as in [`Hit::prim`]) the ray starts on, skipped by every query
    /// (Cycles' self-intersection rule); [`NO_PRIM`] for rays that start in free space.
    pub skip: u32,
}

/// [`Ray::skip`] of a ray that starts on no primitive.
pub const NO_PRIM: u32 = u32::MAX;

/// A ray's constants for the watertight triangle test, made once per query (or per lane of a
/// [`RayPack`]) from its direction `d` and reciprocal `inv_d`: `kz`, the axis of the
/// direction's largest magnitude (the others taken as `kx = kz + 1`, `ky = kz + 2`, mod 3), and
/// the shear `s = (d[kx] / d[kz], d[ky] / d[kz], 1 / d[kz])` (as `d[kx] · inv_d[kz]`, …) that
/// maps the ray onto the `kz` axis.
#[derive(Clone, Copy, Debug)]
struct Shear {
    kz: usize,
    s: [f32; 3],
}

impl Shear {
    #[inline(always)]
    fn new(d: V3, inv_d: V3) -> Shear {
        let (x, y, z) = (d.x.abs(), d.y.abs(), d.z.abs());
        let kz = if x > y && x > z {
            0
        } else if y > z {
            1
        } else {
            2
        };
        let [kx, ky, _] = axes(kz);
        let sz = inv_d[kz];
        Shear {
            kz,
            s: [d[kx] * sz, d[ky] * sz, sz],
        }
    }
}

/// The permuted axes `[kx, ky, kz]` of a ray whose largest direction axis is `kz`.
#[inline(always)]
fn axes(kz: usize) -> [usize; 3] {
    match kz {
        0 => [1, 2, 0],
        1 => [2, 0, 1],
        _ => [0, 1, 2],
    }
}

impl Ray {
    pub fn new(o: V3, d: V3) -> Self {
        Ray {
            o,
            d,
            inv_d: V3::new(1.0 / d.x, 1.0 / d.y, 1.0 / d.z),
            skip: NO_PRIM,
        }
    }

    /// A ray leaving primitive `prim` (which it then never hits) from `o`.
    pub fn leaving(prim: u32, o: V3, d: V3) -> Self {
        Ray {
            skip: prim,
            ..Ray::new(o, d)
        }
    }
}

/// A ray–triangle hit: distance, barycentrics of vertices 1 and 2, primitive index, and the
/// point `p0 + e1·b1 + e2·b2` (computed from the leaf data, saving a fetch of the triangle).
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f32,
    pub b1: f32,
    pub b2: f32,
    pub prim: u32,
    pub p: V3,
}

/// Four triangles, structure of arrays: vertices `p0[axis][lane]`, `p1`, `p2` likewise, and
/// the index of each lane's triangle (`u32::MAX` for padding lanes, whose vertices are NaN:
/// never hit, and never the watertight test's f64 fallback).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct Tri4 {
    p0: [[f32; 4]; 3],
    p1: [[f32; 4]; 3],
    p2: [[f32; 4]; 3],
    prim: [u32; 4],
}

impl Tri4 {
    /// Lane `l`'s triangle.
    #[inline(always)]
    fn tri(&self, l: usize) -> Tri {
        let lane = |a: &[[f32; 4]; 3]| V3::new(a[0][l], a[1][l], a[2][l]);
        Tri {
            p0: lane(&self.p0),
            p1: lane(&self.p1),
            p2: lane(&self.p2),
        }
    }

    /// Lane `l`'s hit point with barycentrics `b1`, `b2`, as [`Tri::point`].
    #[inline(always)]
    fn point(&self, l: usize, b1: f32, b2: f32) -> V3 {
        let lane = |a: &[[f32; 4]; 3]| V3::new(a[0][l], a[1][l], a[2][l]);
        let p0 = lane(&self.p0);
        p0 + (lane(&self.p1) - p0) * b1 + (lane(&self.p2) - p0) * b2
    }
}

/// Children per interior node.
const NW: usize = 4;

/// An `NW`-wide interior node: child boxes as rows `lo_x, lo_y, lo_z, hi_x, hi_y, hi_z` of
/// `NW` lanes, and the children ([`EMPTY`], an interior node index, or [`LEAF`] | packet
/// fields).
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Node {
    b: [[f32; NW]; 6],
    child: [u32; NW],
}

impl Node {
    /// No children: empty boxes (`lo = +∞`, `hi = −∞`) that no ray enters.
    const EMPTY: Node = Node {
        b: [
            [f32::INFINITY; NW],
            [f32::INFINITY; NW],
            [f32::INFINITY; NW],
            [f32::NEG_INFINITY; NW],
            [f32::NEG_INFINITY; NW],
            [f32::NEG_INFINITY; NW],
        ],
        child: [EMPTY; NW],
    };
}

/// Child slot flag: a leaf; bits 28..31 hold the packet count − 1, bits 0..28 the first packet.
const LEAF: u32 = 1 << 31;
const LEAF_COUNT_SHIFT: u32 = 28;
const LEAF_INDEX_MASK: u32 = (1 << LEAF_COUNT_SHIFT) - 1;
/// An unused child slot (its box is empty, so it is never entered).
const EMPTY: u32 = u32::MAX;

#[derive(Clone, Debug, Default)]
pub struct Bvh {
    nodes: Vec<Node>,
    packets: Vec<Tri4>,
}

/// A box as four lanes of `lo` and of `hi` (x, y, z and a spare lane that stays at the empty
/// box's ±∞), so that growing one is a vector min and max.
#[derive(Clone, Copy)]
#[repr(C, align(16))]
struct Aabb {
    lo: [f32; 4],
    hi: [f32; 4],
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        lo: [f32::INFINITY; 4],
        hi: [f32::NEG_INFINITY; 4],
    };
    fn point(p: V3) -> Aabb {
        Aabb {
            lo: [p.x, p.y, p.z, f32::INFINITY],
            hi: [p.x, p.y, p.z, f32::NEG_INFINITY],
        }
    }
    // Plain compare-selects (the inputs are finite): cheaper than `f32::min`'s NaN rules.
    #[inline]
    fn grow(&mut self, o: &Aabb) {
        for i in 0..4 {
            self.lo[i] = if o.lo[i] < self.lo[i] { o.lo[i] } else { self.lo[i] };
            self.hi[i] = if o.hi[i] > self.hi[i] { o.hi[i] } else { self.hi[i] };
        }
    }
    fn grow_p(&mut self, p: V3) {
        self.grow(&Aabb::point(p));
    }
    fn extent(&self) -> V3 {
        V3::new(
            self.hi[0] - self.lo[0],
            self.hi[1] - self.lo[1],
            self.hi[2] - self.lo[2],
        )
    }
    fn area(&self) -> f32 {
        let d = self.extent();
        if d.x < 0.0 {
            return 0.0;
        }
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }
}

const BINS: usize = 12;
/// Triangles per packet and the most in a leaf.
const LANES: usize = 4;
/// Below this many primitives a subtree is built on the current thread.
const PAR_MIN: usize = 8192;
/// From this binary depth on, splits are object medians, so the depth stays below
/// `MEDIAN_DEPTH + log2(n)` whatever the geometry (bounds the traversal stack's use).
const MEDIAN_DEPTH: usize = 40;
/// Traversal stack entries; deeper pushes fall back to recursion (never reached in practice).
const STACK: usize = 40;

/// A node of the temporary binary tree.
struct BNode {
    bb: Aabb,
    /// Primitives in the subtree.
    count: u32,
    /// Leaf: `Some((first, count))` into the permuted primitive order.
    leaf: Option<(u32, u32)>,
    kids: Option<Box<(BNode, BNode)>>,
}

fn packets_of(n: usize) -> f32 {
    n.div_ceil(LANES) as f32
}

/// From this many primitives on, a node's bounds and bins are gathered by parallel chunks.
const PAR_BIN: usize = 1 << 16;

/// A primitive as the build sees it: its box, its centroid and its input index. The build
/// partitions these records themselves (not indices into them), so every pass over a node
/// reads memory in order.
#[derive(Clone, Copy)]
struct Prim {
    bb: Aabb,
    c: V3,
    i: u32,
}

/// The union of the boxes and of the centroids of `prims`.
fn bounds(prims: &[Prim], par: bool) -> (Aabb, Aabb) {
    let one = |prims: &[Prim]| {
        let (mut bb, mut cb) = (Aabb::EMPTY, Aabb::EMPTY);
        for p in prims {
            bb.grow(&p.bb);
            cb.grow_p(p.c);
        }
        (bb, cb)
    };
    by_chunks(prims, par, one, |(mut b0, mut c0), (b1, c1)| {
        b0.grow(&b1);
        c0.grow(&c1);
        (b0, c0)
    })
}

/// `one(prims)`, or with `par` and from [`PAR_BIN`] primitives on, `one` of parallel chunks
/// combined by `merge` (which must be associative, as unions and sums are: the result is the
/// same either way).
fn by_chunks<T: Send>(
    prims: &[Prim],
    par: bool,
    one: impl Fn(&[Prim]) -> T + Sync,
    merge: impl Fn(T, T) -> T + Sync + Send,
) -> T {
    if !par || prims.len() < PAR_BIN {
        return one(prims);
    }
    use rayon::prelude::*;
    prims
        .par_chunks(PAR_BIN / 4)
        .map(&one)
        .reduce_with(merge)
        .unwrap_or_else(|| one(&[]))
}

/// SAH bins of one node on the three axes at once: per axis and bin, the union of the boxes
/// whose centroid falls in it, and their number.
#[derive(Clone, Copy)]
struct Bins {
    bb: [[Aabb; BINS]; 3],
    n: [[u32; BINS]; 3],
}

impl Bins {
    const EMPTY: Bins = Bins {
        bb: [[Aabb::EMPTY; BINS]; 3],
        n: [[0; BINS]; 3],
    };

    fn add(&mut self, prims: &[Prim], bin: &Binning) {
        for p in prims {
            for axis in 0..3 {
                let k = bin.of(axis, p.c[axis]);
                self.bb[axis][k].grow(&p.bb);
                self.n[axis][k] += 1;
            }
        }
    }

    fn merge(mut self, o: &Bins) -> Bins {
        for axis in 0..3 {
            for k in 0..BINS {
                self.bb[axis][k].grow(&o.bb[axis][k]);
                self.n[axis][k] += o.n[axis][k];
            }
        }
        self
    }

    /// The bins of `prims`.
    fn gather(prims: &[Prim], bin: &Binning, par: bool) -> Bins {
        let one = |prims: &[Prim]| {
            let mut b = Bins::EMPTY;
            b.add(prims, bin);
            b
        };
        by_chunks(prims, par, one, |a, b| a.merge(&b))
    }
}

/// Maps a centroid coordinate to its bin, per axis, over a node's centroid bounds.
struct Binning {
    lo: V3,
    scale: V3,
}

impl Binning {
    fn new(cb: &Aabb) -> Binning {
        let s = |a: usize| {
            let ext = cb.hi[a] - cb.lo[a];
            if ext <= 1e-12 {
                0.0
            } else {
                BINS as f32 / ext
            }
        };
        Binning {
            lo: V3::new(cb.lo[0], cb.lo[1], cb.lo[2]),
            scale: V3::new(s(0), s(1), s(2)),
        }
    }

    /// `⌊(c − lo)·scale⌋` clamped to the bins (NaN to 0). Through `i32`, whose saturating
    /// conversion is a few instructions where `usize`'s is a dozen; same result for every input.
    #[inline(always)]
    fn of(&self, axis: usize, c: f32) -> usize {
        (((c - self.lo[axis]) * self.scale[axis]) as i32).clamp(0, BINS as i32 - 1) as usize
    }
}

/// Builds the binary tree over `prims` (reordered in place); `first` is `prims[0]`'s
/// position, `bb` and `cb` the union of their boxes and of their centroids.
fn build_bin(prims: &mut [Prim], first: usize, depth: usize, bb: Aabb, cb: Aabb, par: bool) -> BNode {
    let n = prims.len();
    if n <= LANES {
        return BNode {
            bb,
            count: n as u32,
            leaf: Some((first as u32, n as u32)),
            kids: None,
        };
    }
    // The split position and both sides' bounds, from the binned SAH when it finds a split.
    let mut split = None;
    if depth < MEDIAN_DEPTH {
        // Binned SAH over the three axes (one pass for all three), cost in packets.
        let bin = Binning::new(&cb);
        let bins = Bins::gather(prims, &bin, par);
        let mut best: Option<(usize, usize, f32)> = None;
        for axis in 0..3 {
            if bin.scale[axis] == 0.0 {
                continue;
            }
            let (bb_axis, n_axis) = (&bins.bb[axis], &bins.n[axis]);
            let mut right_area = [0.0f32; BINS];
            let mut right_count = [0usize; BINS];
            let mut acc = Aabb::EMPTY;
            let mut cnt = 0;
            for b in (1..BINS).rev() {
                acc.grow(&bb_axis[b]);
                cnt += n_axis[b] as usize;
                right_area[b] = acc.area();
                right_count[b] = cnt;
            }
            let mut acc = Aabb::EMPTY;
            let mut cnt = 0;
            for b in 0..BINS - 1 {
                acc.grow(&bb_axis[b]);
                cnt += n_axis[b] as usize;
                if cnt == 0 || right_count[b + 1] == 0 {
                    continue;
                }
                let cost = acc.area() * packets_of(cnt) + right_area[b + 1] * packets_of(right_count[b + 1]);
                if best.is_none_or(|(_, _, c)| cost < c) {
                    best = Some((axis, b, cost));
                }
            }
        }
        if let Some((axis, b, _)) = best {
            // Partition by bin; each side's centroid bounds on the way, its box bounds from
            // the bins (both sides are non-empty: the SAH only scores such splits).
            let (mut lcb, mut rcb) = (Aabb::EMPTY, Aabb::EMPTY);
            let mut mid = 0;
            for k in 0..n {
                let c = prims[k].c;
                if bin.of(axis, c[axis]) <= b {
                    prims.swap(k, mid);
                    mid += 1;
                    lcb.grow_p(c);
                } else {
                    rcb.grow_p(c);
                }
            }
            let (mut lbb, mut rbb) = (Aabb::EMPTY, Aabb::EMPTY);
            for (k, kb) in bins.bb[axis].iter().enumerate() {
                if k <= b {
                    lbb.grow(kb);
                } else {
                    rbb.grow(kb);
                }
            }
            split = Some((mid, (lbb, lcb), (rbb, rcb)));
        }
    }
    let (mid, lb, rb) = match split {
        Some(s) => s,
        None => {
            // No usable SAH split (coincident centroids, or past the depth limit): object
            // median along the widest centroid axis, ties by index.
            let ext = cb.extent();
            let axis = if ext.x >= ext.y && ext.x >= ext.z {
                0
            } else if ext.y >= ext.z {
                1
            } else {
                2
            };
            let mid = n / 2;
            prims.select_nth_unstable_by(mid, |a, b| a.c[axis].total_cmp(&b.c[axis]).then(a.i.cmp(&b.i)));
            let (l, r) = prims.split_at(mid);
            (mid, bounds(l, par), bounds(r, par))
        }
    };
    let (left, right) = prims.split_at_mut(mid);
    let (l, r) = if par && n >= PAR_MIN {
        rayon::join(
            || build_bin(left, first, depth + 1, lb.0, lb.1, par),
            || build_bin(right, first + mid, depth + 1, rb.0, rb.1, par),
        )
    } else {
        (
            build_bin(left, first, depth + 1, lb.0, lb.1, par),
            build_bin(right, first + mid, depth + 1, rb.0, rb.1, par),
        )
    };
    BNode {
        bb,
        count: n as u32,
        leaf: None,
        kids: Some(Box::new((l, r))),
    }
}

impl Bvh {
    /// Builds over `tris` and returns the tree and the permutation: position `i` of the
    /// reordered primitives holds original primitive `perm[i]`. Reorder your arrays with it.
    pub fn build(tris: &[Tri]) -> (Bvh, Vec<u32>) {
        Bvh::build_with(tris, true)
    }

    /// [`Bvh::build`], on several threads where it pays (`par`) or on this one: the same
    /// tree, node for node, either way.
    fn build_with(tris: &[Tri], par: bool) -> (Bvh, Vec<u32>) {
        let mut prims: Vec<Prim> = tris
            .iter()
            .enumerate()
            .map(|(i, t)| {
                let mut bb = Aabb::EMPTY;
                bb.grow_p(t.p0);
                bb.grow_p(t.p1);
                bb.grow_p(t.p2);
                Prim {
                    bb,
                    c: V3::new(
                        (bb.lo[0] + bb.hi[0]) * 0.5,
                        (bb.lo[1] + bb.hi[1]) * 0.5,
                        (bb.lo[2] + bb.hi[2]) * 0.5,
                    ),
                    i: i as u32,
                }
            })
            .collect();
        let mut bvh = Bvh::default();
        if tris.is_empty() {
            return (bvh, Vec::new());
        }
        let (bb, cb) = bounds(&prims, par);
        let root = build_bin(&mut prims, 0, 0, bb, cb, par);
        let idx: Vec<u32> = prims.iter().map(|p| p.i).collect();
        let sorted: Vec<Tri> = idx.iter().map(|&i| tris[i as usize]).collect();
        if root.leaf.is_some() {
            // A single leaf still gets a node, so traversal always starts at node 0.
            bvh.nodes.push(Node::EMPTY);
            bvh.set_child(0, 0, &root, &sorted);
        } else {
            bvh.collapse(&root, &sorted, par);
        }
        (bvh, idx)
    }

    /// Appends the 4-wide node for binary interior node `b` (and its subtree); returns its index.
    /// `par`: collapse large children in parallel (given at the root only).
    fn collapse(&mut self, b: &BNode, tris: &[Tri], par: bool) -> u32 {
        // Open the largest-area interior child until there are four children.
        let mut kids: Vec<&BNode> = match &b.kids {
            Some(k) => vec![&k.0, &k.1],
            None => vec![b],
        };
        while kids.len() < NW {
            let open = kids
                .iter()
                .enumerate()
                .filter(|(_, k)| k.kids.is_some())
                .max_by(|a, b| a.1.bb.area().total_cmp(&b.1.bb.area()).then(b.0.cmp(&a.0)))
                .map(|(i, _)| i);
            let Some(i) = open else { break };
            let Some(k) = &kids[i].kids else { break };
            kids[i] = &k.0;
            kids.insert(i + 1, &k.1);
        }
        // At the root, large interior children are collapsed in parallel, each into a tree of
        // its own that is then appended in slot order: the layout (depth-first, children in
        // slot order) is the one a sequential collapse gives.
        let mut parts: [Option<Bvh>; NW] = Default::default();
        let big = |k: &BNode| k.kids.is_some() && k.count as usize >= PAR_MIN;
        if par && kids.iter().filter(|k| big(k)).count() >= 2 {
            use rayon::prelude::*;
            let built: Vec<Option<Bvh>> = kids
                .par_iter()
                .map(|k| {
                    big(k).then(|| {
                        let mut sub = Bvh::default();
                        sub.collapse(k, tris, false);
                        sub
                    })
                })
                .collect();
            for (slot, part) in built.into_iter().enumerate() {
                parts[slot] = part;
            }
        }
        let ni = self.nodes.len();
        self.nodes.push(Node::EMPTY);
        for (slot, k) in kids.iter().enumerate() {
            match parts[slot].take() {
                Some(sub) => {
                    let root = self.append(sub);
                    self.set_bounds(ni, slot, root, &k.bb);
                }
                None => self.set_child(ni, slot, k, tris),
            }
        }
        ni as u32
    }

    /// Appends a separately collapsed tree (its node 0 a root); returns that root's index.
    fn append(&mut self, sub: Bvh) -> u32 {
        let (no, po) = (self.nodes.len() as u32, self.packets.len() as u32);
        self.nodes.extend(sub.nodes.into_iter().map(|mut n| {
            // Leaf codes hold a packet index in their low bits, interior codes a node index.
            for c in n.child.iter_mut().filter(|c| **c != EMPTY) {
                *c += if *c & LEAF != 0 { po } else { no };
            }
            n
        }));
        self.packets.extend(sub.packets);
        no
    }

    fn set_child(&mut self, ni: usize, slot: usize, k: &BNode, tris: &[Tri]) {
        let child = match k.leaf {
            Some((first, count)) => {
                let p = self.packets.len();
                for chunk in tris[first as usize..(first + count) as usize].chunks(LANES) {
                    let mut pk = Tri4 {
                        p0: [[f32::NAN; 4]; 3],
                        p1: [[f32::NAN; 4]; 3],
                        p2: [[f32::NAN; 4]; 3],
                        prim: [u32::MAX; 4],
                    };
                    let base = first as usize + (self.packets.len() - p) * LANES;
                    for (l, t) in chunk.iter().enumerate() {
                        for a in 0..3 {
                            pk.p0[a][l] = t.p0[a];
                            pk.p1[a][l] = t.p1[a];
                            pk.p2[a][l] = t.p2[a];
                        }
                        pk.prim[l] = (base + l) as u32;
                    }
                    self.packets.push(pk);
                }
                let np = self.packets.len() - p;
                LEAF | ((np as u32 - 1) << LEAF_COUNT_SHIFT) | (p as u32 & LEAF_INDEX_MASK)
            }
            None => self.collapse(k, tris, false),
        };
        self.set_bounds(ni, slot, child, &k.bb);
    }

    /// Sets child `slot` of node `ni`: its code and its box.
    fn set_bounds(&mut self, ni: usize, slot: usize, child: u32, bb: &Aabb) {
        let n = &mut self.nodes[ni];
        n.child[slot] = child;
        for a in 0..3 {
            n.b[a][slot] = bb.lo[a];
            n.b[a + 3][slot] = bb.hi[a];
        }
    }

    /// Number of 4-wide nodes.
    pub fn num_nodes(&self) -> usize {
        self.nodes.len()
    }

    /// Number of 4-triangle leaf packets (padding lanes included).
    pub fn num_packets(&self) -> usize {
        self.packets.len()
    }

    /// Closest hit in `(tmin, tmax)`.
    #[inline]
    pub fn intersect(&self, ray: &Ray, tmin: f32, tmax: f32) -> Option<Hit> {
        self.intersect_isa(Isa::detect(), ray, tmin, tmax)
    }

    /// Whether anything is hit in `(tmin, tmax)`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, tmin: f32, tmax: f32) -> bool {
        self.occluded_isa(Isa::detect(), ray, tmin, tmax)
    }

    /// [`Bvh::intersect`] with the traversal compiled for `isa` (which must be available:
    /// [`Isa::available`]; an unavailable one falls back to [`Isa::Base`]).
    pub fn intersect_isa(&self, isa: Isa, ray: &Ray, tmin: f32, tmax: f32) -> Option<Hit> {
        let mut best = None;
        if !self.nodes.is_empty() {
            self.traverse::<false>(isa, 0, ray, tmin, tmax, &mut best);
        }
        best
    }

    /// [`Bvh::occluded`] with the traversal compiled for `isa` (see [`Bvh::intersect_isa`]).
    pub fn occluded_isa(&self, isa: Isa, ray: &Ray, tmin: f32, tmax: f32) -> bool {
        let mut best = None;
        !self.nodes.is_empty() && self.traverse::<true>(isa, 0, ray, tmin, tmax, &mut best)
    }

    /// [`Bvh::traverse_body`] compiled for `isa`.
    #[inline]
    fn traverse<const ANY: bool>(
        &self,
        isa: Isa,
        start: u32,
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        best: &mut Option<Hit>,
    ) -> bool {
        // Single rays test a node's four children in one SSE vector: AVX-512 brings nothing.
        #[cfg(target_arch = "x86_64")]
        if isa.min(Isa::detect()) >= Isa::Avx2 {
            // SAFETY: `traverse_avx2` only requires the CPU features it is compiled for, and
            // `Isa::detect` returned `Avx2` or more only after `is_x86_feature_detected!`
            // confirmed every one of them (AVX2, FMA, BMI1, BMI2, LZCNT, POPCNT) on this CPU.
            return unsafe { self.traverse_avx2::<ANY>(start, ray, tmin, tmax, best) };
        }
        let _ = isa;
        self.traverse_body::<ANY>(start, ray, tmin, tmax, best)
    }

    /// The traversal with AVX2 (VEX three-operand SIMD, `popcnt`/`tzcnt`) enabled. FMA is
    /// enabled too but never contracted implicitly by rustc, so results are bit-identical to
    /// the baseline build.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn traverse_avx2<const ANY: bool>(
        &self,
        start: u32,
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        best: &mut Option<Hit>,
    ) -> bool {
        self.traverse_body::<ANY>(start, ray, tmin, tmax, best)
    }

    /// Traverses the subtree under child code `start`, updating `best` (hits closer than
    /// `tmax` and the current best only). With `ANY`, returns `true` at the first hit.
    /// Always inlined into [`Bvh::traverse`]'s per-ISA wrappers.
    #[inline(always)]
    fn traverse_body<const ANY: bool>(
        &self,
        start: u32,
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        best: &mut Option<Hit>,
    ) -> bool {
        let mut tmax = match best {
            Some(h) => h.t.min(tmax),
            None => tmax,
        };
        let o = [ray.o.x, ray.o.y, ray.o.z];
        let inv = [ray.inv_d.x, ray.inv_d.y, ray.inv_d.z];
        let rt = RayTri::new(ray);
        // Row of each axis's near and far planes in `Node4::b`.
        let neg: [usize; 3] = std::array::from_fn(|a| (inv[a] < 0.0) as usize);
        let near: [usize; 3] = std::array::from_fn(|a| a + 3 * neg[a]);
        let far: [usize; 3] = std::array::from_fn(|a| a + 3 - 3 * neg[a]);
        let mut stack_c = [std::mem::MaybeUninit::<u32>::uninit(); STACK];
        let mut stack_t = [std::mem::MaybeUninit::<f32>::uninit(); STACK];
        let mut sp = 0usize;
        let mut cur = start;
        loop {
            if cur & LEAF == 0 {
                let n = &self.nodes[cur as usize];
                let (nx, ny, nz) = (&n.b[near[0]], &n.b[near[1]], &n.b[near[2]]);
                let (fx, fy, fz) = (&n.b[far[0]], &n.b[far[1]], &n.b[far[2]]);
                let mut tn = [0f32; NW];
                let mut hit = [false; NW];
                for i in 0..NW {
                    let t0x = (nx[i] - o[0]) * inv[0];
                    let t0y = (ny[i] - o[1]) * inv[1];
                    let t0z = (nz[i] - o[2]) * inv[2];
                    let t1x = (fx[i] - o[0]) * inv[0];
                    let t1y = (fy[i] - o[1]) * inv[1];
                    let t1z = (fz[i] - o[2]) * inv[2];
                    // NaN (0 · ∞) comparisons keep the accumulated value: the slab stays open.
                    let mut t0 = 0.0f32;
                    t0 = if t0x > t0 { t0x } else { t0 };
                    t0 = if t0y > t0 { t0y } else { t0 };
                    t0 = if t0z > t0 { t0z } else { t0 };
                    let mut t1 = tmax;
                    t1 = if t1x < t1 { t1x } else { t1 };
                    t1 = if t1y < t1 { t1y } else { t1 };
                    t1 = if t1z < t1 { t1z } else { t1 };
                    tn[i] = t0;
                    hit[i] = t0 <= t1 * 1.000_000_2;
                }
                let mask = hit.iter().enumerate().fold(0u32, |m, (i, &h)| m | (h as u32) << i);
                match mask.count_ones() {
                    0 => {}
                    1 => {
                        cur = n.child[mask.trailing_zeros() as usize];
                        continue;
                    }
                    2 if sp < STACK => {
                        let i0 = mask.trailing_zeros() as usize;
                        let i1 = (mask & (mask - 1)).trailing_zeros() as usize;
                        let (a, b) = if ANY || tn[i0] <= tn[i1] { (i0, i1) } else { (i1, i0) };
                        self.prefetch(n.child[b]);
                        stack_c[sp].write(n.child[b]);
                        stack_t[sp].write(tn[b]);
                        sp += 1;
                        cur = n.child[a];
                        continue;
                    }
                    k => {
                        // Hit children, then (closest-hit only) sorted nearest first.
                        let mut c = [0u32; NW];
                        let mut t = [0f32; NW];
                        let mut m = mask;
                        for j in 0..k as usize {
                            let i = m.trailing_zeros() as usize;
                            m &= m - 1;
                            c[j] = n.child[i];
                            t[j] = tn[i];
                        }
                        if !ANY {
                            for j in 1..k as usize {
                                let (cj, tj) = (c[j], t[j]);
                                let mut i = j;
                                while i > 0 && t[i - 1] > tj {
                                    c[i] = c[i - 1];
                                    t[i] = t[i - 1];
                                    i -= 1;
                                }
                                c[i] = cj;
                                t[i] = tj;
                            }
                        }
                        for j in (1..k as usize).rev() {
                            if sp < STACK {
                                self.prefetch(c[j]);
                                stack_c[sp].write(c[j]);
                                stack_t[sp].write(t[j]);
                                sp += 1;
                            } else if self.traverse_deep::<ANY>(c[j], ray, tmin, tmax, best) && ANY {
                                // (Closest-hit goes on: `traverse_deep` returning true only
                                // means some hit exists, not that the rest can be skipped.)
                                return true;
                            } else if let Some(h) = best {
                                tmax = h.t;
                            }
                        }
                        cur = c[0];
                        continue;
                    }
                }
            } else if cur != EMPTY {
                for pk in self.leaf_packets(cur) {
                    if let Some(h) = intersect_tri4(pk, &rt, tmin, tmax) {
                        tmax = h.t;
                        *best = Some(h);
                        if ANY {
                            return true;
                        }
                    }
                }
            }
            // Pop the next entry that can still hold a closer hit.
            loop {
                if sp == 0 {
                    return best.is_some();
                }
                sp -= 1;
                // SAFETY: entries `0..sp` were written by the pushes above (the stack
                // pointer only moves past an entry after writing it).
                if ANY || unsafe { stack_t[sp].assume_init() } <= tmax {
                    cur = unsafe { stack_c[sp].assume_init() };
                    break;
                }
            }
        }
    }
}

impl Bvh {
    /// Stack overflow fallback of [`Bvh::traverse_body`] (a separate, never-inlined function,
    /// so the hot loop is not recursive): the baseline build, whatever the caller's ISA.
    #[inline(never)]
    fn traverse_deep<const ANY: bool>(
        &self,
        start: u32,
        ray: &Ray,
        tmin: f32,
        tmax: f32,
        best: &mut Option<Hit>,
    ) -> bool {
        #[cfg(test)]
        tests::DEEP_CALLS.with(|c| c.set(c.get() + 1));
        self.traverse_body::<ANY>(start, ray, tmin, tmax, best)
    }
}

impl Bvh {
    /// Hints the CPU to start loading the node or first leaf packet of child code `c` (the
    /// traversal is bound by the latency of these loads; pushed siblings load meanwhile).
    #[inline(always)]
    fn prefetch(&self, c: u32) {
        let p: *const u8 = if c & LEAF == 0 {
            match self.nodes.get(c as usize) {
                Some(n) => (n as *const Node).cast(),
                None => return,
            }
        } else {
            match self.packets.get((c & LEAF_INDEX_MASK) as usize) {
                Some(t) => (t as *const Tri4).cast(),
                None => return,
            }
        };
        // The node's cache lines (for a leaf, as many of its first packet's).
        for line in 0..std::mem::size_of::<Node>().div_ceil(64) {
            crate::math::prefetch(p.wrapping_add(64 * line));
        }
    }
}

/// The pending subtrees of a packet traversal: child code, live lanes and the nearest lane's
/// entry distance (as bits) of each.
struct PacketStack {
    c: [u32; STACK],
    m: [u32; STACK],
    t: [u32; STACK],
    sp: usize,
}

impl PacketStack {
    fn new() -> PacketStack {
        PacketStack {
            c: [0; STACK],
            m: [0; STACK],
            t: [0; STACK],
            sp: 0,
        }
    }

    /// The children of `n` that some lane enters (`cm`: lanes per child, `ct`: nearest entry
    /// bits), nearest first (any-hit: in slot order): the first is returned as (code, lanes),
    /// the others pushed so that the next nearest pops first; `overflow(code, lanes)` takes
    /// those that do not fit. `None` when no child is entered.
    #[inline(always)]
    fn push_children<const ANY: bool>(
        &mut self,
        bvh: &Bvh,
        n: &Node,
        cm: &[u32; NW],
        ct: &[u32; NW],
        mut overflow: impl FnMut(u32, u32),
    ) -> Option<(u32, u32)> {
        let mut order = [0usize; NW];
        let mut k = 0;
        for c in 0..NW {
            if cm[c] != 0 {
                let mut i = k;
                while !ANY && i > 0 && ct[order[i - 1]] > ct[c] {
                    order[i] = order[i - 1];
                    i -= 1;
                }
                order[i] = c;
                k += 1;
            }
        }
        if k == 0 {
            return None;
        }
        for j in (1..k).rev() {
            let c = order[j];
            if self.sp < STACK {
                bvh.prefetch(n.child[c]);
                (self.c[self.sp], self.m[self.sp], self.t[self.sp]) = (n.child[c], cm[c], ct[c]);
                self.sp += 1;
            } else {
                overflow(n.child[c], cm[c]);
            }
        }
        Some((n.child[order[0]], cm[order[0]]))
    }

    /// Pops entries until one for which `live(lanes, entry bits)` holds: its (code, lanes).
    #[inline(always)]
    fn pop(&mut self, mut live: impl FnMut(u32, u32) -> bool) -> Option<(u32, u32)> {
        while self.sp > 0 {
            self.sp -= 1;
            let (c, m, t) = (self.c[self.sp], self.m[self.sp], self.t[self.sp]);
            if live(m, t) {
                return Some((c, m));
            }
        }
        None
    }
}

impl Bvh {
    /// The triangle packets of leaf child code `code`.
    #[inline(always)]
    fn leaf_packets(&self, code: u32) -> &[Tri4] {
        let first = (code & LEAF_INDEX_MASK) as usize;
        let count = ((code & !LEAF) >> LEAF_COUNT_SHIFT) as usize + 1;
        &self.packets[first..first + count]
    }
}

/// A packet traversal reaching a node with at most this many live lanes finishes the
/// subtree for each of them by single-ray traversal ([`Bvh::finish_lanes`]). Measured on the
/// bench scene's bounce packets: 3.6 → 4.4 Mrays/s (git history of BENCHMARKS.md); 3 since the
/// hand-off is inlined into the packet kernel (render instructions −1.6 % against 2 at 256²,
/// 4 −2.2 %, 6 −1.6 %; timing within noise).
const FINISH_ALONE: u32 = 3;

/// Rays per packet of [`Bvh::intersect_packet`] / [`Bvh::occluded_packet`].
pub const PACKET: usize = 16;
/// Every lane of a [`RayPack`], as a mask.
const PACK_LANES: u32 = (1 << PACKET) - 1;

/// Up to [`PACKET`] rays, structure of arrays, for packet traversal ([`Bvh::intersect_pack`],
/// [`Bvh::occluded_pack`]): only the lanes of the mask given to a query take part; the others
/// may hold anything. Filled lane by lane with [`RayPack::set`], so a caller that gathers
/// rays (the integrator's batches) writes them here directly, without an array of [`Ray`]s
/// to transpose.
#[derive(Clone, Copy)]
#[repr(C, align(64))]
pub struct RayPack {
    o: [[f32; PACKET]; 3],
    d: [[f32; PACKET]; 3],
    inv: [[f32; PACKET]; 3],
    /// The rays' shears, rows `sx`, `sy`, `sz` ([`Shear::s`]), and per axis the lanes whose
    /// [`Shear::kz`] it is.
    sh: [[f32; PACKET]; 3],
    kz: [u32; 3],
    /// Per lane, the primitive the ray leaves ([`Ray::skip`]).
    skip: [u32; PACKET],
    /// Current far limit per lane (the closest hit so far).
    tmax: [f32; PACKET],
    /// Closest hit so far per lane: barycentrics, triangle and point (as [`Hit`]).
    b1: [f32; PACKET],
    b2: [f32; PACKET],
    prim: [u32; PACKET],
    hp: [V3; PACKET],
    /// Lanes that found a hit.
    found: u32,
}

impl RayPack {
    /// For each lane in `m`, which has just hit lane `l` of `pk` (its `tmax`, `b1`, `b2`
    /// already written): the triangle and the hit point, computed as [`intersect_tri4`] does.
    #[inline(always)]
    fn record(&mut self, mut m: u32, pk: &Tri4, l: usize) {
        self.found |= m;
        while m != 0 {
            let r = m.trailing_zeros() as usize;
            m &= m - 1;
            self.prim[r] = pk.prim[l];
            self.hp[r] = pk.point(l, self.b1[r], self.b2[r]);
        }
    }

    /// Lane `r`'s ray as the watertight test reads it.
    #[inline(always)]
    fn ray_tri(&self, r: usize) -> RayTri {
        let k = axes((0..3).find(|&a| self.kz[a] >> r & 1 != 0).unwrap_or(2));
        RayTri {
            k,
            o: k.map(|a| self.o[a][r]),
            s: [self.sh[0][r], self.sh[1][r], self.sh[2][r]],
            skip: self.skip[r],
        }
    }

    /// Fills the shear rows and `kz` lane sets from the rays' directions, every lane as
    /// [`Shear::new`] does (branch-free, so that the compiler vectorises it): once per query,
    /// at the start of each packet kernel.
    #[inline(always)]
    fn prepare_shear(&mut self) {
        let mut kz = [0u32; 3];
        for r in 0..PACKET {
            let d = [self.d[0][r], self.d[1][r], self.d[2][r]];
            let inv = [self.inv[0][r], self.inv[1][r], self.inv[2][r]];
            let (x, y, z) = (d[0].abs(), d[1].abs(), d[2].abs());
            let is_x = (x > y) & (x > z);
            let is_y = !is_x & (y > z);
            // Per axis `kz`: (d[kx], d[ky], inv_d[kz]) as `axes` orders them.
            let pick = |if_x: f32, if_y: f32, if_z: f32| {
                if is_x {
                    if_x
                } else if is_y {
                    if_y
                } else {
                    if_z
                }
            };
            let sz = pick(inv[0], inv[1], inv[2]);
            self.sh[0][r] = pick(d[1], d[2], d[0]) * sz;
            self.sh[1][r] = pick(d[2], d[0], d[1]) * sz;
            self.sh[2][r] = sz;
            kz[0] |= (is_x as u32) << r;
            kz[1] |= (is_y as u32) << r;
        }
        kz[2] = PACK_LANES & !(kz[0] | kz[1]);
        self.kz = kz;
    }

    /// The one [`Shear::kz`] of every lane in `act`, if they share it.
    #[inline(always)]
    fn uniform_kz(&self, act: u32) -> Option<usize> {
        (0..3).find(|&a| act & !self.kz[a] == 0)
    }

    /// A pack with every lane zeroed and no hit.
    pub fn empty() -> RayPack {
        RayPack {
            o: [[0.0; PACKET]; 3],
            d: [[0.0; PACKET]; 3],
            inv: [[0.0; PACKET]; 3],
            sh: [[0.0; PACKET]; 3],
            kz: [0, 0, PACK_LANES],
            skip: [NO_PRIM; PACKET],
            tmax: [f32::NEG_INFINITY; PACKET],
            b1: [0.0; PACKET],
            b2: [0.0; PACKET],
            prim: [0; PACKET],
            hp: [V3::ZERO; PACKET],
            found: 0,
        }
    }

    /// Puts `ray` with far limit `tmax` in lane `r` (`r < PACKET`).
    #[inline(always)]
    pub fn set(&mut self, r: usize, ray: &Ray, tmax: f32) {
        for a in 0..3 {
            self.o[a][r] = ray.o[a];
            self.d[a][r] = ray.d[a];
            self.inv[a][r] = ray.inv_d[a];
        }
        self.skip[r] = ray.skip;
        self.tmax[r] = tmax;
    }

    /// The far limit of lane `r`: as set, or after a closest-hit query the hit distance.
    #[inline(always)]
    pub fn tmax(&self, r: usize) -> f32 {
        self.tmax[r]
    }

    /// Lane `r`'s closest hit after [`Bvh::intersect_pack`] (`None` if it found none).
    #[inline(always)]
    pub fn hit(&self, r: usize) -> Option<Hit> {
        (self.found >> r & 1 != 0).then(|| Hit {
            t: self.tmax[r],
            b1: self.b1[r],
            b2: self.b2[r],
            prim: self.prim[r],
            p: self.hp[r],
        })
    }

    /// Whether lane `r` found a hit in the last query.
    #[inline(always)]
    pub fn found(&self, r: usize) -> bool {
        self.found >> r & 1 != 0
    }

    /// The ray of lane `r`.
    #[inline(always)]
    pub fn ray(&self, r: usize) -> Ray {
        Ray {
            o: V3::new(self.o[0][r], self.o[1][r], self.o[2][r]),
            d: V3::new(self.d[0][r], self.d[1][r], self.d[2][r]),
            inv_d: V3::new(self.inv[0][r], self.inv[1][r], self.inv[2][r]),
            skip: self.skip[r],
        }
    }

    fn new(rays: &[Ray], tmax: &[f32]) -> (RayPack, u32) {
        let mut p = RayPack::empty();
        let mut act = 0u32;
        for (r, (ray, &tm)) in rays.iter().zip(tmax).take(PACKET).enumerate() {
            p.set(r, ray, tm);
            act |= 1 << r;
        }
        (p, act)
    }
}

impl Bvh {
    /// [`Bvh::intersect`] for each of `rays` (with far limits `tmax`), written to `out`; pairs
    /// beyond the shortest of the three slices are not traced. The rays share one traversal
    /// per [`PACKET`] of them, so coherent rays (e.g. the samples of one pixel) are cheaper
    /// than one by one; the hits are [`Bvh::intersect`]'s (same arithmetic per ray).
    pub fn intersect_packet(&self, rays: &[Ray], tmin: f32, tmax: &[f32], out: &mut [Option<Hit>]) {
        self.intersect_packet_isa(Isa::detect(), rays, tmin, tmax, out)
    }

    /// [`Bvh::intersect_packet`] with the traversal compiled for `isa`.
    pub fn intersect_packet_isa(&self, isa: Isa, rays: &[Ray], tmin: f32, tmax: &[f32], out: &mut [Option<Hit>]) {
        for ((rays, tmax), out) in rays.chunks(PACKET).zip(tmax.chunks(PACKET)).zip(out.chunks_mut(PACKET)) {
            let (mut p, act) = RayPack::new(rays, tmax);
            if !self.nodes.is_empty() {
                self.traverse_packet::<false>(isa, 0, act, &mut p, tmin);
            }
            for (r, o) in out.iter_mut().enumerate().take(rays.len().min(tmax.len())) {
                *o = p.hit(r);
            }
        }
    }

    /// [`Bvh::intersect_packet`] for the lanes of `p` in `act` (bit `r` = lane `r`): their
    /// closest hits are then [`RayPack::hit`]. Other lanes are left out and report no hit.
    #[inline]
    pub fn intersect_pack(&self, p: &mut RayPack, act: u32, tmin: f32) {
        p.found = 0;
        if !self.nodes.is_empty() {
            self.traverse_packet::<false>(Isa::detect(), 0, act & PACK_LANES, p, tmin);
        }
    }

    /// [`Bvh::occluded_packet`] for the lanes of `p` in `act`: afterwards
    /// [`RayPack::found`] says whether each is occluded.
    #[inline]
    pub fn occluded_pack(&self, p: &mut RayPack, act: u32, tmin: f32) {
        p.found = 0;
        if !self.nodes.is_empty() {
            self.traverse_packet::<true>(Isa::detect(), 0, act & PACK_LANES, p, tmin);
        }
    }

    /// [`Bvh::occluded`] for each of `rays` (with far limits `tmax`), written to `out`, sharing
    /// traversals as [`Bvh::intersect_packet`] does.
    pub fn occluded_packet(&self, rays: &[Ray], tmin: f32, tmax: &[f32], out: &mut [bool]) {
        self.occluded_packet_isa(Isa::detect(), rays, tmin, tmax, out)
    }

    /// [`Bvh::occluded_packet`] with the traversal compiled for `isa`.
    pub fn occluded_packet_isa(&self, isa: Isa, rays: &[Ray], tmin: f32, tmax: &[f32], out: &mut [bool]) {
        for ((rays, tmax), out) in rays.chunks(PACKET).zip(tmax.chunks(PACKET)).zip(out.chunks_mut(PACKET)) {
            let (mut p, act) = RayPack::new(rays, tmax);
            if !self.nodes.is_empty() {
                self.traverse_packet::<true>(isa, 0, act, &mut p, tmin);
            }
            for (r, o) in out.iter_mut().enumerate().take(rays.len().min(tmax.len())) {
                *o = p.found >> r & 1 != 0;
            }
        }
    }

    /// [`Bvh::traverse_packet_body`] compiled for `isa`.
    #[inline]
    fn traverse_packet<const ANY: bool>(&self, isa: Isa, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        // The requested kernel, or the best this CPU has if it lacks that one (each starts by
        // `RayPack::prepare_shear`, compiled for its instruction set).
        #[cfg(target_arch = "x86_64")]
        match isa.min(Isa::detect()) {
            // SAFETY (both): `Isa::detect` returned at least this `Isa` only after
            // `is_x86_feature_detected!` confirmed every feature the kernel is compiled for.
            Isa::Avx512 => return unsafe { self.traverse_packet_avx512::<ANY>(start, act, p, tmin) },
            Isa::Avx2 => return unsafe { self.traverse_packet_avx2::<ANY>(start, act, p, tmin) },
            Isa::Base => {}
        }
        let _ = isa;
        p.prepare_shear();
        self.traverse_packet_body::<ANY>(start, act, p, tmin)
    }

    #[inline(never)]
    fn traverse_packet_deep<const ANY: bool>(&self, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        #[cfg(test)]
        tests::DEEP_CALLS.with(|c| c.set(c.get() + 1));
        self.traverse_packet_body::<ANY>(start, act, p, tmin)
    }

    /// Finishes the subtree under child code `cur` for each lane in `lanes` alone, by
    /// single-ray traversal, and records the hits in the packet: once a packet has only a few
    /// live lanes, a single ray visits a node for less than a packet does. Same hits as the
    /// packet traversal (same triangle test), within each lane's current limit. The single-ray
    /// body is inlined here, so it is compiled for the calling kernel's instruction set and a
    /// hand-off costs no call or dispatch (render instructions −2.7 %, git history of BENCHMARKS.md).
    #[inline(always)]
    fn finish_lanes<const ANY: bool>(&self, cur: u32, mut lanes: u32, p: &mut RayPack, tmin: f32) {
        while lanes != 0 {
            let r = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            let mut best = None;
            self.traverse_body::<ANY>(cur, &p.ray(r), tmin, p.tmax[r], &mut best);
            if let Some(h) = best {
                p.tmax[r] = h.t;
                p.b1[r] = h.b1;
                p.b2[r] = h.b2;
                p.prim[r] = h.prim;
                p.hp[r] = h.p;
                p.found |= 1 << r;
            }
        }
    }

    /// Packet traversal of the subtree under child code `start` for the lanes in `act`: each
    /// lane runs [`Bvh::traverse_body`]'s box and triangle tests (same arithmetic), a node is
    /// visited while any active lane enters it, and children are visited in order of the
    /// nearest lane's entry. With `ANY`, lanes stop at their first hit.
    #[inline(always)]
    fn traverse_packet_body<const ANY: bool>(&self, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        let mut stack = PacketStack::new();
        let (mut cur, mut act) = (start, act);
        loop {
            if ANY {
                act &= !p.found;
            }
            if act != 0 && act.count_ones() <= FINISH_ALONE && cur != EMPTY {
                self.finish_lanes::<ANY>(cur, act, p, tmin);
            } else if act != 0 && cur & LEAF == 0 {
                let n = &self.nodes[cur as usize];
                // Per child: lanes entering it and the smallest entry distance (as bits:
                // entry distances are ≥ 0, so their bit patterns order as the floats do).
                let mut cm = [0u32; NW];
                let mut ct = [u32::MAX; NW];
                for c in 0..NW {
                    let (lx, ly, lz) = (n.b[0][c], n.b[1][c], n.b[2][c]);
                    let (hx, hy, hz) = (n.b[3][c], n.b[4][c], n.b[5][c]);
                    let mut hit = [false; PACKET];
                    let mut tb = [u32::MAX; PACKET];
                    for r in 0..PACKET {
                        let a0x = (lx - p.o[0][r]) * p.inv[0][r];
                        let a1x = (hx - p.o[0][r]) * p.inv[0][r];
                        let a0y = (ly - p.o[1][r]) * p.inv[1][r];
                        let a1y = (hy - p.o[1][r]) * p.inv[1][r];
                        let a0z = (lz - p.o[2][r]) * p.inv[2][r];
                        let a1z = (hz - p.o[2][r]) * p.inv[2][r];
                        let (t0x, t1x) = if p.inv[0][r] < 0.0 { (a1x, a0x) } else { (a0x, a1x) };
                        let (t0y, t1y) = if p.inv[1][r] < 0.0 { (a1y, a0y) } else { (a0y, a1y) };
                        let (t0z, t1z) = if p.inv[2][r] < 0.0 { (a1z, a0z) } else { (a0z, a1z) };
                        let mut t0 = 0.0f32;
                        t0 = if t0x > t0 { t0x } else { t0 };
                        t0 = if t0y > t0 { t0y } else { t0 };
                        t0 = if t0z > t0 { t0z } else { t0 };
                        let mut t1 = p.tmax[r];
                        t1 = if t1x < t1 { t1x } else { t1 };
                        t1 = if t1y < t1 { t1y } else { t1 };
                        t1 = if t1z < t1 { t1z } else { t1 };
                        let h = (t0 <= t1 * 1.000_000_2) & (act >> r & 1 != 0);
                        hit[r] = h;
                        tb[r] = if h { t0.to_bits() } else { u32::MAX };
                    }
                    let mut m = 0u32;
                    for r in 0..PACKET {
                        m |= (hit[r] as u32) << r;
                    }
                    cm[c] = m;
                    ct[c] = tb.iter().fold(u32::MAX, |a, &b| a.min(b));
                }
                let next = stack.push_children::<ANY>(self, n, &cm, &ct, |c, m| {
                    self.traverse_packet_deep::<ANY>(c, m, p, tmin)
                });
                if let Some((c, m)) = next {
                    (cur, act) = (c, m);
                    continue;
                }
            } else if act != 0 && cur != EMPTY {
                for pk in self.leaf_packets(cur) {
                    for l in 0..4 {
                        if pk.prim[l] == u32::MAX {
                            break;
                        }
                        let m = intersect_tri_lanes(pk, l, p, tmin, act);
                        p.record(m, pk, l);
                    }
                }
            }
            // Pop the next entry that can still hold a closer hit for one of its lanes.
            let live = |m: u32, t: u32| {
                if ANY {
                    return m & !p.found != 0;
                }
                // Farthest limit among the entry's lanes (limits are > tmin ≥ 0 for lanes
                // that can hit; a negative one compares as the largest bits, so never culls).
                let mut far = 0u32;
                for r in 0..PACKET {
                    let b = if m >> r & 1 != 0 { p.tmax[r].to_bits() } else { 0 };
                    far = far.max(b);
                }
                t <= far
            };
            match stack.pop(live) {
                Some((c, m)) => (cur, act) = (c, m),
                None => return,
            }
        }
    }
}

/// Lane `l` of packet `pk` against every ray of `p` active in `act`, with the operations of
/// [`intersect_tri`] in the same order; lanes hit closer than their current limit get the hit
/// recorded (distance, barycentrics) and are returned as a mask.
#[inline(always)]
fn intersect_tri_lanes(pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32) -> u32 {
    let mut m = 0u32;
    for r in 0..PACKET {
        if act >> r & 1 == 0 || pk.prim[l] == p.skip[r] {
            continue;
        }
        let (tri, rt) = (pk.tri(l), p.ray_tri(r));
        if let Some((t, b1, b2)) = tri_test(&tri, &rt, tmin, p.tmax[r]) {
            p.tmax[r] = t;
            p.b1[r] = b1;
            p.b2[r] = b2;
            m |= 1 << r;
        }
    }
    m
}

/// Lane `l` of `pk` against the rays of `p` in `act` with the packet kernel of `isa` (the
/// portable one for [`Isa::Base`]): the kernels on their own, for tests.
#[cfg(test)]
fn tri_lanes_isa(isa: Isa, pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32) -> u32 {
    p.prepare_shear();
    #[cfg(target_arch = "x86_64")]
    match isa.min(Isa::detect()) {
        // SAFETY (both): `Isa::detect` returned at least this `Isa` only after
        // `is_x86_feature_detected!` confirmed every feature the kernel is compiled for.
        Isa::Avx512 => return unsafe { packet_avx512::tri_alone(pk, l, p, tmin, act) },
        Isa::Avx2 => return unsafe { packet_avx2::tri_alone(pk, l, p, tmin, act) },
        Isa::Base => {}
    }
    let _ = isa;
    intersect_tri_lanes(pk, l, p, tmin, act)
}

/// Instruction set a traversal is compiled for (ordered: each one includes the previous).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Isa {
    /// The build target's baseline (SSE2 on x86-64).
    Base,
    /// x86-64 with AVX2, FMA, BMI1/2, LZCNT and POPCNT, detected at run time.
    Avx2,
    /// `Avx2` plus AVX-512F (packets of 16 rays in one vector; single rays as `Avx2`).
    Avx512,
}

impl Isa {
    /// The best instruction set this CPU supports (detected once, then cached), capped by
    /// `PIXL_ISA` if set.
    #[inline]
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            use std::sync::atomic::{AtomicU8, Ordering};
            // 0 = not yet detected, then 1 + the `Isa` as u8.
            static DETECTED: AtomicU8 = AtomicU8::new(0);
            match DETECTED.load(Ordering::Relaxed) {
                1 => Isa::Base,
                2 => Isa::Avx2,
                3 => Isa::Avx512,
                _ => {
                    let avx2 = is_x86_feature_detected!("avx2")
                        && is_x86_feature_detected!("fma")
                        && is_x86_feature_detected!("bmi1")
                        && is_x86_feature_detected!("bmi2")
                        && is_x86_feature_detected!("lzcnt")
                        && is_x86_feature_detected!("popcnt");
                    let avx512 = avx2 && is_x86_feature_detected!("avx512f");
                    let best = match (avx2, avx512) {
                        (_, true) => Isa::Avx512,
                        (true, false) => Isa::Avx2,
                        _ => Isa::Base,
                    };
                    let isa = best.min(Isa::cap_from_env());
                    DETECTED.store(1 + isa as u8, Ordering::Relaxed);
                    isa
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        Isa::Base
    }

    /// The cap set by the environment variable `PIXL_ISA=base` or `PIXL_ISA=avx2`
    /// (case-insensitive), for A/B measurements of the traversal kernels; none when unset or
    /// anything else.
    fn cap_from_env() -> Isa {
        match std::env::var("PIXL_ISA").map(|v| v.to_ascii_lowercase()).as_deref() {
            Ok("base") => Isa::Base,
            Ok("avx2") => Isa::Avx2,
            _ => Isa::Avx512,
        }
    }

    /// Every instruction set usable on this CPU (the baseline first).
    pub fn available() -> Vec<Isa> {
        [Isa::Base, Isa::Avx2, Isa::Avx512]
            .into_iter()
            .filter(|&i| i <= Isa::detect())
            .collect()
    }
}

/// A ray as the watertight test reads it: its axes `[kx, ky, kz]` ([`Shear`]), its origin's
/// coordinates in that order, its shear and the primitive it skips. Made once per traversal.
#[derive(Clone, Copy)]
struct RayTri {
    k: [usize; 3],
    o: [f32; 3],
    s: [f32; 3],
    skip: u32,
}

impl RayTri {
    #[inline(always)]
    fn new(ray: &Ray) -> RayTri {
        let sh = Shear::new(ray.d, ray.inv_d);
        let k = axes(sh.kz);
        RayTri {
            k,
            o: k.map(|a| ray.o[a]),
            s: sh.s,
            skip: ray.skip,
        }
    }
}

/// The vertices of `tri` relative to the origin of `r`, axes permuted, x and y sheared (so that
/// the ray is the z axis of the frame in which the triangle is tested in 2-D): `q = [ax, ay,
/// bx, by, cx, cy]` and `z = [az, bz, cz]`. Every test computes these as written here.
#[inline(always)]
fn sheared(tri: &Tri, r: &RayTri) -> ([f32; 6], [f32; 3]) {
    let [kx, ky, kz] = r.k;
    let [sx, sy, _] = r.s;
    let rel = |p: V3| {
        let z = p[kz] - r.o[2];
        ((p[kx] - r.o[0]) - sx * z, (p[ky] - r.o[1]) - sy * z, z)
    };
    let (a, b, c) = (rel(tri.p0), rel(tri.p1), rel(tri.p2));
    ([a.0, a.1, b.0, b.1, c.0, c.1], [a.2, b.2, c.2])
}

/// The watertight test's edge functions `[U, V, W]` of the triangle with sheared vertices `q`
/// ([`sheared`]): twice the signed areas that the ray's point spans with edges BC, CA and AB,
/// so the weights of vertices A, B and C. A shared edge gives its two triangles the same value
/// with opposite signs, bit for bit.
#[inline(always)]
fn edge_fns(q: [f32; 6]) -> [f32; 3] {
    let [ax, ay, bx, by, cx, cy] = q;
    [cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax]
}

/// [`edge_fns`] in f64, rounded to f32: the products of f32 values are exact in f64, so each
/// sign is the exact one, which agrees with every non-zero [`edge_fns`] result (rounding is
/// monotonic).
#[inline(always)]
fn edge_fns_f64(q: [f32; 6]) -> [f32; 3] {
    let [ax, ay, bx, by, cx, cy] = q.map(f64::from);
    [
        (cx * by - cy * bx) as f32,
        (ax * cy - ay * cx) as f32,
        (bx * ay - by * ax) as f32,
    ]
}

/// `a < b ? a : b` and `a > b ? a : b`, as `minps` and `maxps` compute them (NaN: `b`).
#[inline(always)]
fn min_(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}
#[inline(always)]
fn max_(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// Whether edge functions `e` allow a hit: all ≥ 0 or all ≤ 0 (either side of the triangle
/// faces the ray), tested on their smallest and largest.
#[inline(always)]
fn same_sign(e: [f32; 3]) -> bool {
    let [u, v, w] = e;
    (min_(min_(u, v), w) >= 0.0) | (max_(max_(u, v), w) <= 0.0)
}

/// From edge functions `e` and the vertices' `z`, with the ray's `sz`: the sum `det` of the
/// edge functions, the distance and the barycentrics, `(det, t, b1, b2)`.
#[inline(always)]
fn solve(e: [f32; 3], z: [f32; 3], sz: f32) -> (f32, f32, f32, f32) {
    let [u, v, w] = e;
    let det = u + v + w;
    let inv = 1.0 / det;
    let t = (u * z[0] + v * z[1] + w * z[2]) * sz * inv;
    (det, t, v * inv, w * inv)
}

/// The watertight ray–triangle test (see the module header): `(t, b1, b2)` for a hit in
/// `(tmin, tmax)`, either side of the triangle.
#[inline]
pub fn intersect_tri(tri: &Tri, ray: &Ray, tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
    tri_test(tri, &RayTri::new(ray), tmin, tmax)
}

/// [`intersect_tri`] for a prepared ray (whose `skip` it ignores). Every other test performs
/// these operations per lane, in this order: the sheared vertices, the edge functions in f32,
/// their signs, the distance; then, for a hit with an edge function exactly 0, [`refine`].
#[inline(always)]
fn tri_test(tri: &Tri, r: &RayTri, tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
    let (q, z) = sheared(tri, r);
    let e = edge_fns(q);
    if !same_sign(e) {
        return None;
    }
    let (det, t, b1, b2) = solve(e, z, r.s[2]);
    if !(det != 0.0 && t > tmin && t < tmax) {
        return None;
    }
    if e.contains(&0.0) {
        return refine(tri, r, tmin, tmax);
    }
    Some((t, b1, b2))
}

/// The watertight test's last stage, for a candidate hit whose f32 edge functions include an
/// exact 0 (the ray passes through an edge or a vertex, or rounding made it look so): the edge
/// functions again in f64 ([`edge_fns_f64`]), then the sign and distance tests with them.
/// `(t, b1, b2)` if it is still a hit. Out of line: it is rare.
#[cold]
#[inline(never)]
fn refine(tri: &Tri, r: &RayTri, tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
    #[cfg(test)]
    watertight_tests::REFINES.with(|c| c.set(c.get() + 1));
    let (q, z) = sheared(tri, r);
    let e = edge_fns_f64(q);
    if !same_sign(e) {
        return None;
    }
    let (det, t, b1, b2) = solve(e, z, r.s[2]);
    (det != 0.0 && t > tmin && t < tmax).then_some((t, b1, b2))
}

/// [`refine`] for lane `l` of `pk` and the rays of `p` in `m`, which the packet kernels found
/// hit with an edge function exactly 0 (and have not recorded): writes the hits that remain to
/// `p` (distance, barycentrics) and returns their lanes.
#[cold]
#[inline(never)]
fn refine_pack(pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, mut m: u32) -> u32 {
    let tri = pk.tri(l);
    let mut hit = 0;
    while m != 0 {
        let r = m.trailing_zeros() as usize;
        m &= m - 1;
        if let Some((t, b1, b2)) = refine(&tri, &p.ray_tri(r), tmin, p.tmax[r]) {
            (p.tmax[r], p.b1[r], p.b2[r]) = (t, b1, b2);
            hit |= 1 << r;
        }
    }
    hit
}

/// [`intersect_tri`] on four triangles at once: the closest hit in `(tmin, tmax)` (the lowest
/// lane among equal distances). Per lane the operations of [`tri_test`], in the same order.
#[inline(always)]
fn intersect_tri4(pk: &Tri4, r: &RayTri, tmin: f32, tmax: f32) -> Option<Hit> {
    use simd4::F4;
    let [kx, ky, kz] = r.k;
    let (sx, sy, sz) = (F4::splat(r.s[0]), F4::splat(r.s[1]), F4::splat(r.s[2]));
    let (ox, oy, oz) = (F4::splat(r.o[0]), F4::splat(r.o[1]), F4::splat(r.o[2]));
    // As `sheared`, four triangles at a time.
    let vert = |v: &[[f32; 4]; 3]| {
        let z = F4::load(&v[kz]) - oz;
        ((F4::load(&v[kx]) - ox) - sx * z, (F4::load(&v[ky]) - oy) - sy * z, z)
    };
    let (ax, ay, az) = vert(&pk.p0);
    let (bx, by, bz) = vert(&pk.p1);
    let (cx, cy, cz) = vert(&pk.p2);
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    let zero = F4::splat(0.0);
    // One exit, after the distance test (as the packet kernels' exit after the sign test, it
    // measured no faster for single rays: the leaf a ray starts next to passes it anyway).
    let mut ok = (u.min(v).min(w).ge(zero) | u.max(v).max(w).le(zero)).bits();
    ok &= !(0..4).fold(0, |m, i| m | ((pk.prim[i] == r.skip) as u32) << i);
    let det = u + v + w;
    let inv = F4::splat(1.0) / det;
    let t = (u * az + v * bz + w * cz) * sz * inv;
    ok &= (det.ne(zero) & t.gt(F4::splat(tmin)) & t.lt(F4::splat(tmax))).bits();
    if ok == 0 {
        return None;
    }
    let (mut t, mut b1, mut b2) = (t.to_array(), (v * inv).to_array(), (w * inv).to_array());
    let fix = ok & (u.eq(zero) | v.eq(zero) | w.eq(zero)).bits();
    if fix != 0 {
        ok &= !fix;
        let mut m = fix;
        while m != 0 {
            let i = m.trailing_zeros() as usize;
            m &= m - 1;
            if let Some(h) = refine(&pk.tri(i), r, tmin, tmax) {
                (t[i], b1[i], b2[i]) = h;
                ok |= 1 << i;
            }
        }
    }
    let mut best: Option<(usize, f32)> = None;
    let mut tb = tmax;
    for (i, &ti) in t.iter().enumerate() {
        if ok >> i & 1 != 0 && ti < tb {
            tb = ti;
            best = Some((i, tb));
        }
    }
    let (i, t) = best?;
    Some(Hit {
        t,
        b1: b1[i],
        b2: b2[i],
        prim: pk.prim[i],
        p: pk.point(i, b1[i], b2[i]),
    })
}

#[cfg(test)]
mod watertight_tests;

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_core::Rng;

    /// Random triangle soup in a 10 m cube.
    fn soup(n: usize, seed: u64) -> Vec<Tri> {
        let mut rng = Rng::new(seed);
        let mut r = || rng.uniform(-1.0, 1.0);
        (0..n)
            .map(|_| {
                let p0 = V3::new(r() * 5.0, r() * 5.0, r() * 5.0);
                let e1 = V3::new(r(), r(), r()) * 0.5;
                let e2 = V3::new(r(), r(), r()) * 0.5;
                Tri {
                    p0,
                    p1: p0 + e1,
                    p2: p0 + e2,
                }
            })
            .collect()
    }

    /// A bumpy height field of `2 (n − 1)²` triangles sharing edges (like a depth mesh).
    fn grid(n: usize) -> Vec<Tri> {
        let p = |i: usize, j: usize| {
            let (u, v) = (i as f32 / (n - 1) as f32, j as f32 / (n - 1) as f32);
            V3::new(4.0 * u - 2.0, 4.0 * v - 2.0, 0.3 * (9.0 * u).sin() * (7.0 * v).cos())
        };
        let mut tris = Vec::new();
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let (a, b, c, d) = (p(i, j), p(i + 1, j), p(i, j + 1), p(i + 1, j + 1));
                tris.push(Tri { p0: a, p1: c, p2: b });
                tris.push(Tri { p0: b, p1: c, p2: d });
            }
        }
        tris
    }

    /// Closest hit over all triangles by brute force: `(t, b1, b2, index)`.
    fn brute(tris: &[Tri], ray: &Ray, tmin: f32, tmax: f32) -> Option<(f32, f32, f32, usize)> {
        brute_excluding(tris, ray, tmin, tmax, usize::MAX)
    }

    /// [`brute`] ignoring triangle `skip` (an index into `tris`, the input order).
    fn brute_excluding(tris: &[Tri], ray: &Ray, tmin: f32, tmax: f32, skip: usize) -> Option<(f32, f32, f32, usize)> {
        let mut best: Option<(f32, f32, f32, usize)> = None;
        for (i, t) in tris.iter().enumerate().filter(|(i, _)| *i != skip) {
            if let Some((th, b1, b2)) = intersect_tri(t, ray, tmin, tmax) {
                if best.is_none_or(|b| th < b.0) {
                    best = Some((th, b1, b2, i));
                }
            }
        }
        best
    }

    /// Checks `n_rays` random rays (origins in the box, some on the surfaces, some with zero
    /// direction components, random `(tmin, tmax)` windows) against the brute-force answer,
    /// with the traversal of every instruction set this CPU has; returns the hits per set.
    fn check(tris: &[Tri], n_rays: usize, seed: u64) -> usize {
        let isas = Isa::available();
        if cfg!(target_arch = "x86_64")
            && std::is_x86_feature_detected!("avx2")
            && std::env::var_os("PIXL_ISA").is_none()
        {
            assert!(isas.contains(&Isa::Avx2), "AVX2 CPU but the AVX2 traversal is not used");
            if std::is_x86_feature_detected!("avx512f") {
                assert!(
                    isas.contains(&Isa::Avx512),
                    "AVX-512 CPU but its packet kernel is not used"
                );
            }
        }
        let hits: Vec<usize> = isas
            .iter()
            .map(|&isa| {
                check_packets(isa, tris, n_rays, seed + 1);
                check_isa(isa, tris, n_rays, seed)
            })
            .collect();
        assert!(hits.iter().all(|&h| h == hits[0]), "{hits:?}");
        hits[0]
    }

    /// Compares a hit with the brute-force answer `want` (ties at the same distance allowed).
    fn same_hit(tris: &[Tri], perm: &[u32], ray: &Ray, tmin: f32, tmax: f32, want: (f32, f32, f32, usize), h: &Hit) {
        let (t, b1, b2, i) = want;
        let j = perm[h.prim as usize] as usize;
        assert_eq!(t.to_bits(), h.t.to_bits(), "t {t} vs {}", h.t);
        if j == i {
            assert_eq!((b1, b2), (h.b1, h.b2));
        } else {
            let other = intersect_tri(&tris[j], ray, tmin, tmax).map(|x| x.0);
            assert_eq!(other, Some(t), "prim {j} instead of {i}");
        }
        let tj = &tris[j];
        assert_eq!(h.p, tj.point(h.b1, h.b2));
    }

    /// Packet queries against brute force: bundles of nearly parallel rays from one origin
    /// (like the samples of a pixel; some lanes with zero direction components), random rays,
    /// partial packets, random far limits.
    fn check_packets(isa: Isa, tris: &[Tri], n_rays: usize, seed: u64) {
        let (bvh, perm) = Bvh::build(tris);
        let inv = inverse(&perm);
        let mut rng = Rng::new(seed);
        let mut k = 0;
        while k < n_rays {
            let len = [PACKET, 1, 5, PACKET + 3, 2 * PACKET][k % 5];
            let bundle = k % 2 == 0;
            let o0 = V3::new(rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0));
            let d0 = V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)) - o0 * 0.1;
            let tmin = if k % 3 == 0 { 1e-4 } else { 0.0 };
            let mut rays = Vec::new();
            let mut tmax = Vec::new();
            for j in 0..len {
                let (o, mut d) = if bundle {
                    let jit = V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0));
                    (o0, d0 + jit * 0.01)
                } else {
                    let o = V3::new(rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0));
                    (
                        o,
                        V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)) - o * 0.1,
                    )
                };
                if j % 7 == 3 {
                    d.x = 0.0;
                }
                // Some lanes leave a random triangle (skipped by the query, as for rays
                // spawned on a surface).
                let skip = if j % 4 == 2 {
                    inv[rng.below(tris.len())]
                } else {
                    NO_PRIM
                };
                rays.push(Ray {
                    skip,
                    ..Ray::new(o, d.normalize())
                });
                tmax.push(if j % 3 == 1 {
                    rng.uniform(0.5, 12.0)
                } else {
                    f32::INFINITY
                });
            }
            let mut got = vec![None; len];
            bvh.intersect_packet_isa(isa, &rays, tmin, &tmax, &mut got);
            let mut occ = vec![false; len];
            bvh.occluded_packet_isa(isa, &rays, tmin, &tmax, &mut occ);
            for j in 0..len {
                let skip = if rays[j].skip == NO_PRIM {
                    usize::MAX
                } else {
                    perm[rays[j].skip as usize] as usize
                };
                let want = brute_excluding(tris, &rays[j], tmin, tmax[j], skip);
                match (want, &got[j]) {
                    (None, None) => {}
                    (Some(w), Some(h)) => same_hit(tris, &perm, &rays[j], tmin, tmax[j], w, h),
                    (w, g) => panic!("packet {k} lane {j}: brute {w:?} vs bvh {g:?}"),
                }
                assert_eq!(want.is_some(), occ[j], "packet {k} lane {j}");
            }
            k += len;
        }
    }

    /// Position of each input primitive in the BVH's order (`inverse(perm)[perm[i]] = i`).
    fn inverse(perm: &[u32]) -> Vec<u32> {
        let mut inv = vec![0u32; perm.len()];
        for (i, &p) in perm.iter().enumerate() {
            inv[p as usize] = i as u32;
        }
        inv
    }

    fn check_isa(isa: Isa, tris: &[Tri], n_rays: usize, seed: u64) -> usize {
        let (bvh, perm) = Bvh::build(tris);
        let inv = inverse(&perm);
        let sorted: Vec<Tri> = perm.iter().map(|&i| tris[i as usize]).collect();
        let mut rng = Rng::new(seed);
        let mut hits = 0;
        for k in 0..n_rays {
            let mut on = usize::MAX;
            let o = if k % 3 == 0 {
                // On a random triangle, as for rays leaving a surface.
                on = rng.below(tris.len());
                let t = &tris[on];
                let (a, b) = (rng.f32() * 0.5, rng.f32() * 0.5);
                t.point(a, b)
            } else {
                V3::new(rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0))
            };
            let mut d = V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)) - o * 0.1;
            match k % 7 {
                0 => d.x = 0.0,
                1 => {
                    d.y = 0.0;
                    d.z = 0.0;
                }
                _ => {}
            }
            // Half of the rays on a triangle leave it (it is skipped), half do not.
            let leaves = k % 6 == 0;
            let ray = if leaves {
                Ray::leaving(inv[on], o, d.normalize())
            } else {
                Ray::new(o, d.normalize())
            };
            let (tmin, tmax) = match k % 4 {
                0 => (1e-4, rng.uniform(0.5, 6.0)),
                1 => (rng.uniform(0.0, 2.0), f32::INFINITY),
                _ => (0.0, f32::INFINITY),
            };
            let want = brute_excluding(tris, &ray, tmin, tmax, if leaves { on } else { usize::MAX });
            let got = bvh.intersect_isa(isa, &ray, tmin, tmax);
            match (want, got) {
                (None, None) => {}
                (Some((t, b1, b2, i)), Some(h)) => {
                    hits += 1;
                    let j = perm[h.prim as usize] as usize;
                    // Same arithmetic as `intersect_tri`: bit-identical distance.
                    assert_eq!(t.to_bits(), h.t.to_bits(), "ray {k}: t {t} vs {}", h.t);
                    if j == i {
                        assert_eq!((b1, b2), (h.b1, h.b2), "ray {k}");
                    } else {
                        // A tie at exactly the same distance: the other triangle must be hit there.
                        let other = intersect_tri(&tris[j], &ray, tmin, tmax).map(|x| x.0);
                        assert_eq!(other, Some(t), "ray {k}: prim {j} instead of {i}");
                    }
                    assert_eq!(sorted[h.prim as usize].p0, tris[j].p0);
                    let tj = &tris[j];
                    assert_eq!(h.p, tj.point(h.b1, h.b2), "ray {k}");
                }
                (w, g) => panic!("ray {k}: brute {w:?} vs bvh {g:?}"),
            }
            assert_eq!(want.is_some(), bvh.occluded_isa(isa, &ray, tmin, tmax), "ray {k}");
        }
        hits
    }

    thread_local! {
        /// Calls of the stack-overflow fallbacks (`traverse_deep`, `traverse_packet_deep`).
        pub(super) static DEEP_CALLS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
    }

    /// Triangles nested along the z axis, each 1.25× the previous and all crossing the axis:
    /// SAH peels them off one level at a time, so a ray along the axis must keep a sibling
    /// per level pending — more than the traversal stack holds. The recursive fallback must
    /// then give the brute-force answer (closest hit, any hit, single rays and packets).
    #[test]
    fn stack_overflow_fallback_matches_brute_force() {
        let tris: Vec<Tri> = (0..240)
            .map(|k| {
                let s = 1.25f32.powi(k);
                let p0 = V3::new(-s, -s, 1.0 + k as f32);
                Tri {
                    p0,
                    p1: p0 + V3::new(3.0 * s, 0.0, 0.0),
                    p2: p0 + V3::new(0.0, 3.0 * s, 0.0),
                }
            })
            .collect();
        let before = DEEP_CALLS.with(|c| c.get());
        let mut rng = Rng::new(17);
        let (bvh, perm) = Bvh::build(&tris);
        for isa in Isa::available() {
            for k in 0..40 {
                let o = V3::new(rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), rng.uniform(-1.0, 30.0));
                let d = V3::new(rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), 1.0).normalize();
                let ray = Ray::new(o, d);
                let want = brute(&tris, &ray, 0.0, f32::INFINITY);
                let got = bvh.intersect_isa(isa, &ray, 0.0, f32::INFINITY);
                match (want, got) {
                    (Some(w), Some(h)) => same_hit(&tris, &perm, &ray, 0.0, f32::INFINITY, w, &h),
                    (w, g) => panic!("ray {k}: brute {w:?} vs bvh {g:?}"),
                }
                assert!(bvh.occluded_isa(isa, &ray, 0.0, f32::INFINITY));
                // Beyond the last triangle nothing is hit.
                let past = Ray::new(V3::new(o.x, o.y, 300.0), d);
                assert!(bvh.intersect_isa(isa, &past, 0.0, f32::INFINITY).is_none());
            }
            let rays: Vec<Ray> = (0..PACKET)
                .map(|_| {
                    let o = V3::new(rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), 0.0);
                    Ray::new(
                        o,
                        V3::new(rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), 1.0).normalize(),
                    )
                })
                .collect();
            let tmax = vec![f32::INFINITY; PACKET];
            let mut got = vec![None; PACKET];
            bvh.intersect_packet_isa(isa, &rays, 0.0, &tmax, &mut got);
            for (ray, h) in rays.iter().zip(&got) {
                let w = brute(&tris, ray, 0.0, f32::INFINITY).expect("the axis crosses every triangle");
                same_hit(
                    &tris,
                    &perm,
                    ray,
                    0.0,
                    f32::INFINITY,
                    w,
                    h.as_ref().expect("packet lane missed"),
                );
            }
        }
        let calls = DEEP_CALLS.with(|c| c.get()) - before;
        assert!(
            calls > 0,
            "the fallback was never reached: the test does not exercise it"
        );
    }

    #[test]
    fn matches_brute_force_on_a_soup() {
        let hits = check(&soup(3000, 5), 3000, 9);
        assert!(hits > 600, "only {hits} hits: the test would not exercise much");
    }

    #[test]
    fn parallel_build_gives_the_sequential_tree() {
        // Enough triangles that bins and bounds are gathered by parallel chunks, subtrees
        // built by `rayon::join` and the root's children collapsed in parallel and appended.
        let tris = grid(200);
        assert!(tris.len() > PAR_BIN);
        let (par, par_perm) = Bvh::build_with(&tris, true);
        let (seq, seq_perm) = Bvh::build_with(&tris, false);
        assert_eq!(par_perm, seq_perm);
        assert_eq!(par.nodes.len(), seq.nodes.len());
        assert_eq!(par.packets.len(), seq.packets.len());
        for (k, (a, b)) in par.nodes.iter().zip(&seq.nodes).enumerate() {
            assert_eq!(a.child, b.child, "node {k}");
            let bits = |n: &Node| n.b.map(|row| row.map(f32::to_bits));
            assert_eq!(bits(a), bits(b), "node {k}");
        }
        for (k, (a, b)) in par.packets.iter().zip(&seq.packets).enumerate() {
            let bits = |p: &Tri4| [p.p0, p.p1, p.p2].map(|m| m.map(|row| row.map(f32::to_bits)));
            assert_eq!((bits(a), a.prim), (bits(b), b.prim), "packet {k}");
        }
        // And the tree answers queries as brute force does.
        let hits = check(&tris, 200, 41);
        assert!(hits > 20, "only {hits} hits");
    }

    #[test]
    fn matches_brute_force_on_a_height_field() {
        let hits = check(&grid(60), 3000, 11);
        assert!(hits > 300, "only {hits} hits");
    }

    /// Packets whose lanes share their direction signs (so the AVX2 kernel also bounds the
    /// packet as a whole and skips children no lane can enter): shadow-like rays from a patch
    /// of a surface to a quad light (finite limits or none), camera-like rays from one point,
    /// and widely spread rays from a spread of origins — each lane against brute force.
    #[test]
    fn rays_in_a_box_face_match_brute_force() {
        // Rays in the plane x = −2 of the height field's left edge, direction x exactly +0 or
        // −0: every box with that face gives the slab distance 0 · ±∞ = NaN, which must leave
        // the slab open, for they hit the edge triangles exactly on their edges (v = 0).
        // Packets of +0 lanes, of −0 lanes and mixed; single rays too.
        let tris = grid(40);
        let (bvh, perm) = Bvh::build(&tris);
        let mut rng = Rng::new(5);
        let rays: Vec<Ray> = (0..64)
            .map(|k| {
                let o = V3::new(-2.0, rng.uniform(-1.4, 1.4), 2.0);
                let mut d = V3::new(0.0, rng.uniform(-0.2, 0.2), -1.0).normalize();
                d.x = if k < 16 || (k >= 32 && k % 2 == 0) { 0.0 } else { -0.0 };
                Ray::new(o, d)
            })
            .collect();
        let tmax = vec![f32::INFINITY; rays.len()];
        for isa in Isa::available() {
            let mut got = vec![None; rays.len()];
            bvh.intersect_packet_isa(isa, &rays, 0.0, &tmax, &mut got);
            let mut occ = vec![false; rays.len()];
            bvh.occluded_packet_isa(isa, &rays, 0.0, &tmax, &mut occ);
            for (j, ray) in rays.iter().enumerate() {
                let want = brute(&tris, ray, 0.0, f32::INFINITY);
                assert!(want.is_some(), "ray {j} should hit an edge triangle");
                let single = bvh.intersect_isa(isa, ray, 0.0, f32::INFINITY);
                for (what, got) in [("packet", &got[j]), ("single", &single)] {
                    match (want, got) {
                        (Some(w), Some(h)) => same_hit(&tris, &perm, ray, 0.0, f32::INFINITY, w, h),
                        (w, g) => panic!("{isa:?} {what} ray {j}: brute {w:?} vs bvh {g:?}"),
                    }
                }
                assert!(occ[j], "{isa:?} ray {j}: not occluded");
                assert!(bvh.occluded_isa(isa, ray, 0.0, f32::INFINITY), "{isa:?} single ray {j}");
            }
        }
    }

    #[test]
    fn sign_uniform_packets_match_brute_force() {
        for (tris, seed) in [(grid(60), 21), (soup(2000, 7), 22)] {
            let (bvh, perm) = Bvh::build(&tris);
            let inv = inverse(&perm);
            let mut rng = Rng::new(seed);
            let mut hits = 0;
            for k in 0..240 {
                let len = [PACKET, 11, 3, PACKET][k % 4];
                let kind = k % 3;
                let base = rng.below(tris.len() - 40);
                let eye = V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(2.0, 4.0));
                let aim = V3::new(rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5), 0.0) - eye;
                let corner = V3::new(2.5, 2.5, rng.uniform(0.5, 2.0));
                let finite = k % 2 == 0;
                let mut rays = Vec::new();
                let mut tmax = Vec::new();
                for _ in 0..len {
                    let (ray, tm) = match kind {
                        0 => {
                            // From a triangle near `base` to a point of a 1 m quad light.
                            let on = base + rng.below(40);
                            let t = &tris[on];
                            let (a, b) = (rng.f32() * 0.5, rng.f32() * 0.5);
                            let o = t.point(a, b);
                            let q = corner + V3::new(rng.f32(), rng.f32(), 0.0);
                            let dist = (q - o).length();
                            let tm = if finite { dist * (1.0 - 1e-3) } else { f32::INFINITY };
                            (Ray::leaving(inv[on], o, (q - o).normalize()), tm)
                        }
                        1 => {
                            let jit = V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0));
                            (Ray::new(eye, (aim + jit * 0.01).normalize()), f32::INFINITY)
                        }
                        _ => {
                            let o = eye + V3::new(rng.f32(), rng.f32(), rng.f32());
                            let d = V3::new(-0.1 - rng.f32(), -0.1 - rng.f32(), -0.1 - rng.f32());
                            let tm = if finite { rng.uniform(0.5, 5.0) } else { f32::INFINITY };
                            (Ray::new(o, d.normalize()), tm)
                        }
                    };
                    rays.push(ray);
                    tmax.push(tm);
                }
                for isa in Isa::available() {
                    let mut got = vec![None; len];
                    bvh.intersect_packet_isa(isa, &rays, 0.0, &tmax, &mut got);
                    let mut occ = vec![false; len];
                    bvh.occluded_packet_isa(isa, &rays, 0.0, &tmax, &mut occ);
                    for j in 0..len {
                        let skip = if rays[j].skip == NO_PRIM {
                            usize::MAX
                        } else {
                            perm[rays[j].skip as usize] as usize
                        };
                        let want = brute_excluding(&tris, &rays[j], 0.0, tmax[j], skip);
                        match (want, &got[j]) {
                            (None, None) => {}
                            (Some(w), Some(h)) => {
                                hits += 1;
                                same_hit(&tris, &perm, &rays[j], 0.0, tmax[j], w, h)
                            }
                            (w, g) => panic!("{isa:?} packet {k} lane {j}: brute {w:?} vs bvh {g:?}"),
                        }
                        assert_eq!(want.is_some(), occ[j], "{isa:?} packet {k} lane {j}");
                    }
                }
            }
            assert!(hits > 400, "only {hits} hits");
        }
    }

    #[test]
    fn matches_brute_force_on_tiny_and_degenerate_inputs() {
        for n in [1, 3, 4, 5, 9] {
            check(&soup(n, n as u64), 300, 3);
        }
        // Many coincident triangles: no SAH split exists, so median splits build the tree.
        let same: Vec<Tri> = (0..500)
            .map(|i| {
                let p0 = V3::new(-1.0, -1.0, 0.001 * (i % 7) as f32);
                Tri {
                    p0,
                    p1: p0 + V3::new(2.0, 0.0, 0.0),
                    p2: p0 + V3::new(0.0, 2.0, 0.0),
                }
            })
            .collect();
        check(&same, 300, 4);
        let (bvh, perm) = Bvh::build(&[]);
        assert!(perm.is_empty());
        let ray = Ray::new(V3::ZERO, V3::new(0.0, 0.0, 1.0));
        assert!(bvh.intersect(&ray, 0.0, f32::INFINITY).is_none());
        assert!(!bvh.occluded(&ray, 0.0, f32::INFINITY));
    }
}
