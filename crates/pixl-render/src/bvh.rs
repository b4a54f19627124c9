//! A bounding-volume hierarchy over triangles: binned SAH build (12 bins × 3 axes), flattened
//! depth-first nodes (left child follows its parent), ordered stack traversal.
//!
//! Why our own rather than a crate: we measured the need, not two crates — the renderer needs
//! ~150 lines of BVH, must be deterministic (the build is single-threaded and tie-breaks by
//! index, so the same scene gives the same tree and bit-identical images), and is tuned for our
//! triangle layout ([`Tri`]: vertex + two edges, Möller–Trumbore) with primitives reordered into
//! leaf order for locality. The crates we looked at (`bvh`, `obvhs`) either bring their own
//! vector types or their own ray/primitive traits; adapting to them costs as much code as this.
use crate::math::V3;

/// A triangle as stored for intersection: one vertex and two edges.
#[derive(Clone, Copy, Debug)]
pub struct Tri {
    pub p0: V3,
    pub e1: V3,
    pub e2: V3,
}

/// A ray with precomputed reciprocal direction.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub o: V3,
    pub d: V3,
    pub inv_d: V3,
}

impl Ray {
    pub fn new(o: V3, d: V3) -> Self {
        Ray {
            o,
            d,
            inv_d: V3::new(1.0 / d.x, 1.0 / d.y, 1.0 / d.z),
        }
    }
}

/// A ray–triangle hit: distance, barycentrics of vertices 1 and 2, primitive index.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f32,
    pub b1: f32,
    pub b2: f32,
    pub prim: u32,
}

#[derive(Clone, Copy, Debug)]
struct Node {
    min: [f32; 3],
    /// Leaf: first primitive; interior: index of the right child.
    offset: u32,
    max: [f32; 3],
    /// Leaf: primitive count (> 0); interior: 0.
    count: u32,
}

#[derive(Clone, Debug, Default)]
pub struct Bvh {
    nodes: Vec<Node>,
}

#[derive(Clone, Copy)]
struct Aabb {
    lo: V3,
    hi: V3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        lo: V3::splat_const(f32::INFINITY),
        hi: V3::splat_const(f32::NEG_INFINITY),
    };
    fn grow(&mut self, o: &Aabb) {
        self.lo = self.lo.min(o.lo);
        self.hi = self.hi.max(o.hi);
    }
    fn grow_p(&mut self, p: V3) {
        self.lo = self.lo.min(p);
        self.hi = self.hi.max(p);
    }
    fn area(&self) -> f32 {
        let d = self.hi - self.lo;
        if d.x < 0.0 {
            return 0.0;
        }
        2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
    }
}

impl V3 {
    const fn splat_const(v: f32) -> V3 {
        V3 { x: v, y: v, z: v }
    }
}

const BINS: usize = 12;
const MAX_LEAF: usize = 8;

impl Bvh {
    /// Builds over `tris` and returns the tree and the permutation: position `i` of the
    /// reordered primitives holds original primitive `perm[i]`. Reorder your arrays with it.
    pub fn build(tris: &[Tri]) -> (Bvh, Vec<u32>) {
        let boxes: Vec<Aabb> = tris
            .iter()
            .map(|t| {
                let mut b = Aabb::EMPTY;
                b.grow_p(t.p0);
                b.grow_p(t.p0 + t.e1);
                b.grow_p(t.p0 + t.e2);
                b
            })
            .collect();
        let cents: Vec<V3> = boxes.iter().map(|b| (b.lo + b.hi) * 0.5).collect();
        let mut idx: Vec<u32> = (0..tris.len() as u32).collect();
        let mut bvh = Bvh {
            nodes: Vec::with_capacity(2 * tris.len() / 3 + 1),
        };
        if !tris.is_empty() {
            bvh.build_rec(&boxes, &cents, &mut idx, 0);
        }
        (bvh, idx)
    }

