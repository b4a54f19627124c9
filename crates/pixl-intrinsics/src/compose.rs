//! Composing C_T from Cycles render passes (paper App. B), exactly:
//!
//! ```text
//! A = clip(DiffCol, 0, 1)
//! S = max(DiffDir + DiffInd, 0)
//! R = max(GlossCol⊙(GlossDir+GlossInd) + TransCol⊙(TransDir+TransInd) + VolumeDir + VolumeInd + Emit, 0)
//! τ = max(p98(S), p98(R), ε);   S ← clip(S, 0, τ)/τ;   R ← clip(R, 0, τ)/τ
//! ```
//!
//! - **p98** of a buffer is taken over *all* its samples, every pixel and every colour channel
//!   together (3·W·H values), with linear interpolation between order statistics, as numpy's
//!   default `np.percentile(x, 98)`: with the values sorted ascending `x₀ ≤ … ≤ x_{n−1}`,
//!   `h = 0.98·(n−1)`, `p98 = x_⌊h⌋ + (h − ⌊h⌋)·(x_{⌊h⌋+1} − x_⌊h⌋)`. It is computed with a
//!   selection (`select_nth_unstable`, O(n)), not a sort; see [`percentile`].
//! - **ε** = [`TAU_EPS`] = 1e-6: it only guards the division for an all-black render.
//! - The single cutoff τ is shared by S and R so the diffuse-to-specular balance survives.
//! - The three diffuse passes are required; a missing non-diffuse pass counts as zero (one
//!   `tracing::warn!` lists them all). NaN/Inf is an error with the count and the first location
//!   (pass order as listed above, then row-major, then channel) unless `sanitize` replaces them
//!   by 0. All passes share one size ([`PassSet::insert`] enforces it).
//!
//! Passes come from a Blender multilayer EXR (`<ViewLayer>.<Pass>.<R|G|B>`, pass names short,
//! `DiffDir`, or long, `Diffuse Direct`), from a folder of single-pass EXRs named by pass
//! (`DiffDir.exr` or `Diffuse Direct.exr`), or from memory ([`PassSet::from_exr_channels`]).
use crate::ct::Ct;
use crate::error::{IntrinsicsError, Result};
use pixl_core::exrio::{read_exr_channels, ExrChannels};
use pixl_core::passes::{self, Pass, OPTIONAL_FOR_COMPOSE, REQUIRED_FOR_COMPOSE};
use pixl_core::{CoreError, Image};
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::Path;

/// Lower bound of τ (App. B's ε).
pub const TAU_EPS: f32 = 1e-6;
/// The percentile App. B rescales by.
pub const RESCALE_PERCENTILE: f64 = 98.0;
const CHUNK: usize = 1 << 15;

/// Every pass compose reads, in the order used for reporting.
fn compose_passes() -> impl Iterator<Item = Pass> {
    REQUIRED_FOR_COMPOSE.iter().chain(OPTIONAL_FOR_COMPOSE).copied()
}

fn compose_pass(name: &str) -> Option<Pass> {
    passes::by_name(name).filter(|p| compose_passes().any(|q| q == *p))
}

/// Render passes by short name (`DiffCol`, …), each a 3-channel linear image, all one size.
#[derive(Clone, Debug, Default)]
pub struct PassSet {
    width: usize,
    height: usize,
    passes: BTreeMap<&'static str, Image>,
    source: String,
}

impl PassSet {
    /// An empty set; `source` names it in error messages (a path, "renderer", …).
    pub fn new(source: impl Into<String>) -> PassSet {
        PassSet {
            source: source.into(),
            ..PassSet::default()
        }
    }

