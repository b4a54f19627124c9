//! The pair sampler (paper §3.3, App. A "Data"): each sample is two distinct images of one
//! scene with roles (source, target) drawn at random, the *same* random crop for both — aspect
//! ratio (short/long side) in `[aspect_min, aspect_max]` = [0.33, 1.0], either orientation —
//! resized so the longer side is `long_side` (512) by a tent filter
//! ([`pixl_core::resample::crop_resize`]), and one random horizontal flip applied to
//! source, target and C_T alike. There is no photometric augmentation of source or target.
//!
//! Every draw is a pure function of `(seed, step, index)` ([`Rng::for_stream`]), so the data
//! order needs no state beyond the step counter and the seed: resuming at step `s` reproduces
//! exactly what an uninterrupted run would have drawn. Scenes are visited in epochs: global
//! sample `k = step · batch + index` takes scene `perm_e[k mod n]`, where `perm_e` is the
//! permutation of the `n` scenes for epoch `e = k div n`, drawn from `(seed, e)`.
//!
//! All samples of one step share one output size (so they stack into a batch): the aspect and
//! orientation are drawn per step; sizes are rounded to a multiple of `multiple` (the model's
//! patch size) while staying within the aspect bounds.
//!
//! This is the training recipe, so it lives here and not in `pixl-data`: the datasets only list
//! scenes and read files ([`pixl_data::load_image`], [`pixl_data::load_intrinsics`]).
use crate::error::{Result, TrainError};
use pixl_core::resample::crop_resize;
use pixl_core::{Image, Rng};
use pixl_data::{load_image, ImageEntry, SceneEntry};
use std::collections::HashMap;
use std::sync::Mutex;

/// A crop rectangle in the pixels of the original images.
pub use pixl_core::resample::CropRect;

const STREAM_EPOCH: u64 = 0xE90C;
const STREAM_STEP: u64 = 0x57E9;
const STREAM_SAMPLE: u64 = 0x5A3E;
const STREAM_COARSE: u64 = 0xC0A5;

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SamplerConfig {
    /// Longer side of every training crop after resizing (paper: 512).
    pub long_side: usize,
    /// Bounds of the crop aspect ratio, short side / long side (paper: 0.33 and 1.0).
    pub aspect_min: f32,
    pub aspect_max: f32,
    /// The crop covers a fraction in `[min_scale, 1]` of the largest crop of its aspect that fits.
    pub min_scale: f32,
    /// Output sides are multiples of this (the model's patch size).
    pub multiple: usize,
    /// Random horizontal flip with probability 1/2.
    pub flip: bool,
    /// Probability of conditioning on the *coarse-reconstruction* C_T of the drawn pair
    /// (`source → target`) instead of the target's exact one, where `pixl synth --coarse` wrote
    /// it ([`pixl_data::coarse_ct_path`]): C_T with the artifacts of the paper's inference
    /// setting, a simulation the paper's recipe approximates with App. C's corruptions.
    /// 0 (default) = the paper's recipe.
    pub coarse_ct: f32,
    /// Probability that a sample is instead drawn among its scene's pairs that *have* a coarse
    /// C_T and conditioned on it (`coarse_ct` alone reaches only the few pairs `pixl synth
    /// --coarse` writes, one per lighting). Drawn from its own random stream, so 0 (default)
    /// leaves every other draw as it was.
    pub coarse_pair_share: f32,
}

impl Default for SamplerConfig {
    fn default() -> Self {
        Self {
            long_side: 512,
            aspect_min: 0.33,
            aspect_max: 1.0,
            min_scale: 1.0,
            multiple: 16,
            flip: true,
            coarse_ct: 0.0,
            coarse_pair_share: 0.0,
        }
    }
}

