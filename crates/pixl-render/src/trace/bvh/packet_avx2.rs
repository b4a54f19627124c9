//! The AVX2 packet kernel: each child box and each leaf triangle tested against the 16 lanes
//! of a packet as two 8-wide vectors (the loop around them is [`super::packet_simd`]'s), plus
//! the [`Frustum`] bounds both SIMD kernels use.
//!
//! Contract: the same per-lane results as the portable body — every lane's box and triangle
//! tests are the same IEEE operations in the same order (sub, mul, add and div only; no FMA,
//! no reciprocal estimates; `maxps`/`minps` operand order chosen so that NaN keeps the
//! accumulated slab bound exactly as the portable `if t0x > t0 { t0x } else { t0 }`, and the
//! watertight test's sign test is [`super::same_sign`]'s), so hit distances and barycentrics
//! are bit-identical to [`super::intersect_tri`]'s. The watertight test's per-lane axis
//! permutation picks rows when the active lanes share `kz` (most packets), else blends per
//! lane; its f64 stage runs out of line, lane by lane ([`super::refine_pack`]). A half of 8
//! lanes without active rays is skipped, so packets of up to 8 rays cost about half.
//!
//! Why: the portable body's lane loops compile to per-lane selects and bit gathers (~120 ns per
//! node on the benchmark); this form tests a node's four children against 16 rays in ~40 ns,
//! which makes packets of a pixel's divergent bounce and shadow rays cheaper than tracing them
//! one by one (git history of BENCHMARKS.md).
use super::packet_simd::Lanes;
use super::{refine_pack, Bvh, Node, RayPack, Tri4, NW, PACKET};
use std::arch::x86_64::*;

/// Lanes per vector; a packet is `HALVES` vectors.
const W: usize = 8;
const HALVES: usize = PACKET / W;

/// Lanes `8h..8h+8` of a 16-lane row.
#[inline]
#[target_feature(enable = "avx2")]
fn ld(a: &[f32; PACKET], h: usize) -> __m256 {
    let s = &a[W * h..W * h + W];
    // SAFETY: `s` is a slice of exactly 8 initialised f32 (bounds-checked above); `loadu`
    // has no alignment requirement.
    unsafe { _mm256_loadu_ps(s.as_ptr()) }
}

#[inline]
#[target_feature(enable = "avx2")]
fn st(a: &mut [f32; PACKET], h: usize, v: __m256) {
    let s = &mut a[W * h..W * h + W];
    // SAFETY: as in `ld`, for a mutable slice of exactly 8 f32.
    unsafe { _mm256_storeu_ps(s.as_mut_ptr(), v) }
}

#[inline]
#[target_feature(enable = "avx2")]
fn ld_u32(a: &[u32; PACKET], h: usize) -> __m256i {
    let s = &a[W * h..W * h + W];
    // SAFETY: `s` is exactly 8 initialised u32 (32 bytes); `loadu` is unaligned.
    unsafe { _mm256_loadu_si256(s.as_ptr().cast()) }
}

/// The lanes of half `h` set in bit mask `act`, as an all-ones / all-zeros vector mask.
#[inline]
#[target_feature(enable = "avx2")]
fn lane_mask(act: u32, h: usize) -> __m256 {
    let bits = _mm256_set1_epi32(((act >> (W * h)) & 0xff) as i32);
    let sel = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
    _mm256_castsi256_ps(_mm256_cmpeq_epi32(_mm256_and_si256(bits, sel), sel))
}

/// The smallest of 8 floats (none NaN).
#[inline]
#[target_feature(enable = "avx2")]
fn hmin(v: __m256) -> f32 {
    let x = _mm256_min_ps(v, _mm256_permute2f128_ps::<1>(v, v));
    let x = _mm256_min_ps(x, _mm256_shuffle_ps::<0b01_00_11_10>(x, x));
    let x = _mm256_min_ps(x, _mm256_shuffle_ps::<0b10_11_00_01>(x, x));
    _mm256_cvtss_f32(x)
}

