//! Packet traversal with AVX-512F: [`super::packet_avx2`]'s algorithm with the 16 lanes of a
//! packet in one 512-bit vector and lane sets as mask registers (one box test per child, one
//! triangle test per leaf lane, masked stores of the hits).
//!
//! Contract: as `packet_avx2`'s — per lane the same IEEE operations in the same order as
//! [`super::intersect_tri`] and the portable box test (`vmaxps`/`vminps` keep the same operand
//! order, so a NaN slab stays open; `vdivps`, no reciprocal estimates; no FMA), hence the same
//! results bit for bit. Packets whose lanes share direction signs are culled by the AVX2
//! kernel's [`Frustum`](super::packet_avx2) bounds first, as there.
use super::packet_avx2::Frustum;
use super::{Bvh, PacketStack, RayPack, Tri4, EMPTY, FINISH_ALONE, LEAF, NW, PACKET};
use std::arch::x86_64::*;

#[inline]
#[target_feature(enable = "avx512f")]
fn ld(a: &[f32; PACKET]) -> __m512 {
    // SAFETY: `a` is exactly 16 initialised f32; `loadu` has no alignment requirement.
    unsafe { _mm512_loadu_ps(a.as_ptr()) }
}

#[inline]
#[target_feature(enable = "avx512f")]
fn ld_u32(a: &[u32; PACKET]) -> __m512i {
    // SAFETY: `a` is exactly 16 initialised u32 (64 bytes); `loadu` is unaligned.
    unsafe { _mm512_loadu_si512(a.as_ptr().cast()) }
}

/// Writes the lanes of `v` selected by `k` to `a`.
#[inline]
#[target_feature(enable = "avx512f")]
fn st_masked(a: &mut [f32; PACKET], k: __mmask16, v: __m512) {
    // SAFETY: `a` is exactly 16 f32; masked-off lanes are neither read nor written.
    unsafe { _mm512_mask_storeu_ps(a.as_mut_ptr(), k, v) }
}

impl Bvh {
    /// [`Bvh::traverse_packet_body`] with AVX-512F (see the module header).
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    pub(super) fn traverse_packet_avx512<const ANY: bool>(&self, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        let zero = _mm512_setzero_ps();
        let neg: [__mmask16; 3] = std::array::from_fn(|a| _mm512_cmp_ps_mask::<_CMP_LT_OQ>(ld(&p.inv[a]), zero));
        let act16 = act as __mmask16;
        let uniform = neg.iter().all(|&n| n & act16 == 0 || n & act16 == act16);
        let sign: [bool; 3] = std::array::from_fn(|a| neg[a] & act16 != 0);
        if uniform {
            self.traverse_packet_avx512_body::<ANY, true>(start, act, p, tmin, sign, neg)
        } else {
            self.traverse_packet_avx512_body::<ANY, false>(start, act, p, tmin, sign, neg)
        }
    }