impl SamplerConfig {
    /// Whether samples are ever conditioned on a coarse C_T (`coarse_ct` or `coarse_pair_share`).
    pub fn wants_coarse(&self) -> bool {
        self.coarse_ct > 0.0 || self.coarse_pair_share > 0.0
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(TrainError::Config(format!("sampler: {m}")));
        if self.multiple == 0 || self.long_side < self.multiple || !self.long_side.is_multiple_of(self.multiple) {
            return bad(format!(
                "long_side {} must be a positive multiple of {}",
                self.long_side, self.multiple
            ));
        }
        if !(self.aspect_min > 0.0 && self.aspect_min <= self.aspect_max && self.aspect_max <= 1.0) {
            return bad(format!(
                "need 0 < aspect_min {} <= aspect_max {} <= 1",
                self.aspect_min, self.aspect_max
            ));
        }
        if !(self.min_scale > 0.0 && self.min_scale <= 1.0) {
            return bad(format!("min_scale {} must be in (0, 1]", self.min_scale));
        }
        if !(0.0..=1.0).contains(&self.coarse_ct) {
            return bad(format!("coarse_ct {} must be a probability in [0, 1]", self.coarse_ct));
        }
        if !(0.0..=1.0).contains(&self.coarse_pair_share) {
            return bad(format!(
                "coarse_pair_share {} must be a probability in [0, 1]",
                self.coarse_pair_share
            ));
        }
        Ok(())
    }
}

/// One training pair, ready to batch: all three share `width × height`.
#[derive(Clone, Debug)]
pub struct Sample {
    pub scene: String,
    /// Indices into the scene's images.
    pub source_index: usize,
    pub target_index: usize,
    /// sRGB in [0, 1], 3 channels.
    pub source: Image,
    pub target: Image,
    /// C_T of the target, 9 channels `[albedo RGB, shading RGB, residual RGB]`.
    pub ct: Image,
    /// Whether `ct` is the coarse reconstruction's C_T of the pair rather than the target's own.
    pub coarse_ct: bool,
    pub crop: CropRect,
    pub flipped: bool,
}

/// Where the sampler gets pixels from. [`DiskLoader`] reads files; tests can provide their own.
pub trait Loader: Send + Sync {
    /// The image as sRGB RGB in [0, 1].
    fn image(&self, entry: &ImageEntry) -> Result<Image>;
    /// The image's C_T as one 9-channel HWC image.
    fn intrinsics(&self, entry: &ImageEntry) -> Result<Image>;
}

/// Reads images and C_T from disk ([`load_image`], [`pixl_data::load_intrinsics`]), optionally keeping
/// every decoded file in memory (for small data sets read over and over).
#[derive(Default)]
pub struct DiskLoader {
    cache: Option<Mutex<HashMap<std::path::PathBuf, Image>>>,
}

impl DiskLoader {
    pub fn new(cache: bool) -> Self {
        Self {
            cache: cache.then(|| Mutex::new(HashMap::new())),
        }
    }

    fn cached(&self, key: &std::path::Path, load: impl FnOnce() -> Result<Image>) -> Result<Image> {
        let Some(cache) = &self.cache else { return load() };
        if let Some(img) = cache
            .lock()
            .map_err(|_| TrainError::Other("loader cache poisoned".into()))?
            .get(key)
        {
            return Ok(img.clone());
        }
        let img = load()?;
        cache
            .lock()
            .map_err(|_| TrainError::Other("loader cache poisoned".into()))?
            .insert(key.to_owned(), img.clone());
        Ok(img)
    }
}

impl Loader for DiskLoader {
    fn image(&self, entry: &ImageEntry) -> Result<Image> {
        self.cached(&entry.image, || Ok(load_image(&entry.image)?))
    }
    fn intrinsics(&self, entry: &ImageEntry) -> Result<Image> {
        // Keyed by the C_T file itself: one image can have several (exact, coarse). (No file
        // check here: a cache hit must not touch the disk; the load reports a missing file.)
        let key = match &entry.intrinsics {
            Some(p) => p.clone(),
            None => pixl_data::ct_cache_path(&entry.image),
        }
        .with_extension("ct-cache");
        self.cached(&key, || Ok(pixl_data::load_intrinsics_image(entry)?))
    }
}

