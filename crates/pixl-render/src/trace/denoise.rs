//! A cheap, edge-preserving clean-up of a render's `Combined`: the **guided median** of the
//! demodulated light.
//!
//! The film stores each lobe's light divided by its colour pass (`DiffDir + DiffInd` is the light
//! a white diffuse surface would reflect, free of texture). Per channel, the diffuse and
//! transmission light is replaced by the median over the pixels of a `(2r + 1)²` window that see
//! the same surface — normal within `cos 10°` and depth within 5 % of the centre's, and a
//! non-zero colour in the lobe — then multiplied back by the pixel's own colour; the glossy light
//! (highlights are detail, not noise), `Emit` and `Env` are added unfiltered:
//!
//! `Combined' = Σ_{diffuse, transmission} Col ⊙ median_{q ~ p}(Dir + Ind)_q
//!              + GlossCol ⊙ (GlossDir + GlossInd) + Emit + Env`.
//!
//! Textures stay as sharp as the colour passes, the median keeps shadow edges (a step survives a
//! median) and removes isolated fireflies and most of the grain of few-sample indirect light on
//! walls and floors. It is biased (a median is not a mean; curved surfaces lose a little shading
//! contrast) and meant for images that are looked at or learnt from, never for the passes C_T is
//! composed from. `BENCHMARKS.md` measures it on the synthetic scenes it serves.
use crate::trace::film::Film;
use pixl_core::passes::{self, Pass};
use pixl_core::Image;
use rayon::prelude::*;

/// The lobes' (colour, direct, indirect) passes.
const LOBES: [(Pass, Pass, Pass); 3] = [
    (passes::DIFF_COL, passes::DIFF_DIR, passes::DIFF_IND),
    (passes::GLOSS_COL, passes::GLOSS_DIR, passes::GLOSS_IND),
    (passes::TRANS_COL, passes::TRANS_DIR, passes::TRANS_IND),
];

/// Neighbours count as the same surface when their normals are within this cosine …
const NORMAL_COS: f32 = 0.985; // cos 10°
/// … and their depths within this fraction of the centre pixel's.
const DEPTH_REL: f32 = 0.05;

