//! Where estimator weights come from: a registry of the released models this crate loads, and
//! the lookup that finds their files on disk or downloads them once.
//!
//! # Registry
//! [`REGISTRY`] lists every model by a short name (`da3-metric`, `da3-mono`): its Hugging Face
//! repository and revision, the files it needs (a model is a list of [`ModelFile`]s, relative
//! paths inside the repository, so a diffusers-style folder with `unet/…`, `vae/…` fits as well as
//! a single `model.safetensors`), its licence, its approximate size and what it is for.
//!
//! # Lookup order ([`Hub::resolve`])
//! 1. **The models folder** (`--models DIR`, else the environment variable `PIXL_MODELS_DIR`):
//!    - `DIR/<name>/<file>` for every file (a plain copy, e.g.
//!      `huggingface-cli download depth-anything/DA3METRIC-LARGE --local-dir DIR/da3-metric`).
//!      If `DIR/<name>/` exists but lacks a file, that is an error naming the file
//!      ([`HubError::MissingFile`]); the lookup does not go on past a half-copied folder.
//!    - else `DIR` laid out as a Hugging Face cache (what `pixl models fetch --models DIR` writes).
//! 2. **The local Hugging Face cache**, in the layout the Python `huggingface_hub` writes, so an
//!    existing cache is reused: `$HF_HUB_CACHE`, else `$HUGGINGFACE_HUB_CACHE`, else
//!    `$HF_HOME/hub`, else `$XDG_CACHE_HOME/huggingface/hub`, else `~/.cache/huggingface/hub`.
//!    A model is there when `models--<org>--<name>/refs/<revision>` names a snapshot
//!    `snapshots/<commit>/` holding every file (symlinks into `blobs/` are followed; a dangling
//!    one counts as absent). Without the ref file, any snapshot holding every file is used (the
//!    first in name order).
//! 3. **A download** with the `hf-hub` crate (blocking client) into the models folder if one was
//!    given, else into the Hugging Face cache, so the Python tools share it. Before it starts, the
//!    caller is told the model's licence and size ([`FetchObserver::before_download`]); progress
//!    is reported per file. `HF_ENDPOINT` (a mirror) and `HF_TOKEN` are honoured.
//!
//! **Offline** (`--offline`, or `PIXL_OFFLINE` / `HF_HUB_OFFLINE` set to `1`, `true`, `yes` or
//! `on`): steps 1–2 only; a model that is not found fails at once with [`HubError::Offline`],
//! whose message names `pixl models fetch NAME` and `--models DIR`. Nothing touches the network.
//!
//! The environment is read once, through a function ([`HubOptions::from_vars`]), so tests can
//! give a fake environment instead of changing the process's.
use std::path::{Path, PathBuf};

/// One file of a model, relative to the repository's root (`/`-separated).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelFile {
    /// The file fetched on download.
    pub path: &'static str,
    /// Another name that serves as well when it is on disk (the f32 weights of a model whose
    /// `path` is the `.fp16` variant, as a full `huggingface-cli download` copy holds both).
    pub alt: Option<&'static str>,
    /// Approximate size in bytes (for messages; the download reports the exact size).
    pub approx_bytes: u64,
}

impl ModelFile {
    const fn new(path: &'static str, approx_bytes: u64) -> Self {
        Self {
            path,
            alt: None,
            approx_bytes,
        }
    }

    const fn or(path: &'static str, alt: &'static str, approx_bytes: u64) -> Self {
        Self {
            path,
            alt: Some(alt),
            approx_bytes,
        }
    }

    /// Whether this file (or its alternative) is in `dir`.
    pub fn present_in(&self, dir: &Path) -> bool {
        is_file(&dir.join(self.path)) || self.alt.is_some_and(|a| is_file(&dir.join(a)))
    }
}

/// A released model this crate can load.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelSpec {
    /// Short name used on the command line (`da3-metric`).
    pub name: &'static str,
    /// Hugging Face repository id (`org/name`).
    pub repo: &'static str,
    /// Revision (branch, tag or commit) to look up and download.
    pub revision: &'static str,
    /// Files the loader needs, relative to the repository's root.
    pub files: &'static [ModelFile],
    /// SPDX identifier (or name) of the weights' licence.
    pub licence: &'static str,
    /// Where the licence is stated.
    pub licence_url: &'static str,
    /// What the model is for, in one line.
    pub purpose: &'static str,
}