pub struct Sampler {
    scenes: Vec<SceneEntry>,
    cfg: SamplerConfig,
    seed: u64,
    batch_size: usize,
    /// Per scene, the ordered pairs `(source, target)` that have a coarse C_T file (only
    /// looked up when `coarse_ct` or `coarse_pair_share` is above 0), and all pairs counted.
    coarse: Vec<Vec<(usize, usize)>>,
    pairs: usize,
}

/// Per scene, the ordered pairs with a coarse C_T file; and the number of all ordered pairs.
/// Looked up only when `cfg` draws coarse C_T at all (else no pairs, and 0 counted).
fn find_coarse_pairs(scenes: &[SceneEntry], cfg: &SamplerConfig) -> (Vec<Vec<(usize, usize)>>, usize) {
    if !cfg.wants_coarse() {
        return (vec![Vec::new(); scenes.len()], 0);
    }
    let mut all = 0;
    let found = scenes
        .iter()
        .map(|s| {
            let n = s.images.len();
            all += n * (n - 1);
            (0..n)
                .flat_map(|i| (0..n).map(move |j| (i, j)))
                .filter(|&(i, j)| i != j && pixl_data::coarse_ct_path(&s.images[i].image, &s.images[j].image).is_file())
                .collect()
        })
        .collect();
    (found, all)
}

impl Sampler {
    /// `scenes` must each hold ≥ 2 images (the loaders guarantee it).
    pub fn new(scenes: Vec<SceneEntry>, cfg: SamplerConfig, batch_size: usize, seed: u64) -> Result<Self> {
        cfg.validate()?;
        if batch_size == 0 {
            return Err(TrainError::Config("batch size must be at least 1".into()));
        }
        if let Some(s) = scenes.iter().find(|s| s.images.len() < 2) {
            return Err(TrainError::Config(format!(
                "scene {} has fewer than two images",
                s.name
            )));
        }
        if scenes.is_empty() {
            return Err(TrainError::Config("the sampler needs at least one scene".into()));
        }
        let (coarse, pairs) = find_coarse_pairs(&scenes, &cfg);
        if cfg.wants_coarse() && coarse.iter().all(Vec::is_empty) {
            return Err(TrainError::Config(format!(
                "[data.sampler] coarse_ct = {} / coarse_pair_share = {} but no pair of this data set has a \
                 coarse-reconstruction C_T (`pixl synth --coarse` writes them, as \
                 <target>.from_<source>.intrinsics.exr); regenerate the set with --coarse or set both to 0",
                cfg.coarse_ct, cfg.coarse_pair_share
            )));
        }
        Ok(Self {
            scenes,
            cfg,
            seed,
            batch_size,
            coarse,
            pairs,
        })
    }

    /// With `coarse_ct` or `coarse_pair_share` above 0: how many ordered pairs `(source,
    /// target)` have a coarse C_T, out of how many pairs there are (`(0, 0)` otherwise: not
    /// looked up).
    pub fn coarse_pairs(&self) -> (usize, usize) {
        (self.coarse.iter().map(Vec::len).sum(), self.pairs)
    }

    /// The expected fraction of samples conditioned on a coarse C_T (scenes are visited
    /// uniformly): in a scene with `c` of its `n (n − 1)` pairs having one (`c > 0`), a sample
    /// takes one of them with probability `coarse_pair_share`, else draws any pair, which has one
    /// with probability `c / (n (n − 1))` and then uses it with probability `coarse_ct`.
    pub fn coarse_fraction(&self) -> f64 {
        let (ct, share) = (self.cfg.coarse_ct as f64, self.cfg.coarse_pair_share as f64);
        let sum: f64 = self
            .scenes
            .iter()
            .zip(&self.coarse)
            .filter(|(_, c)| !c.is_empty())
            .map(|(s, c)| {
                let n = s.images.len();
                share + (1.0 - share) * ct * c.len() as f64 / (n * (n - 1)) as f64
            })
            .sum();
        sum / self.scenes.len() as f64
    }

