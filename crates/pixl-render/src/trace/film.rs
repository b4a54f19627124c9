//! The film: per-pixel render passes with **Cycles' meanings** (names from
//! [`pixl_core::passes`]).
//!
//! - `DiffCol`, `GlossCol`, `TransCol`: the albedo of the lobes of each kind at the first camera
//!   hit for the view direction, as Cycles' `bsdf_albedo` (see [`crate::trace::material`]): diffuse
//!   `base·(1−metallic)·(1−transmission)·(1 − A_spec/w)` (the base under the specular coat of
//!   albedo `A_spec`); glossy the energy-compensated, Fresnel-weighted albedos of the metal and
//!   dielectric GGX lobes plus the glass's Fresnel reflectance; transmission
//!   `√base·(1−metallic)·transmission·(1−F)` (the per-interface tint). Averaged over samples.
//! - `*Dir`: light reaching the first hit straight from a light (next-event estimation plus
//!   MIS-weighted emission found by the first BSDF ray); `*Ind`: all other light scattered at the
//!   first hit. Both are stored **divided by the colour pass** as Cycles does: accumulated as
//!   `Col ⊙ light`, then divided by the accumulated colour after averaging (0 where the colour
//!   is 0). Hence, per pixel, `Col ⊙ (Dir + Ind)` summed over the three lobes `+ Emit + Env`
//!   equals `Combined` up to float rounding.
//! - `Emit`: emission seen directly by the camera: emissive surfaces, and area lights marked
//!   `visible_to_camera` (lights are invisible to camera rays by default, as in Blender 4/5).
//! - `Env`: the world seen directly by the camera.
//! - `VolumeDir`, `VolumeInd`: always 0 (no participating media).
//! - `Combined`: RGB plus alpha 1 (Cycles with an opaque film).
//! - `Depth` (`Z`): distance along the camera's viewing axis, minimum over samples; 1e10 where
//!   only the world is seen (as Cycles writes).
//! - `Normal` (`X, Y, Z`): world-space shading normal (our Y-up world; the Blender bridge rotates
//!   it), averaged over the samples that hit a surface.
use crate::math::V3;
use pixl_core::exrio::ExrChannels;
use pixl_core::passes::{self, Pass};
use pixl_core::Image;
use rayon::prelude::*;

/// Depth written where no surface is seen.
pub const BACKGROUND_DEPTH: f32 = 1e10;

/// Per-pixel sums over samples (crate-internal accumulation).
#[derive(Clone, Copy, Debug)]
pub struct PixelSum {
    /// Diffuse, glossy, transmission colour weights.
    pub col: [V3; 3],
    /// `Col ⊙ direct light` per lobe.
    pub dir: [V3; 3],
    /// `Col ⊙ indirect light` per lobe.
    pub ind: [V3; 3],
    pub emit: V3,
    pub env: V3,
    pub combined: V3,
    pub depth: f32,
    pub normal: V3,
    pub normal_n: u32,
}

impl Default for PixelSum {
    fn default() -> Self {
        PixelSum {
            col: [V3::ZERO; 3],
            dir: [V3::ZERO; 3],
            ind: [V3::ZERO; 3],
            emit: V3::ZERO,
            env: V3::ZERO,
            combined: V3::ZERO,
            depth: BACKGROUND_DEPTH,
            normal: V3::ZERO,
            normal_n: 0,
        }
    }
}

impl PixelSum {
    pub fn add(&mut self, o: &PixelSum) {
        for k in 0..3 {
            self.col[k] += o.col[k];
            self.dir[k] += o.dir[k];
            self.ind[k] += o.ind[k];
        }
        self.emit += o.emit;
        self.env += o.env;
        self.combined += o.combined;
        self.depth = self.depth.min(o.depth);
        self.normal += o.normal;
        self.normal_n += o.normal_n;
    }
}

/// Rendered passes. Each pass is an [`Image`] (3 channels; `Combined` 4, `Depth` 1).
#[derive(Clone, Debug)]
pub struct Film {
    pub width: usize,
    pub height: usize,
    pub spp: u32,
    passes: Vec<(Pass, Image)>,
}

const LOBE_PASSES: [(Pass, Pass, Pass); 3] = [
    (passes::DIFF_COL, passes::DIFF_DIR, passes::DIFF_IND),
    (passes::GLOSS_COL, passes::GLOSS_DIR, passes::GLOSS_IND),
    (passes::TRANS_COL, passes::TRANS_DIR, passes::TRANS_IND),
];

/// The 3-channel passes written per pixel, in the order [`Film::from_rows`] stores them:
/// DiffCol, DiffDir, DiffInd, GlossCol, …, TransInd, then Emit, Env, Normal.
const RGB_PASSES: usize = 12;

/// One row of every pass being written (disjoint slices of the film's images).
struct RowOut<'a> {
    rgb: [&'a mut [f32]; RGB_PASSES],
    combined: &'a mut [f32],
    depth: &'a mut [f32],
}

