//! Packet traversal with AVX-512: [`super::packet_avx2`]'s kernel with the 16 lanes of a
//! packet in one 512-bit vector and the lane sets in mask registers (one instruction per
//! operation instead of two, no mask conversions).
//!
//! Contract: as [`super::packet_avx2`] — per lane the same IEEE operations in the same order
//! as [`super::intersect_tri`] and the portable box test (`vmaxps`/`vminps` operand order
//! keeps the accumulated slab bound when a plane distance is NaN), so per-lane results are
//! bit-identical to the portable traversal's.
use super::{Bvh, Isa, RayPack, Tri4, EMPTY, FINISH_ALONE, LEAF, LEAF_COUNT_SHIFT, LEAF_INDEX_MASK, PACKET, STACK};
use std::arch::x86_64::*;

#[inline]
#[target_feature(enable = "avx512f")]
fn ld(a: &[f32; PACKET]) -> __m512 {
    // SAFETY: `a` is 16 initialised f32 (64 bytes); `loadu` has no alignment requirement.
    unsafe { _mm512_loadu_ps(a.as_ptr()) }
}

#[inline]
#[target_feature(enable = "avx512f")]
fn st(a: &mut [f32; PACKET], v: __m512) {
    // SAFETY: as in `ld`, for 16 writable f32.
    unsafe { _mm512_storeu_ps(a.as_mut_ptr(), v) }
}

#[inline]
#[target_feature(enable = "avx512f")]
fn ld_u32(a: &[u32; PACKET]) -> __m512i {
    // SAFETY: `a` is 16 initialised u32 (64 bytes); `loadu` has no alignment requirement.
    unsafe { _mm512_loadu_si512(a.as_ptr().cast()) }
}

impl Bvh {
    /// [`Bvh::traverse_packet_body`] with AVX-512 (see the module header).
    #[target_feature(enable = "avx512f,avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    pub(super) fn traverse_packet_avx512<const ANY: bool>(&self, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        let zero = _mm512_setzero_ps();
        // Per axis: lanes whose direction is negative (near plane = the box's `hi`).
        let neg: [__mmask16; 3] = std::array::from_fn(|a| _mm512_cmp_ps_mask::<_CMP_LT_OQ>(ld(&p.inv[a]), zero));
        let o = [ld(&p.o[0]), ld(&p.o[1]), ld(&p.o[2])];
        let inv = [ld(&p.inv[0]), ld(&p.inv[1]), ld(&p.inv[2])];
        let slack = _mm512_set1_ps(1.000_000_2);
        let inf = _mm512_set1_ps(f32::INFINITY);
        let mut stack_c = [0u32; STACK];
        let mut stack_m = [0u32; STACK];
        let mut stack_t = [0u32; STACK];
        let mut sp = 0usize;
        let (mut cur, mut act) = (start, act);
        loop {
            if ANY {
                act &= !p.found;
            }
            if act != 0 && act.count_ones() <= FINISH_ALONE && cur != EMPTY {
                let mut m = act;
                while m != 0 {
                    let r = m.trailing_zeros() as usize;
                    m &= m - 1;
                    self.finish_lane::<ANY>(Isa::Avx2, cur, r, p, tmin);
                }
            } else if act != 0 && cur & LEAF == 0 {
                let n = &self.nodes[cur as usize];
                let tmax = ld(&p.tmax);
                let mut cm = [0u32; 4];
                let mut ct = [u32::MAX; 4];
                for c in 0..4 {
                    let slab = |a: usize| {
                        let (lo, hi) = (_mm512_set1_ps(n.b[a][c]), _mm512_set1_ps(n.b[a + 3][c]));
                        let a0 = _mm512_mul_ps(_mm512_sub_ps(lo, o[a]), inv[a]);
                        let a1 = _mm512_mul_ps(_mm512_sub_ps(hi, o[a]), inv[a]);
                        (
                            _mm512_mask_blend_ps(neg[a], a0, a1),
                            _mm512_mask_blend_ps(neg[a], a1, a0),
                        )
                    };
                    let (t0x, t1x) = slab(0);
                    let (t0y, t1y) = slab(1);
                    let (t0z, t1z) = slab(2);
                    // `vmaxps(a, b)` is `a > b ? a : b`: a NaN `a` keeps `b`, the slab stays open.
                    let t0 = _mm512_max_ps(t0z, _mm512_max_ps(t0y, _mm512_max_ps(t0x, zero)));
                    let t1 = _mm512_min_ps(t1z, _mm512_min_ps(t1y, _mm512_min_ps(t1x, tmax)));
                    let m =
                        _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(act as __mmask16, t0, _mm512_mul_ps(t1, slack)) as u32;
                    cm[c] = m;
                    if !ANY && m != 0 {
                        // Entry distances are ≥ +0, so their bits order as the floats do.
                        ct[c] = _mm512_reduce_min_ps(_mm512_mask_blend_ps(m as __mmask16, inf, t0)).to_bits();
                    }
                }
                // Hit children, nearest first (any-hit: in slot order).
                let mut order = [0usize; 4];
                let mut k = 0;
                for c in 0..4 {
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
                if k > 0 {
                    for j in (1..k).rev() {
                        let c = order[j];
                        if sp < STACK {
                            self.prefetch(n.child[c]);
                            stack_c[sp] = n.child[c];
                            stack_m[sp] = cm[c];
                            stack_t[sp] = ct[c];
                            sp += 1;
                        } else {
                            self.traverse_packet_deep::<ANY>(n.child[c], cm[c], p, tmin);
                        }
                    }
                    cur = n.child[order[0]];
                    act = cm[order[0]];
                    continue;
                }
            } else if act != 0 && cur != EMPTY {
                let first = (cur & LEAF_INDEX_MASK) as usize;
                let count = ((cur & !LEAF) >> LEAF_COUNT_SHIFT) as usize + 1;
                for pk in &self.packets[first..first + count] {
                    for l in 0..4 {
                        if pk.prim[l] == u32::MAX {
                            break;
                        }
                        let m = tri_lanes(pk, l, p, tmin, act);
                        p.record(m, pk, l);
                    }
                }
            }
            // Pop the next entry that can still hold a closer hit for one of its lanes.
            loop {
                if sp == 0 {
                    return;
                }
                sp -= 1;
                let m = stack_m[sp];
                if ANY {
                    if m & !p.found != 0 {
                        cur = stack_c[sp];
                        act = m;
                        break;
                    }
                    continue;
                }
                // Farthest limit (as bits, as the portable body compares them) among the
                // entry's lanes.
                let bits = _mm512_castps_si512(ld(&p.tmax));
                let far = _mm512_reduce_max_epu32(_mm512_maskz_mov_epi32(m as __mmask16, bits));
                if stack_t[sp] <= far {
                    cur = stack_c[sp];
                    act = m;
                    break;
                }
            }
        }
    }
}