    pub fn scenes(&self) -> &[SceneEntry] {
        &self.scenes
    }

    /// Adds the scenes of `scenes` whose names are not in the sampler yet (a data set that grows
    /// while a run reads it: `[data] refresh_every`); returns how many were added. From the next
    /// draw on, the epoch permutations run over all scenes, old and new alike, so the draws of
    /// later steps differ from those of a run that had every scene from the start. Scenes with
    /// fewer than two images are skipped.
    pub fn add_scenes(&mut self, scenes: Vec<SceneEntry>) -> usize {
        let known: std::collections::HashSet<String> = self.scenes.iter().map(|s| s.name.clone()).collect();
        let new: Vec<SceneEntry> = scenes
            .into_iter()
            .filter(|s| s.images.len() >= 2 && !known.contains(&s.name))
            .collect();
        let (coarse, pairs) = find_coarse_pairs(&new, &self.cfg);
        let added = new.len();
        self.scenes.extend(new);
        self.coarse.extend(coarse);
        self.pairs += pairs;
        added
    }

    pub fn config(&self) -> &SamplerConfig {
        &self.cfg
    }

    /// Output `(width, height)` of every sample of `step`.
    pub fn batch_size_px(&self, step: u64) -> (usize, usize) {
        let mut rng = Rng::for_stream(self.seed, &[STREAM_STEP, step]);
        let (m, long) = (self.cfg.multiple, self.cfg.long_side);
        let aspect = rng.uniform(self.cfg.aspect_min, self.cfg.aspect_max);
        let portrait = rng.bernoulli(0.5);
        // the shortest/longest short side that keeps the aspect inside its bounds, as multiples of m
        let lo = ((long as f32 * self.cfg.aspect_min / m as f32).ceil() as usize).max(1) * m;
        let hi = ((long as f32 * self.cfg.aspect_max / m as f32).floor() as usize * m).max(lo);
        let short = (((long as f32 * aspect) / m as f32).round() as usize * m).clamp(lo, hi);
        if portrait {
            (short, long)
        } else {
            (long, short)
        }
    }

    /// The scene index of global sample `(step, index)` (epoch-permuted, see module docs).
    pub fn scene_of(&self, step: u64, index: usize) -> usize {
        let n = self.scenes.len() as u64;
        let k = step * self.batch_size as u64 + index as u64;
        let mut perm: Vec<usize> = (0..self.scenes.len()).collect();
        Rng::for_stream(self.seed, &[STREAM_EPOCH, k / n]).shuffle(&mut perm);
        perm[(k % n) as usize]
    }