impl ModelSpec {
    /// Approximate total size in bytes.
    pub fn approx_bytes(&self) -> u64 {
        self.files.iter().map(|f| f.approx_bytes).sum()
    }

    /// Folder name of this model in a Hugging Face cache (`models--org--name`).
    pub fn cache_folder(&self) -> String {
        format!("models--{}", self.repo.replace('/', "--"))
    }
}

const DA3_FILES: &[ModelFile] = &[
    ModelFile::new("config.json", 1_000),
    // 0.35 B parameters in f32.
    ModelFile::new("model.safetensors", 1_400_000_000),
];

/// A Marigold-IID v1.1 checkpoint in the diffusers layout; the weights are fetched as their
/// `.fp16` variants (half the download, upcast to f32 on load), the f32 files serve as well.
const MARIGOLD_IID_FILES: &[ModelFile] = &[
    ModelFile::new("model_index.json", 1_000),
    ModelFile::new("scheduler/scheduler_config.json", 1_000),
    ModelFile::new("unet/config.json", 2_000),
    // 0.87 B parameters in f16.
    ModelFile::or(
        "unet/diffusion_pytorch_model.fp16.safetensors",
        "unet/diffusion_pytorch_model.safetensors",
        1_732_000_000,
    ),
    ModelFile::new("vae/config.json", 1_000),
    ModelFile::or(
        "vae/diffusion_pytorch_model.fp16.safetensors",
        "vae/diffusion_pytorch_model.safetensors",
        167_000_000,
    ),
    ModelFile::new("text_encoder/config.json", 1_000),
    // Run once: the empty-prompt embedding is cached beside it.
    ModelFile::or(
        "text_encoder/model.fp16.safetensors",
        "text_encoder/model.safetensors",
        681_000_000,
    ),
    ModelFile::new("tokenizer/vocab.json", 1_060_000),
    ModelFile::new("tokenizer/tokenizer_config.json", 1_000),
];

/// Every model this crate knows, by name.
pub const REGISTRY: &[ModelSpec] = &[
    ModelSpec {
        name: "da3-metric",
        repo: "depth-anything/DA3METRIC-LARGE",
        revision: "main",
        files: DA3_FILES,
        licence: "Apache-2.0",
        licence_url: "https://huggingface.co/depth-anything/DA3METRIC-LARGE",
        purpose: "Depth Anything 3 metric: single-image depth in metres (scaled by the focal length) and a sky mask",
    },
    ModelSpec {
        name: "da3-mono",
        repo: "depth-anything/DA3MONO-LARGE",
        revision: "main",
        files: DA3_FILES,
        licence: "Apache-2.0",
        licence_url: "https://huggingface.co/depth-anything/DA3MONO-LARGE",
        purpose: "Depth Anything 3 monocular: single-image relative depth (up to scale) and a sky mask",
    },
    ModelSpec {
        name: "marigold-appearance",
        repo: "prs-eth/marigold-iid-appearance-v1-1",
        revision: "main",
        files: MARIGOLD_IID_FILES,
        licence: "OpenRAIL++-M",
        licence_url: "https://huggingface.co/prs-eth/marigold-iid-appearance-v1-1",
        purpose: "Marigold-IID Appearance: albedo (sRGB), roughness and metallicity of a photo's materials",
    },
    ModelSpec {
        name: "marigold-lighting",
        repo: "prs-eth/marigold-iid-lighting-v1-1",
        revision: "main",
        files: MARIGOLD_IID_FILES,
        licence: "OpenRAIL++-M",
        licence_url: "https://huggingface.co/prs-eth/marigold-iid-lighting-v1-1",
        purpose: "Marigold-IID Lighting: albedo, diffuse shading and non-diffuse residual of a photo (linear)",
    },
];

/// The registry entry called `name`.
pub fn lookup(name: &str) -> Result<&'static ModelSpec, HubError> {
    REGISTRY
        .iter()
        .find(|m| m.name == name)
        .ok_or_else(|| HubError::UnknownModel {
            name: name.to_string(),
            known: REGISTRY.iter().map(|m| m.name).collect::<Vec<_>>().join(", "),
        })
}