    /// The traversal; with `UNI`, every active lane's direction has the negative components
    /// given by `sign`; otherwise `neg` holds, per axis, the lanes whose direction is negative.
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    fn traverse_packet_avx512_body<const ANY: bool, const UNI: bool>(
        &self,
        start: u32,
        act: u32,
        p: &mut RayPack,
        tmin: f32,
        sign: [bool; 3],
        neg: [__mmask16; 3],
    ) {
        let near: [usize; 3] = std::array::from_fn(|a| a + 3 * sign[a] as usize);
        let far: [usize; 3] = std::array::from_fn(|a| a + 3 - 3 * sign[a] as usize);
        let zero = _mm512_setzero_ps();
        let slack = _mm512_set1_ps(1.000_000_2);
        let inf = _mm512_set1_ps(f32::INFINITY);
        let o: [__m512; 3] = std::array::from_fn(|a| ld(&p.o[a]));
        let inv: [__m512; 3] = std::array::from_fn(|a| ld(&p.inv[a]));
        let act0 = act;
        let mut frustum = if UNI { Frustum::new(p, act, sign) } else { None };
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
                let actk = act as __mmask16;
                let tmax = ld(&p.tmax);
                let mut cm = [0u32; NW];
                let mut ct = [u32::MAX; NW];
                let enter = match &frustum {
                    Some(f) => f.may_enter(n, near, far),
                    None => (1 << NW) - 1,
                };
                for c in 0..NW {
                    if enter >> c & 1 == 0 {
                        continue;
                    }
                    let b = |row: usize| _mm512_set1_ps(n.b[row][c]);
                    let slab = |a: usize| {
                        let (lo, hi) = if UNI { (b(near[a]), b(far[a])) } else { (b(a), b(a + 3)) };
                        let a0 = _mm512_mul_ps(_mm512_sub_ps(lo, o[a]), inv[a]);
                        let a1 = _mm512_mul_ps(_mm512_sub_ps(hi, o[a]), inv[a]);
                        if UNI {
                            (a0, a1)
                        } else {
                            (
                                _mm512_mask_blend_ps(neg[a], a0, a1),
                                _mm512_mask_blend_ps(neg[a], a1, a0),
                            )
                        }
                    };
                    let (t0x, t1x) = slab(0);
                    let (t0y, t1y) = slab(1);
                    let (t0z, t1z) = slab(2);
                    // `vmaxps(a, b)` is `a > b ? a : b`: a NaN `a` keeps `b`, the slab stays open.
                    let t0 = _mm512_max_ps(t0z, _mm512_max_ps(t0y, _mm512_max_ps(t0x, zero)));
                    let t1 = _mm512_min_ps(t1z, _mm512_min_ps(t1y, _mm512_min_ps(t1x, tmax)));
                    let hit = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(actk, t0, _mm512_mul_ps(t1, slack));
                    cm[c] = hit as u32;
                    if !ANY && hit != 0 {
                        // Entry distances are ≥ +0, so their bits order as the floats do.
                        ct[c] = _mm512_reduce_min_ps(_mm512_mask_blend_ps(hit, inf, t0)).to_bits();
                    }
                }
                let next = stack.push_children::<ANY>(self, n, &cm, &ct, |c, m| {
                    self.traverse_packet_deep::<ANY>(c, m, p, tmin)
                });
                if let Some((c, m)) = next {
                    (cur, act) = (c, m);
                    continue;
                }
            } else if act != 0 && cur != EMPTY {
                let mut hit = 0u32;
                for pk in self.leaf_packets(cur) {
                    for l in 0..4 {
                        if pk.prim[l] == u32::MAX {
                            break;
                        }
                        let m = tri_lanes(pk, l, p, tmin, act);
                        p.record(m, pk, l);
                        hit |= m;
                    }
                }
                if !ANY && hit != 0 {
                    if let Some(f) = &mut frustum {
                        f.tmax = _mm512_mask_reduce_max_ps(act0 as __mmask16, ld(&p.tmax));
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
                let bits = _mm512_castps_si512(ld(&p.tmax));
                t <= _mm512_mask_reduce_max_epu32(m as __mmask16, bits)
            };
            match stack.pop(live) {
                Some((c, m)) => (cur, act) = (c, m),
                None => return,
            }
        }
    }
}

/// Lane `l` of packet `pk` against every ray of `p` active in `act` (the operations of
/// [`super::intersect_tri`] in the same order); lanes hit closer than their current limit get
/// the hit recorded (distance, barycentrics) and are returned as a mask.
#[inline]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
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
    let mut ok = act as __mmask16;
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(ok, _mm512_abs_ps(det), s(1e-20));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(ok, u, s(0.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(ok, u, s(1.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(ok, v, s(0.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(ok, add(u, v), s(1.0));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(ok, tt, s(tmin));
    ok = _mm512_mask_cmp_ps_mask::<_CMP_LT_OQ>(ok, tt, tmax);
    ok &= !_mm512_cmpeq_epi32_mask(_mm512_set1_epi32(pk.prim[l] as i32), ld_u32(&p.skip));
    if ok != 0 {
        st_masked(&mut p.tmax, ok, tt);
        st_masked(&mut p.b1, ok, u);
        st_masked(&mut p.b2, ok, v);
    }
    ok as u32
}
