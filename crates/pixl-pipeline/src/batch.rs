//! Many photos, one process: the inputs listed ([`list_inputs`], [`read_manifest`]), a stable
//! share of them taken ([`Shard`]), and each relit as a [`crate::job`] with the network and the
//! estimators loaded once by the caller ([`run`]).
//!
//! **Contract.**
//! - Inputs: files, folders (walked recursively for `.png`, `.jpg`, `.jpeg`, `.exr`; hidden
//!   entries skipped), glob patterns, and list files (one path per line, relative to the list's
//!   folder; `#` starts a comment). Each input has a relative name ([`Input::rel`]): its path
//!   under the folder or the pattern's fixed prefix, else its file name; outputs keep it under the
//!   output folder. Two inputs with the same relative name are refused (their outputs would
//!   collide), as is an output that would be an input. Sorted by relative name.
//! - Sharding: the `i`-th input in that order belongs to shard `i mod N`: the shards are disjoint,
//!   their union is every input, and a shard does not change with the machine it runs on.
//! - Resumable: each photo's outcome is a JSON line ([`Record`]) appended to a log in the output
//!   folder ([`log_name`], one per shard so that shards never share a file), flushed as it is
//!   written. A photo is skipped when its output exists and a log of the folder records it done
//!   from an input with the same SHA-256 and the same set-up ([`Item::setup_key`], which covers
//!   the lighting, the weights and the settings); `force` redoes it. Outputs are written
//!   atomically (a kill leaves either the old file or the new one).
//! - Failures: a photo that cannot be read or relit is recorded as failed with the message and
//!   the run goes on; [`Summary::failed`] counts them.
//! - Pipelined: a second thread decodes the next photo and reads or estimates its depth (or reads
//!   its reference photo) while the network runs on the current one: one photo ahead, so the
//!   peak is one job's plan plus one decoded photo and its depth.
use crate::depth::{read_depth_file, DepthEstimator, DepthFile};
use crate::error::{PipelineError, Result};
use crate::job::{self, DepthSource, Job, LightSet, Lighting};
use crate::like::LightingEstimator;
use crate::observe::Observer;
use crate::photo::Photo;
use crate::relight::Network;
use crate::render::RenderSettings;
use candle_core::Device;
use pixl_core::Image;
use pixl_render::depth::DepthMap;
use std::collections::HashMap;
use std::io::Write;
use std::path::{Component, Path, PathBuf};
use std::time::Instant;

/// The photo formats a folder is searched for.
pub const PHOTO_EXTS: &[&str] = &["png", "jpg", "jpeg", "exr"];
/// The depth formats `--depth-dir` is searched for, in this order.
pub const DEPTH_EXTS: &[&str] = &["exr", "png", "npy"];
/// The variables `--shard auto` reads its index from (Kubernetes Indexed Jobs, Slurm arrays).
pub const SHARD_INDEX_VARS: &[&str] = &["JOB_COMPLETION_INDEX", "SLURM_ARRAY_TASK_ID"];
/// The variables `--shard auto` reads the shard count from when no count is given.
pub const SHARD_COUNT_VARS: &[&str] = &["PIXL_SHARD_COUNT", "SLURM_ARRAY_TASK_COUNT"];

/// One photo and its name relative to the input root.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Input {
    pub path: PathBuf,
    pub rel: PathBuf,
}

/// Whether `s` is a glob pattern rather than a path.
pub fn is_pattern(s: &str) -> bool {
    s.contains(['*', '?', '['])
}

fn is_photo(path: &Path) -> bool {
    PHOTO_EXTS.contains(&pixl_core::io::extension(path).as_str())
}

fn hidden(path: &Path) -> bool {
    path.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.'))
}

