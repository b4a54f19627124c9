//! The traversal loop shared by the SIMD packet kernels (`packet_avx2.rs`, `packet_avx512.rs`):
//! the algorithm of [`Bvh::traverse_packet_body`] — a node is visited while any active lane
//! enters one of its children, children nearest-entry first, few-lane subtrees finished by
//! single rays, lanes retired at their first hit for any-hit queries — with the per-lane
//! arithmetic (child boxes, leaf triangles, lane reductions) supplied by a [`Lanes`] kernel.
//!
//! Contract: the kernels' per-lane results are those of the portable body, bit for bit (see
//! each kernel's header). Packets whose lanes share their direction signs (a pixel's camera
//! rays, its shadow rays to one light) are also bounded as a whole ([`Frustum`]: ranges of
//! origins and reciprocal directions, largest limit): a node's four children are first tested
//! against those bounds in one SSE step, and only the children the bounds cannot exclude get
//! the per-lane tests. The bounds are conservative under rounding (every operation is
//! monotonic), so the per-lane masks, and with them the results, are exactly those without it.
//!
//! The loop is `#[inline(always)]` and `unsafe`: it is compiled into each kernel's
//! `#[target_feature]` entry points (whose `Lanes` methods carry the same features, so that
//! their intrinsics inline), which the caller may use only on a CPU that has those features
//! ([`super::Isa::detect`]).
use super::packet_avx2::Frustum;
use super::{Bvh, Node, PacketStack, RayPack, Tri4, EMPTY, FINISH_ALONE, LEAF, NW, PACKET};

/// The lane arithmetic of a SIMD packet kernel. Safety (every method): the CPU has the
/// kernel's target features.
pub(super) trait Lanes: Sized {
    /// Per-traversal state (the rays' fixed rows as vectors, per-axis sign masks).
    unsafe fn new(p: &RayPack) -> Self;
    /// Lanes whose reciprocal direction on axis `a` is negative (`< 0`).
    fn neg(&self, a: usize) -> u32;
    /// For each child `c` of `n` set in `enter`: the lanes of `act` whose ray enters its box
    /// within their current limit (`cm[c]`) and, for closest-hit queries, the bits of the
    /// nearest such entry distance (`ct[c]`, `u32::MAX` if none). With `UNI`, every active
    /// lane's near and far planes are the rows `near` and `far` of `n`'s boxes.
    unsafe fn children<const ANY: bool, const UNI: bool>(
        &self,
        n: &Node,
        p: &RayPack,
        act: u32,
        enter: u32,
        near: [usize; 3],
        far: [usize; 3],
    ) -> ([u32; NW], [u32; NW]);
    /// Lane `l` of `pk` against the rays of `p` in `act`, which share their axes `k` (`[kx, ky,
    /// kz]`, see [`super::RayPack::uniform_kz`]) — the watertight test, the operations of
    /// [`super::intersect_tri`] per lane: lanes hit closer than their limit get the distance
    /// and barycentrics written and are returned as a mask.
    unsafe fn tri_uniform(&self, pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32, k: [usize; 3]) -> u32;
    /// Every triangle of leaf packets `pks` against the rays of `p` in `act`, whose axes differ
    /// (the same test with the axes permuted lane by lane), hits recorded
    /// ([`RayPack::record`]); returns the lanes hit. Out of line: a leaf per call, so that the
    /// common case, [`Lanes::tri_uniform`], stays small enough to inline into the loop.
    unsafe fn leaf_mixed(&self, pks: &[Tri4], p: &mut RayPack, tmin: f32, act: u32) -> u32;
    /// The largest of `v`'s values in the lanes of `act` (−∞ if none).
    unsafe fn lanes_max(v: &[f32; PACKET], act: u32) -> f32;
    /// The largest limit among the lanes in `m`, as bits (limits are ≥ +0 or +∞).
    unsafe fn far_bits(p: &RayPack, m: u32) -> u32;
}