impl RowOut<'_> {
    /// Writes pixel `x`'s final values from its sums over `n` samples.
    #[inline]
    fn set(&mut self, x: usize, s: &PixelSum, n: f32) {
        let mut put = |k: usize, v: V3| self.rgb[k][3 * x..3 * x + 3].copy_from_slice(&v.to_arr());
        for k in 0..3 {
            put(3 * k, s.col[k] / n);
            put(3 * k + 1, s.dir[k].safe_div(s.col[k]));
            put(3 * k + 2, s.ind[k].safe_div(s.col[k]));
        }
        put(9, s.emit / n);
        put(10, s.env / n);
        put(
            11,
            if s.normal_n > 0 {
                s.normal / s.normal_n as f32
            } else {
                V3::ZERO
            },
        );
        let c = s.combined / n;
        self.combined[4 * x..4 * x + 4].copy_from_slice(&[c.x, c.y, c.z, 1.0]);
        self.depth[x] = s.depth;
    }
}

impl Film {
    /// Final passes from per-pixel sums over `spp` samples (row-major).
    pub fn from_sums(width: usize, height: usize, spp: u32, sums: &[PixelSum]) -> Film {
        Film::from_rows(width, height, spp, &|y, row| {
            for (x, px) in row.iter_mut().enumerate() {
                *px = sums.get(y * width + x).copied().unwrap_or_default();
            }
        })
    }

    /// Final passes from sums over `spp` samples that `row(y, sums)` writes for each row `y`
    /// (`sums` holds `width` entries); rows run in parallel (rayon), each converted to the
    /// passes as soon as it is done, so no image-sized buffer of sums is ever held (at 512²
    /// that was ~43 MB written and read back 13 times).
    pub fn from_rows(width: usize, height: usize, spp: u32, row: &(dyn Fn(usize, &mut [PixelSum]) + Sync)) -> Film {
        let n = spp.max(1) as f32;
        let mut rgb: [Image; RGB_PASSES] = std::array::from_fn(|_| Image::new(width, height, 3));
        let mut comb = Image::new(width, height, 4);
        let mut depth = Image::new(width, height, 1);
        {
            let w = width.max(1);
            let mut rgb_rows: Vec<_> = rgb.iter_mut().map(|im| im.data.chunks_mut(3 * w)).collect();
            let (mut comb_rows, mut depth_rows) = (comb.data.chunks_mut(4 * w), depth.data.chunks_mut(w));
            let mut rows = Vec::with_capacity(height);
            for _ in 0..height {
                rows.push(RowOut {
                    rgb: std::array::from_fn(|k| rgb_rows[k].next().unwrap_or(&mut [])),
                    combined: comb_rows.next().unwrap_or(&mut []),
                    depth: depth_rows.next().unwrap_or(&mut []),
                });
            }
            rows.into_par_iter().enumerate().for_each_init(
                || vec![PixelSum::default(); width],
                |sums, (y, mut out)| {
                    row(y, sums);
                    for (x, s) in sums.iter().enumerate() {
                        out.set(x, s, n);
                    }
                },
            );
        }
        let [diff_col, diff_dir, diff_ind, gloss_col, gloss_dir, gloss_ind, trans_col, trans_dir, trans_ind, emit, env, normal] =
            rgb;
        let lobes = [
            [diff_col, diff_dir, diff_ind],
            [gloss_col, gloss_dir, gloss_ind],
            [trans_col, trans_dir, trans_ind],
        ];
        let mut out = Vec::new();
        for ((col, dir, ind), [c, d, i]) in LOBE_PASSES.into_iter().zip(lobes) {
            out.push((col, c));
            out.push((dir, d));
            out.push((ind, i));
        }
        out.push((passes::VOLUME_DIR, Image::new(width, height, 3)));
        out.push((passes::VOLUME_IND, Image::new(width, height, 3)));
        out.push((passes::EMIT, emit));
        out.push((passes::ENV, env));
        out.push((passes::COMBINED, comb));
        out.push((passes::DEPTH, depth));
        out.push((passes::NORMAL, normal));
        Film {
            width,
            height,
            spp,
            passes: out,
        }
    }

    /// A pass by short (`DiffDir`) or long (`Diffuse Direct`) name.
    pub fn pass(&self, name: &str) -> Option<Image> {
        self.passes
            .iter()
            .find(|(p, _)| p.short == name || p.long == name)
            .map(|(_, img)| img.clone())
    }

    /// Borrowed pass by short or long name.
    pub fn pass_ref(&self, name: &str) -> Option<&Image> {
        self.passes
            .iter()
            .find(|(p, _)| p.short == name || p.long == name)
            .map(|(_, img)| img)
    }

    /// All passes as EXR channels named like Cycles' (`ViewLayer.Diffuse Direct.R`, …).
    pub fn to_exr_channels(&self) -> ExrChannels {
        let mut ex = ExrChannels::new(self.width, self.height);
        for (pass, img) in &self.passes {
            for (c, ch) in pass.channels.iter().enumerate() {
                let data: Vec<f32> = img.data.iter().skip(c).step_by(img.channels).copied().collect();
                ex.channels
                    .push((format!("{}.{}.{}", passes::VIEW_LAYER, pass.long, ch), data));
            }
        }
        ex
    }