/// The photos under `dir`, recursively, named relative to it.
fn walk(dir: &Path, root: &Path, out: &mut Vec<Input>) -> Result<()> {
    let entries = std::fs::read_dir(dir).map_err(|e| PipelineError::io(dir, e))?;
    let mut paths: Vec<PathBuf> = entries
        .map(|e| e.map(|e| e.path()).map_err(|e| PipelineError::io(dir, e)))
        .collect::<Result<_>>()?;
    paths.sort();
    for p in paths {
        if hidden(&p) {
            continue;
        }
        if p.is_dir() {
            walk(&p, root, out)?;
        } else if is_photo(&p) {
            let rel = p.strip_prefix(root).unwrap_or(&p).to_path_buf();
            out.push(Input { path: p, rel });
        }
    }
    Ok(())
}

/// The inputs one source names (a file, a folder or a pattern).
fn expand(source: &Path, out: &mut Vec<Input>) -> Result<()> {
    let text = source.to_string_lossy();
    if is_pattern(&text) {
        // Relative names start after the pattern's fixed leading folders.
        let base: PathBuf = source
            .components()
            .take_while(|c| !is_pattern(&c.as_os_str().to_string_lossy()))
            .collect();
        let paths = glob::glob(&text).map_err(|e| PipelineError::input(format!("{text}: {e}")))?;
        let before = out.len();
        for p in paths {
            let p = p.map_err(|e| PipelineError::input(format!("{text}: {e}")))?;
            if p.is_file() && !hidden(&p) {
                let rel = p.strip_prefix(&base).unwrap_or(&p).to_path_buf();
                out.push(Input { path: p, rel });
            }
        }
        if out.len() == before {
            return Err(PipelineError::input(format!("{text}: no file matches")));
        }
    } else if source.is_dir() {
        let before = out.len();
        walk(source, source, out)?;
        if out.len() == before {
            return Err(PipelineError::input(format!(
                "{}: no photos in it (looked for {})",
                source.display(),
                PHOTO_EXTS.join(", ")
            )));
        }
    } else if source.is_file() {
        let name = source
            .file_name()
            .map(PathBuf::from)
            .unwrap_or_else(|| source.to_owned());
        out.push(Input {
            path: source.to_owned(),
            rel: name,
        });
    } else {
        return Err(PipelineError::input(format!(
            "{}: no such file or folder",
            source.display()
        )));
    }
    Ok(())
}

/// The paths of a list file, relative to its folder.
fn read_list(list: &Path) -> Result<Vec<PathBuf>> {
    let text = std::fs::read_to_string(list).map_err(|e| PipelineError::io(list, e))?;
    let base = list.parent().unwrap_or(Path::new(""));
    Ok(text
        .lines()
        .map(|l| l.split('#').next().unwrap_or("").trim())
        .filter(|l| !l.is_empty())
        .map(|l| base.join(l))
        .collect())
}

/// Every input of `sources` and of the list file `list`, sorted by relative name; two with the
/// same relative name are refused.
pub fn list_inputs(sources: &[PathBuf], list: Option<&Path>) -> Result<Vec<Input>> {
    let mut all = Vec::new();
    for s in sources {
        expand(s, &mut all)?;
    }
    if let Some(list) = list {
        let paths = read_list(list)?;
        if paths.is_empty() {
            return Err(PipelineError::input(format!("{}: lists no photo", list.display())));
        }
        for p in paths {
            expand(&p, &mut all).map_err(|e| e.context(format!("in {}", list.display())))?;
        }
    }
    all.sort_by(|a, b| a.rel.cmp(&b.rel));
    all.dedup_by(|b, a| a.rel == b.rel && pixl_core::output::same_file(&a.path, &b.path));
    if let Some(w) = all.windows(2).find(|w| w[0].rel == w[1].rel) {
        return Err(PipelineError::input(format!(
            "{} and {} would both be written as {}: give them from different folders or rename one",
            w[0].path.display(),
            w[1].path.display(),
            w[0].rel.display()
        )));
    }
    Ok(all)
}