impl Bvh {
    /// Packet traversal of the subtree under `start` for the lanes in `act` with kernel `K`:
    /// its per-traversal state, then the loop specialised for sign-uniform packets or not.
    ///
    /// # Safety
    /// As [`Bvh::packet_loop`].
    #[inline(always)]
    pub(super) unsafe fn packet_traverse<K: Lanes, const ANY: bool>(
        &self,
        start: u32,
        act: u32,
        p: &mut RayPack,
        tmin: f32,
    ) {
        // SAFETY (all three): the caller's contract.
        let k = unsafe { K::new(p) };
        match Bvh::packet_signs(&k, act) {
            (true, sign) => unsafe { self.packet_loop::<K, ANY, true>(&k, start, act, p, tmin, sign) },
            (false, sign) => unsafe { self.packet_loop::<K, ANY, false>(&k, start, act, p, tmin, sign) },
        }
    }

    /// The loop of [`Bvh::packet_traverse`]; `sign`: with `UNI`, the axes on which every active
    /// lane's direction is negative.
    ///
    /// # Safety
    /// The CPU has `K`'s target features (and AVX2, which [`Frustum`] uses).
    #[inline(always)]
    unsafe fn packet_loop<K: Lanes, const ANY: bool, const UNI: bool>(
        &self,
        k: &K,
        start: u32,
        act: u32,
        p: &mut RayPack,
        tmin: f32,
        sign: [bool; 3],
    ) {
        // Rows of `Node::b` holding each axis's near and far planes (used with `UNI`).
        let near: [usize; 3] = std::array::from_fn(|a| a + 3 * sign[a] as usize);
        let far: [usize; 3] = std::array::from_fn(|a| a + 3 - 3 * sign[a] as usize);
        let act0 = act;
        // SAFETY (all `unsafe` calls below): the CPU has `K`'s features and AVX2 (contract).
        let mut frustum = if UNI {
            unsafe { Frustum::new(p, act, sign) }
        } else {
            None
        };
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
                let enter = match &frustum {
                    Some(f) => unsafe { f.may_enter(n, near, far) },
                    None => (1 << NW) - 1,
                };
                let (cm, ct) = unsafe { k.children::<ANY, UNI>(n, p, act, enter, near, far) };
                let next = stack.push_children::<ANY>(self, n, &cm, &ct, |c, m| {
                    self.traverse_packet_deep::<ANY>(c, m, p, tmin)
                });
                if let Some((c, m)) = next {
                    (cur, act) = (c, m);
                    continue;
                }
            } else if act != 0 && cur != EMPTY {
                let pks = self.leaf_packets(cur);
                let hit = match p.uniform_kz(act) {
                    Some(kz) => {
                        let axes = super::axes(kz);
                        let mut hit = 0u32;
                        for pk in pks {
                            for l in 0..4 {
                                if pk.prim[l] == u32::MAX {
                                    break;
                                }
                                let m = unsafe { k.tri_uniform(pk, l, p, tmin, act, axes) };
                                p.record(m, pk, l);
                                hit |= m;
                            }
                        }
                        hit
                    }
                    None => unsafe { k.leaf_mixed(pks, p, tmin, act) },
                };
                if !ANY && hit != 0 {
                    if let Some(f) = &mut frustum {
                        f.tmax = unsafe { K::lanes_max(&p.tmax, act0) };
                    }
                }
            }
            // Pop the next entry that can still hold a closer hit for one of its lanes.
            let live = |m: u32, t: u32| {
                if ANY {
                    return m & !p.found != 0;
                }
                // Farthest limit (as bits, as the portable body compares them) among the
                // entry's lanes.
                t <= unsafe { K::far_bits(p, m) }
            };
            match stack.pop(live) {
                Some((c, m)) => (cur, act) = (c, m),
                None => return,
            }
        }
    }

    /// Whether every active lane's direction has the same sign on each axis, and which axes
    /// are negative (for [`Bvh::packet_loop`]'s `UNI` and `sign`).
    #[inline(always)]
    fn packet_signs<K: Lanes>(k: &K, act: u32) -> (bool, [bool; 3]) {
        let mut uniform = true;
        let mut sign = [false; 3];
        for (a, s) in sign.iter_mut().enumerate() {
            let neg = k.neg(a) & act;
            uniform &= neg == 0 || neg == act;
            *s = neg != 0;
        }
        (uniform, sign)
    }
}
