//! The evaluation loop of paper §4.1: for every (source, target) pair of a dataset, every method
//! predicts the target from the source and the target's intrinsics C_T; the prediction is
//! scale-corrected per channel against the target (unless turned off) and scored with PSNR, SSIM
//! and, when weights are given, LPIPS, at native target resolution. Each method's forward pass
//! is timed on the first pair with the paper's protocol ([`crate::timing`]).
//!
//! **Default pair list** ([`default_pairs`]): for each scene (sorted by name) with images
//! `0..n` (sorted by file name), image `i` relights to image `(i + 1) mod n` — every image is a
//! source once and a target once, `n` pairs per scene, deterministic. `--pairs FILE` fixes any
//! other list ([`read_pairs`]).
use crate::baselines::Method;
use crate::error::{EvalError, Result};
use crate::lpips::Lpips;
use crate::metrics::{psnr, scale_correct, ssim};
use crate::sheet::{ct_panels, sheet_columns, SheetRow};
use crate::timing::{Timing, DEFAULT_RUNS, DEFAULT_WARMUPS};
use pixl_data::{load_image, load_intrinsics, Dataset, ImageEntry};
use pixl_intrinsics::ct::Ct;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// One evaluation pair: relight `source` to the lighting of `target`, both of scene `scene`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Pair {
    pub scene: String,
    pub source: ImageEntry,
    pub target: ImageEntry,
}

impl Pair {
    fn file_name(entry: &ImageEntry) -> String {
        entry
            .image
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    }
    pub fn source_name(&self) -> String {
        Self::file_name(&self.source)
    }
    pub fn target_name(&self) -> String {
        Self::file_name(&self.target)
    }
}

/// The default pair list: per scene, image `i` → image `(i + 1) mod n` (see the module docs).
pub fn default_pairs(dataset: &dyn Dataset) -> Vec<Pair> {
    let mut pairs = Vec::new();
    for scene in dataset.scenes() {
        let n = scene.images.len();
        if n < 2 {
            continue;
        }
        for i in 0..n {
            pairs.push(Pair {
                scene: scene.name.clone(),
                source: scene.images[i].clone(),
                target: scene.images[(i + 1) % n].clone(),
            });
        }
    }
    pairs
}

/// Reads a pair list: CSV lines `scene,source,target`, where `source` and `target` are image file
/// names inside the scene (as listed by the dataset, e.g. `dir_0_mip2.jpg`). Blank lines, lines
/// starting with `#`, and a header line `scene,source,target` are skipped. `source == target` is
/// allowed (a sanity check: the identity scores PSNR ∞ there).
pub fn read_pairs(path: &Path, dataset: &dyn Dataset) -> Result<Vec<Pair>> {
    let text = std::fs::read_to_string(path).map_err(|source| EvalError::Io {
        path: path.to_owned(),
        source,
    })?;
    let mut pairs = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let bad = |reason: String| EvalError::Pairs {
            path: path.to_owned(),
            line: i + 1,
            reason,
        };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || line.replace(' ', "") == "scene,source,target" {
            continue;
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let [scene, source, target] = fields[..] else {
            return Err(bad(format!(
                "expected `scene,source,target`, found {} field(s)",
                fields.len()
            )));
        };
        let entry = dataset
            .scenes()
            .iter()
            .find(|s| s.name == scene)
            .ok_or_else(|| bad(format!("no scene {scene:?} in the dataset (split)")))?;
        let find = |name: &str| {
            entry
                .images
                .iter()
                .find(|e| e.image.file_name().is_some_and(|n| n == name))
                .cloned()
                .ok_or_else(|| bad(format!("scene {scene:?} has no image {name:?}")))
        };
        pairs.push(Pair {
            scene: scene.to_string(),
            source: find(source)?,
            target: find(target)?,
        });
    }
    if pairs.is_empty() {
        return Err(EvalError::Empty(format!("{} lists no pairs", path.display())));
    }
    Ok(pairs)
}

/// Switches of [`run_eval`].
#[derive(Clone, Debug)]
pub struct EvalOptions {
    /// Per-channel least-squares scale correction before scoring (paper: on for every method).
    pub scale_correction: bool,
    /// Timing protocol: untimed warm-ups (paper: 2).
    pub warmups: usize,
    /// Timing protocol: timed runs (paper: 5); 0 turns timing off.
    pub runs: usize,
    /// Keep the images of the first `sheet_pairs` pairs for a contact sheet
    /// ([`EvalReport::sheet_rows`], [`crate::sheet`]); 0 keeps none.
    pub sheet_pairs: usize,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            scale_correction: true,
            warmups: DEFAULT_WARMUPS,
            runs: DEFAULT_RUNS,
            sheet_pairs: 0,
        }
    }
}

/// The scores of one method on one pair.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PairScore {
    pub scene: String,
    pub source: String,
    pub target: String,
    pub method: String,
    /// dB; `+∞` when the (corrected) prediction equals the target exactly.
    #[serde(with = "crate::report::score")]
    pub psnr: f64,
    pub ssim: f64,
    /// `None` when no LPIPS weights were given.
    pub lpips: Option<f64>,
}