    /// Adds a pass by short or long name (any Cycles pass compose uses). The image must be RGB
    /// and of the size of the passes already present.
    pub fn insert(&mut self, name: &str, img: Image) -> Result<()> {
        let Some(pass) = compose_pass(name) else {
            return Err(IntrinsicsError::Invalid(format!(
                "{}: `{name}` is not a pass compose uses",
                self.source_name()
            )));
        };
        if img.channels != 3 {
            return Err(IntrinsicsError::Invalid(format!(
                "{}: pass {} has {} channels, expected 3",
                self.source_name(),
                pass.short,
                img.channels
            )));
        }
        if let Some((first, f)) = self.passes.iter().next() {
            if img.width != f.width || img.height != f.height {
                return Err(IntrinsicsError::SizeMismatch {
                    source_name: self.source_name(),
                    pass: pass.short.into(),
                    width: img.width,
                    height: img.height,
                    first: (*first).into(),
                    first_width: f.width,
                    first_height: f.height,
                });
            }
        }
        self.width = img.width;
        self.height = img.height;
        self.passes.insert(pass.short, img);
        Ok(())
    }

    /// A pass by short or long name.
    pub fn get(&self, name: &str) -> Option<&Image> {
        compose_pass(name).and_then(|p| self.passes.get(p.short))
    }

    /// Short names of the passes present.
    pub fn names(&self) -> Vec<&'static str> {
        self.passes.keys().copied().collect()
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    pub fn is_empty(&self) -> bool {
        self.passes.is_empty()
    }

    fn source_name(&self) -> String {
        if self.source.is_empty() {
            "render passes".into()
        } else {
            self.source.clone()
        }
    }

    /// Collects passes from named channels `<Layer>.<Pass>.<R|G|B>` (short or long pass names;
    /// `<Pass>.<R|G|B>` without a layer is accepted as an unnamed layer). `layer` picks the view
    /// layer; without it the only layer holding passes is used, and several are an error that
    /// lists them. Channels of other passes (Combined, Depth, …) are ignored.
    pub fn from_exr_channels(chans: &ExrChannels, layer: Option<&str>) -> Result<PassSet> {
        Self::from_channels_named(chans, layer, "EXR channels")
    }

