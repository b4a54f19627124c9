//! Where pretrained weights come from: a registry of the released models the toolkit loads (the
//! estimators of this crate and the released PIXLRelight network), and the lookup that finds their
//! files on disk or downloads them once.
//!
//! # Registry
//! [`REGISTRY`] lists every model by a short name (`da3-metric`, `pixlrelight`): its Hugging Face
//! repository and revision, the files it needs (a model is a list of [`ModelFile`]s, relative
//! paths inside the repository, so a diffusers-style folder with `unet/…`, `vae/…` fits as well as
//! a single `model.safetensors`), its licence, its approximate size and what it is for. A file
//! may carry the SHA-256 of its content ([`ModelFile::sha256`]); `pixlrelight` pins both of its
//! files at a fixed commit.
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
//! # Pinned digests
//! A download goes first into a staging folder (`<cache>/models--org--name/.pixl-incoming/`,
//! itself a Hugging Face cache, so an interrupted download resumes there). A file whose registry
//! entry pins a SHA-256 is hashed there; if the digest differs, the file is deleted and the
//! download fails with [`HubError::DigestMismatch`] (the file, the expected and the found digest),
//! so a corrupted or substituted file never reaches the cache. A file that passes (or pins no
//! digest) is moved into the cache's layout (`blobs/`, a `snapshots/<commit>/` link,
//! `refs/<revision>`). Files already on disk are not hashed on every lookup (the PIXLRelight
//! weights are 2.6 GB); [`Resolved::verify`] (`pixl models path NAME --verify`) re-checks them and
//! fails with [`HubError::CorruptFile`] naming the file that differs.
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
    /// SHA-256 of `path`'s content (64 lowercase hex digits) where the registry pins one: a
    /// download is checked against it before it is put in place, and [`Resolved::verify`]
    /// checks the file on disk. `None`: the content is not checked. It does not apply to `alt`.
    pub sha256: Option<&'static str>,
}

impl ModelFile {
    const fn new(path: &'static str, approx_bytes: u64) -> Self {
        Self {
            path,
            alt: None,
            approx_bytes,
            sha256: None,
        }
    }

    const fn or(path: &'static str, alt: &'static str, approx_bytes: u64) -> Self {
        Self {
            path,
            alt: Some(alt),
            approx_bytes,
            sha256: None,
        }
    }

    const fn pinned(path: &'static str, approx_bytes: u64, sha256: &'static str) -> Self {
        Self {
            path,
            alt: None,
            approx_bytes,
            sha256: Some(sha256),
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

/// A Marigold v1.1 checkpoint (IID or normals) in the diffusers layout; the weights are fetched
/// as their `.fp16` variants (half the download, upcast to f32 on load), the f32 files serve as
/// well.
const MARIGOLD_FILES: &[ModelFile] = &[
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

/// The released PIXLRelight checkpoint (code: <https://github.com/mlfarinha/pixlrelight>), pinned
/// to one commit with the SHA-256 of each file.
const PIXLRELIGHT_FILES: &[ModelFile] = &[
    ModelFile::pinned(
        "config.yaml",
        4_000,
        "a3ef2cada8a223aee15b2e85d6627980962ea5446242d0d8ec24791ec2e21021",
    ),
    // About 641 M parameters in f32.
    ModelFile::pinned(
        "model.safetensors",
        2_560_000_000,
        "69c2bd11c2f272754f7080bc33e4b049fd334ea5d596df0c475f51c93699710e",
    ),
];

/// Every model the toolkit knows, by name.
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
        files: MARIGOLD_FILES,
        licence: "OpenRAIL++-M",
        licence_url: "https://huggingface.co/prs-eth/marigold-iid-appearance-v1-1",
        purpose: "Marigold-IID Appearance: albedo (sRGB), roughness and metallicity of a photo's materials",
    },
    ModelSpec {
        name: "marigold-lighting",
        repo: "prs-eth/marigold-iid-lighting-v1-1",
        revision: "main",
        files: MARIGOLD_FILES,
        licence: "OpenRAIL++-M",
        licence_url: "https://huggingface.co/prs-eth/marigold-iid-lighting-v1-1",
        purpose: "Marigold-IID Lighting: albedo, diffuse shading and non-diffuse residual of a photo (linear)",
    },
    ModelSpec {
        name: "marigold-normals",
        repo: "prs-eth/marigold-normals-v1-1",
        revision: "main",
        files: MARIGOLD_FILES,
        licence: "Apache-2.0",
        licence_url: "https://huggingface.co/prs-eth/marigold-normals-v1-1",
        purpose: "Marigold Normals: camera-space surface normals of a photo (x right, y up, z towards the viewer)",
    },
    ModelSpec {
        name: "pixlrelight",
        repo: "mlfarinha/pixlrelight",
        revision: "5def370459c15ee36c524068bb8338b3f6c6d6c0",
        files: PIXLRELIGHT_FILES,
        licence: "CC BY-NC 4.0 — non-commercial use only",
        licence_url: "https://huggingface.co/mlfarinha/pixlrelight",
        purpose: "PIXLRelight (the paper's released model): relights a photo from target intrinsics",
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
    /// A downloaded file whose SHA-256 is not the one the registry pins; it was deleted before
    /// it reached the cache.
    #[error(
        "downloaded `{file}` of model `{model}` has sha256 {found}, expected {expected}; \
the file was deleted. Run the command again; if it fails the same way, the server (HF_ENDPOINT) serves other content"
    )]
    DigestMismatch {
        model: String,
        file: String,
        expected: String,
        found: String,
    },
    /// A file on disk whose SHA-256 is not the one the registry pins ([`Resolved::verify`]).
    #[error(
        "{}: `{file}` of model `{model}` has sha256 {found}, expected {expected}; \
delete it and run `pixl models fetch {model}`",
        path.display()
    )]
    CorruptFile {
        model: String,
        file: String,
        path: PathBuf,
        expected: String,
        found: String,
    },
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
}