/// A stable share of the inputs: those whose index in relative-name order is `index` mod `count`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Shard {
    pub const ALL: Shard = Shard { index: 0, count: 1 };

    /// `I/N`, or `auto`: the index from [`SHARD_INDEX_VARS`] (less `SLURM_ARRAY_TASK_MIN` for
    /// Slurm) and the count from `count`, else [`SHARD_COUNT_VARS`]. `env` reads a variable.
    pub fn parse(s: &str, count: Option<usize>, env: &dyn Fn(&str) -> Option<String>) -> Result<Shard> {
        let bad = |why: &str| PipelineError::input(format!("--shard {s:?}: {why}"));
        let num = |v: &str, what: &str| {
            v.trim()
                .parse::<usize>()
                .map_err(|_| bad(&format!("{what} {v:?} is not a whole number")))
        };
        let shard = if s == "auto" {
            let (var, value) = SHARD_INDEX_VARS
                .iter()
                .find_map(|v| env(v).map(|x| (*v, x)))
                .ok_or_else(|| bad(&format!("none of {} is set", SHARD_INDEX_VARS.join(", "))))?;
            let mut index = num(&value, var)?;
            if var == "SLURM_ARRAY_TASK_ID" {
                if let Some(min) = env("SLURM_ARRAY_TASK_MIN") {
                    index = index.saturating_sub(num(&min, "SLURM_ARRAY_TASK_MIN")?);
                }
            }
            let count = match count {
                Some(c) => c,
                None => {
                    let (var, value) = SHARD_COUNT_VARS
                        .iter()
                        .find_map(|v| env(v).map(|x| (*v, x)))
                        .ok_or_else(|| {
                            bad(&format!(
                                "give the number of shards (--shard-count N, or {})",
                                SHARD_COUNT_VARS.join(" or ")
                            ))
                        })?;
                    num(&value, var)?
                }
            };
            Shard { index, count }
        } else {
            let (i, n) = s
                .split_once('/')
                .ok_or_else(|| bad("expected I/N (e.g. 0/4) or auto"))?;
            Shard {
                index: num(i, "index")?,
                count: num(n, "count")?,
            }
        };
        if shard.count == 0 || shard.index >= shard.count {
            return Err(bad(&format!(
                "shard {} of {} does not exist (shards are 0 to count-1)",
                shard.index, shard.count
            )));
        }
        Ok(shard)
    }

    /// This shard's share of `items` (in their order).
    pub fn take<T>(&self, items: Vec<T>) -> Vec<T> {
        items
            .into_iter()
            .enumerate()
            .filter(|(i, _)| i % self.count == self.index)
            .map(|(_, t)| t)
            .collect()
    }
}

/// One line of a manifest: a photo and its own lighting (fields left empty are not given).
#[derive(Clone, Debug, Default, PartialEq, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ManifestRow {
    pub photo: PathBuf,
    #[serde(default)]
    pub preset: Option<String>,
    /// Lights as the flags of `pixl light add`; in a CSV several are separated by `;`.
    #[serde(default, alias = "light")]
    pub lights: Vec<String>,
    /// A lights file (`[[lights]]` of a .toml/.json).
    #[serde(default)]
    pub scene: Option<PathBuf>,
    /// A reference photo whose lighting to take.
    #[serde(default)]
    pub like: Option<PathBuf>,
    /// A `C_T` file.
    #[serde(default)]
    pub intrinsics: Option<PathBuf>,
    /// The photo's depth map.
    #[serde(default)]
    pub depth: Option<PathBuf>,
}

/// A CSV row as read: every column a string.
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct CsvRow {
    photo: String,
    #[serde(default)]
    preset: String,
    #[serde(default, alias = "lights")]
    light: String,
    #[serde(default)]
    scene: String,
    #[serde(default)]
    like: String,
    #[serde(default)]
    intrinsics: String,
    #[serde(default)]
    depth: String,
}