/// Errors of the weight lookup and download. Each names the model and, where there is one, the file.
#[derive(Debug, thiserror::Error)]
pub enum HubError {
    #[error("unknown model `{name}` (known: {known})")]
    UnknownModel { name: String, known: String },
    /// A model folder (`--models DIR/<name>/`) that lacks one of the model's files.
    #[error("{}: model `{model}` is missing its file `{file}` (expected at {}); copy the file there or remove the folder", dir.display(), path.display())]
    MissingFile {
        model: String,
        dir: PathBuf,
        file: String,
        path: PathBuf,
    },
    /// Downloads are off and the model is not on disk.
    #[error(
        "model `{model}` ({repo}) is not on this machine and downloads are off (--offline, PIXL_OFFLINE or HF_HUB_OFFLINE); \
looked in: {looked}. Fetch it once with `pixl models fetch {model}` (with network access), \
or pass `--models DIR` with the files in DIR/{model}/ ({files})"
    )]
    Offline {
        model: String,
        repo: String,
        looked: String,
        files: String,
    },
    /// The model is not on disk (for commands that never download, like `pixl models path`).
    #[error(
        "model `{model}` ({repo}) is not on this machine; looked in: {looked}. \
`pixl models fetch {model}` downloads it, or pass `--models DIR` with the files in DIR/{model}/ ({files})"
    )]
    NotOnDisk {
        model: String,
        repo: String,
        looked: String,
        files: String,
    },
    /// Neither a Hugging Face cache location nor a home folder is known.
    #[error("no Hugging Face cache folder: set HF_HOME or HF_HUB_CACHE, or pass --models DIR")]
    NoCacheDir,
    #[error("downloading `{file}` of model `{model}` from {repo}: {reason}")]
    Download {
        model: String,
        repo: String,
        file: String,
        reason: String,
    },
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
}

/// Where to look and whether downloads are allowed.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct HubOptions {
    /// The models folder (`--models DIR` or `PIXL_MODELS_DIR`).
    pub models_dir: Option<PathBuf>,
    /// The Hugging Face cache folder (`None` when no location is known).
    pub hf_cache: Option<PathBuf>,
    /// No network at all.
    pub offline: bool,
    /// Hub endpoint (`HF_ENDPOINT`), default `https://huggingface.co`.
    pub endpoint: Option<String>,
    /// Access token (`HF_TOKEN`); without it `hf-hub` reads `<HF_HOME>/token` if present.
    pub token: Option<String>,
}

/// Whether an environment flag is on (`1`, `true`, `yes`, `on`, any case).
fn truthy(v: Option<String>) -> bool {
    v.is_some_and(|v| matches!(v.trim().to_ascii_lowercase().as_str(), "1" | "true" | "yes" | "on"))
}

impl HubOptions {
    /// Options from the command line (`models_dir`, `offline`) and the environment, read through
    /// `var` (see the module docs for the variables and their order).
    pub fn from_vars(models_dir: Option<PathBuf>, offline: bool, var: impl Fn(&str) -> Option<String>) -> Self {
        let var = |k: &str| var(k).filter(|v| !v.is_empty());
        let hf_cache = var("HF_HUB_CACHE")
            .or_else(|| var("HUGGINGFACE_HUB_CACHE"))
            .map(PathBuf::from)
            .or_else(|| var("HF_HOME").map(|h| PathBuf::from(h).join("hub")))
            .or_else(|| var("XDG_CACHE_HOME").map(|c| PathBuf::from(c).join("huggingface").join("hub")))
            .or_else(|| var("HOME").map(|h| PathBuf::from(h).join(".cache").join("huggingface").join("hub")));
        Self {
            models_dir: models_dir.or_else(|| var("PIXL_MODELS_DIR").map(PathBuf::from)),
            hf_cache,
            offline: offline || truthy(var("PIXL_OFFLINE")) || truthy(var("HF_HUB_OFFLINE")),
            endpoint: var("HF_ENDPOINT"),
            token: var("HF_TOKEN"),
        }
    }

    /// [`HubOptions::from_vars`] over the process's environment.
    pub fn from_env(models_dir: Option<PathBuf>, offline: bool) -> Self {
        Self::from_vars(models_dir, offline, |k| std::env::var(k).ok())
    }
}