/// SHA-256 of everything `reader` yields, as 64 lowercase hex digits.
pub fn sha256_reader(mut reader: impl std::io::Read) -> std::io::Result<String> {
    use sha2::Digest;
    let mut hasher = sha2::Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        match reader.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => hasher.update(&buf[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        }
    }
    Ok(format!("{:x}", hasher.finalize()))
}

/// SHA-256 of the file at `path` (symlinks followed), as 64 lowercase hex digits.
pub fn sha256_file(path: &Path) -> Result<String, HubError> {
    let io = |source| HubError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    sha256_reader(file).map_err(io)
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

    /// Hashes every file whose registry entry pins a SHA-256 and compares (the whole file is
    /// read: seconds per GB); files without a pinned digest are listed but not read. Fails with
    /// [`HubError::CorruptFile`] at the first file that differs.
    pub fn verify(&self, observer: &mut dyn FetchObserver) -> Result<Vec<FileCheck>, HubError> {
        let mut checks = Vec::with_capacity(self.spec.files.len());
        for f in self.spec.files {
            let path = self.file(f.path);
            let (path, expected) = match (f.sha256, f.alt) {
                // The digest is that of `path`; an alternative found in its place is not checked.
                (Some(expected), _) if is_file(&path) => (path, Some(expected)),
                (_, Some(alt)) if !is_file(&path) => (self.file(alt), None),
                _ => (path, None),
            };
            let Some(expected) = expected else {
                checks.push(FileCheck {
                    file: f.path,
                    path,
                    sha256: None,
                });
                continue;
            };
            let bytes = std::fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
            observer.file_checking(f.path, bytes);
            let found = sha256_file(&path)?;
            if !found.eq_ignore_ascii_case(expected) {
                return Err(HubError::CorruptFile {
                    model: self.spec.name.to_string(),
                    file: f.path.to_string(),
                    path,
                    expected: expected.to_string(),
                    found,
                });
            }
            checks.push(FileCheck {
                file: f.path,
                path,
                sha256: Some(found),
            });
        }
        Ok(checks)
    }
}