/// The rows of a `.csv` (a header row naming the columns `photo`, `preset`, `light`, `scene`,
/// `like`, `intrinsics`, `depth`; only `photo` is required) or `.jsonl` manifest (one object per
/// line with the same keys, `lights` a list). Paths are relative to the manifest's folder; a
/// photo's relative name is its path as written (its file name when absolute).
pub fn read_manifest(path: &Path) -> Result<Vec<(Input, ManifestRow)>> {
    let name = path.display();
    let text = std::fs::read_to_string(path).map_err(|e| PipelineError::io(path, e))?;
    let rows: Vec<ManifestRow> = match pixl_core::io::extension(path).as_str() {
        "jsonl" | "ndjson" => text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
            .map(|(i, l)| {
                serde_json::from_str(l).map_err(|e| PipelineError::input(format!("{name} line {}: {e}", i + 1)))
            })
            .collect::<Result<_>>()?,
        "csv" => {
            let mut reader = csv::ReaderBuilder::new()
                .trim(csv::Trim::All)
                .from_reader(text.as_bytes());
            let opt = |s: String| (!s.is_empty()).then_some(s);
            reader
                .deserialize::<CsvRow>()
                .enumerate()
                .map(|(i, r)| {
                    let r = r.map_err(|e| PipelineError::input(format!("{name} row {}: {e}", i + 1)))?;
                    Ok(ManifestRow {
                        photo: r.photo.into(),
                        preset: opt(r.preset),
                        lights: r
                            .light
                            .split(';')
                            .map(str::trim)
                            .filter(|s| !s.is_empty())
                            .map(String::from)
                            .collect(),
                        scene: opt(r.scene).map(PathBuf::from),
                        like: opt(r.like).map(PathBuf::from),
                        intrinsics: opt(r.intrinsics).map(PathBuf::from),
                        depth: opt(r.depth).map(PathBuf::from),
                    })
                })
                .collect::<Result<_>>()?
        }
        other => {
            return Err(PipelineError::input(format!(
                "{name}: a manifest must be .csv or .jsonl, not {other:?}"
            )))
        }
    };
    if rows.is_empty() {
        return Err(PipelineError::input(format!("{name}: no rows")));
    }
    let base = path.parent().unwrap_or(Path::new(""));
    let at = |p: &Path| base.join(p);
    let mut out: Vec<(Input, ManifestRow)> = rows
        .into_iter()
        .map(|mut r| {
            let rel = if r.photo.is_absolute() {
                r.photo.file_name().map(PathBuf::from).unwrap_or_default()
            } else {
                r.photo
                    .components()
                    .filter(|c| matches!(c, Component::Normal(_)))
                    .collect()
            };
            let input = Input {
                path: at(&r.photo),
                rel,
            };
            for p in [&mut r.scene, &mut r.like, &mut r.intrinsics, &mut r.depth]
                .into_iter()
                .flatten()
            {
                *p = at(p);
            }
            (input, r)
        })
        .collect();
    out.sort_by(|a, b| a.0.rel.cmp(&b.0.rel));
    if let Some(w) = out.windows(2).find(|w| w[0].0.rel == w[1].0.rel) {
        return Err(PipelineError::input(format!(
            "{name}: {} is listed twice",
            w[0].0.rel.display()
        )));
    }
    Ok(out)
}

/// The depth of the photo named `rel` in `dir`: `dir/rel` with a depth extension ([`DEPTH_EXTS`]).
pub fn depth_in(dir: &Path, rel: &Path) -> Option<PathBuf> {
    DEPTH_EXTS
        .iter()
        .map(|ext| dir.join(rel).with_extension(ext))
        .find(|p| p.is_file())
}

/// The output of `rel` in `out_dir`: the same relative name, with `format`'s extension (default:
/// the input's own).
pub fn output_for(out_dir: &Path, rel: &Path, format: Option<&str>) -> PathBuf {
    let ext = match format {
        Some(f) => f.to_string(),
        None => pixl_core::io::extension(rel),
    };
    out_dir.join(rel).with_extension(ext)
}

/// A photo's lighting, owned.
#[derive(Clone, Debug)]
pub enum Setup {
    /// Lights in the reconstructed scene; the depth file, else the depth estimator.
    Lights {
        lights: LightSet,
        depth: Option<PathBuf>,
    },
    Intrinsics(PathBuf),
    Like(PathBuf),
}

