//! Procedural material textures for the photo-like synthetic scenes: wood, stone and marble,
//! woven fabric, wall paint, printed patterns (stripes, dots, checks, plaid, motifs), tiles and
//! brick, brushed metal. Each is a pure function of its random stream and of the physical width
//! the texture will cover (`extent`, metres: planks, tiles, prints and weaves keep plausible real
//! sizes), and returns a base colour map (sRGB-encoded RGB in [0, 1]) and a roughness map (one
//! channel in [0, 1]), both `size × size`, plus the material's metallic.
//!
//! Noise is value noise on a random lattice (smoothstep-interpolated), summed over octaves
//! (fractal Brownian motion); colours are drawn in HSV with the saturations and values of
//! household materials (mostly muted, some dark, some saturated prints).
use pixl_core::{Image, Rng};

/// What a texture generator draws: maps plus the material's scalars.
pub struct SurfaceMaps {
    /// sRGB-encoded base colour, 3 channels.
    pub color: Image,
    /// Roughness, 1 channel.
    pub roughness: Image,
    pub metallic: f32,
    /// The family, for the manifest and for debugging.
    pub kind: &'static str,
}

/// The material families.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Family {
    Wood,
    Stone,
    Fabric,
    Paint,
    Print,
    Tiles,
    Metal,
}

/// Value noise on a `g × g` lattice (wrapping), smoothstep-interpolated, in [0, 1].
struct Lattice {
    g: usize,
    v: Vec<f32>,
}

impl Lattice {
    fn new(rng: &mut Rng, g: usize) -> Self {
        let g = g.max(1);
        Lattice {
            g,
            v: (0..g * g).map(|_| rng.f32()).collect(),
        }
    }

    /// At `(x, y)` in lattice units.
    fn at(&self, x: f32, y: f32) -> f32 {
        let g = self.g as i64;
        let (fx, fy) = (x.floor(), y.floor());
        let (tx, ty) = (smooth(x - fx), smooth(y - fy));
        let idx = |i: i64, j: i64| self.v[(j.rem_euclid(g) * g + i.rem_euclid(g)) as usize];
        let (ix, iy) = (fx as i64, fy as i64);
        let top = idx(ix, iy) * (1.0 - tx) + idx(ix + 1, iy) * tx;
        let bottom = idx(ix, iy + 1) * (1.0 - tx) + idx(ix + 1, iy + 1) * tx;
        top * (1.0 - ty) + bottom * ty
    }
}

fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Fractal noise in [0, 1]: `octaves` lattices of doubling frequency and halving weight, the
/// first with `base` cells across the texture.
struct Fbm {
    octaves: Vec<Lattice>,
    base: f32,
}

impl Fbm {
    fn new(rng: &mut Rng, base: usize, octaves: usize) -> Self {
        Fbm {
            octaves: (0..octaves).map(|o| Lattice::new(rng, base << o)).collect(),
            base: base as f32,
        }
    }

    /// At texture coordinates `(u, v)` in [0, 1).
    fn at(&self, u: f32, v: f32) -> f32 {
        let (mut sum, mut norm, mut w, mut f) = (0.0, 0.0, 1.0, self.base);
        for l in &self.octaves {
            sum += w * l.at(u * f, v * f);
            norm += w;
            w *= 0.5;
            f *= 2.0;
        }
        sum / norm
    }
}