/// `Combined` (RGB, linear) of `film` with the guided median of radius `radius` (window
/// `(2r + 1)²`) applied to each lobe's light; `radius = 0` returns the recombined passes
/// unfiltered. `None` when the film lacks a pass it needs.
pub fn guided_median(film: &Film, radius: usize) -> Option<Image> {
    let (w, h) = (film.width, film.height);
    let normal = film.pass_ref(passes::NORMAL.short)?;
    let depth = film.pass_ref(passes::DEPTH.short)?;
    let mut out = Image::new(w, h, 3);
    for extra in [passes::EMIT, passes::ENV] {
        let e = film.pass_ref(extra.short)?;
        out.data.iter_mut().zip(&e.data).for_each(|(o, v)| *o += v);
    }
    let same = |p: usize, q: usize| {
        let (np, nq) = (&normal.data[3 * p..3 * p + 3], &normal.data[3 * q..3 * q + 3]);
        let dot = np[0] * nq[0] + np[1] * nq[1] + np[2] * nq[2];
        let (zp, zq) = (depth.data[p], depth.data[q]);
        dot >= NORMAL_COS && (zp - zq).abs() <= DEPTH_REL * zp
    };
    for (lobe, (col, dir, ind)) in LOBES.into_iter().enumerate() {
        let radius = if lobe == 1 { 0 } else { radius };
        let (col, dir, ind) = (
            film.pass_ref(col.short)?,
            film.pass_ref(dir.short)?,
            film.pass_ref(ind.short)?,
        );
        let light: Vec<f32> = dir.data.iter().zip(&ind.data).map(|(a, b)| a + b).collect();
        let lit = |q: usize| col.data[3 * q..3 * q + 3].iter().any(|&c| c > 0.0);
        out.data.par_chunks_mut(3 * w).enumerate().for_each(|(y, row)| {
            let mut vals: [Vec<f32>; 3] = Default::default();
            for x in 0..w {
                let p = y * w + x;
                if !lit(p) {
                    continue;
                }
                vals.iter_mut().for_each(Vec::clear);
                for qy in y.saturating_sub(radius)..(y + radius + 1).min(h) {
                    for qx in x.saturating_sub(radius)..(x + radius + 1).min(w) {
                        let q = qy * w + qx;
                        if q == p || (lit(q) && same(p, q)) {
                            for (c, v) in vals.iter_mut().enumerate() {
                                v.push(light[3 * q + c]);
                            }
                        }
                    }
                }
                for (c, v) in vals.iter_mut().enumerate() {
                    let mid = v.len() / 2;
                    let m = if v.len() % 2 == 1 {
                        *v.select_nth_unstable_by(mid, f32::total_cmp).1
                    } else {
                        // even count: the mean of the two middle values
                        let hi = *v.select_nth_unstable_by(mid, f32::total_cmp).1;
                        let lo = v[..mid].iter().copied().fold(f32::NEG_INFINITY, f32::max);
                        0.5 * (lo + hi)
                    };
                    row[3 * x + c] += col.data[3 * p + c] * m;
                }
            }
        });
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{RenderOptions, Scene};

    fn film_of(scene: &str, spp: u32, seed: u64) -> Film {
        let s = Scene::from_toml_str(scene).expect("scene");
        let opts = RenderOptions {
            spp,
            seed,
            max_bounces: 2,
            ..Default::default()
        };
        crate::render(&s, &opts, &|_, _| {}).expect("render")
    }

    const SCENE: &str = r#"
        [camera]
        width = 48
        height = 32
        fov_y_deg = 50.0
        position = [0.0, 1.0, 3.0]
        look_at = [0.0, 0.4, 0.0]
        [[objects]]
        name = "floor"
        shape = { type = "quad", size = [6.0, 6.0] }
        transform = { rotate_deg = [-90.0, 0.0, 0.0] }
        material = { base_color = [0.7, 0.6, 0.5] }
        [[objects]]
        name = "ball"
        shape = { type = "sphere", radius = 0.4 }
        transform = { translate = [0.0, 0.4, 0.0] }
        material = { base_color = [0.2, 0.5, 0.8], roughness = 0.4 }
        [[lights]]
        type = "area"
        position = [1.0, 2.0, 1.0]
        look_at = [0.0, 0.0, 0.0]
        size = 0.5
        power = 300.0
        [world]
        strength = 0.3
    "#;

    /// Radius 0 is the identity on the recombined passes: it reproduces `Combined`.
    #[test]
    fn radius_zero_recombines_the_passes() {
        let film = film_of(SCENE, 4, 1);
        let out = guided_median(&film, 0).expect("passes");
        let comb = film.pass_ref("Combined").expect("combined");
        for p in 0..film.width * film.height {
            for c in 0..3 {
                let (a, b) = (out.data[3 * p + c], comb.data[4 * p + c]);
                assert!((a - b).abs() <= 1e-4 * (1.0 + b.abs()), "pixel {p}: {a} vs {b}");
            }
        }
    }

    /// On a grainy 2-spp render the filtered image is much closer to a 1024-spp reference than
    /// the render itself (squared error 61 vs 91 since rectangles are sampled by solid angle at
    /// every distance; 65 vs 109 before), and its mean stays within 3 %
    /// of the reference's (the median of a skewed distribution sits below its mean: 1.4 % low
    /// here). (At many samples per pixel on so small an image the median's bias on the ball
    /// outweighs the noise it removes: it is for grainy images.)
    #[test]
    fn brings_a_noisy_render_closer_to_the_reference() {
        let noisy = film_of(SCENE, 2, 1);
        let reference = film_of(SCENE, 1024, 2);
        let r = reference.pass_ref("Combined").expect("combined");
        let n = noisy.pass_ref("Combined").expect("combined");
        let f = guided_median(&noisy, 2).expect("passes");
        let (mut e_noisy, mut e_filtered, mut m_ref, mut m_f) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for p in 0..noisy.width * noisy.height {
            for c in 0..3 {
                let rv = r.data[4 * p + c] as f64;
                e_noisy += (n.data[4 * p + c] as f64 - rv).powi(2);
                e_filtered += (f.data[3 * p + c] as f64 - rv).powi(2);
                m_ref += rv;
                m_f += f.data[3 * p + c] as f64;
            }
        }
        assert!(
            e_filtered < 0.75 * e_noisy,
            "squared error {e_filtered} vs unfiltered {e_noisy}"
        );
        assert!((m_f / m_ref - 1.0).abs() < 0.03, "mean ratio {}", m_f / m_ref);
    }

    /// The median never mixes light across a depth edge: a bright square in front of a dark
    /// wall, lit evenly, keeps both sides' values exactly (the window sees only its surface).
    #[test]
    fn keeps_a_depth_edge() {
        use crate::math::V3;
        use crate::trace::film::PixelSum;
        let (w, h) = (12usize, 8usize);
        let sums: Vec<PixelSum> = (0..w * h)
            .map(|p| {
                let near = p % w < 6;
                let mut s = PixelSum::default();
                s.col[0] = V3::new(0.5, 0.5, 0.5);
                let light = if near { 2.0 } else { 0.1 };
                s.dir[0] = V3::new(0.5 * light, 0.5 * light, 0.5 * light);
                s.normal = V3::new(0.0, 0.0, 1.0);
                s.normal_n = 1;
                s.depth = if near { 1.0 } else { 3.0 };
                s
            })
            .collect();
        let film = Film::from_sums(w, h, 1, &sums);
        let out = guided_median(&film, 2).expect("passes");
        for y in 0..h {
            for x in 0..w {
                let want = if x < 6 { 1.0 } else { 0.05 };
                assert_eq!(out.data[3 * (y * w + x)], want, "({x}, {y})");
            }
        }
    }
}