/// The largest of 8 floats (none NaN).
#[inline]
#[target_feature(enable = "avx2")]
fn hmax(v: __m256) -> f32 {
    let x = _mm256_max_ps(v, _mm256_permute2f128_ps::<1>(v, v));
    let x = _mm256_max_ps(x, _mm256_shuffle_ps::<0b01_00_11_10>(x, x));
    let x = _mm256_max_ps(x, _mm256_shuffle_ps::<0b10_11_00_01>(x, x));
    _mm256_cvtss_f32(x)
}

/// The largest of 8 unsigned integers.
#[inline]
#[target_feature(enable = "avx2")]
fn hmax_u32(v: __m256i) -> u32 {
    let x = _mm256_max_epu32(v, _mm256_permute2x128_si256::<1>(v, v));
    let x = _mm256_max_epu32(x, _mm256_shuffle_epi32::<0b01_00_11_10>(x));
    let x = _mm256_max_epu32(x, _mm256_shuffle_epi32::<0b10_11_00_01>(x));
    _mm256_cvtsi256_si32(x) as u32
}

/// Per lane, `if0` where mask `k0` is set, else `if1` where `k1` is set, else `if2`.
#[inline]
#[target_feature(enable = "avx2")]
fn pick3(k0: __m256, k1: __m256, if0: __m256, if1: __m256, if2: __m256) -> __m256 {
    _mm256_blendv_ps(_mm256_blendv_ps(if2, if1, k1), if0, k0)
}

/// The lanes whose edge functions `u`, `v`, `w` allow a hit (all ≥ 0 or all ≤ 0), as a mask,
/// tested as [`super::same_sign`] does: on their smallest and largest (`vminps`/`vmaxps` in its
/// operand order).
#[inline]
#[target_feature(enable = "avx2")]
fn same_sign(u: __m256, v: __m256, w: __m256) -> __m256 {
    let zero = _mm256_setzero_ps();
    let lo = _mm256_min_ps(_mm256_min_ps(u, v), w);
    let hi = _mm256_max_ps(_mm256_max_ps(u, v), w);
    _mm256_or_ps(
        _mm256_cmp_ps::<_CMP_GE_OQ>(lo, zero),
        _mm256_cmp_ps::<_CMP_LE_OQ>(hi, zero),
    )
}

/// The AVX2 kernel's per-traversal state: per half and axis, the lanes whose direction is
/// negative (as a vector mask, and as bits), and the lanes whose shear axis `kz` is x and y
/// (vector masks).
pub(super) struct Avx2 {
    neg: [[__m256; 3]; HALVES],
    neg_bits: [u32; 3],
    kz: [[__m256; 2]; HALVES],
}

impl Bvh {
    /// Packet traversal with the AVX2 kernel (see [`super::packet_simd`]).
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    pub(super) fn traverse_packet_avx2<const ANY: bool>(&self, start: u32, act: u32, p: &mut RayPack, tmin: f32) {
        p.prepare_shear();
        // SAFETY: this function is compiled for, and only called with, the kernel's features.
        unsafe { self.packet_traverse::<Avx2, ANY>(start, act, p, tmin) }
    }
}