/// Where a model's files were found.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Source {
    /// `DIR/<name>/` in the models folder.
    ModelsDir(PathBuf),
    /// A snapshot in a Hugging Face cache (the models folder or the user's cache).
    HfCache { cache: PathBuf, commit: String },
    /// Downloaded just now into this Hugging Face cache.
    Downloaded { cache: PathBuf, commit: String },
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Source::ModelsDir(d) => write!(f, "models folder {}", d.display()),
            Source::HfCache { cache, commit } => {
                write!(f, "Hugging Face cache {} (snapshot {})", cache.display(), short(commit))
            }
            Source::Downloaded { cache, commit } => {
                write!(f, "downloaded into {} (snapshot {})", cache.display(), short(commit))
            }
        }
    }
}

fn short(commit: &str) -> &str {
    commit.get(..12).unwrap_or(commit)
}

/// A model whose files are all on disk.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Resolved {
    pub spec: &'static ModelSpec,
    pub source: Source,
    /// The folder holding the files (their paths are `dir/<file>`).
    pub dir: PathBuf,
}

impl Resolved {
    /// Full path of one of the model's files.
    pub fn file(&self, path: &str) -> PathBuf {
        self.dir.join(path)
    }

    /// Full paths of every file, in registry order.
    pub fn files(&self) -> Vec<PathBuf> {
        self.spec.files.iter().map(|f| self.file(f.path)).collect()
    }
}

/// Told about a download before and while it happens.
pub trait FetchObserver {
    /// Before anything is downloaded: the model (licence, size), the files still missing and
    /// the cache folder they go to.
    fn before_download(&mut self, _spec: &ModelSpec, _missing: &[ModelFile], _into: &Path) {}
    /// A file's download starts (`bytes`: its exact size).
    fn file_started(&mut self, _file: &str, _bytes: u64) {}
    /// `bytes` more bytes of the current file arrived.
    fn file_progress(&mut self, _bytes: u64) {}
    /// The current file is complete.
    fn file_finished(&mut self) {}
}

/// A [`FetchObserver`] that ignores everything.
pub struct Silent;
impl FetchObserver for Silent {}

/// The weight lookup (see the module docs).
#[derive(Clone, Debug)]
pub struct Hub {
    pub opts: HubOptions,
}

/// `true` if `p` is a file (symlinks followed; a dangling link is not).
fn is_file(p: &Path) -> bool {
    p.is_file()
}

impl Hub {
    pub fn new(opts: HubOptions) -> Self {
        Self { opts }
    }

    /// The Hugging Face cache folders to search, in order (models folder first).
    fn caches(&self) -> Vec<PathBuf> {
        self.opts
            .models_dir
            .iter()
            .chain(self.opts.hf_cache.iter())
            .cloned()
            .collect()
    }

    /// Where a download goes: the models folder if given, else the Hugging Face cache.
    pub fn download_target(&self) -> Result<PathBuf, HubError> {
        self.opts
            .models_dir
            .clone()
            .or_else(|| self.opts.hf_cache.clone())
            .ok_or(HubError::NoCacheDir)
    }

    /// The places [`Hub::locate`] looks, in order, for messages.
    pub fn search_paths(&self, spec: &ModelSpec) -> Vec<PathBuf> {
        let mut v = Vec::new();
        if let Some(d) = &self.opts.models_dir {
            v.push(d.join(spec.name));
        }
        v.extend(self.caches().into_iter().map(|c| c.join(spec.cache_folder())));
        v
    }

    /// Finds the model on disk without any network access: `Ok(None)` if it is nowhere, an
    /// error for a models folder `DIR/<name>/` that lacks a file.
    pub fn locate(&self, spec: &'static ModelSpec) -> Result<Option<Resolved>, HubError> {
        if let Some(dir) = &self.opts.models_dir {
            let own = dir.join(spec.name);
            if own.is_dir() {
                for f in spec.files {
                    let path = own.join(f.path);
                    if !f.present_in(&own) {
                        return Err(HubError::MissingFile {
                            model: spec.name.to_string(),
                            dir: own.clone(),
                            file: f.path.to_string(),
                            path,
                        });
                    }
                }
                return Ok(Some(Resolved {
                    spec,
                    source: Source::ModelsDir(own.clone()),
                    dir: own,
                }));
            }
        }
        for cache in self.caches() {
            if let Some((commit, dir)) = cached_snapshot(&cache, spec)? {
                return Ok(Some(Resolved {
                    spec,
                    source: Source::HfCache { cache, commit },
                    dir,
                }));
            }
        }
        Ok(None)
    }