    fn build_rec(&mut self, boxes: &[Aabb], cents: &[V3], idx: &mut [u32], first: usize) -> usize {
        let node_i = self.nodes.len();
        let mut bb = Aabb::EMPTY;
        let mut cb = Aabb::EMPTY;
        for &i in idx.iter() {
            bb.grow(&boxes[i as usize]);
            cb.grow_p(cents[i as usize]);
        }
        let n = idx.len();
        self.nodes.push(Node {
            min: bb.lo.to_arr(),
            offset: first as u32,
            max: bb.hi.to_arr(),
            count: n as u32,
        });
        if n <= 2 {
            return node_i;
        }
        // Binned SAH over the three axes.
        let mut best: Option<(usize, usize, f32)> = None;
        for axis in 0..3 {
            let (lo, hi) = (cb.lo[axis], cb.hi[axis]);
            if hi - lo <= 1e-12 {
                continue;
            }
            let scale = BINS as f32 / (hi - lo);
            let mut bins = [(Aabb::EMPTY, 0usize); BINS];
            for &i in idx.iter() {
                let b = (((cents[i as usize][axis] - lo) * scale) as usize).min(BINS - 1);
                bins[b].0.grow(&boxes[i as usize]);
                bins[b].1 += 1;
            }
            let mut right_area = [0.0f32; BINS];
            let mut right_count = [0usize; BINS];
            let mut acc = Aabb::EMPTY;
            let mut cnt = 0;
            for b in (1..BINS).rev() {
                acc.grow(&bins[b].0);
                cnt += bins[b].1;
                right_area[b] = acc.area();
                right_count[b] = cnt;
            }
            let mut acc = Aabb::EMPTY;
            let mut cnt = 0;
            for b in 0..BINS - 1 {
                acc.grow(&bins[b].0);
                cnt += bins[b].1;
                if cnt == 0 || right_count[b + 1] == 0 {
                    continue;
                }
                let cost = acc.area() * cnt as f32 + right_area[b + 1] * right_count[b + 1] as f32;
                if best.is_none_or(|(_, _, c)| cost < c) {
                    best = Some((axis, b, cost));
                }
            }
        }
        let parent_area = bb.area().max(1e-30);
        let mid = match best {
            Some((axis, b, cost)) if 1.0 + cost / parent_area < n as f32 || n > MAX_LEAF => {
                let (lo, hi) = (cb.lo[axis], cb.hi[axis]);
                let scale = BINS as f32 / (hi - lo);
                let mut l = 0;
                for k in 0..n {
                    let c = cents[idx[k] as usize][axis];
                    if (((c - lo) * scale) as usize).min(BINS - 1) <= b {
                        idx.swap(k, l);
                        l += 1;
                    }
                }
                l
            }
            Some(_) => return node_i,
            None if n > MAX_LEAF => n / 2,
            None => return node_i,
        };
        if mid == 0 || mid == n {
            return node_i;
        }
        let (left, right) = idx.split_at_mut(mid);
        self.build_rec(boxes, cents, left, first);
        let r = self.build_rec(boxes, cents, right, first + mid);
        self.nodes[node_i].offset = r as u32;
        self.nodes[node_i].count = 0;
        node_i
    }

    pub fn num_nodes(&self) -> usize {
        self.nodes.len()
    }

    #[inline]
    fn slab(node: &Node, ray: &Ray, tmax: f32) -> f32 {
        let mut t0 = 0.0f32;
        let mut t1 = tmax;
        for k in 0..3 {
            let o = ray.o[k];
            let inv = ray.inv_d[k];
            let a = (node.min[k] - o) * inv;
            let b = (node.max[k] - o) * inv;
            let (near, far) = if a < b { (a, b) } else { (b, a) };
            // NaN (0 * inf) comparisons fall through and keep the slab open.
            t0 = if near > t0 { near } else { t0 };
            t1 = if far < t1 { far } else { t1 };
        }
        if t0 <= t1 * 1.000_000_2 {
            t0
        } else {
            f32::INFINITY
        }
    }

    /// Closest hit in `(tmin, tmax)`.
    pub fn intersect(&self, tris: &[Tri], ray: &Ray, tmin: f32, tmax: f32) -> Option<Hit> {
        self.traverse::<false>(tris, ray, tmin, tmax)
    }

    /// Whether anything is hit in `(tmin, tmax)`.
    pub fn occluded(&self, tris: &[Tri], ray: &Ray, tmin: f32, tmax: f32) -> bool {
        self.traverse::<true>(tris, ray, tmin, tmax).is_some()
    }

