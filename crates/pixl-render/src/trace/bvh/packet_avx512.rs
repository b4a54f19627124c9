//! The AVX-512 packet kernel: the 16 lanes of a packet in one 512-bit vector and lane sets as
//! mask registers — one box test per child, one triangle test per leaf lane, masked stores of
//! the hits (the loop around them is [`super::packet_simd`]'s). Needs AVX-512F only.
//!
//! Contract: as the AVX2 kernel's — per lane the same IEEE operations in the same order as
//! [`super::intersect_tri`] (the watertight test: rows picked or blended per lane's `kz`, f64
//! stage out of line) and the portable box test (`vmaxps`/`vminps` keep the same operand order,
//! so a NaN slab stays open; `vdivps`, no reciprocal estimates; no FMA), hence the same results
//! bit for bit (tested against brute force and the other kernels).
//!
//! Why: on a Zen 5 host, packets of a pixel's rays are 25–45 % faster than with the AVX2 kernel
//! and the benchmark render ~4 % (git history of BENCHMARKS.md).
use super::packet_simd::Lanes;
use super::{refine_pack, Bvh, Node, RayPack, Tri4, NW, PACKET};
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

/// Per lane, `if0` where `k0` is set, else `if1` where `k1` is set, else `if2`.
#[inline]
#[target_feature(enable = "avx512f")]
fn pick3(k0: __mmask16, k1: __mmask16, if0: __m512, if1: __m512, if2: __m512) -> __m512 {
    _mm512_mask_blend_ps(k0, _mm512_mask_blend_ps(k1, if2, if1), if0)
}

/// The lanes of `m` whose edge functions `u`, `v`, `w` allow a hit (all ≥ 0 or all ≤ 0), as
/// [`super::same_sign`] tests it: on their smallest and largest (`vminps`/`vmaxps` in its
/// operand order).
#[inline]
#[target_feature(enable = "avx512f")]
fn same_sign(m: __mmask16, u: __m512, v: __m512, w: __m512) -> __mmask16 {
    let zero = _mm512_setzero_ps();
    let lo = _mm512_min_ps(_mm512_min_ps(u, v), w);
    let hi = _mm512_max_ps(_mm512_max_ps(u, v), w);
    _mm512_mask_cmp_ps_mask::<_CMP_GE_OQ>(m, lo, zero) | _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(m, hi, zero)
}

/// The AVX-512 kernel's per-traversal state: the rays' origins, reciprocal directions and
/// shears (fixed during a traversal) and, per axis, the lanes whose direction is negative.
pub(super) struct Avx512 {
    o: [__m512; 3],
    inv: [__m512; 3],
    sh: [__m512; 3],
    neg: [__mmask16; 3],
}

impl Bvh {
    /// Packet traversal with the AVX-512 kernel (see [`super::packet_simd`]).
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    pub(super) fn traverse_packet_avx512<const ANY: bool>(&self, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        p.prepare_shear();
        // SAFETY: this function is compiled for, and only called with, the kernel's features.
        unsafe { self.packet_traverse::<Avx512, ANY>(start, act, p, tmin) }
    }
}