impl Avx2 {
    /// Lane `l` of `pk` against the rays of `p` in `act` (the watertight test, the operations
    /// of [`super::intersect_tri`] per lane; with `UNI` every active ray's axes are `k`, else
    /// each lane's are blended per lane); lanes hit closer than their limit get the distance
    /// and barycentrics written and are returned as a mask.
    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    fn tri<const UNI: bool>(&self, pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32, k: [usize; 3]) -> u32 {
        let (mul, sub, add, and, or) = (_mm256_mul_ps, _mm256_sub_ps, _mm256_add_ps, _mm256_and_ps, _mm256_or_ps);
        let zero = _mm256_setzero_ps();
        let prim = _mm256_set1_epi32(pk.prim[l] as i32);
        let mut out = 0u32;
        for h in 0..HALVES {
            if (act >> (W * h)) & 0xff == 0 {
                continue;
            }
            // Per vertex and lane: the vertex relative to the ray origin, axes permuted to the
            // lane's (kx, ky, kz) — when the active lanes share kz, by picking rows; else by
            // blends.
            let rel = |v: &[[f32; 4]; 3], a: usize| sub(_mm256_set1_ps(v[a][l]), ld(&p.o[a], h));
            let [a, b, c] = if UNI {
                let [kx, ky, kz] = k;
                let perm = |v: &[[f32; 4]; 3]| [rel(v, kx), rel(v, ky), rel(v, kz)];
                [perm(&pk.p0), perm(&pk.p1), perm(&pk.p2)]
            } else {
                let [k0, k1] = self.kz[h];
                // kz = 0: (y, z, x); kz = 1: (z, x, y); kz = 2: (x, y, z).
                let perm = |v: &[[f32; 4]; 3]| {
                    let (x, y, z) = (rel(v, 0), rel(v, 1), rel(v, 2));
                    [pick3(k0, k1, y, z, x), pick3(k0, k1, z, x, y), pick3(k0, k1, x, y, z)]
                };
                [perm(&pk.p0), perm(&pk.p1), perm(&pk.p2)]
            };
            let (sx, sy, sz) = (ld(&p.sh[0], h), ld(&p.sh[1], h), ld(&p.sh[2], h));
            let (ax, ay) = (sub(a[0], mul(sx, a[2])), sub(a[1], mul(sy, a[2])));
            let (bx, by) = (sub(b[0], mul(sx, b[2])), sub(b[1], mul(sy, b[2])));
            let (cx, cy) = (sub(c[0], mul(sx, c[2])), sub(c[1], mul(sy, c[2])));
            let u = sub(mul(cx, by), mul(cy, bx));
            let v = sub(mul(ax, cy), mul(ay, cx));
            let w = sub(mul(bx, ay), mul(by, ax));
            let mut ok = and(lane_mask(act, h), same_sign(u, v, w));
            if _mm256_movemask_ps(ok) == 0 {
                continue;
            }
            let same = _mm256_castsi256_ps(_mm256_cmpeq_epi32(prim, ld_u32(&p.skip, h)));
            ok = _mm256_andnot_ps(same, ok);
            let det = add(add(u, v), w);
            ok = and(ok, _mm256_cmp_ps::<_CMP_NEQ_UQ>(det, zero));
            let tz = add(add(mul(u, a[2]), mul(v, b[2])), mul(w, c[2]));
            let inv = _mm256_div_ps(_mm256_set1_ps(1.0), det);
            let t = mul(mul(tz, sz), inv);
            let tmax = ld(&p.tmax, h);
            ok = and(ok, _mm256_cmp_ps::<_CMP_GT_OQ>(t, _mm256_set1_ps(tmin)));
            ok = and(ok, _mm256_cmp_ps::<_CMP_LT_OQ>(t, tmax));
            if _mm256_movemask_ps(ok) == 0 {
                continue;
            }
            let zu = _mm256_cmp_ps::<_CMP_EQ_OQ>(u, zero);
            let zv = _mm256_cmp_ps::<_CMP_EQ_OQ>(v, zero);
            let zw = _mm256_cmp_ps::<_CMP_EQ_OQ>(w, zero);
            let fix = and(ok, or(or(zu, zv), zw));
            ok = _mm256_andnot_ps(fix, ok);
            let bits = _mm256_movemask_ps(ok) as u32;
            if bits != 0 {
                st(&mut p.tmax, h, _mm256_blendv_ps(tmax, t, ok));
                let (old1, old2) = (ld(&p.b1, h), ld(&p.b2, h));
                st(&mut p.b1, h, _mm256_blendv_ps(old1, mul(v, inv), ok));
                st(&mut p.b2, h, _mm256_blendv_ps(old2, mul(w, inv), ok));
                out |= bits << (W * h);
            }
            let fix = _mm256_movemask_ps(fix) as u32;
            if fix != 0 {
                // A hit with an edge function exactly 0: those lanes' last stage in f64.
                out |= refine_pack(pk, l, p, tmin, fix << (W * h));
            }
        }
        out
    }
}