    /// Finds the model on disk, else downloads it (unless offline; see the module docs).
    pub fn resolve(&self, spec: &'static ModelSpec, observer: &mut dyn FetchObserver) -> Result<Resolved, HubError> {
        if let Some(r) = self.locate(spec)? {
            return Ok(r);
        }
        if self.opts.offline {
            return Err(self.offline_error(spec));
        }
        self.download(spec, observer)
    }

    /// The places searched and the files wanted, for the "not found" errors.
    fn not_found_parts(&self, spec: &ModelSpec) -> (String, String, String, String) {
        let looked: Vec<String> = self
            .search_paths(spec)
            .iter()
            .map(|p| p.display().to_string())
            .collect();
        (
            spec.name.to_string(),
            spec.repo.to_string(),
            if looked.is_empty() {
                "nowhere (no models folder, no Hugging Face cache location)".into()
            } else {
                looked.join(", ")
            },
            spec.files.iter().map(|f| f.path).collect::<Vec<_>>().join(", "),
        )
    }

    /// The error for a model that is not on disk while downloads are off.
    pub fn offline_error(&self, spec: &ModelSpec) -> HubError {
        let (model, repo, looked, files) = self.not_found_parts(spec);
        HubError::Offline {
            model,
            repo,
            looked,
            files,
        }
    }

    /// The error for a model that is not on disk, for commands that never download.
    pub fn not_on_disk_error(&self, spec: &ModelSpec) -> HubError {
        let (model, repo, looked, files) = self.not_found_parts(spec);
        HubError::NotOnDisk {
            model,
            repo,
            looked,
            files,
        }
    }

    /// Downloads the files missing from the target cache's current snapshot.
    fn download(&self, spec: &'static ModelSpec, observer: &mut dyn FetchObserver) -> Result<Resolved, HubError> {
        let cache = self.download_target()?;
        std::fs::create_dir_all(&cache).map_err(|source| HubError::Io {
            path: cache.clone(),
            source,
        })?;
        let mut builder = hf_hub::api::sync::ApiBuilder::from_cache(hf_hub::Cache::new(cache.clone()))
            .with_progress(false)
            .with_retries(2);
        if let Some(e) = &self.opts.endpoint {
            builder = builder.with_endpoint(e.clone());
        }
        if self.opts.token.is_some() {
            builder = builder.with_token(self.opts.token.clone());
        }
        let err = |file: &str, reason: String| HubError::Download {
            model: spec.name.to_string(),
            repo: spec.repo.to_string(),
            file: file.to_string(),
            reason,
        };
        let api = builder.build().map_err(|e| err("(client)", e.to_string()))?;
        let repo = api.repo(hf_hub::Repo::with_revision(
            spec.repo.to_string(),
            hf_hub::RepoType::Model,
            spec.revision.to_string(),
        ));
        let mut announced = false;
        // The repository may gain a commit while we download; then the ref moves to a snapshot
        // that lacks the files fetched before, which a second round fills in.
        for _round in 0..3 {
            if let Some((commit, dir)) = cached_snapshot(&cache, spec)? {
                return Ok(Resolved {
                    spec,
                    source: Source::Downloaded { cache, commit },
                    dir,
                });
            }
            let missing = missing_in_current_snapshot(&cache, spec);
            if !announced {
                observer.before_download(spec, &missing, &cache);
                announced = true;
            }
            for f in &missing {
                let progress = ProgressAdapter {
                    observer: &mut *observer,
                };
                repo.download_with_progress(f.path, progress)
                    .map_err(|e| err(f.path, e.to_string()))?;
            }
        }
        Err(err(
            spec.files.last().map(|f| f.path).unwrap_or("?"),
            "the repository changed during the download; run the command again".into(),
        ))
    }
}

/// Forwards `hf-hub`'s progress calls to a [`FetchObserver`].
struct ProgressAdapter<'a> {
    observer: &'a mut dyn FetchObserver,
}

impl hf_hub::api::Progress for ProgressAdapter<'_> {
    fn init(&mut self, size: usize, filename: &str) {
        self.observer.file_started(filename, size as u64);
    }
    fn update(&mut self, size: usize) {
        self.observer.file_progress(size as u64);
    }
    fn finish(&mut self) {
        self.observer.file_finished();
    }
}