/// One method's row of the table: means over all pairs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MethodSummary {
    pub method: String,
    pub cue: String,
    pub pairs: usize,
    /// Mean of the per-pair PSNRs (dB); `+∞` if any pair is exact.
    #[serde(with = "crate::report::score")]
    pub psnr: f64,
    pub ssim: f64,
    pub lpips: Option<f64>,
    /// Forward-pass timing on the first pair (`None` when timing is off).
    pub timing: Option<Timing>,
    /// Where it ran: "cpu f32", …
    pub device: String,
}

/// Everything [`run_eval`] measured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Dataset spec or description.
    pub dataset: String,
    pub pairs: usize,
    pub scale_correction: bool,
    /// `"alex"` / `"vgg"`, or `None` when LPIPS was not computed.
    pub lpips_net: Option<String>,
    pub methods: Vec<MethodSummary>,
    pub per_pair: Vec<PairScore>,
    /// The light-response score per method ([`run_response`]), when the data set has what it
    /// needs; what the renders were.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub response: Vec<ResponseSummary>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub response_renders: Option<String>,
    /// Where the contact sheet was written (set by the caller that writes it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sheet: Option<String>,
    /// How many pairs the contact sheet shows (its rows).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub sheet_pairs: usize,
    /// The contact sheet's columns, left to right ([`crate::sheet::sheet_columns`]); empty when
    /// no pair was kept.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sheet_columns: Vec<String>,
    /// The kept images of the first [`EvalOptions::sheet_pairs`] pairs, one row per pair
    /// ([`crate::sheet::contact_sheet`] makes the picture). Not serialised.
    #[serde(skip)]
    pub sheet_rows: Vec<SheetRow>,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// One case of the light-response score ([`crate::response`]): a source relit to two lightings
/// (C_T files `cts`), against the renders of its scene under those two lightings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ResponseCase {
    pub scene: String,
    pub source: std::path::PathBuf,
    pub cts: [std::path::PathBuf; 2],
    pub renders: [std::path::PathBuf; 2],
}

/// A method's light-response score, pooled over every case.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ResponseSummary {
    pub method: String,
    pub gain: f64,
    pub correlation: f64,
    /// Cases (lighting pairs) pooled.
    pub pairs: usize,
}

/// Scores every method's light response over `cases`: each relights the case's source with
/// both C_T and the pair of outputs is compared with the pair of renders, pooled over all cases
/// ([`crate::ResponseSums`]). No scale correction (a scale common to both outputs cancels in
/// the log-luminance change). `on_case` is called after each case.
pub fn run_response(
    cases: &[ResponseCase],
    methods: &[Box<dyn Method>],
    mut on_case: impl FnMut(usize),
) -> Result<Vec<ResponseSummary>> {
    if cases.is_empty() {
        return Err(EvalError::Empty("no light-response case".into()));
    }
    let mut sums = vec![crate::ResponseSums::default(); methods.len()];
    for (i, case) in cases.iter().enumerate() {
        let err = |reason: String| EvalError::Pair {
            scene: case.scene.clone(),
            source_name: case.source.display().to_string(),
            target: case.cts[1].display().to_string(),
            reason,
        };
        let source = load_image(&case.source)?;
        let mut cts = Vec::with_capacity(2);
        for path in &case.cts {
            cts.push(load_intrinsics(&ImageEntry {
                image: case.source.clone(),
                intrinsics: Some(path.clone()),
            })?);
        }
        let renders = [load_image(&case.renders[0])?, load_image(&case.renders[1])?];
        for (method, sum) in methods.iter().zip(&mut sums) {
            let outs = [
                method.predict(&source, Some(&cts[0]))?,
                method.predict(&source, Some(&cts[1]))?,
            ];
            sum.add(&[&outs[0], &outs[1]], &[&renders[0], &renders[1]])
                .map_err(|e| err(format!("{}: light response: {e}", method.name())))?;
        }
        on_case(i + 1);
    }
    methods
        .iter()
        .zip(&sums)
        .map(|(m, s)| {
            let r = s.finish()?;
            Ok(ResponseSummary {
                method: m.name().to_string(),
                gain: r.gain,
                correlation: r.correlation,
                pairs: r.pairs,
            })
        })
        .collect()
}

struct Loaded {
    source: pixl_core::Image,
    target: pixl_core::Image,
    ct: Option<Ct>,
}

fn load_pair(pair: &Pair, need_ct: bool) -> Result<Loaded> {
    let err = |reason: String| EvalError::Pair {
        scene: pair.scene.clone(),
        source_name: pair.source_name(),
        target: pair.target_name(),
        reason,
    };
    let source = load_image(&pair.source.image)?;
    let target = load_image(&pair.target.image)?;
    if (source.width, source.height) != (target.width, target.height) {
        return Err(err(format!(
            "source is {}x{} but target is {}x{}",
            source.width, source.height, target.width, target.height
        )));
    }
    let ct = if need_ct {
        let ct = load_intrinsics(&pair.target)?;
        if (ct.width(), ct.height()) != (target.width, target.height) {
            return Err(err(format!(
                "target intrinsics are {}x{} but the target is {}x{}",
                ct.width(),
                ct.height(),
                target.width,
                target.height
            )));
        }
        Some(ct)
    } else {
        None
    };
    Ok(Loaded { source, target, ct })
}