impl Avx2 {
    /// [`Lanes::leaf_mixed`]: the triangles of leaf packets `pks` in turn with
    /// [`Avx2::tri`], axes blended lane by lane.
    #[inline(never)]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
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

impl Lanes for Avx2 {
    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn new(p: &RayPack) -> Avx2 {
        let zero = _mm256_setzero_ps();
        let neg: [[__m256; 3]; HALVES] =
            std::array::from_fn(|h| std::array::from_fn(|a| _mm256_cmp_ps::<_CMP_LT_OQ>(ld(&p.inv[a], h), zero)));
        let neg_bits = std::array::from_fn(|a| {
            (0..HALVES).fold(0u32, |m, h| m | (_mm256_movemask_ps(neg[h][a]) as u32) << (W * h))
        });
        let kz = std::array::from_fn(|h| [lane_mask(p.kz[0], h), lane_mask(p.kz[1], h)]);
        Avx2 { neg, neg_bits, kz }
    }

    #[inline(always)]
    fn neg(&self, a: usize) -> u32 {
        self.neg_bits[a]
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn children<const ANY: bool, const UNI: bool>(
        &self,
        n: &Node,
        p: &RayPack,
        act: u32,
        enter: u32,
        near: [usize; 3],
        far: [usize; 3],
    ) -> ([u32; NW], [u32; NW]) {
        let zero = _mm256_setzero_ps();
        let slack = _mm256_set1_ps(1.000_000_2);
        let inf = _mm256_set1_ps(f32::INFINITY);
        let actv = [lane_mask(act, 0), lane_mask(act, 1)];
        let mut cm = [0u32; NW];
        let mut ct = [u32::MAX; NW];
        for c in 0..NW {
            if enter >> c & 1 == 0 {
                continue;
            }
            let b = |row: usize| _mm256_set1_ps(n.b[row][c]);
            // Without `UNI`: low and high planes, blended per lane; with it: near and far.
            let (lx, ly, lz, hx, hy, hz) = if UNI {
                (b(near[0]), b(near[1]), b(near[2]), b(far[0]), b(far[1]), b(far[2]))
            } else {
                (b(0), b(1), b(2), b(3), b(4), b(5))
            };
            let mut m = 0u32;
            let mut entry = inf;
            for h in 0..HALVES {
                if (act >> (W * h)) & 0xff == 0 {
                    continue;
                }
                let slab = |lo: __m256, hi: __m256, a: usize| {
                    let (o, inv) = (ld(&p.o[a], h), ld(&p.inv[a], h));
                    let a0 = _mm256_mul_ps(_mm256_sub_ps(lo, o), inv);
                    let a1 = _mm256_mul_ps(_mm256_sub_ps(hi, o), inv);
                    if UNI {
                        (a0, a1)
                    } else {
                        let neg = self.neg[h][a];
                        (_mm256_blendv_ps(a0, a1, neg), _mm256_blendv_ps(a1, a0, neg))
                    }
                };
                let (t0x, t1x) = slab(lx, hx, 0);
                let (t0y, t1y) = slab(ly, hy, 1);
                let (t0z, t1z) = slab(lz, hz, 2);
                // `maxps(a, b)` is `a > b ? a : b`: a NaN `a` keeps `b`, the slab stays open.
                let t0 = _mm256_max_ps(t0z, _mm256_max_ps(t0y, _mm256_max_ps(t0x, zero)));
                let t1 = _mm256_min_ps(t1z, _mm256_min_ps(t1y, _mm256_min_ps(t1x, ld(&p.tmax, h))));
                let hit = _mm256_and_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(t0, _mm256_mul_ps(t1, slack)), actv[h]);
                m |= (_mm256_movemask_ps(hit) as u32) << (W * h);
                if !ANY {
                    entry = _mm256_min_ps(entry, _mm256_blendv_ps(inf, t0, hit));
                }
            }
            cm[c] = m;
            if !ANY && m != 0 {
                // Entry distances are ≥ +0, so their bits order as the floats do.
                ct[c] = hmin(entry).to_bits();
            }
        }
        (cm, ct)
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn tri_uniform(&self, pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32, k: [usize; 3]) -> u32 {
        self.tri::<true>(pk, l, p, tmin, act, k)
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn leaf_mixed(&self, pks: &[Tri4], p: &mut RayPack, tmin: f32, act: u32) -> u32 {
        Avx2::leaf_mixed(self, pks, p, tmin, act)
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn lanes_max(v: &[f32; PACKET], act: u32) -> f32 {
        lanes_max(v, act)
    }

    #[inline]
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn far_bits(p: &RayPack, m: u32) -> u32 {
        let mut far = _mm256_setzero_si256();
        for h in 0..HALVES {
            let lanes = _mm256_castps_si256(lane_mask(m, h));
            let bits = _mm256_castps_si256(ld(&p.tmax, h));
            far = _mm256_max_epu32(far, _mm256_and_si256(bits, lanes));
        }
        hmax_u32(far)
    }
}

/// Interval bounds over a packet's lanes whose directions share their signs on every axis:
/// per axis the origin coordinate that gives the smallest entry (`o_near`) and the largest
/// exit (`o_far`) distance, the range of reciprocal directions, and the largest far limit.
/// Rounding is monotonic, so for every lane its computed slab entry is ≥ the bound computed
/// from these and its exit ≤ the bound: a box whose bounds do not overlap is entered by no lane.
pub(super) struct Frustum {
    o_near: [f32; 3],
    o_far: [f32; 3],
    inv_lo: [f32; 3],
    inv_hi: [f32; 3],
    pub(super) tmax: f32,
}

impl Frustum {
    /// The bounds of the lanes in `act` (directions negative on the axes where `sign` is set);
    /// `None` if an origin is not finite, a reciprocal direction is 0 or not finite (those make
    /// `0 · ∞` NaNs, which the lane test treats as an open slab), or a limit is NaN.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) fn new(p: &RayPack, act: u32, sign: [bool; 3]) -> Option<Frustum> {
        let mut f = Frustum {
            o_near: [0.0; 3],
            o_far: [0.0; 3],
            inv_lo: [0.0; 3],
            inv_hi: [0.0; 3],
            tmax: lanes_max(&p.tmax, act),
        };
        let inf = _mm256_set1_ps(f32::INFINITY);
        let abs = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
        for a in 0..3 {
            for h in 0..HALVES {
                // Active lanes whose origin is ±∞ or NaN or whose reciprocal is that or 0
                // (comparisons with NaN are false).
                let fin = |v: __m256| _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(v, abs), inf);
                let inv = ld(&p.inv[a], h);
                let nonzero = _mm256_cmp_ps::<_CMP_GT_OQ>(_mm256_and_ps(inv, abs), _mm256_setzero_ps());
                let ok = _mm256_and_ps(_mm256_and_ps(fin(ld(&p.o[a], h)), fin(inv)), nonzero);
                if _mm256_movemask_ps(_mm256_andnot_ps(ok, lane_mask(act, h))) != 0 {
                    return None;
                }
            }
            let (o_lo, o_hi) = (lanes_min(&p.o[a], act), lanes_max(&p.o[a], act));
            (f.inv_lo[a], f.inv_hi[a]) = (lanes_min(&p.inv[a], act), lanes_max(&p.inv[a], act));
            // Positive direction: entry (near − o)·inv is smallest for the largest origin,
            // exit (far − o)·inv largest for the smallest; negative directions the reverse.
            (f.o_near[a], f.o_far[a]) = if sign[a] { (o_lo, o_hi) } else { (o_hi, o_lo) };
        }
        for h in 0..HALVES {
            let t = ld(&p.tmax, h);
            let nan = _mm256_cmp_ps::<_CMP_UNORD_Q>(t, t);
            if _mm256_movemask_ps(_mm256_and_ps(nan, lane_mask(act, h))) != 0 {
                return None;
            }
        }
        Some(f)
    }

    /// Mask of the children of `n` (rows `near`, `far` of each axis's near and far planes)
    /// that some lane may enter.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) fn may_enter(&self, n: &Node, near: [usize; 3], far: [usize; 3]) -> u32 {
        const { assert!(NW == 4, "one SSE vector per node row") };
        let row = |r: usize| {
            let s: &[f32; 4] = &n.b[r];
            // SAFETY: `s` is exactly 4 initialised f32; `loadu` has no alignment requirement.
            unsafe { _mm_loadu_ps(s.as_ptr()) }
        };
        let mut entry = _mm_setzero_ps();
        let mut exit = _mm_set1_ps(self.tmax);
        for a in 0..3 {
            let (lo, hi) = (_mm_set1_ps(self.inv_lo[a]), _mm_set1_ps(self.inv_hi[a]));
            // A product with a ranged factor is extreme at an end of the range.
            let x = _mm_sub_ps(row(near[a]), _mm_set1_ps(self.o_near[a]));
            entry = _mm_max_ps(entry, _mm_min_ps(_mm_mul_ps(x, lo), _mm_mul_ps(x, hi)));
            let x = _mm_sub_ps(row(far[a]), _mm_set1_ps(self.o_far[a]));
            exit = _mm_min_ps(exit, _mm_max_ps(_mm_mul_ps(x, lo), _mm_mul_ps(x, hi)));
        }
        let ok = _mm_cmp_ps::<_CMP_LE_OQ>(entry, _mm_mul_ps(exit, _mm_set1_ps(1.000_000_2)));
        _mm_movemask_ps(ok) as u32
    }
}

/// The smallest of the values of the lanes in `act` (+∞ if none).
#[inline]
#[target_feature(enable = "avx2")]
fn lanes_min(v: &[f32; PACKET], act: u32) -> f32 {
    const { assert!(HALVES == 2, "two vectors per row") };
    let inf = _mm256_set1_ps(f32::INFINITY);
    let m = _mm256_min_ps(
        _mm256_blendv_ps(inf, ld(v, 0), lane_mask(act, 0)),
        _mm256_blendv_ps(inf, ld(v, 1), lane_mask(act, 1)),
    );
    hmin(m)
}

/// The largest of the values of the lanes in `act` (−∞ if none).
#[inline]
#[target_feature(enable = "avx2")]
fn lanes_max(v: &[f32; PACKET], act: u32) -> f32 {
    const { assert!(HALVES == 2, "two vectors per row") };
    let ninf = _mm256_set1_ps(f32::NEG_INFINITY);
    let m = _mm256_max_ps(
        _mm256_blendv_ps(ninf, ld(v, 0), lane_mask(act, 0)),
        _mm256_blendv_ps(ninf, ld(v, 1), lane_mask(act, 1)),
    );
    hmax(m)
}

/// The kernel's triangle test on its own (for tests of the kernels).
#[cfg(test)]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
pub(super) fn tri_alone(pk: &Tri4, l: usize, p: &mut RayPack, tmin: f32, act: u32) -> u32 {
    // SAFETY: this function is compiled for, and only called with, the kernel's features.
    let k = unsafe { Avx2::new(p) };
    match p.uniform_kz(act) {
        Some(kz) => k.tri::<true>(pk, l, p, tmin, act, super::axes(kz)),
        None => k.tri::<false>(pk, l, p, tmin, act, [0, 1, 2]),
    }
}