/// Reads `refs/<revision>` of the model in `cache`; `None` if absent.
fn read_ref(cache: &Path, spec: &ModelSpec) -> Result<Option<String>, HubError> {
    let path = cache.join(spec.cache_folder()).join("refs").join(spec.revision);
    match std::fs::read_to_string(&path) {
        Ok(s) => Ok(Some(s.trim().to_string()).filter(|s| !s.is_empty())),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(source) => Err(HubError::Io { path, source }),
    }
}

fn has_all(dir: &Path, spec: &ModelSpec) -> bool {
    spec.files.iter().all(|f| f.present_in(dir))
}

/// The snapshot of `spec` in the Hugging Face cache `cache` that holds every file:
/// the one `refs/<revision>` names, else (no ref file) the first complete one in name order.
fn cached_snapshot(cache: &Path, spec: &ModelSpec) -> Result<Option<(String, PathBuf)>, HubError> {
    let snapshots = cache.join(spec.cache_folder()).join("snapshots");
    if !snapshots.is_dir() {
        return Ok(None);
    }
    if let Some(commit) = read_ref(cache, spec)? {
        let dir = snapshots.join(&commit);
        return Ok(has_all(&dir, spec).then_some((commit, dir)));
    }
    // A revision that is itself a commit has no ref file; nor has a copied cache sometimes.
    let entries = std::fs::read_dir(&snapshots).map_err(|source| HubError::Io {
        path: snapshots.clone(),
        source,
    })?;
    let mut names: Vec<String> = entries
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir())
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .collect();
    names.sort();
    if names.iter().any(|n| n == spec.revision) {
        names.retain(|n| n == spec.revision);
    }
    Ok(names
        .into_iter()
        .map(|n| (snapshots.join(&n), n))
        .find(|(d, _)| has_all(d, spec))
        .map(|(d, n)| (n, d)))
}

/// The files of `spec` not in the snapshot `refs/<revision>` names (all of them without a ref).
fn missing_in_current_snapshot(cache: &Path, spec: &ModelSpec) -> Vec<ModelFile> {
    let dir = read_ref(cache, spec)
        .ok()
        .flatten()
        .map(|c| cache.join(spec.cache_folder()).join("snapshots").join(c));
    spec.files
        .iter()
        .filter(|f| dir.as_ref().is_none_or(|d| !f.present_in(d)))
        .copied()
        .collect()
}