    fn from_channels_named(chans: &ExrChannels, layer: Option<&str>, source: &str) -> Result<PassSet> {
        // layer -> pass short name -> [R, G, B] planes
        type Planes<'a> = [Option<&'a [f32]>; 3];
        let mut layers: BTreeMap<&str, BTreeMap<&'static str, Planes>> = BTreeMap::new();
        for (name, data) in &chans.channels {
            let Some((rest, comp)) = name.rsplit_once('.') else {
                continue;
            };
            let Some(c) = ["R", "G", "B"].iter().position(|s| *s == comp) else {
                continue;
            };
            let (lay, pass_name) = rest.rsplit_once('.').unwrap_or(("", rest));
            let Some(pass) = compose_pass(pass_name) else { continue };
            let planes = layers.entry(lay).or_default().entry(pass.short).or_insert([None; 3]);
            if planes[c].is_none() {
                planes[c] = Some(data.as_slice());
            }
        }
        let show = |l: &str| {
            if l.is_empty() {
                "(unnamed)".to_string()
            } else {
                l.to_string()
            }
        };
        let list = || layers.keys().map(|l| show(l)).collect::<Vec<_>>().join(", ");
        let chosen = match layer {
            Some(l) => layers.get(l).ok_or_else(|| IntrinsicsError::UnknownLayer {
                source_name: source.into(),
                layer: l.into(),
                layers: if layers.is_empty() { "none".into() } else { list() },
            })?,
            None => match layers.len() {
                0 => {
                    let found: Vec<&str> = chans.names().take(12).collect();
                    return Err(IntrinsicsError::NoPasses {
                        source_name: source.into(),
                        detail: format!("expected channels like ViewLayer.DiffDir.R; found {}", found.join(", ")),
                    });
                }
                1 => layers
                    .values()
                    .next()
                    .ok_or_else(|| IntrinsicsError::Invalid("no layer".into()))?,
                _ => {
                    return Err(IntrinsicsError::AmbiguousLayer {
                        source_name: source.into(),
                        layers: list(),
                    })
                }
            },
        };
        let mut set = PassSet::new(source);
        let (w, h) = (chans.width, chans.height);
        for (short, planes) in chosen {
            let missing: Vec<&str> = ["R", "G", "B"]
                .iter()
                .zip(planes)
                .filter(|(_, p)| p.is_none())
                .map(|(c, _)| *c)
                .collect();
            if !missing.is_empty() {
                return Err(IntrinsicsError::PassChannels {
                    source_name: source.into(),
                    pass: (*short).into(),
                    missing: missing.join(", "),
                });
            }
            let mut img = Image::new(w, h, 3);
            for (c, plane) in planes.iter().enumerate() {
                for (p, v) in plane.unwrap_or(&[]).iter().enumerate() {
                    img.data[p * 3 + c] = *v;
                }
            }
            set.insert(short, img)?;
        }
        Ok(set)
    }

    /// Reads passes from a multilayer EXR file, or from a folder of single-pass EXRs whose file
    /// stem is a pass name (`DiffDir.exr`, `Diffuse Direct.exr`; also `ViewLayer.DiffDir.exr`).
    /// In a folder, other files are ignored and `layer` is not used.
    pub fn read(path: &Path, layer: Option<&str>) -> Result<PassSet> {
        if path.is_dir() {
            return Self::read_folder(path);
        }
        if !path.exists() {
            return Err(CoreError::NotFound { path: path.to_owned() }.into());
        }
        let chans = read_exr_channels(path)?;
        Self::from_channels_named(&chans, layer, &path.display().to_string())
    }

    fn read_folder(dir: &Path) -> Result<PassSet> {
        let entries = std::fs::read_dir(dir).map_err(|e| CoreError::io(dir, e))?;
        let mut files: Vec<(Pass, std::path::PathBuf)> = Vec::new();
        for entry in entries {
            let p = entry.map_err(|e| CoreError::io(dir, e))?.path();
            if pixl_core::io::extension(&p) != "exr" {
                continue;
            }
            let Some(stem) = p.file_stem().and_then(|s| s.to_str()) else {
                continue;
            };
            let pass = compose_pass(stem).or_else(|| stem.rsplit_once('.').and_then(|(_, s)| compose_pass(s)));
            if let Some(pass) = pass {
                files.push((pass, p));
            }
        }
        files.sort_by(|a, b| a.1.cmp(&b.1));
        let mut set = PassSet::new(dir.display().to_string());
        if files.is_empty() {
            return Err(IntrinsicsError::NoPasses {
                source_name: set.source_name(),
                detail: "no EXR file named after a pass (e.g. DiffCol.exr, Diffuse Direct.exr)".into(),
            });
        }
        for (pass, p) in files {
            let img = pixl_core::io::read_rgb(&p)?;
            set.insert(pass.short, img).map_err(|e| match e {
                IntrinsicsError::SizeMismatch {
                    pass,
                    width,
                    height,
                    first,
                    first_width,
                    first_height,
                    ..
                } => IntrinsicsError::SizeMismatch {
                    source_name: p.display().to_string(),
                    pass,
                    width,
                    height,
                    first,
                    first_width,
                    first_height,
                },
                other => other,
            })?;
        }
        Ok(set)
    }
}

/// Options of [`compose`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ComposeOptions {
    /// Apply the joint p98 rescale (App. B). `false` keeps S and R in HDR (debugging, round trips).
    pub rescale: bool,
    /// Replace NaN/Inf in the passes by 0 (and report how many) instead of failing.
    pub sanitize: bool,
}

impl Default for ComposeOptions {
    fn default() -> Self {
        ComposeOptions {
            rescale: true,
            sanitize: false,
        }
    }
}