/// One file as [`Resolved::verify`] found it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FileCheck {
    /// The file's registry path.
    pub file: &'static str,
    /// Where it is on disk.
    pub path: PathBuf,
    /// Its SHA-256, equal to the pinned one; `None` when the registry pins none (not read).
    pub sha256: Option<String>,
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
    /// The SHA-256 of `file` (`bytes` long) is being computed, after its download or by
    /// [`Resolved::verify`].
    fn file_checking(&mut self, _file: &str, _bytes: u64) {}
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

    /// Downloads the files missing from the target cache's current snapshot (through the
    /// staging folder; see the module docs).
    fn download(&self, spec: &'static ModelSpec, observer: &mut dyn FetchObserver) -> Result<Resolved, HubError> {
        let cache = self.download_target()?;
        std::fs::create_dir_all(&cache).map_err(|source| HubError::Io {
            path: cache.clone(),
            source,
        })?;
        let staging = staging_root(&cache, spec);
        let result = self.download_via(spec, &cache, &staging, observer);
        clean_staging(&staging);
        result
    }

    /// [`Hub::download`] with `hf-hub` writing into `staging`; each file is checked and moved
    /// into `cache` as soon as it is complete.
    fn download_via(
        &self,
        spec: &'static ModelSpec,
        cache: &Path,
        staging: &Path,
        observer: &mut dyn FetchObserver,
    ) -> Result<Resolved, HubError> {
        let cache = cache.to_path_buf();
        remove_dangling_links(staging);
        let mut builder = hf_hub::api::sync::ApiBuilder::from_cache(hf_hub::Cache::new(staging.to_path_buf()))
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
                let staged = repo
                    .download_with_progress(f.path, progress)
                    .map_err(|e| err(f.path, e.to_string()))?;
                install(spec, f, &cache, staging, &staged, observer)?;
            }
        }
        Err(err(
            spec.files.last().map(|f| f.path).unwrap_or("?"),
            "the repository changed during the download; run the command again".into(),
        ))
    }
}

/// The staging folder of `spec`'s downloads into `cache` (a Hugging Face cache of its own).
fn staging_root(cache: &Path, spec: &ModelSpec) -> PathBuf {
    cache.join(spec.cache_folder()).join(".pixl-incoming")
}

/// Removes the staging folder unless it holds a partial download (`*.part`: resumable, or in
/// progress in another process). Failures are ignored: the folder is only clutter.
fn clean_staging(staging: &Path) {
    fn has_part(dir: &Path) -> bool {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return false;
        };
        entries.filter_map(Result::ok).any(|e| {
            let p = e.path();
            match e.file_type() {
                Ok(t) if t.is_dir() => has_part(&p),
                _ => p.extension().is_some_and(|x| x == "part"),
            }
        })
    }
    if staging.is_dir() && !has_part(staging) {
        let _ = std::fs::remove_dir_all(staging);
    }
}

/// Removes the links under `dir` whose target is gone: snapshot entries of the staging cache
/// left by an interrupted run after their file was moved, which `hf-hub` would refuse to
/// replace.
fn remove_dangling_links(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.filter_map(Result::ok) {
        let p = e.path();
        match e.file_type() {
            Ok(t) if t.is_symlink() && !p.exists() => {
                let _ = std::fs::remove_file(&p);
            }
            Ok(t) if t.is_dir() => remove_dangling_links(&p),
            _ => {}
        }
    }
}