/// Human-readable size (`1.4 GB`, `12 kB`), decimal units.
pub fn human_bytes(n: u64) -> String {
    let n = n as f64;
    if n >= 1e9 {
        format!("{:.1} GB", n / 1e9)
    } else if n >= 1e6 {
        format!("{:.0} MB", n / 1e6)
    } else if n >= 1e3 {
        format!("{:.0} kB", n / 1e3)
    } else {
        format!("{n} B")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn env(pairs: &[(&str, &Path)]) -> impl Fn(&str) -> Option<String> {
        let m: HashMap<String, String> = pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.display().to_string()))
            .collect();
        move |k| m.get(k).cloned()
    }

    fn write(p: &Path, bytes: &[u8]) {
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, bytes).unwrap();
    }

    /// A Python-layout cache entry: blobs + snapshot symlinks + refs/main.
    fn fake_cache(cache: &Path, spec: &ModelSpec, commit: &str, files: &[&str], with_ref: bool) -> PathBuf {
        let root = cache.join(spec.cache_folder());
        let snap = root.join("snapshots").join(commit);
        std::fs::create_dir_all(&snap).unwrap();
        for (i, f) in files.iter().enumerate() {
            let blob = root.join("blobs").join(format!("{commit}-{i}"));
            write(&blob, f.as_bytes());
            #[cfg(unix)]
            std::os::unix::fs::symlink(format!("../../blobs/{commit}-{i}"), snap.join(f)).unwrap();
            #[cfg(not(unix))]
            std::fs::copy(&blob, snap.join(f)).unwrap();
        }
        if with_ref {
            write(&root.join("refs").join("main"), commit.as_bytes());
        }
        snap
    }

    #[test]
    fn registry_names_are_unique_and_files_listed() {
        for (i, m) in REGISTRY.iter().enumerate() {
            assert!(REGISTRY[i + 1..].iter().all(|o| o.name != m.name), "{}", m.name);
            assert!(!m.files.is_empty() && m.repo.contains('/'));
            assert_eq!(lookup(m.name).unwrap().repo, m.repo);
        }
        assert_eq!(
            lookup("da3-metric").unwrap().cache_folder(),
            "models--depth-anything--DA3METRIC-LARGE"
        );
        let e = lookup("da3").unwrap_err().to_string();
        assert!(e.contains("da3-metric") && e.contains("da3-mono"), "{e}");
    }

    #[test]
    fn cache_location_follows_the_python_order() {
        let (a, b, c, d, h) = (
            Path::new("/a"),
            Path::new("/b"),
            Path::new("/c"),
            Path::new("/x"),
            Path::new("/home/u"),
        );
        let o = |pairs: &[(&str, &Path)]| HubOptions::from_vars(None, false, env(pairs)).hf_cache;
        let all = [("HF_HUB_CACHE", a), ("HF_HOME", b), ("XDG_CACHE_HOME", d), ("HOME", h)];
        assert_eq!(o(&all), Some(PathBuf::from("/a")));
        assert_eq!(o(&all[1..]), Some(PathBuf::from("/b/hub")));
        assert_eq!(o(&all[2..]), Some(PathBuf::from("/x/huggingface/hub")));
        assert_eq!(o(&all[3..]), Some(PathBuf::from("/home/u/.cache/huggingface/hub")));
        assert_eq!(
            o(&[("HUGGINGFACE_HUB_CACHE", c), ("HF_HOME", b)]),
            Some(PathBuf::from("/c"))
        );
        assert_eq!(o(&[]), None);
    }

    #[test]
    fn offline_flags_and_models_dir_from_the_environment() {
        let one = Path::new("1");
        let off = |pairs: &[(&str, &Path)]| HubOptions::from_vars(None, false, env(pairs)).offline;
        assert!(!off(&[]));
        assert!(off(&[("PIXL_OFFLINE", one)]));
        assert!(off(&[("HF_HUB_OFFLINE", Path::new("TRUE"))]));
        assert!(!off(&[("HF_HUB_OFFLINE", Path::new("0"))]));
        assert!(HubOptions::from_vars(None, true, env(&[])).offline);
        let o = HubOptions::from_vars(None, false, env(&[("PIXL_MODELS_DIR", Path::new("/m"))]));
        assert_eq!(o.models_dir, Some(PathBuf::from("/m")));
        // The flag wins over the variable.
        let o = HubOptions::from_vars(
            Some("/flag".into()),
            false,
            env(&[("PIXL_MODELS_DIR", Path::new("/m"))]),
        );
        assert_eq!(o.models_dir, Some(PathBuf::from("/flag")));
    }

    /// Models folder before the user's cache; the cache's `refs/main` snapshot; nothing → offline error.
    #[test]
    fn lookup_order_models_dir_then_cache() {
        let t = tempfile::tempdir().unwrap();
        let spec = lookup("da3-metric").unwrap();
        let hf = t.path().join("hf");
        let models = t.path().join("models");
        let opts = |models_dir: Option<&Path>| {
            HubOptions::from_vars(models_dir.map(Path::to_path_buf), true, env(&[("HF_HOME", &hf)]))
        };
        let hub = Hub::new(opts(Some(&models)));

        // Nothing anywhere: offline error naming the fetch command and --models.
        assert_eq!(hub.locate(spec).unwrap(), None);
        let e = hub.resolve(spec, &mut Silent).unwrap_err();
        assert!(matches!(e, HubError::Offline { .. }));
        let msg = e.to_string();
        assert!(
            msg.contains("pixl models fetch da3-metric") && msg.contains("--models DIR"),
            "{msg}"
        );
        assert!(msg.contains(&hf.join("hub").display().to_string()), "{msg}");

        // An older snapshot with everything, and the current one (refs/main) with everything.
        fake_cache(
            &hf.join("hub"),
            spec,
            "0ld",
            &["config.json", "model.safetensors"],
            false,
        );
        let snap = fake_cache(
            &hf.join("hub"),
            spec,
            "c0ffee",
            &["config.json", "model.safetensors"],
            true,
        );
        let r = hub.resolve(spec, &mut Silent).unwrap();
        assert_eq!(r.dir, snap);
        assert_eq!(
            r.source,
            Source::HfCache {
                cache: hf.join("hub"),
                commit: "c0ffee".into()
            }
        );
        assert_eq!(
            std::fs::read_to_string(r.file("model.safetensors")).unwrap(),
            "model.safetensors"
        );

        // The models folder comes first.
        let own = models.join("da3-metric");
        write(&own.join("config.json"), b"{}");
        write(&own.join("model.safetensors"), b"w");
        let r = hub.resolve(spec, &mut Silent).unwrap();
        assert_eq!(
            (r.dir.clone(), r.source.clone()),
            (own.clone(), Source::ModelsDir(own.clone()))
        );
        assert_eq!(r.files(), vec![own.join("config.json"), own.join("model.safetensors")]);
        // ...but only for that model: da3-mono is in neither.
        assert!(hub.locate(lookup("da3-mono").unwrap()).unwrap().is_none());
    }

    #[test]
    fn models_dir_lacking_a_file_names_it() {
        let t = tempfile::tempdir().unwrap();
        let spec = lookup("da3-mono").unwrap();
        let own = t.path().join("da3-mono");
        write(&own.join("config.json"), b"{}");
        let hub = Hub::new(HubOptions {
            models_dir: Some(t.path().to_path_buf()),
            offline: true,
            ..Default::default()
        });
        let e = hub.resolve(spec, &mut Silent).unwrap_err();
        match &e {
            HubError::MissingFile { file, path, .. } => {
                assert_eq!(file, "model.safetensors");
                assert_eq!(path, &own.join("model.safetensors"));
            }
            other => panic!("expected MissingFile, got {other:?}"),
        }
        assert!(e.to_string().contains("model.safetensors"), "{e}");
    }

    #[test]
    fn incomplete_or_dangling_snapshots_are_not_found() {
        let t = tempfile::tempdir().unwrap();
        let spec = lookup("da3-metric").unwrap();
        let cache = t.path().to_path_buf();
        let hub = Hub::new(HubOptions {
            hf_cache: Some(cache.clone()),
            offline: true,
            ..Default::default()
        });
        // refs/main names a snapshot holding only config.json.
        let snap = fake_cache(&cache, spec, "abc", &["config.json"], true);
        assert_eq!(hub.locate(spec).unwrap(), None);
        assert_eq!(
            missing_in_current_snapshot(&cache, spec),
            vec![spec.files[1]],
            "only the weights are missing"
        );
        // A dangling link (interrupted download) counts as absent.
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink("../../blobs/none", snap.join("model.safetensors")).unwrap();
            assert_eq!(hub.locate(spec).unwrap(), None);
            std::fs::remove_file(snap.join("model.safetensors")).unwrap();
        }
        // Without a ref file, a complete snapshot is still used.
        let t2 = tempfile::tempdir().unwrap();
        let snap2 = fake_cache(t2.path(), spec, "def", &["config.json", "model.safetensors"], false);
        let hub2 = Hub::new(HubOptions {
            hf_cache: Some(t2.path().to_path_buf()),
            offline: true,
            ..Default::default()
        });
        assert_eq!(hub2.locate(spec).unwrap().map(|r| r.dir), Some(snap2));
    }

    /// `--models DIR` may itself be laid out as a Hugging Face cache (what `fetch --models` writes).
    #[test]
    fn models_dir_as_a_cache_and_download_target() {
        let t = tempfile::tempdir().unwrap();
        let spec = lookup("da3-metric").unwrap();
        let snap = fake_cache(t.path(), spec, "123", &["config.json", "model.safetensors"], true);
        let hub = Hub::new(HubOptions {
            models_dir: Some(t.path().to_path_buf()),
            hf_cache: Some("/nonexistent-cache".into()),
            offline: true,
            ..Default::default()
        });
        assert_eq!(hub.locate(spec).unwrap().map(|r| r.dir), Some(snap));
        assert_eq!(hub.download_target().unwrap(), t.path());
        let none = Hub::new(HubOptions::default());
        assert!(matches!(none.download_target(), Err(HubError::NoCacheDir)));
    }

    #[test]
    fn sizes_read_well() {
        assert_eq!(human_bytes(1_400_000_000), "1.4 GB");
        assert_eq!(human_bytes(2_500_000), "2 MB");
        assert_eq!(human_bytes(999), "999 B");
        assert!(lookup("da3-metric").unwrap().approx_bytes() > 1_000_000_000);
    }
}
