//! Four `f32` lanes for the single-ray four-triangle test ([`super::intersect_tri4`]): SSE
//! vectors on x86-64 (baseline SSE2, VEX-encoded where the caller is compiled for AVX2),
//! arrays elsewhere. Written out because the compiler's vectorisation of the test as array
//! loops is fragile (it mixed scalar and vector code and spilled).
//!
//! Contract: every operation is the IEEE one of the scalar code, lane by lane — `min`/`max` as
//! `a < b ? a : b` / `a > b ? a : b` (`minps`/`maxps`), comparisons ordered except `ne`
//! (unordered: NaN ≠ anything) — so lanes are bit for bit [`super::tri_test`]'s.
use std::ops::{Add, BitAnd, BitOr, Div, Mul, Sub};

#[cfg(target_arch = "x86_64")]
use std::arch::x86_64::*;

#[cfg(target_arch = "x86_64")]
type Lanes = __m128;
#[cfg(target_arch = "x86_64")]
type Mask = __m128;
#[cfg(not(target_arch = "x86_64"))]
type Lanes = [f32; 4];
#[cfg(not(target_arch = "x86_64"))]
type Mask = [bool; 4];

/// Four f32 lanes.
#[derive(Clone, Copy)]
pub(super) struct F4(Lanes);

/// A per-lane condition of four lanes.
#[derive(Clone, Copy)]
pub(super) struct M4(Mask);

#[cfg(target_arch = "x86_64")]
mod imp {
    use super::*;

    /// An SSE intrinsic call.
    macro_rules! sse {
        ($e:expr) => {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline (every x86-64 CPU has them);
            // loads and stores are given exactly 4 initialised f32.
            unsafe { $e }
        };
    }

    impl F4 {
        #[inline(always)]
        pub(in crate::trace::bvh) fn load(a: &[f32; 4]) -> F4 {
            F4(sse!(_mm_loadu_ps(a.as_ptr())))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn splat(x: f32) -> F4 {
            F4(sse!(_mm_set1_ps(x)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn to_array(self) -> [f32; 4] {
            let mut a = [0f32; 4];
            sse!(_mm_storeu_ps(a.as_mut_ptr(), self.0));
            a
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn min(self, o: F4) -> F4 {
            F4(sse!(_mm_min_ps(self.0, o.0)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn max(self, o: F4) -> F4 {
            F4(sse!(_mm_max_ps(self.0, o.0)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn lt(self, o: F4) -> M4 {
            M4(sse!(_mm_cmplt_ps(self.0, o.0)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn gt(self, o: F4) -> M4 {
            M4(sse!(_mm_cmpgt_ps(self.0, o.0)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn le(self, o: F4) -> M4 {
            M4(sse!(_mm_cmple_ps(self.0, o.0)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn ge(self, o: F4) -> M4 {
            M4(sse!(_mm_cmpge_ps(self.0, o.0)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn eq(self, o: F4) -> M4 {
            M4(sse!(_mm_cmpeq_ps(self.0, o.0)))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn ne(self, o: F4) -> M4 {
            M4(sse!(_mm_cmpneq_ps(self.0, o.0)))
        }
    }

    impl M4 {
        /// Bit `i` set where lane `i` holds.
        #[inline(always)]
        pub(in crate::trace::bvh) fn bits(self) -> u32 {
            sse!(_mm_movemask_ps(self.0)) as u32
        }
    }

    macro_rules! binop {
        ($t:ident, $tr:ident, $f:ident, $op:ident) => {
            impl $tr for $t {
                type Output = $t;
                #[inline(always)]
                fn $f(self, o: $t) -> $t {
                    $t(sse!($op(self.0, o.0)))
                }
            }
        };
    }
    binop!(F4, Add, add, _mm_add_ps);
    binop!(F4, Sub, sub, _mm_sub_ps);
    binop!(F4, Mul, mul, _mm_mul_ps);
    binop!(F4, Div, div, _mm_div_ps);
    binop!(M4, BitAnd, bitand, _mm_and_ps);
    binop!(M4, BitOr, bitor, _mm_or_ps);
}

#[cfg(not(target_arch = "x86_64"))]
mod imp {
    use super::*;

    impl F4 {
        #[inline(always)]
        pub(in crate::trace::bvh) fn load(a: &[f32; 4]) -> F4 {
            F4(*a)
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn splat(x: f32) -> F4 {
            F4([x; 4])
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn to_array(self) -> [f32; 4] {
            self.0
        }
        #[inline(always)]
        fn zip(self, o: F4, f: impl Fn(f32, f32) -> f32) -> F4 {
            F4(std::array::from_fn(|i| f(self.0[i], o.0[i])))
        }
        #[inline(always)]
        fn cmp(self, o: F4, f: impl Fn(f32, f32) -> bool) -> M4 {
            M4(std::array::from_fn(|i| f(self.0[i], o.0[i])))
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn min(self, o: F4) -> F4 {
            self.zip(o, |a, b| if a < b { a } else { b })
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn max(self, o: F4) -> F4 {
            self.zip(o, |a, b| if a > b { a } else { b })
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn lt(self, o: F4) -> M4 {
            self.cmp(o, |a, b| a < b)
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn gt(self, o: F4) -> M4 {
            self.cmp(o, |a, b| a > b)
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn le(self, o: F4) -> M4 {
            self.cmp(o, |a, b| a <= b)
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn ge(self, o: F4) -> M4 {
            self.cmp(o, |a, b| a >= b)
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn eq(self, o: F4) -> M4 {
            self.cmp(o, |a, b| a == b)
        }
        #[inline(always)]
        pub(in crate::trace::bvh) fn ne(self, o: F4) -> M4 {
            self.cmp(o, |a, b| a != b)
        }
    }

    impl M4 {
        /// Bit `i` set where lane `i` holds.
        #[inline(always)]
        pub(in crate::trace::bvh) fn bits(self) -> u32 {
            (0..4).fold(0, |m, i| m | (self.0[i] as u32) << i)
        }
    }

    macro_rules! binop {
        ($t:ident, $tr:ident, $f:ident, $op:tt) => {
            impl $tr for $t {
                type Output = $t;
                #[inline(always)]
                fn $f(self, o: $t) -> $t {
                    $t(std::array::from_fn(|i| self.0[i] $op o.0[i]))
                }
            }
        };
    }
    binop!(F4, Add, add, +);
    binop!(F4, Sub, sub, -);
    binop!(F4, Mul, mul, *);
    binop!(F4, Div, div, /);
    binop!(M4, BitAnd, bitand, &);
    binop!(M4, BitOr, bitor, |);
}
