//! The film: per-pixel render passes with **Cycles' meanings** (names from
//! [`pixl_core::passes`]).
//!
//! - `DiffCol`, `GlossCol`, `TransCol`: the albedo of the lobes of each kind at the first camera
//!   hit for the view direction, as Cycles' `bsdf_albedo` (see [`crate::material`]): diffuse
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

impl Film {
    /// Final passes from per-pixel sums over `spp` samples (row-major).
    pub fn from_sums(width: usize, height: usize, spp: u32, sums: &[PixelSum]) -> Film {
        let n = spp.max(1) as f32;
        // Each pass is filled in parallel (a 512² film has ~60 MB of sums to read).
        let rgb = |f: &(dyn Fn(&PixelSum) -> V3 + Sync)| {
            let mut img = Image::new(width, height, 3);
            img.data
                .par_chunks_mut(3)
                .zip(sums.par_iter())
                .for_each(|(px, s)| px.copy_from_slice(&f(s).to_arr()));
            img
        };
        let mut out = Vec::new();
        for (k, (col, dir, ind)) in LOBE_PASSES.iter().enumerate() {
            out.push((*col, rgb(&|s| s.col[k] / n)));
            out.push((*dir, rgb(&|s| s.dir[k].safe_div(s.col[k]))));
            out.push((*ind, rgb(&|s| s.ind[k].safe_div(s.col[k]))));
        }
        out.push((passes::VOLUME_DIR, Image::new(width, height, 3)));
        out.push((passes::VOLUME_IND, Image::new(width, height, 3)));
        out.push((passes::EMIT, rgb(&|s| s.emit / n)));
        out.push((passes::ENV, rgb(&|s| s.env / n)));
        let mut comb = Image::new(width, height, 4);
        comb.data.par_chunks_mut(4).zip(sums.par_iter()).for_each(|(px, s)| {
            let c = s.combined / n;
            px.copy_from_slice(&[c.x, c.y, c.z, 1.0]);
        });
        out.push((passes::COMBINED, comb));
        let depth = Image::from_vec(width, height, 1, sums.iter().map(|s| s.depth).collect())
            .unwrap_or_else(|_| Image::new(width, height, 1));
        out.push((passes::DEPTH, depth));
        out.push((
            passes::NORMAL,
            rgb(&|s| {
                if s.normal_n > 0 {
                    s.normal / s.normal_n as f32
                } else {
                    V3::ZERO
                }
            }),
        ));
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
