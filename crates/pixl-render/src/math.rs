//! A small `f32` 3-vector for the renderer ([`V3`]) and an orthonormal frame.
use std::ops::{Add, AddAssign, Div, Index, Mul, MulAssign, Neg, Sub};

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct V3 {
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

impl V3 {
    pub const ZERO: V3 = V3 { x: 0.0, y: 0.0, z: 0.0 };
    pub const ONE: V3 = V3 { x: 1.0, y: 1.0, z: 1.0 };

    #[inline]
    pub const fn new(x: f32, y: f32, z: f32) -> Self {
        V3 { x, y, z }
    }
    #[inline]
    pub fn splat(v: f32) -> Self {
        V3 { x: v, y: v, z: v }
    }
    #[inline]
    pub fn from_arr(a: [f32; 3]) -> Self {
        V3 {
            x: a[0],
            y: a[1],
            z: a[2],
        }
    }
    #[inline]
    pub fn to_arr(self) -> [f32; 3] {
        [self.x, self.y, self.z]
    }
    #[inline]
    pub fn dot(self, o: V3) -> f32 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    #[inline]
    pub fn cross(self, o: V3) -> V3 {
        V3::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }
    #[inline]
    pub fn length(self) -> f32 {
        self.dot(self).sqrt()
    }
    #[inline]
    pub fn normalize(self) -> V3 {
        let l = self.length();
        if l > 0.0 {
            self * (1.0 / l)
        } else {
            self
        }
    }
    #[inline]
    pub fn min(self, o: V3) -> V3 {
        V3::new(self.x.min(o.x), self.y.min(o.y), self.z.min(o.z))
    }
    #[inline]
    pub fn max(self, o: V3) -> V3 {
        V3::new(self.x.max(o.x), self.y.max(o.y), self.z.max(o.z))
    }
    #[inline]
    pub fn max_comp(self) -> f32 {
        self.x.max(self.y).max(self.z)
    }
    #[inline]
    pub fn luminance(self) -> f32 {
        0.2126 * self.x + 0.7152 * self.y + 0.0722 * self.z
    }
    #[inline]
    pub fn is_zero(self) -> bool {
        self.x == 0.0 && self.y == 0.0 && self.z == 0.0
    }
    #[inline]
    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }
    #[inline]
    pub fn lerp(a: V3, b: V3, t: f32) -> V3 {
        a * (1.0 - t) + b * t
    }
    /// Component-wise `a / b`, 0 where `b == 0`.
    #[inline]
    pub fn safe_div(self, b: V3) -> V3 {
        let d = |a: f32, b: f32| if b != 0.0 { a / b } else { 0.0 };
        V3::new(d(self.x, b.x), d(self.y, b.y), d(self.z, b.z))
    }
}

