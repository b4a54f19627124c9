//! Colour helpers: blackbody temperature → linear Rec.709 RGB, and luminance.
//!
//! # Blackbody approximation
//! Planck's law is integrated against the CIE 1931 2° colour-matching functions, approximated by
//! the multi-lobe Gaussian fit of Wyman, Sloan & Shirley (JCGT 2013), over 380–780 nm in 1 nm
//! steps; XYZ is converted to linear Rec.709 / sRGB primaries (D65), negative components are
//! clipped to 0, and the result is normalised to **luminance 1** (`0.2126 R + 0.7152 G +
//! 0.0722 B = 1`), so a light's power keeps its meaning whatever its temperature. Blender's
//! Blackbody node uses a fitted table with a similar normalisation; hues agree to within a few
//! percent per channel over 1500–12000 K, which is well inside what lighting design needs.
//! Temperatures are clamped to [800, 40000] K.

/// Rec.709 luminance of a linear RGB triple.
#[inline]
pub fn luminance(c: [f32; 3]) -> f32 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

fn gauss(x: f64, mu: f64, s1: f64, s2: f64) -> f64 {
    let t = (x - mu) / if x < mu { s1 } else { s2 };
    (-0.5 * t * t).exp()
}

/// CIE 1931 2° colour-matching functions at wavelength `nm` (Wyman et al. 2013 fit).
fn cie_xyz(nm: f64) -> [f64; 3] {
    let x = 1.056 * gauss(nm, 599.8, 37.9, 31.0) + 0.362 * gauss(nm, 442.0, 16.0, 26.7)
        - 0.065 * gauss(nm, 501.1, 20.4, 26.2);
    let y = 0.821 * gauss(nm, 568.8, 46.9, 40.5) + 0.286 * gauss(nm, 530.9, 16.3, 31.1);
    let z = 1.217 * gauss(nm, 437.0, 11.8, 36.0) + 0.681 * gauss(nm, 459.0, 26.0, 13.8);
    [x, y, z]
}

/// Linear Rec.709 RGB of a blackbody at `kelvin`, normalised to luminance 1.
pub fn blackbody(kelvin: f32) -> [f32; 3] {
    let t = (kelvin as f64).clamp(800.0, 40000.0);
    // Planck: B(λ) ∝ λ^-5 / (exp(hc/(λkT)) - 1); constant factors cancel in the normalisation.
    const C2: f64 = 1.438_776_9e-2; // hc/k in m·K
    let mut xyz = [0.0f64; 3];
    for i in 0..=400 {
        let nm = 380.0 + i as f64;
        let lambda = nm * 1e-9;
        let b = 1.0 / (lambda.powi(5) * ((C2 / (lambda * t)).exp() - 1.0));
        let cmf = cie_xyz(nm);
        for k in 0..3 {
            xyz[k] += b * cmf[k];
        }
    }
    let [x, y, z] = xyz;
    let rgb = [
        3.240_454_2 * x - 1.537_138_5 * y - 0.498_531_4 * z,
        -0.969_266 * x + 1.876_010_8 * y + 0.041_556 * z,
        0.055_643_4 * x - 0.204_025_9 * y + 1.057_225_2 * z,
    ];
    let rgb = rgb.map(|v| v.max(0.0));
    let lum = 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2];
    if lum <= 0.0 || !lum.is_finite() {
        return [1.0, 1.0, 1.0];
    }
    rgb.map(|v| (v / lum) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blackbody_is_normalised_and_ordered() {
        for k in [1500.0, 2700.0, 4000.0, 6500.0, 10000.0] {
            let c = blackbody(k);
            assert!((luminance(c) - 1.0).abs() < 1e-4, "{k} K: {c:?}");
        }
        // Low temperatures are red-heavy, high temperatures blue-heavy.
        let warm = blackbody(2700.0);
        let cool = blackbody(10000.0);
        assert!(warm[0] > warm[2] * 2.0, "{warm:?}");
        assert!(cool[2] > cool[0], "{cool:?}");
        // D65 is close to a 6500 K blackbody: near-neutral (within ~10 % per channel).
        let d = blackbody(6504.0);
        for v in d {
            assert!((v - 1.0).abs() < 0.12, "{d:?}");
        }
    }
}