/// The result of [`compose`].
#[derive(Clone, Debug)]
pub struct Composed {
    pub ct: Ct,
    /// The shared cutoff τ, when rescaled.
    pub tau: Option<f32>,
    /// Short names of the optional passes that were absent (counted as zero).
    pub missing: Vec<&'static str>,
    /// How many NaN/Inf samples were replaced by 0 (only with `sanitize`).
    pub sanitized: usize,
}

/// The joint p98 rescale of App. B on S and R (finite values ≥ 0): τ = max(p98(S), p98(R), ε),
/// then `v ← clip(v, 0, τ)/τ` in both. Returns τ.
pub fn rescale_joint(s: &mut [f32], r: &mut [f32]) -> f32 {
    let (ps, pr) = rayon::join(
        || percentile_nonneg(s, RESCALE_PERCENTILE),
        || percentile_nonneg(r, RESCALE_PERCENTILE),
    );
    let tau = ps.max(pr).max(TAU_EPS);
    let inv = 1.0 / tau;
    s.par_iter_mut()
        .chain(r.par_iter_mut())
        .for_each(|v| *v = v.clamp(0.0, tau) * inv);
    tau
}

/// C_T from an estimated decomposition (linear albedo, diffuse shading and non-diffuse
/// residual, e.g. Marigold-IID-Lighting's), by the same rule as [`compose`]: A clipped to [0, 1],
/// S and R made finite and ≥ 0 (NaN → 0), then the joint p98 rescale. Returns C_T and τ.
pub fn ct_from_decomposition(albedo: &Image, shading: &Image, residual: &Image) -> Result<(Ct, f32)> {
    let (w, h) = (albedo.width, albedo.height);
    for (name, img) in [("albedo", albedo), ("shading", shading), ("residual", residual)] {
        if (img.width, img.height, img.channels) != (w, h, 3) {
            return Err(IntrinsicsError::Core(CoreError::Invalid(format!(
                "{name} is {}x{}x{}, expected {w}x{h}x3",
                img.width, img.height, img.channels
            ))));
        }
    }
    let clean = |v: f32| if v.is_finite() { v.max(0.0) } else { 0.0 };
    let a: Vec<f32> = albedo.data.iter().map(|&v| clean(v).min(1.0)).collect();
    let mut s: Vec<f32> = shading.data.iter().map(|&v| clean(v)).collect();
    let mut r: Vec<f32> = residual.data.iter().map(|&v| clean(v)).collect();
    let tau = rescale_joint(&mut s, &mut r);
    let ct = Ct::new(
        Image::from_vec(w, h, 3, a)?,
        Image::from_vec(w, h, 3, s)?,
        Image::from_vec(w, h, 3, r)?,
    )?;
    Ok((ct, tau))
}

/// Count and first index of the non-finite samples of a buffer.
fn non_finite(data: &[f32]) -> (usize, Option<usize>) {
    data.par_chunks(CHUNK)
        .enumerate()
        .map(|(k, chunk)| {
            let mut count = 0;
            let mut first = None;
            for (i, v) in chunk.iter().enumerate() {
                if !v.is_finite() {
                    count += 1;
                    first.get_or_insert(k * CHUNK + i);
                }
            }
            (count, first)
        })
        .reduce(|| (0, None), |a, b| (a.0 + b.0, a.1.or(b.1)))
}

/// C_T of a native render: its passes (Cycles names, `pixl_render::Film::to_exr_channels`)
/// composed as [`compose`] does. The one way a render becomes C_T in the pipeline, the studio,
/// `pixl demo` and `pixl synth`.
pub fn compose_film(film: &pixl_render::Film, opts: &ComposeOptions) -> Result<Composed> {
    compose(&PassSet::from_exr_channels(&film.to_exr_channels(), None)?, opts)
}