/// Moves a file `hf-hub` downloaded into the staging cache (`staged`: its
/// `snapshots/<commit>/<file>` entry there) into `cache`, after checking its SHA-256 if the
/// registry pins one. On a mismatch the staged file is deleted and nothing is moved.
fn install(
    spec: &ModelSpec,
    file: &ModelFile,
    cache: &Path,
    staging: &Path,
    staged: &Path,
    observer: &mut dyn FetchObserver,
) -> Result<(), HubError> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| HubError::Io { path, source }
    };
    let staged_snapshots = staging.join(spec.cache_folder()).join("snapshots");
    let commit = staged
        .strip_prefix(&staged_snapshots)
        .ok()
        .and_then(|rest| rest.components().next())
        .and_then(|c| c.as_os_str().to_str())
        // The commit comes from a response header: it must be a plain name to become a folder.
        .filter(|c| !c.is_empty() && c.bytes().all(|b| b.is_ascii_alphanumeric()))
        .map(str::to_string)
        .ok_or_else(|| HubError::Download {
            model: spec.name.to_string(),
            repo: spec.repo.to_string(),
            file: file.path.to_string(),
            reason: format!("the server named an unusable commit (file at {})", staged.display()),
        })?;
    // `hf-hub` links the snapshot entry to `blobs/<etag>`, or (where links are not allowed)
    // moves the file there itself.
    let linked = std::fs::symlink_metadata(staged)
        .map_err(io(staged))?
        .file_type()
        .is_symlink();
    let content = if linked {
        std::fs::canonicalize(staged).map_err(io(staged))?
    } else {
        staged.to_path_buf()
    };
    if let Some(expected) = file.sha256 {
        let bytes = std::fs::metadata(&content).map(|m| m.len()).unwrap_or(0);
        observer.file_checking(file.path, bytes);
        let found = sha256_file(&content)?;
        if !found.eq_ignore_ascii_case(expected) {
            let _ = std::fs::remove_file(staged);
            let _ = std::fs::remove_file(&content);
            return Err(HubError::DigestMismatch {
                model: spec.name.to_string(),
                file: file.path.to_string(),
                expected: expected.to_string(),
                found,
            });
        }
    }
    let root = cache.join(spec.cache_folder());
    let pointer = root.join("snapshots").join(&commit).join(file.path);
    if let Some(parent) = pointer.parent() {
        std::fs::create_dir_all(parent).map_err(io(parent))?;
    }
    // A dangling link or an older copy left by an interrupted run.
    if std::fs::symlink_metadata(&pointer).is_ok() {
        std::fs::remove_file(&pointer).map_err(io(&pointer))?;
    }
    match content.file_name().filter(|_| linked) {
        Some(etag) => {
            let blobs = root.join("blobs");
            std::fs::create_dir_all(&blobs).map_err(io(&blobs))?;
            let blob = blobs.join(etag);
            std::fs::rename(&content, &blob).map_err(io(&blob))?;
            link_blob(&blob, etag, file.path, &pointer).map_err(io(&pointer))?;
            let _ = std::fs::remove_file(staged);
        }
        None => std::fs::rename(&content, &pointer).map_err(io(&pointer))?,
    }
    let reference = root.join("refs").join(spec.revision);
    if let Some(parent) = reference.parent() {
        std::fs::create_dir_all(parent).map_err(io(parent))?;
    }
    std::fs::write(&reference, commit.as_bytes()).map_err(io(&reference))
}

/// Points the snapshot entry `pointer` (of the repository file `file`) at `blobs/<etag>` with a
/// relative link, as the Python cache does.
#[cfg(unix)]
fn link_blob(_blob: &Path, etag: &std::ffi::OsStr, file: &str, pointer: &Path) -> std::io::Result<()> {
    // From `snapshots/<commit>/<dirs of file>/` up to the model's folder.
    let mut target = PathBuf::new();
    for _ in 0..2 + file.matches('/').count() {
        target.push("..");
    }
    target.push("blobs");
    target.push(etag);
    std::os::unix::fs::symlink(target, pointer)
}