/// One photo to relight and where its result goes.
#[derive(Clone, Debug)]
pub struct Item {
    pub input: Input,
    pub setup: Setup,
    pub output: PathBuf,
}

impl Item {
    /// A digest of everything that decides the result besides the photo: the lighting (and the
    /// contents of the files it names), the weights and `settings`.
    pub fn setup_key(&self, settings: &str) -> String {
        let files = match &self.setup {
            Setup::Lights { depth, .. } => depth.iter().collect::<Vec<_>>(),
            Setup::Intrinsics(p) | Setup::Like(p) => vec![p],
        };
        let digests: Vec<String> = files
            .into_iter()
            .map(|p| pixl_estimate::hub::sha256_file(p).unwrap_or_default())
            .collect();
        let text = format!("{:?}|{digests:?}|{settings}", self.setup);
        use sha2::Digest;
        let d = sha2::Sha256::digest(text.as_bytes());
        d.iter().take(12).map(|b| format!("{b:02x}")).collect()
    }
}

/// What happened to one photo.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    Done,
    Skipped,
    Failed,
}

/// One line of the log.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Record {
    pub input: String,
    pub output: String,
    /// The output's name relative to the output folder (what a rerun matches on, however the
    /// folder is spelt).
    #[serde(default)]
    pub rel: String,
    pub status: Status,
    pub seconds: f64,
    pub weights: String,
    pub setup: String,
    pub input_sha256: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub error: Option<String>,
    pub shard: String,
}

/// The log's file name for `shard`: `pixl-batch.jsonl`, or `pixl-batch.I-of-N.jsonl`.
pub fn log_name(shard: Shard) -> String {
    if shard == Shard::ALL {
        "pixl-batch.jsonl".into()
    } else {
        format!("pixl-batch.{}-of-{}.jsonl", shard.index, shard.count)
    }
}

/// The photos recorded done in `out_dir`'s logs: output relative to `out_dir` → (input SHA-256,
/// set-up), the last record of each output winning. Unreadable lines (a log cut by a kill) are ignored.
pub fn done_records(out_dir: &Path) -> HashMap<String, (String, String)> {
    let mut done = HashMap::new();
    let Ok(entries) = std::fs::read_dir(out_dir) else {
        return done;
    };
    let mut logs: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let n = p
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            n.starts_with("pixl-batch") && n.ends_with(".jsonl")
        })
        .collect();
    logs.sort();
    for log in logs {
        let Ok(text) = std::fs::read_to_string(&log) else {
            continue;
        };
        for r in text.lines().filter_map(|l| serde_json::from_str::<Record>(l).ok()) {
            match (r.status, r.input_sha256) {
                (Status::Done, Some(sha)) => {
                    done.insert(r.rel, (sha, r.setup));
                }
                (Status::Failed, _) => {
                    done.remove(&r.rel);
                }
                _ => {}
            }
        }
    }
    done
}

/// `item`'s output relative to `out_dir` (its full path when it is not under it).
fn rel_of(item: &Item, out_dir: &Path) -> String {
    item.output
        .strip_prefix(out_dir)
        .unwrap_or(&item.output)
        .display()
        .to_string()
}

/// How every photo of a batch is relit.
pub struct Options<'a> {
    pub out_dir: PathBuf,
    pub shard: Shard,
    /// Redo photos already done.
    pub force: bool,
    pub max_side: usize,
    pub render: RenderSettings,
    pub max_memory: Option<u64>,
    /// A folder for each photo's intermediates (`keep/REL` without its extension).
    pub keep: Option<PathBuf>,
    /// How depth files are read.
    pub depth_file: DepthFile,
    /// For photos without a depth file.
    pub depth: Option<&'a dyn DepthEstimator>,
    /// For photos relit like a reference photo.
    pub lighting: Option<&'a dyn LightingEstimator>,
    /// The focal length (pixels) or vertical field of view (degrees) of every photo, if given.
    pub focal_px: Option<f64>,
    pub fov_deg: Option<f64>,
    /// The other settings that decide a result (for [`Item::setup_key`]).
    pub settings: String,
}