/// Composes C_T from a pass set (see the module docs for the exact formulas).
pub fn compose(set: &PassSet, opts: &ComposeOptions) -> Result<Composed> {
    let missing_required: Vec<&str> = REQUIRED_FOR_COMPOSE
        .iter()
        .filter(|p| !set.passes.contains_key(p.short))
        .map(|p| p.short)
        .collect();
    if !missing_required.is_empty() {
        let found = set.names();
        return Err(IntrinsicsError::MissingPasses {
            source_name: set.source_name(),
            missing: missing_required.join(", "),
            found: if found.is_empty() {
                "none".into()
            } else {
                found.join(", ")
            },
        });
    }
    let missing: Vec<&'static str> = OPTIONAL_FOR_COMPOSE
        .iter()
        .filter(|p| !set.passes.contains_key(p.short))
        .map(|p| p.short)
        .collect();
    if !missing.is_empty() {
        tracing::warn!(
            "{}: non-diffuse pass(es) missing, counted as zero: {}",
            set.source_name(),
            missing.join(", ")
        );
    }

    let get = |p: Pass| set.passes.get(p.short).map(|img| img.data.as_slice());
    let src = Sources {
        diff_col: get(passes::DIFF_COL).unwrap_or(&[]),
        diff_dir: get(passes::DIFF_DIR).unwrap_or(&[]),
        diff_ind: get(passes::DIFF_IND).unwrap_or(&[]),
        optional: [
            get(passes::GLOSS_COL),
            get(passes::GLOSS_DIR),
            get(passes::GLOSS_IND),
            get(passes::TRANS_COL),
            get(passes::TRANS_DIR),
            get(passes::TRANS_IND),
            get(passes::VOLUME_DIR),
            get(passes::VOLUME_IND),
            get(passes::EMIT),
        ],
    };
    let n = set.width * set.height * 3;
    let (mut a, mut s, mut r) = (vec![0f32; n], vec![0f32; n], vec![0f32; n]);
    // The kernel flags non-finite inputs as it goes (one read of the passes); only then are they
    // counted and located, and composed again with them read as 0 if `sanitize`.
    let mut count = 0;
    if !compose_kernel::<false>(&src, &mut a, &mut s, &mut r) {
        // NaN/Inf: count over every pass used, first location in compose order.
        let mut first: Option<(&str, usize)> = None;
        for pass in compose_passes() {
            if let Some(img) = set.passes.get(pass.short) {
                let (n, f) = non_finite(&img.data);
                count += n;
                if let (None, Some(i)) = (first, f) {
                    first = Some((pass.short, i));
                }
            }
        }
        if let Some((pass, i)) = first {
            if !opts.sanitize {
                let p = i / 3;
                return Err(IntrinsicsError::NonFinitePasses {
                    source_name: set.source_name(),
                    count,
                    pass: pass.into(),
                    x: p % set.width,
                    y: p / set.width,
                    channel: ["R", "G", "B"][i % 3].into(),
                });
            }
        }
        compose_kernel::<true>(&src, &mut a, &mut s, &mut r);
    }

    let tau = opts.rescale.then(|| rescale_joint(&mut s, &mut r));
    let (w, h) = (set.width, set.height);
    let ct = Ct::new(
        Image::from_vec(w, h, 3, a)?,
        Image::from_vec(w, h, 3, s)?,
        Image::from_vec(w, h, 3, r)?,
    )?;
    Ok(Composed {
        ct,
        tau,
        missing,
        sanitized: if opts.sanitize { count } else { 0 },
    })
}

struct Sources<'a> {
    diff_col: &'a [f32],
    diff_dir: &'a [f32],
    diff_ind: &'a [f32],
    /// GlossCol, GlossDir, GlossInd, TransCol, TransDir, TransInd, VolumeDir, VolumeInd, Emit.
    optional: [Option<&'a [f32]>; 9],
}