/// Lane `l` of packet `pk` against every ray of `p` active in `act` (the operations of
/// [`super::intersect_tri`] in the same order); lanes hit closer than their current limit get
/// the hit recorded (distance, barycentrics) and are returned as a mask.
#[inline]
#[target_feature(enable = "avx512f,avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
fn tri_lanes(pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32) -> u32 {
    let s = |v: f32| _mm512_set1_ps(v);
    let (e1x, e1y, e1z) = (s(pk.e1[0][l]), s(pk.e1[1][l]), s(pk.e1[2][l]));
    let (e2x, e2y, e2z) = (s(pk.e2[0][l]), s(pk.e2[1][l]), s(pk.e2[2][l]));
    let (p0x, p0y, p0z) = (s(pk.p0[0][l]), s(pk.p0[1][l]), s(pk.p0[2][l]));
    let (mul, sub, add) = (_mm512_mul_ps, _mm512_sub_ps, _mm512_add_ps);
    let (dx, dy, dz) = (ld(&p.d[0]), ld(&p.d[1]), ld(&p.d[2]));
    let (ox, oy, oz) = (ld(&p.o[0]), ld(&p.o[1]), ld(&p.o[2]));
    let px = sub(mul(dy, e2z), mul(dz, e2y));
    let py = sub(mul(dz, e2x), mul(dx, e2z));
    let pz = sub(mul(dx, e2y), mul(dy, e2x));
    let det = add(add(mul(e1x, px), mul(e1y, py)), mul(e1z, pz));
    let inv = _mm512_div_ps(s(1.0), det);
    let (sx, sy, sz) = (sub(ox, p0x), sub(oy, p0y), sub(oz, p0z));
    let u = mul(add(add(mul(sx, px), mul(sy, py)), mul(sz, pz)), inv);
    let qx = sub(mul(sy, e1z), mul(sz, e1y));
    let qy = sub(mul(sz, e1x), mul(sx, e1z));
    let qz = sub(mul(sx, e1y), mul(sy, e1x));
    let v = mul(add(add(mul(dx, qx), mul(dy, qy)), mul(dz, qz)), inv);
    let tt = mul(add(add(mul(e2x, qx), mul(e2y, qy)), mul(e2z, qz)), inv);
    let tmax = ld(&p.tmax);
    // Each compare only over the lanes still passing (a zero-masking chain of ANDs).
    let mut ok = _mm512_cmpneq_epi32_mask(_mm512_set1_epi32(pk.prim[l] as i32), ld_u32(&p.skip)) & act as __mmask16;
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(ok, _mm512_abs_ps(det), s(1e-20));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(ok, u, s(0.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(ok, u, s(1.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(ok, v, s(0.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(ok, add(u, v), s(1.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(ok, tt, s(tmin));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_LT_OQ>(ok, tt, tmax);
    if ok != 0 {
        st(&mut p.tmax, _mm512_mask_blend_ps(ok, tmax, tt));
        let (b1, b2) = (ld(&p.b1), ld(&p.b2));
        st(&mut p.b1, _mm512_mask_blend_ps(ok, b1, u));
        st(&mut p.b2, _mm512_mask_blend_ps(ok, b2, v));
    }
    ok as u32
}