/// Scores every method on every pair (see the module docs). `on_pair` is called after each pair
/// (for a progress bar). Errors stop the evaluation and name the pair or method.
pub fn run_eval(
    dataset: &str,
    pairs: &[Pair],
    methods: &[Box<dyn Method>],
    lpips: Option<&Lpips>,
    opts: &EvalOptions,
    mut on_pair: impl FnMut(usize),
) -> Result<EvalReport> {
    if pairs.is_empty() {
        return Err(EvalError::Empty("the pair list is empty".into()));
    }
    if methods.is_empty() {
        return Err(EvalError::Empty("no method (give --weights and/or --baselines)".into()));
    }
    // The summaries and the CSV key rows by method name: two methods of one name would merge.
    for (k, m) in methods.iter().enumerate() {
        if methods[..k].iter().any(|o| o.name() == m.name()) {
            return Err(EvalError::Method {
                method: m.name().to_string(),
                reason: "given twice (every method needs its own name)".into(),
            });
        }
    }
    let need_ct = methods.iter().any(|m| m.needs_ct());
    let mut sheet_rows = Vec::new();
    let mut per_pair = Vec::with_capacity(pairs.len() * methods.len());
    let mut timings: Vec<Option<Timing>> = vec![None; methods.len()];
    for (i, pair) in pairs.iter().enumerate() {
        let data = load_pair(pair, need_ct)?;
        // The panels of this pair's contact-sheet row, in the order of `sheet_columns`.
        let mut panels = (i < opts.sheet_pairs).then(|| {
            let mut v = vec![data.source.clone()];
            v.extend(data.ct.iter().flat_map(ct_panels));
            v
        });
        for (m, method) in methods.iter().enumerate() {
            if i == 0 && opts.runs > 0 {
                timings[m] = Some(method.time(&data.source, data.ct.as_ref(), opts.warmups, opts.runs)?);
            }
            let pred = method.predict(&data.source, data.ct.as_ref())?;
            let pred = if opts.scale_correction {
                scale_correct(&pred, &data.target)
            } else {
                Ok(pred)
            };
            let score = |pred: &pixl_core::Image| -> Result<(f64, f64, Option<f64>)> {
                let l = match lpips {
                    Some(l) => Some(l.distance(pred, &data.target)?),
                    None => None,
                };
                Ok((psnr(pred, &data.target)?, ssim(pred, &data.target)?, l))
            };
            let ((p, s, l), pred) = pred
                .map_err(EvalError::from)
                .and_then(|pred| Ok((score(&pred)?, pred)))
                .map_err(|e| EvalError::Pair {
                    scene: pair.scene.clone(),
                    source_name: pair.source_name(),
                    target: pair.target_name(),
                    reason: format!("{}: {e}", method.name()),
                })?;
            per_pair.push(PairScore {
                scene: pair.scene.clone(),
                source: pair.source_name(),
                target: pair.target_name(),
                method: method.name().to_string(),
                psnr: p,
                ssim: s,
                lpips: l,
            });
            if let Some(v) = panels.as_mut() {
                v.push(pred);
            }
        }
        if let Some(mut panels) = panels {
            panels.push(data.target);
            sheet_rows.push(SheetRow {
                scene: pair.scene.clone(),
                source: pair.source_name(),
                target: pair.target_name(),
                panels,
            });
        }
        on_pair(i + 1);
    }
    let summaries = methods
        .iter()
        .zip(timings)
        .map(|(method, timing)| {
            let rows: Vec<&PairScore> = per_pair.iter().filter(|r| r.method == method.name()).collect();
            let n = rows.len() as f64;
            let mean = |f: &dyn Fn(&PairScore) -> f64| rows.iter().map(|r| f(r)).sum::<f64>() / n;
            MethodSummary {
                method: method.name().to_string(),
                cue: method.cue().to_string(),
                pairs: rows.len(),
                psnr: mean(&|r| r.psnr),
                ssim: mean(&|r| r.ssim),
                lpips: lpips.map(|_| mean(&|r| r.lpips.unwrap_or(f64::NAN))),
                timing,
                device: method.device_desc(),
            }
        })
        .collect();
    Ok(EvalReport {
        dataset: dataset.to_string(),
        pairs: pairs.len(),
        scale_correction: opts.scale_correction,
        lpips_net: lpips.map(|l| l.net().name().to_string()),
        methods: summaries,
        per_pair,
        response: Vec::new(),
        response_renders: None,
        sheet: None,
        sheet_pairs: sheet_rows.len(),
        sheet_columns: if sheet_rows.is_empty() {
            Vec::new()
        } else {
            sheet_columns(methods.iter().map(|m| m.name()), need_ct)
        },
        sheet_rows,
    })
}