/// A, S and R before rescaling, element-wise over the interleaved buffers. With `SANITIZE`,
/// non-finite inputs read as 0. Returns whether every input sample read was finite.
fn compose_kernel<const SANITIZE: bool>(src: &Sources, a: &mut [f32], s: &mut [f32], r: &mut [f32]) -> bool {
    let read = |v: f32| if SANITIZE && !v.is_finite() { 0.0 } else { v };
    a.par_chunks_mut(CHUNK)
        .zip(s.par_chunks_mut(CHUNK))
        .zip(r.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(k, ((a, s), r))| {
            let base = k * CHUNK;
            let opt = |j: usize, i: usize| src.optional[j].map_or(0.0, |d| read(d[i]));
            // `v * 0` is 0 for finite v and NaN otherwise: a branch-free finiteness probe.
            let mut probe = 0f32;
            for (o, ((a, s), r)) in a.iter_mut().zip(s.iter_mut()).zip(r.iter_mut()).enumerate() {
                let i = base + o;
                let (dc, dd, di) = (read(src.diff_col[i]), read(src.diff_dir[i]), read(src.diff_ind[i]));
                let o = [
                    opt(0, i),
                    opt(1, i),
                    opt(2, i),
                    opt(3, i),
                    opt(4, i),
                    opt(5, i),
                    opt(6, i),
                    opt(7, i),
                    opt(8, i),
                ];
                probe += (dc + dd + di + o.iter().sum::<f32>()) * 0.0;
                *a = dc.clamp(0.0, 1.0);
                *s = (dd + di).max(0.0);
                let gloss = o[0] * (o[1] + o[2]);
                let trans = o[3] * (o[4] + o[5]);
                *r = (gloss + trans + o[6] + o[7] + o[8]).max(0.0);
            }
            probe == 0.0
        })
        .reduce(|| true, |x, y| x && y)
}

/// The `q`-th percentile (0–100) of `values`, linear interpolation between order statistics
/// (numpy's default): `h = q/100·(n−1)`, `x_⌊h⌋ + (h−⌊h⌋)(x_{⌊h⌋+1} − x_⌊h⌋)`. Reorders
/// `values` (selection, O(n)). Empty input gives 0. Values must be finite.
pub fn percentile(values: &mut [f32], q: f64) -> f32 {
    let n = values.len();
    if n == 0 {
        return 0.0;
    }
    let h = (q / 100.0).clamp(0.0, 1.0) * (n - 1) as f64;
    let lo = (h.floor() as usize).min(n - 1);
    let frac = h - lo as f64;
    let (_, &mut x_lo, rest) = values.select_nth_unstable_by(lo, f32::total_cmp);
    if frac == 0.0 || rest.is_empty() {
        return x_lo;
    }
    let x_hi = rest.iter().copied().fold(f32::INFINITY, f32::min);
    (x_lo as f64 + frac * (x_hi as f64 - x_lo as f64)) as f32
}

/// [`percentile`] of finite values ≥ 0 (S and R after `max(·, 0)`), without reordering them: the
/// selection runs on a copy of their bit patterns, which order like the values for finite
/// non-negative floats and compare faster than `f32::total_cmp`.
fn percentile_nonneg(values: &[f32], q: f64) -> f32 {
    let n = values.len();
    if n == 0 {
        return 0.0;
    }
    // `+ 0.0` turns −0.0 (which `max(−0.0, 0.0)` may return) into +0.0, whose bits sort first.
    let mut bits: Vec<u32> = values.par_iter().map(|v| (v + 0.0).to_bits()).collect();
    let h = (q / 100.0).clamp(0.0, 1.0) * (n - 1) as f64;
    let lo = (h.floor() as usize).min(n - 1);
    let frac = h - lo as f64;
    let (_, &mut b_lo, rest) = bits.select_nth_unstable(lo);
    let x_lo = f32::from_bits(b_lo);
    if frac == 0.0 || rest.is_empty() {
        return x_lo;
    }
    let x_hi = f32::from_bits(rest.iter().copied().min().unwrap_or(b_lo));
    (x_lo as f64 + frac * (x_hi as f64 - x_lo as f64)) as f32
}
