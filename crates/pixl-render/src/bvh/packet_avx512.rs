//! The AVX-512 packet kernel: the 16 lanes of a packet in one 512-bit vector and lane sets as
//! mask registers — one box test per child, one triangle test per leaf lane, masked stores of
//! the hits (the loop around them is [`super::packet_simd`]'s). Needs AVX-512F only.
//!
//! Contract: as the AVX2 kernel's — per lane the same IEEE operations in the same order as
//! [`super::intersect_tri`] and the portable box test (`vmaxps`/`vminps` keep the same operand
//! order, so a NaN slab stays open; `vdivps`, no reciprocal estimates; no FMA), hence the same
//! results bit for bit (tested against brute force and the other kernels).
//!
//! Why: on a Zen 5 host, packets of a pixel's rays are 25–45 % faster than with the AVX2 kernel
//! and the benchmark render ~4 % (git history of BENCHMARKS.md).
use super::packet_simd::Lanes;
use super::{Bvh, Node, RayPack, Tri4, NW, PACKET};
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

/// The AVX-512 kernel's per-traversal state: the rays' origins and reciprocal directions (fixed
/// during a traversal) and, per axis, the lanes whose direction is negative.
pub(super) struct Avx512 {
    o: [__m512; 3],
    inv: [__m512; 3],
    neg: [__mmask16; 3],
}

impl Bvh {
    /// Packet traversal with the AVX-512 kernel (see [`super::packet_simd`]).
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    pub(super) fn traverse_packet_avx512<const ANY: bool>(&self, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        // SAFETY: this function is compiled for, and only called with, the kernel's features.
        unsafe { self.packet_traverse::<Avx512, ANY>(start, act, p, tmin) }
    }
}

impl Lanes for Avx512 {
    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    unsafe fn new(p: &RayPack) -> Avx512 {
        let zero = _mm512_setzero_ps();
        let inv: [__m512; 3] = std::array::from_fn(|a| ld(&p.inv[a]));
        Avx512 {
            o: std::array::from_fn(|a| ld(&p.o[a])),
            inv,
            neg: std::array::from_fn(|a| _mm512_cmp_ps_mask::<_CMP_LT_OQ>(inv[a], zero)),
        }
    }

    #[inline(always)]
    fn neg(&self, a: usize) -> u32 {
        self.neg[a] as u32
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    unsafe fn children<const ANY: bool, const UNI: bool>(
        &self,
        n: &Node,
        p: &RayPack,
        act: u32,
        enter: u32,
        near: [usize; 3],
        far: [usize; 3],
    ) -> ([u32; NW], [u32; NW]) {
        let zero = _mm512_setzero_ps();
        let slack = _mm512_set1_ps(1.000_000_2);
        let inf = _mm512_set1_ps(f32::INFINITY);
        let actk = act as __mmask16;
        let tmax = ld(&p.tmax);
        let mut cm = [0u32; NW];
        let mut ct = [u32::MAX; NW];
        for c in 0..NW {
            if enter >> c & 1 == 0 {
                continue;
            }
            let b = |row: usize| _mm512_set1_ps(n.b[row][c]);
            let slab = |a: usize| {
                let (lo, hi) = if UNI { (b(near[a]), b(far[a])) } else { (b(a), b(a + 3)) };
                let a0 = _mm512_mul_ps(_mm512_sub_ps(lo, self.o[a]), self.inv[a]);
                let a1 = _mm512_mul_ps(_mm512_sub_ps(hi, self.o[a]), self.inv[a]);
                if UNI {
                    (a0, a1)
                } else {
                    let neg = self.neg[a];
                    (_mm512_mask_blend_ps(neg, a0, a1), _mm512_mask_blend_ps(neg, a1, a0))
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
        (cm, ct)
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    unsafe fn tri(pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32) -> u32 {
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

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    unsafe fn lanes_max(v: &[f32; PACKET], act: u32) -> f32 {
        _mm512_mask_reduce_max_ps(act as __mmask16, ld(v))
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    unsafe fn far_bits(p: &RayPack, m: u32) -> u32 {
        _mm512_mask_reduce_max_epu32(m as __mmask16, _mm512_castps_si512(ld(&p.tmax)))
    }
}
