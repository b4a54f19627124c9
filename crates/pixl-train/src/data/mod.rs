//! Paired multi-illumination datasets (paper §3.3 "Training Data").
//!
//! A dataset is a list of *scenes*; each scene is a static view photographed (or rendered) under
//! several lights. Training draws two distinct images of one scene ([`sampler`]).
//!
//! Specs accepted by [`open`] (`KIND:ROOT`):
//! - `miiw:ROOT` (or `miiw@N:ROOT` for mip level `N`, default 2): `ROOT/<scene>/dir_<0..24>_mip<N>.(jpg|exr)`.
//!   Test split: every scene whose name starts with `everett`; train: the rest.
//! - `bigtime:ROOT`: `ROOT/<scene>/data/<frame>.(png|jpg)` or frames directly in `ROOT/<scene>/`;
//!   `*_mask.png` and `*_skymask.png` are ignored.
//! - `vidit:ROOT`: `ROOT/Image<NNN>_<temp>_<dir>.png`, one scene per `<NNN>`.
//! - `folder:ROOT`: `ROOT/<scene>/*.(png|jpg|jpeg|exr)`, excluding `*.intrinsics.exr`.
//! - `synth:ROOT`: the output of `pixl synth` (`ROOT/scenes.json` + `ROOT/<scene>/*.png` each with
//!   its exact `*.intrinsics.exr`).
//!
//! Splits for the datasets without an official one (BigTime, VIDIT, folder): if `ROOT/test.txt`
//! exists it lists the test scenes (one name a line); otherwise, over the sorted scene names, every
//! tenth scene (index 9, 19, …) is test. Synthetic sets carry their split in `scenes.json`.
//!
//! Scenes are sorted by name and images within a scene by file name, so the order is
//! deterministic. Scenes with fewer than two images cannot form a pair and are skipped (with a
//! warning).
//!
//! **Target intrinsics** ([`load_intrinsics`]), in order: the entry's exact renderer intrinsics
//! (synthetic sets), else the cached file `<image stem>.intrinsics.exr` beside the image (e.g.
//! `scene/dir_3_mip2.jpg` → `scene/dir_3_mip2.intrinsics.exr`; any external decomposer can fill
//! this cache), else an error saying how to produce it.
use crate::error::{Result, TrainError};
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;
use std::path::{Path, PathBuf};

mod bigtime;
pub mod folder;
mod miiw;
pub mod sampler;
mod vidit;

pub use bigtime::BigTime;
pub use folder::{Folder, Synth};
pub use miiw::Miiw;
pub use sampler::{Sample, Sampler, SamplerConfig};
pub use vidit::Vidit;

/// Which scenes of a dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Test,
    All,
}

impl Split {
    fn keeps(self, is_test: bool) -> bool {
        match self {
            Split::All => true,
            Split::Test => is_test,
            Split::Train => !is_test,
        }
    }
}

impl std::str::FromStr for Split {
    type Err = TrainError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "train" => Ok(Split::Train),
            "test" => Ok(Split::Test),
            "all" => Ok(Split::All),
            _ => Err(TrainError::Config(format!(
                "unknown split {s:?} (expected train, test or all)"
            ))),
        }
    }
}

/// One image of a scene and, when known, its exact/cached target intrinsics file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ImageEntry {
    pub image: PathBuf,
    pub intrinsics: Option<PathBuf>,
}

/// One static scene under several lights.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SceneEntry {
    pub name: String,
    pub images: Vec<ImageEntry>,
}

/// A paired multi-illumination dataset: scenes, each with ≥ 2 images, sorted.
pub trait Dataset: Send + Sync {
    /// `"miiw"`, `"bigtime"`, `"vidit"`, `"folder"` or `"synth"`.
    fn kind(&self) -> &'static str;
    fn scenes(&self) -> &[SceneEntry];
}

/// Opens a dataset from a `KIND:ROOT` spec (see the module docs).
pub fn open(spec: &str, split: Split) -> Result<Box<dyn Dataset>> {
    let bad = |reason: &str| TrainError::Spec {
        spec: spec.to_string(),
        reason: reason.to_string(),
    };
    let Some((kind, root)) = spec.split_once(':') else {
        return Err(bad(
            "expected KIND:ROOT with KIND one of miiw, bigtime, vidit, folder, synth",
        ));
    };
    if root.is_empty() {
        return Err(bad("empty root directory"));
    }
    let root = Path::new(root);
    let (kind, opt) = match kind.split_once('@') {
        Some((k, o)) => (k, Some(o)),
        None => (kind, None),
    };
    if opt.is_some() && kind != "miiw" {
        return Err(bad("only miiw takes an option (miiw@MIP:ROOT)"));
    }
    Ok(match kind {
        "miiw" => {
            let mip = match opt {
                Some(o) => o
                    .trim_start_matches("mip")
                    .parse::<u32>()
                    .map_err(|_| bad("mip level must be a number"))?,
                None => miiw::DEFAULT_MIP,
            };
            Box::new(Miiw::open(root, split, mip)?)
        }
        "bigtime" => Box::new(BigTime::open(root, split)?),
        "vidit" => Box::new(Vidit::open(root, split)?),
        "folder" => Box::new(Folder::open(root, split)?),
        "synth" => Box::new(Synth::open(root, split)?),
        _ => {
            return Err(bad(&format!(
                "unknown dataset kind {kind:?} (expected miiw, bigtime, vidit, folder, synth)"
            )))
        }
    })
}