/// How a batch went.
#[derive(Clone, Debug, Default)]
pub struct Summary {
    pub total: usize,
    pub done: usize,
    pub skipped: usize,
    pub failed: usize,
    pub seconds: f64,
    pub log: PathBuf,
}

/// A photo decoded ahead, with its depth or reference photo.
struct Ready {
    photo: Photo,
    depth: Option<DepthMap>,
    target: Option<Image>,
}

/// Decodes `item`'s photo and reads (or estimates) what its job needs besides the network.
fn prepare(item: &Item, opts: &Options) -> Result<Ready> {
    let photo = Photo::open(&item.input.path, opts.focal_px, opts.fov_deg)?;
    let (mut depth, mut target) = (None, None);
    match &item.setup {
        Setup::Lights { depth: Some(path), .. } => {
            depth = Some(read_depth_file(path, &opts.depth_file, photo.size())?);
        }
        Setup::Lights { depth: None, .. } => {
            let est = opts.depth.ok_or_else(|| {
                PipelineError::input("no depth map for this photo and no depth estimator (give --depth-dir)")
            })?;
            depth = Some(
                est.estimate(&photo.srgb(), photo.focal.px)?
                    .to_metric(photo.size())
                    .map_err(|e| e.context("estimating depth"))?,
            );
        }
        Setup::Like(path) => target = Some(crate::like::read_target(path)?),
        Setup::Intrinsics(_) => {}
    }
    Ok(Ready { photo, depth, target })
}

/// Relights one prepared photo and writes its output.
fn relight_one(
    net: &Network,
    item: &Item,
    ready: Ready,
    opts: &Options,
    device: &Device,
    observer: &dyn Observer,
) -> Result<()> {
    let Ready { photo, depth, target } = ready;
    let lighting = match (&item.setup, depth, &target) {
        (Setup::Lights { lights, .. }, Some(map), _) => Lighting::Lights {
            lights,
            depth: DepthSource::Given(map),
        },
        (Setup::Intrinsics(p), _, _) => Lighting::Intrinsics(p),
        (Setup::Like(_), _, Some(target)) => Lighting::Like {
            target,
            estimator: opts
                .lighting
                .ok_or_else(|| PipelineError::input("no lighting estimator for --like"))?,
        },
        _ => return Err(PipelineError::input("the photo's depth or reference photo is missing")),
    };
    let keep = opts.keep.as_ref().map(|k| k.join(item.input.rel.with_extension("")));
    let job = Job {
        photo,
        lighting,
        max_side: opts.max_side,
        render: opts.render,
        max_memory: opts.max_memory,
        keep,
    };
    let relit = job::run(net, job, device, observer)?;
    if let Some(dir) = item.output.parent() {
        std::fs::create_dir_all(dir).map_err(|e| PipelineError::io(dir, e))?;
    }
    pixl_core::io::write_image(&item.output, &relit.image)?;
    Ok(())
}