/// Where links are not available the file itself goes into the snapshot (as the Python cache
/// does without symlink rights).
#[cfg(not(unix))]
fn link_blob(blob: &Path, _etag: &std::ffi::OsStr, _file: &str, pointer: &Path) -> std::io::Result<()> {
    std::fs::rename(blob, pointer)
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

/// The files of `spec` not in the snapshot `refs/<revision>` names, else (no ref file) in the
/// snapshot named like the revision (a pinned commit); all of them if there is neither.
fn missing_in_current_snapshot(cache: &Path, spec: &ModelSpec) -> Vec<ModelFile> {
    let snapshots = cache.join(spec.cache_folder()).join("snapshots");
    let dir = read_ref(cache, spec)
        .ok()
        .flatten()
        .map(|c| snapshots.join(c))
        .or_else(|| Some(snapshots.join(spec.revision)).filter(|d| d.is_dir()));
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

    /// Digests computed elsewhere (FIPS 180-2 examples), not by this code.
    #[test]
    fn sha256_of_known_inputs() {
        assert_eq!(
            sha256_reader(&b"abc"[..]).unwrap(),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(
            sha256_reader(&b""[..]).unwrap(),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
        // Longer than the read buffer: 1 000 000 times `a`.
        let million = vec![b'a'; 1_000_000];
        let t = tempfile::tempdir().unwrap();
        let p = t.path().join("a");
        write(&p, &million);
        assert_eq!(
            sha256_file(&p).unwrap(),
            "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0"
        );
        assert!(matches!(
            sha256_file(&t.path().join("absent")),
            Err(HubError::Io { .. })
        ));
    }

    #[test]
    fn pixlrelight_is_registered_at_a_pinned_commit() {
        let spec = lookup("pixlrelight").unwrap();
        assert_eq!(spec.repo, "mlfarinha/pixlrelight");
        assert_eq!(spec.revision, "5def370459c15ee36c524068bb8338b3f6c6d6c0");
        assert_eq!(spec.licence, "CC BY-NC 4.0 — non-commercial use only");
        assert_eq!(spec.licence_url, "https://huggingface.co/mlfarinha/pixlrelight");
        assert_eq!(spec.cache_folder(), "models--mlfarinha--pixlrelight");
        let files: Vec<_> = spec.files.iter().map(|f| (f.path, f.sha256)).collect();
        assert_eq!(
            files,
            [
                (
                    "config.yaml",
                    Some("a3ef2cada8a223aee15b2e85d6627980962ea5446242d0d8ec24791ec2e21021")
                ),
                (
                    "model.safetensors",
                    Some("69c2bd11c2f272754f7080bc33e4b049fd334ea5d596df0c475f51c93699710e")
                ),
            ]
        );
        // 641 M f32 parameters.
        assert!((2_500_000_000..2_600_000_000).contains(&spec.approx_bytes()));
        // Every pinned digest in the registry is 64 lowercase hex digits; the other models pin none.
        for m in REGISTRY {
            for f in m.files {
                if let Some(d) = f.sha256 {
                    assert!(
                        d.len() == 64 && d.bytes().all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b)),
                        "{}: {}",
                        m.name,
                        f.path
                    );
                } else {
                    assert_ne!(m.name, "pixlrelight");
                }
            }
        }
    }

    /// A cache holding the pinned commit's snapshot without a ref file (as the Python tools
    /// write it for a commit revision): found, and only the absent file counts as missing.
    #[test]
    fn a_pinned_commit_is_found_without_a_ref() {
        let t = tempfile::tempdir().unwrap();
        let spec = lookup("pixlrelight").unwrap();
        let snap = fake_cache(t.path(), spec, spec.revision, &["config.yaml"], false);
        assert_eq!(missing_in_current_snapshot(t.path(), spec), vec![spec.files[1]]);
        write(&snap.join("model.safetensors"), b"w");
        let hub = Hub::new(HubOptions {
            hf_cache: Some(t.path().to_path_buf()),
            offline: true,
            ..Default::default()
        });
        assert_eq!(hub.locate(spec).unwrap().map(|r| r.dir), Some(snap));
    }

    /// Counts the files whose digest is computed.
    #[derive(Default)]
    struct Checked(Vec<(String, u64)>);
    impl FetchObserver for Checked {
        fn file_checking(&mut self, file: &str, bytes: u64) {
            self.0.push((file.to_string(), bytes));
        }
    }

    /// `verify` reads only the pinned files, accepts matching ones, names the first that differs.
    #[test]
    fn verify_checks_pinned_files_on_disk() {
        static FILES: &[ModelFile] = &[
            ModelFile::new("config.json", 2),
            ModelFile::pinned(
                "w.bin",
                3,
                "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad",
            ),
        ];
        static SPEC: ModelSpec = ModelSpec {
            name: "pinned-test",
            repo: "test/pinned",
            revision: "main",
            files: FILES,
            licence: "test",
            licence_url: "",
            purpose: "",
        };
        let t = tempfile::tempdir().unwrap();
        let dir = t.path().join("pinned-test");
        write(&dir.join("config.json"), b"{}");
        write(&dir.join("w.bin"), b"abc");
        let r = Resolved {
            spec: &SPEC,
            source: Source::ModelsDir(dir.clone()),
            dir: dir.clone(),
        };
        let mut seen = Checked::default();
        let checks = r.verify(&mut seen).unwrap();
        assert_eq!(seen.0, [("w.bin".to_string(), 3)]);
        assert_eq!(
            checks,
            [
                FileCheck {
                    file: "config.json",
                    path: dir.join("config.json"),
                    sha256: None
                },
                FileCheck {
                    file: "w.bin",
                    path: dir.join("w.bin"),
                    sha256: Some("ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad".into())
                },
            ]
        );
        write(&dir.join("w.bin"), b"");
        match r.verify(&mut Silent).unwrap_err() {
            HubError::CorruptFile {
                model,
                file,
                path,
                expected,
                found,
            } => {
                assert_eq!((model.as_str(), file.as_str()), ("pinned-test", "w.bin"));
                assert_eq!(path, dir.join("w.bin"));
                assert_eq!(
                    expected,
                    "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
                );
                assert_eq!(
                    found,
                    "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
                );
            }
            other => panic!("expected CorruptFile, got {other:?}"),
        }
    }
}