/// HSV (all in [0, 1]) to linear-ish RGB in [0, 1] (used as sRGB-encoded values).
pub fn hsv(h: f32, s: f32, v: f32) -> [f32; 3] {
    let h6 = h.rem_euclid(1.0) * 6.0;
    let c = v * s;
    let x = c * (1.0 - ((h6 % 2.0) - 1.0).abs());
    let (r, g, b) = match h6 as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// A household colour: mostly muted, sometimes dark or saturated (sRGB-encoded).
pub fn household_color(rng: &mut Rng) -> [f32; 3] {
    let h = rng.f32();
    match rng.below(10) {
        0..=4 => hsv(h, rng.uniform(0.05, 0.45), rng.uniform(0.35, 0.9)),
        5..=6 => hsv(h, rng.uniform(0.5, 0.9), rng.uniform(0.4, 0.9)),
        7 => hsv(h, rng.uniform(0.0, 0.3), rng.uniform(0.04, 0.2)),
        _ => hsv(h, rng.uniform(0.0, 0.08), rng.uniform(0.8, 0.95)),
    }
}

fn mix(a: [f32; 3], b: [f32; 3], t: f32) -> [f32; 3] {
    [0, 1, 2].map(|c| a[c] + (b[c] - a[c]) * t)
}

fn scale(a: [f32; 3], k: f32) -> [f32; 3] {
    a.map(|v| (v * k).clamp(0.0, 1.0))
}

/// Builds the two maps from a per-texel function returning (colour, roughness).
fn maps(size: usize, metallic: f32, kind: &'static str, f: impl Fn(f32, f32) -> ([f32; 3], f32)) -> SurfaceMaps {
    let mut color = Image::new(size, size, 3);
    let mut roughness = Image::new(size, size, 1);
    for y in 0..size {
        for x in 0..size {
            let (u, v) = ((x as f32 + 0.5) / size as f32, (y as f32 + 0.5) / size as f32);
            let (c, r) = f(u, v);
            let i = y * size + x;
            for (k, cv) in c.iter().enumerate() {
                color.data[3 * i + k] = cv.clamp(0.0, 1.0);
            }
            roughness.data[i] = r.clamp(0.02, 1.0);
        }
    }
    SurfaceMaps {
        color,
        roughness,
        metallic,
        kind,
    }
}

/// Planks of wood with growth rings bent by noise; each plank its own tone.
fn wood(rng: &mut Rng, size: usize, extent: f32) -> SurfaceMaps {
    let light = hsv(rng.uniform(0.05, 0.1), rng.uniform(0.35, 0.6), rng.uniform(0.55, 0.85));
    let dark = scale(light, rng.uniform(0.45, 0.7));
    let planks = (extent / rng.uniform(0.1, 0.3)).round().clamp(1.0, 32.0) as usize;
    let tones: Vec<f32> = (0..planks).map(|_| rng.uniform(0.8, 1.15)).collect();
    let offsets: Vec<f32> = (0..planks).map(|_| rng.uniform(0.0, 10.0)).collect();
    let warp = Fbm::new(rng, 3, 3);
    let grain = Fbm::new(rng, 16, 2);
    let rings = rng.uniform(12.0, 30.0);
    let (r0, dr) = (rng.uniform(0.25, 0.6), rng.uniform(0.05, 0.2));
    maps(size, 0.0, "wood", move |u, v| {
        let p = ((v * planks as f32) as usize).min(planks - 1);
        let ring = ((u * 0.3 + offsets[p] + warp.at(u, v) * 1.5) * rings).fract();
        let t = smooth((ring * 2.0 - 1.0).abs()) * 0.7 + grain.at(u * 0.25, v) * 0.3;
        let c = scale(mix(dark, light, t), tones[p]);
        (c, r0 + dr * (1.0 - t))
    })
}

/// Marble (turbulent veins) or granite (speckles).
fn stone(rng: &mut Rng, size: usize, extent: f32) -> SurfaceMaps {
    let base = hsv(rng.uniform(0.0, 0.15), rng.uniform(0.0, 0.25), rng.uniform(0.3, 0.92));
    let vein = scale(base, rng.uniform(0.2, 0.6));
    let turb = Fbm::new(rng, 4, 5);
    if rng.bernoulli(0.5) {
        let freq = rng.uniform(3.0, 9.0) * extent.max(0.3).sqrt();
        let r = rng.uniform(0.1, 0.35);
        maps(size, 0.0, "marble", move |u, v| {
            let s = ((u + v * 0.5) * freq + turb.at(u, v) * 6.0).sin();
            let t = (1.0 - s.abs()).powf(6.0);
            (mix(base, vein, t), r)
        })
    } else {
        let speck = Fbm::new(rng, 48, 2);
        let r = rng.uniform(0.3, 0.7);
        maps(size, 0.0, "granite", move |u, v| {
            let t = (speck.at(u, v) * 1.6 - 0.3).clamp(0.0, 1.0) * 0.7 + turb.at(u, v) * 0.3;
            (mix(vein, base, t), r + 0.1 * t)
        })
    }
}

/// A plain or twill weave of two thread colours, slightly uneven.
fn fabric(rng: &mut Rng, size: usize, extent: f32) -> SurfaceMaps {
    let a = household_color(rng);
    let b = if rng.bernoulli(0.5) {
        scale(a, rng.uniform(0.6, 0.9))
    } else {
        household_color(rng)
    };
    let threads = (extent / rng.uniform(0.004, 0.02)).clamp(8.0, size as f32 / 4.0);
    let twill = rng.bernoulli(0.4);
    let uneven = Fbm::new(rng, 6, 3);
    maps(size, 0.0, "fabric", move |u, v| {
        let (x, y) = (u * threads, v * threads);
        let over = if twill {
            ((x.floor() + y.floor()) as i64).rem_euclid(3) == 0
        } else {
            ((x.floor() + y.floor()) as i64).rem_euclid(2) == 0
        };
        let across = if over { y.fract() } else { x.fract() };
        let bump = (std::f32::consts::PI * across).sin() * 0.25 + 0.75;
        let c = if over { a } else { b };
        let k = bump * (0.85 + 0.3 * uneven.at(u, v));
        (scale(c, k), 0.85 + 0.15 * uneven.at(v, u))
    })
}

/// Wall paint: one colour with faint low-frequency unevenness.
fn paint(rng: &mut Rng, size: usize) -> SurfaceMaps {
    let c = household_color(rng);
    let uneven = Fbm::new(rng, 3, 4);
    let (r, amp) = (rng.uniform(0.35, 0.95), rng.uniform(0.02, 0.08));
    maps(size, 0.0, "paint", move |u, v| {
        (scale(c, 1.0 - amp + 2.0 * amp * uneven.at(u, v)), r)
    })
}

/// Printed patterns: stripes, dots, checks, plaid, or a diamond motif, in two or three colours.
fn print(rng: &mut Rng, size: usize, extent: f32) -> SurfaceMaps {
    let (a, b, c) = (household_color(rng), household_color(rng), household_color(rng));
    let n = (extent / rng.uniform(0.04, 0.4)).clamp(1.0, size as f32 / 8.0);
    let kind = rng.below(5);
    let angle = if rng.bernoulli(0.3) { rng.uniform(0.0, 1.5) } else { 0.0 };
    let (ca, sa) = (angle.cos(), angle.sin());
    let r = rng.uniform(0.3, 0.9);
    let duty = rng.uniform(0.2, 0.6);
    maps(size, 0.0, "print", move |u, v| {
        let (x, y) = ((u * ca - v * sa) * n, (u * sa + v * ca) * n);
        let col = match kind {
            0 => {
                if x.fract() < duty {
                    a
                } else {
                    b
                }
            }
            1 => {
                let (dx, dy) = (x.fract() - 0.5, y.fract() - 0.5);
                if (dx * dx + dy * dy).sqrt() < duty * 0.5 {
                    a
                } else {
                    b
                }
            }
            2 => {
                if ((x.floor() + y.floor()) as i64).rem_euclid(2) == 0 {
                    a
                } else {
                    b
                }
            }
            3 => {
                let sx = (x.fract() < duty) as u32 as f32;
                let sy = (y.fract() < duty) as u32 as f32;
                mix(mix(b, a, 0.5 * sx), c, 0.4 * sy)
            }
            _ => {
                let (dx, dy) = ((x.fract() - 0.5).abs(), (y.fract() - 0.5).abs());
                if dx + dy < duty * 0.6 {
                    c
                } else if dx + dy < duty * 0.8 {
                    a
                } else {
                    b
                }
            }
        };
        (col, r)
    })
}

/// Tiles or bricks with mortar joints, each tile's tone jittered.
fn tiles(rng: &mut Rng, size: usize, extent: f32) -> SurfaceMaps {
    let brick = rng.bernoulli(0.5);
    let face = if brick {
        hsv(rng.uniform(0.0, 0.08), rng.uniform(0.35, 0.7), rng.uniform(0.35, 0.7))
    } else {
        household_color(rng)
    };
    let mortar = hsv(0.1, rng.uniform(0.0, 0.15), rng.uniform(0.5, 0.85));
    let most = size as f32 / 8.0;
    let (nx, ny) = if brick {
        let nx = (extent / rng.uniform(0.2, 0.3)).clamp(1.0, most / 3.0).round();
        (nx, (nx * 3.0).round())
    } else {
        let n = (extent / rng.uniform(0.1, 0.6)).clamp(1.0, most).round();
        (n, n)
    };
    let joint = rng.uniform(0.03, 0.08);
    let jitter = Lattice::new(rng, 64);
    let dirt = Fbm::new(rng, 8, 3);
    let (rf, rm) = (rng.uniform(0.1, 0.6), rng.uniform(0.7, 1.0));
    maps(size, 0.0, if brick { "brick" } else { "tiles" }, move |u, v| {
        let row = (v * ny).floor();
        let shift = if brick && (row as i64) % 2 == 1 { 0.5 } else { 0.0 };
        let x = u * nx + shift;
        let (fx, fy) = (x.fract(), (v * ny).fract());
        let joint_x = joint * if brick { 0.5 } else { 1.0 };
        if fx < joint_x || fy < joint {
            (mortar, rm)
        } else {
            let tone = 0.8 + 0.4 * jitter.at(x.floor() * 7.0 + 0.5, row * 3.0 + 0.5);
            (scale(face, tone * (0.9 + 0.2 * dirt.at(u, v))), rf)
        }
    })
}

/// Brushed metal: a tint stretched along one direction.
fn metal(rng: &mut Rng, size: usize) -> SurfaceMaps {
    let tint = match rng.below(4) {
        0 => [0.91, 0.92, 0.92],                                           // aluminium / steel
        1 => [0.95, 0.64, 0.54],                                           // copper
        2 => [1.0, 0.78, 0.34],                                            // gold / brass
        _ => hsv(rng.f32(), rng.uniform(0.0, 0.3), rng.uniform(0.5, 0.9)), // anodised
    };
    let brush = Fbm::new(rng, 64, 2);
    let r = rng.uniform(0.12, 0.5);
    maps(size, 1.0, "metal", move |u, v| {
        let t = brush.at(u * 0.05, v);
        (scale(tint, 0.9 + 0.1 * t), r * (0.8 + 0.4 * t))
    })
}

/// A texture of the given family, drawn from `rng`, to cover `extent` metres.
pub fn surface(family: Family, rng: &mut Rng, size: usize, extent: f32) -> SurfaceMaps {
    match family {
        Family::Wood => wood(rng, size, extent),
        Family::Stone => stone(rng, size, extent),
        Family::Fabric => fabric(rng, size, extent),
        Family::Paint => paint(rng, size),
        Family::Print => print(rng, size, extent),
        Family::Tiles => tiles(rng, size, extent),
        Family::Metal => metal(rng, size),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const ALL: [Family; 7] = [
        Family::Wood,
        Family::Stone,
        Family::Fabric,
        Family::Paint,
        Family::Print,
        Family::Tiles,
        Family::Metal,
    ];

    /// Every family gives maps of the asked size in range, is a pure function of the stream,
    /// and is not flat (except paint, which is nearly flat by design): its colour varies.
    #[test]
    fn families_are_deterministic_in_range_and_textured() {
        for (k, fam) in ALL.into_iter().enumerate() {
            for seed in 0..6u64 {
                let draw = || surface(fam, &mut Rng::for_stream(seed, &[k as u64]), 32, 0.2 + seed as f32);
                let (a, b) = (draw(), draw());
                assert_eq!(a.color.data, b.color.data, "{fam:?} not deterministic");
                assert_eq!((a.color.width, a.color.height, a.color.channels), (32, 32, 3));
                assert_eq!(a.roughness.channels, 1);
                assert!(a.color.data.iter().all(|v| (0.0..=1.0).contains(v)));
                assert!(a.roughness.data.iter().all(|v| (0.02..=1.0).contains(v)));
                let mean = a.color.data.iter().sum::<f32>() / a.color.data.len() as f32;
                let var = a.color.data.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / a.color.data.len() as f32;
                if fam != Family::Paint {
                    assert!(var > 1e-5, "{fam:?} seed {seed}: flat texture (var {var})");
                }
                assert_eq!(a.metallic, if fam == Family::Metal { 1.0 } else { 0.0 });
            }
        }
    }

    /// Value noise interpolates its lattice: at integer points it returns the lattice values,
    /// and it wraps with the lattice period.
    #[test]
    fn lattice_hits_its_values_and_wraps() {
        let l = Lattice::new(&mut Rng::new(3), 5);
        for j in 0..5 {
            for i in 0..5 {
                assert_eq!(l.at(i as f32, j as f32), l.v[j * 5 + i]);
                assert!((l.at(i as f32 + 5.0 + 0.3, j as f32 - 5.0) - l.at(i as f32 + 0.3, j as f32)).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn hsv_primaries() {
        assert_eq!(hsv(0.0, 1.0, 1.0), [1.0, 0.0, 0.0]);
        let g = hsv(1.0 / 3.0, 1.0, 1.0);
        assert!(g[0].abs() < 1e-6 && (g[1] - 1.0).abs() < 1e-6 && g[2].abs() < 1e-6);
        assert_eq!(hsv(0.5, 0.0, 0.4), [0.4, 0.4, 0.4]);
    }
}