impl Avx512 {
    /// Lane `l` of `pk` against the rays of `p` in `act` (the watertight test, the operations
    /// of [`super::intersect_tri`] per lane; with `UNI` every active ray's axes are `k`, else
    /// each lane's are blended per lane); lanes hit closer than their limit get the distance
    /// and barycentrics written and are returned as a mask.
    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    fn tri<const UNI: bool>(&self, pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32, k: [usize; 3]) -> u32 {
        let (mul, sub, add) = (_mm512_mul_ps, _mm512_sub_ps, _mm512_add_ps);
        // Per vertex and lane: the vertex relative to the ray origin, axes permuted to the
        // lane's (kx, ky, kz) — when the active lanes share kz, by picking rows; else by blends.
        let rel = |v: &[[f32; 4]; 3], a: usize| sub(_mm512_set1_ps(v[a][l]), self.o[a]);
        let [a, b, c] = if UNI {
            let [kx, ky, kz] = k;
            let perm = |v: &[[f32; 4]; 3]| [rel(v, kx), rel(v, ky), rel(v, kz)];
            [perm(&pk.p0), perm(&pk.p1), perm(&pk.p2)]
        } else {
            let (k0, k1) = (p.kz[0] as __mmask16, p.kz[1] as __mmask16);
            // kz = 0: (y, z, x); kz = 1: (z, x, y); kz = 2: (x, y, z).
            let perm = |v: &[[f32; 4]; 3]| {
                let (x, y, z) = (rel(v, 0), rel(v, 1), rel(v, 2));
                [pick3(k0, k1, y, z, x), pick3(k0, k1, z, x, y), pick3(k0, k1, x, y, z)]
            };
            [perm(&pk.p0), perm(&pk.p1), perm(&pk.p2)]
        };
        let [sx, sy, sz] = self.sh;
        let (ax, ay) = (sub(a[0], mul(sx, a[2])), sub(a[1], mul(sy, a[2])));
        let (bx, by) = (sub(b[0], mul(sx, b[2])), sub(b[1], mul(sy, b[2])));
        let (cx, cy) = (sub(c[0], mul(sx, c[2])), sub(c[1], mul(sy, c[2])));
        let u = sub(mul(cx, by), mul(cy, bx));
        let v = sub(mul(ax, cy), mul(ay, cx));
        let w = sub(mul(bx, ay), mul(by, ax));
        let zero = _mm512_setzero_ps();
        let mut ok = same_sign(act as __mmask16, u, v, w);
        if ok == 0 {
            return 0;
        }
        ok &= !_mm512_cmpeq_epi32_mask(_mm512_set1_epi32(pk.prim[l] as i32), ld_u32(&p.skip));
        let det = add(add(u, v), w);
        ok = _mm512_mask_cmp_ps_mask::<_CMP_NEQ_UQ>(ok, det, zero);
        let tz = add(add(mul(u, a[2]), mul(v, b[2])), mul(w, c[2]));
        let inv = _mm512_div_ps(_mm512_set1_ps(1.0), det);
        let t = mul(mul(tz, sz), inv);
        ok = _mm512_mask_cmp_ps_mask::<_CMP_GT_OQ>(ok, t, _mm512_set1_ps(tmin));
        ok = _mm512_mask_cmp_ps_mask::<_CMP_LT_OQ>(ok, t, ld(&p.tmax));
        if ok == 0 {
            return 0;
        }
        let fix = _mm512_mask_cmp_ps_mask::<_CMP_EQ_OQ>(ok, u, zero)
            | _mm512_mask_cmp_ps_mask::<_CMP_EQ_OQ>(ok, v, zero)
            | _mm512_mask_cmp_ps_mask::<_CMP_EQ_OQ>(ok, w, zero);
        ok &= !fix;
        if ok != 0 {
            st_masked(&mut p.tmax, ok, t);
            st_masked(&mut p.b1, ok, mul(v, inv));
            st_masked(&mut p.b2, ok, mul(w, inv));
        }
        if fix != 0 {
            // A hit with an edge function exactly 0: those lanes' last stage in f64.
            ok |= refine_pack(pk, l, p, tmin, fix as u32) as __mmask16;
        }
        ok as u32
    }
}

impl Avx512 {
    /// [`Lanes::leaf_mixed`]: the triangles of leaf packets `pks` in turn with
    /// [`Avx512::tri`], axes blended lane by lane.
    #[inline(never)]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    fn leaf_mixed(&self, pks: &[Tri4], p: &mut RayPack, tmin: f32, act: u32) -> u32 {
        let mut hit = 0u32;
        for pk in pks {
            for l in 0..4 {
                if pk.prim[l] == u32::MAX {
                    break;
                }
                let m = self.tri::<false>(pk, l, p, tmin, act, [0, 1, 2]);
                p.record(m, pk, l);
                hit |= m;
            }
        }
        hit
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
            sh: std::array::from_fn(|a| ld(&p.sh[a])),
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
    unsafe fn tri_uniform(&self, pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32, k: [usize; 3]) -> u32 {
        self.tri::<true>(pk, l, p, tmin, act, k)
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
    unsafe fn leaf_mixed(&self, pks: &[Tri4], p: &mut RayPack, tmin: f32, act: u32) -> u32 {
        Avx512::leaf_mixed(self, pks, p, tmin, act)
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

/// The kernel's triangle test on its own (for tests of the kernels).
#[cfg(test)]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt,avx512f")]
pub(super) fn tri_alone(pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32) -> u32 {
    // SAFETY: this function is compiled for, and only called with, the kernel's features.
    let k = unsafe { Avx512::new(p) };
    match p.uniform_kz(act) {
        Some(kz) => k.tri::<true>(pk, l, p, tmin, act, super::axes(kz)),
        None => k.tri::<false>(pk, l, p, tmin, act, [0, 1, 2]),
    }
}