/// Relights this shard's share of `items` with `net` (see the module docs). Each photo's
/// outcome goes to the log and to `observer` as a note; the error of one photo does not stop
/// the others. Errors only for what stops the whole batch (the log cannot be written).
pub fn run(
    net: &Network,
    device: &Device,
    items: Vec<Item>,
    opts: &Options,
    observer: &dyn Observer,
) -> Result<Summary> {
    let start = Instant::now();
    let items = opts.shard.take(items);
    std::fs::create_dir_all(&opts.out_dir).map_err(|e| PipelineError::io(&opts.out_dir, e))?;
    let log_path = opts.out_dir.join(log_name(opts.shard));
    let mut log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .map_err(|e| PipelineError::io(&log_path, e))?;
    let done = if opts.force {
        HashMap::new()
    } else {
        done_records(&opts.out_dir)
    };
    let shard = format!("{}/{}", opts.shard.index, opts.shard.count);
    let mut summary = Summary {
        total: items.len(),
        log: log_path.clone(),
        ..Default::default()
    };
    let mut write = |r: &Record| -> Result<()> {
        let line = serde_json::to_string(r).map_err(|e| PipelineError::input(e.to_string()))?;
        writeln!(log, "{line}")
            .and_then(|()| log.flush())
            .map_err(|e| PipelineError::io(&log_path, e))
    };

    // Which photos are to do; the others are recorded skipped at once.
    let mut todo = Vec::new();
    for item in &items {
        let sha = pixl_estimate::hub::sha256_file(&item.input.path).ok();
        let key = item.setup_key(&opts.settings);
        let output = item.output.display().to_string();
        let rel = rel_of(item, &opts.out_dir);
        let finished = item.output.is_file()
            && matches!((done.get(&rel), &sha), (Some((s, k)), Some(sha)) if s == sha && *k == key);
        if finished {
            summary.skipped += 1;
            write(&Record {
                input: item.input.path.display().to_string(),
                output,
                status: Status::Skipped,
                seconds: 0.0,
                weights: net.name.clone(),
                setup: key,
                input_sha256: sha,
                error: None,
                shard: shard.clone(),
                rel,
            })?;
        } else {
            todo.push((item, sha, key));
        }
    }
    if summary.skipped > 0 {
        observer.note(&format!(
            "{} of {} photos already done (in {}); --force redoes them",
            summary.skipped,
            items.len(),
            opts.out_dir.display()
        ));
    }

    let n = todo.len();
    std::thread::scope(|scope| -> Result<()> {
        let (tx, rx) = std::sync::mpsc::sync_channel::<(Result<Ready>, Instant)>(1);
        let ahead = &todo;
        scope.spawn(move || {
            for (item, _, _) in ahead {
                let t = Instant::now();
                if tx.send((prepare(item, opts), t)).is_err() {
                    break;
                }
            }
        });
        for (i, ((item, sha, key), (ready, t0))) in todo.iter().zip(rx.iter()).enumerate() {
            let t = t0.min(Instant::now());
            let outcome = ready.and_then(|r| relight_one(net, item, r, opts, device, observer));
            let seconds = t.elapsed().as_secs_f64();
            let rel = item.input.rel.display();
            let error = match &outcome {
                Ok(()) => {
                    summary.done += 1;
                    observer.note(&format!(
                        "[{}/{n}] {rel} → {} ({seconds:.1} s)",
                        i + 1,
                        item.output.display()
                    ));
                    None
                }
                Err(e) => {
                    summary.failed += 1;
                    observer.note(&format!("[{}/{n}] {rel} failed: {e}", i + 1));
                    Some(e.to_string())
                }
            };
            write(&Record {
                input: item.input.path.display().to_string(),
                output: item.output.display().to_string(),
                status: if error.is_none() { Status::Done } else { Status::Failed },
                seconds,
                weights: net.name.clone(),
                setup: key.clone(),
                input_sha256: sha.clone(),
                error,
                shard: shard.clone(),
                rel: rel_of(item, &opts.out_dir),
            })?;
        }
        Ok(())
    })?;
    summary.seconds = start.elapsed().as_secs_f64();
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env<'a>(vars: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |k| vars.iter().find(|(n, _)| *n == k).map(|(_, v)| v.to_string())
    }

    #[test]
    fn shards_parse_from_flags_and_the_cluster_variables_and_partition_the_inputs() {
        let none = env(&[]);
        assert_eq!(Shard::parse("1/3", None, &none).unwrap(), Shard { index: 1, count: 3 });
        for bad in ["3/3", "1/0", "x/2", "2", "auto"] {
            assert!(Shard::parse(bad, None, &none).is_err(), "{bad}");
        }
        let k8s = env(&[("JOB_COMPLETION_INDEX", "2")]);
        assert_eq!(
            Shard::parse("auto", Some(4), &k8s).unwrap(),
            Shard { index: 2, count: 4 }
        );
        assert!(Shard::parse("auto", None, &k8s).is_err(), "a count is needed");
        let slurm = env(&[
            ("SLURM_ARRAY_TASK_ID", "11"),
            ("SLURM_ARRAY_TASK_MIN", "10"),
            ("SLURM_ARRAY_TASK_COUNT", "3"),
        ]);
        assert_eq!(
            Shard::parse("auto", None, &slurm).unwrap(),
            Shard { index: 1, count: 3 }
        );
        // Three shards of ten: disjoint, together everything, sizes within one.
        let all: Vec<usize> = (0..10).collect();
        let parts: Vec<Vec<usize>> = (0..3).map(|i| Shard { index: i, count: 3 }.take(all.clone())).collect();
        assert_eq!(parts[0], [0, 3, 6, 9]);
        let mut union: Vec<usize> = parts.concat();
        union.sort();
        assert_eq!(union, all);
    }

    #[test]
    fn inputs_from_folders_patterns_and_lists_keep_their_relative_names() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        for p in [
            "shots/a.png",
            "shots/sub/b.jpg",
            "shots/notes.txt",
            "shots/.hidden.png",
            "other/a.png",
        ] {
            let path = root.join(p);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, b"x").unwrap();
        }
        let rels = |v: Vec<Input>| v.into_iter().map(|i| i.rel.display().to_string()).collect::<Vec<_>>();
        let shots = root.join("shots");
        assert_eq!(
            rels(list_inputs(std::slice::from_ref(&shots), None).unwrap()),
            ["a.png", "sub/b.jpg"]
        );
        let pattern = root.join("shots/*/*.jpg");
        assert_eq!(rels(list_inputs(&[pattern], None).unwrap()), ["sub/b.jpg"]);
        let list = root.join("list.txt");
        std::fs::write(&list, "# photos\nshots/sub/b.jpg\n\nother/a.png  # the other one\n").unwrap();
        let listed = list_inputs(&[], Some(&list)).unwrap();
        assert_eq!(rels(listed.clone()), ["a.png", "b.jpg"]);
        assert_eq!(listed[0].path, root.join("other/a.png"));
        // Two photos named a.png from two folders would write one output: refused.
        let err = list_inputs(&[shots, root.join("other")], None).unwrap_err().to_string();
        assert!(err.contains("a.png"), "{err}");
        assert!(list_inputs(&[root.join("missing")], None).is_err());
        assert_eq!(
            output_for(Path::new("out"), Path::new("sub/b.jpg"), Some("png")),
            Path::new("out/sub/b.png")
        );
    }

    #[test]
    fn csv_and_jsonl_manifests_read_the_same_rows() {
        let dir = tempfile::tempdir().unwrap();
        let csv = dir.path().join("m.csv");
        std::fs::write(
            &csv,
            "photo, preset, light, depth\nx/a.png, cool-side-flash,\"--type spot --at-pixel 3,4; --type sun\", d/a.exr\n",
        )
        .unwrap();
        let jsonl = dir.path().join("m.jsonl");
        std::fs::write(
            &jsonl,
            r#"{"photo": "x/a.png", "preset": "cool-side-flash", "lights": ["--type spot --at-pixel 3,4", "--type sun"], "depth": "d/a.exr"}"#,
        )
        .unwrap();
        let a = read_manifest(&csv).unwrap();
        let b = read_manifest(&jsonl).unwrap();
        assert_eq!(a, b);
        assert_eq!(a[0].0.rel, Path::new("x/a.png"));
        assert_eq!(a[0].1.depth.as_deref(), Some(dir.path().join("d/a.exr").as_path()));
        assert_eq!(a[0].1.lights, ["--type spot --at-pixel 3,4", "--type sun"]);
        std::fs::write(&csv, "photo,colour\na.png,red\n").unwrap();
        assert!(read_manifest(&csv).unwrap_err().to_string().contains("colour"));
    }
}