    /// Sample `index` of `step`.
    pub fn sample(&self, step: u64, index: usize, loader: &dyn Loader) -> Result<Sample> {
        let scene_index = self.scene_of(step, index);
        let scene = &self.scenes[scene_index];
        let mut rng = Rng::for_stream(self.seed, &[STREAM_SAMPLE, step, index as u64]);
        let n = scene.images.len();
        let mut source_index = rng.below(n);
        let mut target_index = rng.below(n - 1);
        if target_index >= source_index {
            target_index += 1;
        }
        // A pair with a coarse C_T instead, from its own stream (the main one is unchanged).
        let coarse_pairs = &self.coarse[scene_index];
        let forced = (self.cfg.coarse_pair_share > 0.0 && !coarse_pairs.is_empty())
            .then(|| {
                let mut r = Rng::for_stream(self.seed, &[STREAM_COARSE, step, index as u64]);
                (r.f32() < self.cfg.coarse_pair_share).then(|| coarse_pairs[r.below(coarse_pairs.len())])
            })
            .flatten();
        if let Some((s, t)) = forced {
            (source_index, target_index) = (s, t);
        }
        let (src_e, tgt_e) = (&scene.images[source_index], &scene.images[target_index]);
        let source = loader.image(src_e)?;
        let target = loader.image(tgt_e)?;
        let (ow, oh) = self.batch_size_px(step);
        let crop = draw_crop(
            &mut rng,
            source.width,
            source.height,
            ow as f32 / oh as f32,
            self.cfg.min_scale,
        );
        let flipped = self.cfg.flip && rng.bernoulli(0.5);
        // Drawn last and only when enabled: the paper's recipe keeps its random stream.
        // Whether the pair has a coarse C_T was looked up once, in `new` (no file check here).
        let by_ct = self.cfg.coarse_ct > 0.0 && rng.f32() < self.cfg.coarse_ct;
        let coarse = (forced.is_some() || (by_ct && coarse_pairs.contains(&(source_index, target_index))))
            .then(|| pixl_data::coarse_ct_path(&src_e.image, &tgt_e.image));
        let coarse_ct = coarse.is_some();
        let ct = match coarse {
            Some(path) => loader.intrinsics(&ImageEntry {
                image: tgt_e.image.clone(),
                intrinsics: Some(path),
            })?,
            None => loader.intrinsics(tgt_e)?,
        };
        for (what, img, entry) in [("target", &target, tgt_e), ("C_T", &ct, tgt_e)] {
            if (img.width, img.height) != (source.width, source.height) {
                return Err(TrainError::File {
                    path: entry.image.clone(),
                    reason: format!(
                        "{what} is {}x{} but the source {} is {}x{}; images of one scene must share one size",
                        img.width,
                        img.height,
                        src_e.image.display(),
                        source.width,
                        source.height
                    ),
                });
            }
        }
        let prep = |img: &Image| -> Result<Image> {
            let out = crop_resize(img, crop, ow, oh)?;
            Ok(if flipped { flip_horizontal(&out) } else { out })
        };
        Ok(Sample {
            scene: scene.name.clone(),
            source_index,
            target_index,
            source: prep(&source)?,
            target: prep(&target)?,
            ct: prep(&ct)?,
            coarse_ct,
            crop,
            flipped,
        })
    }

    /// All `batch_size` samples of `step`.
    pub fn batch(&self, step: u64, loader: &dyn Loader) -> Result<Vec<Sample>> {
        (0..self.batch_size).map(|i| self.sample(step, i, loader)).collect()
    }
}

/// A random crop of aspect `width/height = ratio` inside a `w × h` image: the largest such crop
/// scaled by a factor in `[min_scale, 1]`, at a uniformly random position.
fn draw_crop(rng: &mut Rng, w: usize, h: usize, ratio: f32, min_scale: f32) -> CropRect {
    let (mut cw, mut ch) = if (w as f32 / h as f32) > ratio {
        ((h as f32 * ratio).round() as usize, h)
    } else {
        (w, (w as f32 / ratio).round() as usize)
    };
    let scale = rng.uniform(min_scale, 1.0).min(1.0);
    cw = ((cw as f32 * scale).round() as usize).clamp(1, w);
    ch = ((ch as f32 * scale).round() as usize).clamp(1, h);
    let x = rng.below(w - cw + 1);
    let y = rng.below(h - ch + 1);
    CropRect {
        x,
        y,
        width: cw,
        height: ch,
    }
}

/// Mirror image left ↔ right.
pub fn flip_horizontal(img: &Image) -> Image {
    let mut out = img.clone();
    let (w, ch) = (img.width, img.channels);
    for y in 0..img.height {
        for x in 0..w {
            let src = (y * w + (w - 1 - x)) * ch;
            let dst = (y * w + x) * ch;
            out.data[dst..dst + ch].copy_from_slice(&img.data[src..src + ch]);
        }
    }
    out
}