    fn traverse<const ANY: bool>(&self, tris: &[Tri], ray: &Ray, tmin: f32, tmax: f32) -> Option<Hit> {
        if self.nodes.is_empty() {
            return None;
        }
        let mut best: Option<Hit> = None;
        let mut tmax = tmax;
        let mut stack = [0u32; 64];
        let mut sp = 0usize;
        let mut ni = 0usize;
        if Self::slab(&self.nodes[0], ray, tmax) == f32::INFINITY {
            return None;
        }
        loop {
            let node = &self.nodes[ni];
            if node.count > 0 {
                let first = node.offset as usize;
                for p in first..first + node.count as usize {
                    if let Some((t, b1, b2)) = intersect_tri(&tris[p], ray, tmin, tmax) {
                        tmax = t;
                        best = Some(Hit {
                            t,
                            b1,
                            b2,
                            prim: p as u32,
                        });
                        if ANY {
                            return best;
                        }
                    }
                }
            } else {
                let (l, r) = (ni + 1, node.offset as usize);
                let tl = Self::slab(&self.nodes[l], ray, tmax);
                let tr = Self::slab(&self.nodes[r], ray, tmax);
                let (near, far, tn, tf) = if tl <= tr { (l, r, tl, tr) } else { (r, l, tr, tl) };
                if tn != f32::INFINITY {
                    if tf != f32::INFINITY && sp < stack.len() {
                        stack[sp] = far as u32;
                        sp += 1;
                    }
                    ni = near;
                    continue;
                }
            }
            if sp == 0 {
                break;
            }
            sp -= 1;
            ni = stack[sp] as usize;
        }
        best
    }
}

/// Möller–Trumbore; returns `(t, b1, b2)` for a hit in `(tmin, tmax)`. Two-sided.
#[inline]
pub fn intersect_tri(tri: &Tri, ray: &Ray, tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
    let p = ray.d.cross(tri.e2);
    let det = tri.e1.dot(p);
    if det.abs() < 1e-20 {
        return None;
    }
    let inv = 1.0 / det;
    let s = ray.o - tri.p0;
    let b1 = s.dot(p) * inv;
    if !(0.0..=1.0).contains(&b1) {
        return None;
    }
    let q = s.cross(tri.e1);
    let b2 = ray.d.dot(q) * inv;
    if b2 < 0.0 || b1 + b2 > 1.0 {
        return None;
    }
    let t = tri.e2.dot(q) * inv;
    if t > tmin && t < tmax {
        Some((t, b1, b2))
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_core::Rng;

    #[test]
    fn matches_brute_force() {
        let mut rng = Rng::new(5);
        let mut r = || rng.uniform(-1.0, 1.0);
        let tris: Vec<Tri> = (0..2000)
            .map(|_| {
                let p0 = V3::new(r() * 5.0, r() * 5.0, r() * 5.0);
                Tri {
                    p0,
                    e1: V3::new(r(), r(), r()) * 0.5,
                    e2: V3::new(r(), r(), r()) * 0.5,
                }
            })
            .collect();
        let (bvh, perm) = Bvh::build(&tris);
        let sorted: Vec<Tri> = perm.iter().map(|&i| tris[i as usize]).collect();
        let mut rng = Rng::new(9);
        for _ in 0..500 {
            let o = V3::new(rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0), rng.uniform(-8.0, 8.0));
            let d =
                (V3::new(rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0)) - o * 0.1).normalize();
            let ray = Ray::new(o, d);
            let brute = tris
                .iter()
                .enumerate()
                .filter_map(|(i, t)| intersect_tri(t, &ray, 0.0, f32::INFINITY).map(|h| (h.0, i)))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            let fast = bvh.intersect(&sorted, &ray, 0.0, f32::INFINITY);
            match (brute, fast) {
                (None, None) => {}
                (Some((t, i)), Some(h)) => {
                    assert!((t - h.t).abs() < 1e-5, "{t} vs {}", h.t);
                    assert_eq!(perm[h.prim as usize] as usize, i);
                }
                (b, f) => panic!("brute {b:?} vs bvh {f:?}"),
            }
            assert_eq!(brute.is_some(), bvh.occluded(&sorted, &ray, 0.0, f32::INFINITY));
        }
    }
}