    /// Writes all passes to one EXR file (atomically).
    pub fn write_exr(&self, path: &std::path::Path) -> crate::Result<()> {
        pixl_core::exrio::write_exr_channels(path, &self.to_exr_channels())?;
        Ok(())
    }

    /// A display preview of `Combined`: Reinhard tonemap with auto-exposure (key 0.18 on the
    /// log-average luminance), sRGB-encoded, RGB in [0, 1] — the paper's display convention
    /// (§4.2, [`pixl_core::image::tonemap_reinhard`]).
    pub fn combined_srgb(&self) -> Image {
        match self.pass_ref("Combined") {
            Some(c) => pixl_core::image::tonemap_reinhard(&c.select_channels(0..3)),
            None => Image::new(self.width, self.height, 3),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sums that differ in every field and every pixel, so a value written to the wrong pass,
    /// channel or pixel shows.
    fn sums_at(x: usize, y: usize) -> PixelSum {
        let f = (1 + x + 10 * y) as f32;
        let v = |k: f32| V3::new(f + k, 2.0 * f + k, 3.0 * f + k);
        PixelSum {
            col: [v(0.5), v(1.5), if x == 1 { V3::ZERO } else { v(2.5) }],
            dir: [v(3.0), v(4.0), v(5.0)],
            ind: [v(6.0), v(7.0), v(8.0)],
            emit: v(9.0),
            env: v(10.0),
            combined: v(11.0),
            depth: f * 0.25,
            normal: v(12.0),
            normal_n: (x % 2) as u32 * 2,
        }
    }

    /// Every pass of a 3×2 film from known sums, against values computed here in f64 from the
    /// passes' definitions (module header): colours and light averaged over the samples, Dir /
    /// Ind divided by the colour (0 where it is 0), normals by their count, alpha 1, min depth.
    #[test]
    fn passes_from_sums_hold_each_pixels_values() {
        let (w, h, spp) = (3usize, 2usize, 4u32);
        let sums: Vec<PixelSum> = (0..w * h).map(|i| sums_at(i % w, i / w)).collect();
        let film = Film::from_sums(w, h, spp, &sums);
        let n = spp as f64;
        let div = |a: f32, b: f32| if b == 0.0 { 0.0 } else { a as f64 / b as f64 };
        let names = [
            ["DiffCol", "DiffDir", "DiffInd"],
            ["GlossCol", "GlossDir", "GlossInd"],
            ["TransCol", "TransDir", "TransInd"],
        ];
        let mut checked = 0;
        for y in 0..h {
            for x in 0..w {
                let s = sums_at(x, y);
                let mut want: Vec<(&str, [f64; 3])> = Vec::new();
                let arr = |v: V3| [v.x as f64, v.y as f64, v.z as f64];
                for k in 0..3 {
                    let c = arr(s.col[k]);
                    want.push((names[k][0], c.map(|c| c / n)));
                    let d = [
                        div(s.dir[k].x, s.col[k].x),
                        div(s.dir[k].y, s.col[k].y),
                        div(s.dir[k].z, s.col[k].z),
                    ];
                    let i = [
                        div(s.ind[k].x, s.col[k].x),
                        div(s.ind[k].y, s.col[k].y),
                        div(s.ind[k].z, s.col[k].z),
                    ];
                    want.push((names[k][1], d));
                    want.push((names[k][2], i));
                }
                want.push(("Emit", arr(s.emit).map(|v| v / n)));
                want.push(("Env", arr(s.env).map(|v| v / n)));
                let nn = s.normal_n as f64;
                want.push(("Normal", arr(s.normal).map(|v| if nn > 0.0 { v / nn } else { 0.0 })));
                want.push(("VolumeDir", [0.0; 3]));
                for (name, v) in want {
                    let img = film.pass_ref(name).expect(name);
                    for c in 0..3 {
                        let got = img.data[(y * w + x) * 3 + c] as f64;
                        let rel = (got - v[c]).abs() / v[c].abs().max(1e-30);
                        assert!(rel < 1e-6 || got == v[c], "{name} ({x},{y}) ch {c}: {got} vs {}", v[c]);
                        checked += 1;
                    }
                }
                let comb = film.pass_ref("Combined").expect("Combined");
                let px = &comb.data[(y * w + x) * 4..(y * w + x) * 4 + 4];
                let cw = arr(s.combined).map(|v| v / n);
                for c in 0..3 {
                    assert!((px[c] as f64 - cw[c]).abs() <= 1e-6 * cw[c].abs(), "Combined ({x},{y})");
                }
                assert_eq!(px[3], 1.0);
                let depth = film.pass_ref("Depth").expect("Depth");
                assert_eq!(depth.data[y * w + x], s.depth);
            }
        }
        assert_eq!(checked, w * h * 13 * 3);
        // TransCol is 0 where the sums say so, and TransDir then 0, not NaN.
        let td = film.pass_ref("TransDir").expect("TransDir");
        assert!(td.data.iter().all(|v| v.is_finite()));
        assert_eq!(td.data[3], 0.0);
    }
}