/// The cached-intrinsics file name for an image: `<dir>/<stem>.intrinsics.exr`.
pub fn intrinsics_path(image: &Path) -> PathBuf {
    let stem = image.file_stem().and_then(|s| s.to_str()).unwrap_or("image");
    image.with_file_name(format!("{stem}.intrinsics.exr"))
}

/// Whether a file name is a cached C_T (`*.intrinsics.exr`), never a photograph.
pub fn is_intrinsics_file(path: &Path) -> bool {
    path.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.to_ascii_lowercase().ends_with(".intrinsics.exr"))
}

/// Loads an image as sRGB-encoded RGB in [0, 1]. PNG/JPEG are taken as stored; EXR is linear and
/// is converted with the sRGB transfer function after clipping to [0, 1].
pub fn load_image(path: &Path) -> Result<Image> {
    let img = pixl_core::io::read_rgb_finite(path)?;
    if pixl_core::io::extension(path) == "exr" {
        return Ok(img.map(|v| pixl_core::image::linear_to_srgb(v.clamp(0.0, 1.0))));
    }
    Ok(img)
}

/// Lists the entries of a directory, sorted by file name. Missing directory → error naming it.
pub(crate) fn sorted_dir(dir: &Path) -> Result<Vec<PathBuf>> {
    let rd = std::fs::read_dir(dir).map_err(|e| TrainError::io(dir, e))?;
    let mut out = Vec::new();
    for entry in rd {
        out.push(entry.map_err(|e| TrainError::io(dir, e))?.path());
    }
    out.sort();
    Ok(out)
}

/// An entry whose intrinsics field is filled when the cached file exists.
pub(crate) fn entry_with_cache(image: PathBuf) -> ImageEntry {
    let cached = intrinsics_path(&image);
    ImageEntry {
        intrinsics: cached.is_file().then_some(cached),
        image,
    }
}

/// Test split for datasets without an official one: `ROOT/test.txt` if present, else every tenth
/// sorted scene. `scenes` must be sorted by name.
pub(crate) fn default_split(root: &Path, scenes: Vec<SceneEntry>, split: Split) -> Result<Vec<SceneEntry>> {
    let list = root.join("test.txt");
    let test_names: Option<Vec<String>> = if list.is_file() {
        let text = std::fs::read_to_string(&list).map_err(|e| TrainError::io(&list, e))?;
        Some(
            text.lines()
                .map(str::trim)
                .filter(|l| !l.is_empty() && !l.starts_with('#'))
                .map(String::from)
                .collect(),
        )
    } else {
        None
    };
    Ok(scenes
        .into_iter()
        .enumerate()
        .filter(|(i, s)| {
            let is_test = match &test_names {
                Some(names) => names.iter().any(|n| n == &s.name),
                None => i % 10 == 9,
            };
            split.keeps(is_test)
        })
        .map(|(_, s)| s)
        .collect())
}

/// Drops scenes with fewer than two images (they cannot form a pair), with a warning.
pub(crate) fn keep_pairable(root: &Path, scenes: Vec<SceneEntry>) -> Vec<SceneEntry> {
    scenes
        .into_iter()
        .filter(|s| {
            let ok = s.images.len() >= 2;
            if !ok {
                tracing::warn!(
                    "{}: scene {} has {} image(s); skipped (a pair needs 2)",
                    root.display(),
                    s.name,
                    s.images.len()
                );
            }
            ok
        })
        .collect()
}

/// Errors when a dataset ends up with no scenes, naming the root and the split.
pub(crate) fn non_empty(root: &Path, split: Split, scenes: Vec<SceneEntry>) -> Result<Vec<SceneEntry>> {
    if scenes.is_empty() {
        return Err(TrainError::Dataset {
            root: root.to_owned(),
            reason: format!("no scene with at least two images in the {split:?} split"),
        });
    }
    Ok(scenes)
}

pub(crate) fn is_ldr(path: &Path) -> bool {
    matches!(pixl_core::io::extension(path).as_str(), "png" | "jpg" | "jpeg")
}

/// Where the target intrinsics of `entry` live (see the module docs for the rule), or an error
/// that says how to produce them.
pub fn intrinsics_file(entry: &ImageEntry) -> Result<PathBuf> {
    if let Some(p) = &entry.intrinsics {
        return Ok(p.clone());
    }
    let cached = intrinsics_path(&entry.image);
    if cached.is_file() {
        return Ok(cached);
    }
    Err(TrainError::MissingIntrinsics {
        image: entry.image.clone(),
        expected: cached,
    })
}

/// The target intrinsics of `entry` (exact renderer C_T for synthetic sets, else the cached
/// `<stem>.intrinsics.exr`), or [`TrainError::MissingIntrinsics`] saying how to produce them.
pub fn load_intrinsics(entry: &ImageEntry) -> Result<Ct> {
    let path = intrinsics_file(entry)?;
    Ok(pixl_intrinsics::ct::read_ct(&path)?)
}

/// The target intrinsics of `entry` as one 9-channel HWC image `[albedo; shading; residual]`.
pub fn load_intrinsics_image(entry: &ImageEntry) -> Result<Image> {
    Ok(ct_to_image(&load_intrinsics(entry)?))
}

/// A C_T as one 9-channel HWC image `[albedo RGB, shading RGB, residual RGB]`.
pub fn ct_to_image(ct: &Ct) -> Image {
    let (w, h) = (ct.width(), ct.height());
    let mut img = Image::new(w, h, 9);
    for (g, part) in ct.groups().iter().enumerate() {
        for (p, px) in part.data.chunks_exact(3).enumerate() {
            img.data[p * 9 + 3 * g..p * 9 + 3 * g + 3].copy_from_slice(px);
        }
    }
    img
}