impl Add for V3 {
    type Output = V3;
    #[inline]
    fn add(self, o: V3) -> V3 {
        V3::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}
impl AddAssign for V3 {
    #[inline]
    fn add_assign(&mut self, o: V3) {
        *self = *self + o;
    }
}
impl Sub for V3 {
    type Output = V3;
    #[inline]
    fn sub(self, o: V3) -> V3 {
        V3::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}
impl Mul<f32> for V3 {
    type Output = V3;
    #[inline]
    fn mul(self, s: f32) -> V3 {
        V3::new(self.x * s, self.y * s, self.z * s)
    }
}
impl Mul<V3> for V3 {
    type Output = V3;
    #[inline]
    fn mul(self, o: V3) -> V3 {
        V3::new(self.x * o.x, self.y * o.y, self.z * o.z)
    }
}
impl MulAssign<V3> for V3 {
    #[inline]
    fn mul_assign(&mut self, o: V3) {
        *self = *self * o;
    }
}
impl MulAssign<f32> for V3 {
    #[inline]
    fn mul_assign(&mut self, s: f32) {
        *self = *self * s;
    }
}
impl Div<f32> for V3 {
    type Output = V3;
    #[inline]
    fn div(self, s: f32) -> V3 {
        self * (1.0 / s)
    }
}
impl Neg for V3 {
    type Output = V3;
    #[inline]
    fn neg(self) -> V3 {
        V3::new(-self.x, -self.y, -self.z)
    }
}
impl Index<usize> for V3 {
    type Output = f32;
    #[inline]
    fn index(&self, i: usize) -> &f32 {
        match i {
            0 => &self.x,
            1 => &self.y,
            _ => &self.z,
        }
    }
}

/// An orthonormal frame around a unit normal `n` (Duff et al. 2017 branchless construction).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub t: V3,
    pub b: V3,
    pub n: V3,
}

impl Frame {
    pub fn new(n: V3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let t = V3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let bb = V3::new(b, sign + n.y * n.y * a, -n.y);
        Frame { t, b: bb, n }
    }
    #[inline]
    pub fn to_local(&self, v: V3) -> V3 {
        V3::new(v.dot(self.t), v.dot(self.b), v.dot(self.n))
    }
    #[inline]
    pub fn to_world(&self, v: V3) -> V3 {
        self.t * v.x + self.b * v.y + self.n * v.z
    }
}

/// Hints the CPU to start loading the cache line holding `p` (into all cache levels). Only a
/// hint: it never faults, whatever `p` is, and changes no value the program can see; a no-op
/// off x86-64.
#[inline(always)]
pub fn prefetch<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: `prefetcht0` performs no access that can fault or be observed: it is valid for
    // any address, dangling or not.
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p.cast());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// `(sin x, cos x)` with no call and no branch (vectorisable; the spherical rectangles of
/// [`crate::trace::light`] are sampled a packet at a time), within 1.2e-7 of the true values
/// for `|x| ≤ 64` (tested; libm's `sinf`/`cosf` are within 6e-8): `x = q·π/2 + r` with `q` the
/// nearest integer (Cody and Waite's reduction, π/2 in three parts, the first two short enough
/// that their products with `q` are exact), Taylor polynomials of `sin r` and `cos r` on
/// `|r| ≤ π/4` (truncation error ≤ 2e-9), and the quadrant from `q`.
#[inline(always)]
pub fn sin_cos_poly(x: f32) -> (f32, f32) {
    const PIO2_1: f32 = 1.570_312_5;
    const PIO2_2: f32 = 4.837_513e-4;
    const PIO2_3: f32 = 7.549_79e-8;
    // Rounded to the nearest integer by adding and removing 1.5·2^23 (no `roundss` needed
    // outside the SSE4.1 kernels, where `round_ties_even` would be a libm call).
    const ROUND: f32 = 12_582_912.0;
    let q = (x * std::f32::consts::FRAC_2_PI + ROUND) - ROUND;
    let r = ((x - q * PIO2_1) - q * PIO2_2) - q * PIO2_3;
    let r2 = r * r;
    let s = r + r * r2 * (-1.0 / 6.0 + r2 * (1.0 / 120.0 + r2 * (-1.0 / 5040.0 + r2 * (1.0 / 362_880.0))));
    let c =
        1.0 + r2 * (-0.5 + r2 * (1.0 / 24.0 + r2 * (-1.0 / 720.0 + r2 * (1.0 / 40_320.0 + r2 * (-1.0 / 3_628_800.0)))));
    // sin(r + qπ/2), cos(r + qπ/2): quadrants 0..3 give (s, c), (c, −s), (−s, −c), (−c, s).
    let qi = q as i32;
    let (a, b) = if qi & 1 == 0 { (s, c) } else { (c, s) };
    (if qi & 2 == 0 { a } else { -a }, if (qi + 1) & 2 == 0 { b } else { -b })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polynomial_sine_and_cosine_are_within_1_2e7_of_f64() {
        // Every 2^-14 step over [−64, 64], and the multiples of π/4 (where the quadrant flips)
        // with their neighbours.
        let mut worst = 0.0f64;
        let check = |x: f32, worst: &mut f64| {
            let (s, c) = sin_cos_poly(x);
            let e = (s as f64 - (x as f64).sin())
                .abs()
                .max((c as f64 - (x as f64).cos()).abs());
            *worst = worst.max(e);
        };
        let n = 64i32 << 14;
        for i in -n..=n {
            check(i as f32 / (1 << 14) as f32, &mut worst);
        }
        for k in -81..=81 {
            let x = k as f32 * std::f32::consts::FRAC_PI_4;
            for x in [x, x.next_up(), x.next_down()] {
                check(x, &mut worst);
            }
        }
        assert!(worst < 1.2e-7, "max error {worst}");
    }
}
