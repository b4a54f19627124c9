//! `pixl-data`: paired multi-illumination datasets (paper §3.3 "Training Data"), read by
//! training (`pixl-train`), evaluation (`pixl-eval`) and the CLI.
//!
//! A dataset is a list of *scenes*; each scene is a static view photographed (or rendered) under
//! several lights. Training draws two distinct images of one scene (`pixl_train::sampler`);
//! evaluation relights one image of a scene to the lighting of another.
//!
//! Specs accepted by [`open`] and [`list_images`] (`KIND:ROOT`):
//! - `miiw:ROOT` (or `miiw@N:ROOT` for mip level `N`, default 2): `ROOT/<scene>/dir_<0..24>_mip<N>.(jpg|exr)`.
//!   Test split: every scene whose name starts with `everett`; train: the rest.
//! - `bigtime:ROOT`: `ROOT/<scene>/data/<frame>.(png|jpg)` or frames directly in `ROOT/<scene>/`;
//!   `*_mask.png` and `*_skymask.png` are ignored.
//! - `vidit:ROOT`: `ROOT/Image<NNN>_<temp>_<dir>.png`, one scene per `<NNN>`.
//! - `folder:ROOT`: `ROOT/<scene>/*.(png|jpg|jpeg|exr)`, excluding `*.intrinsics.exr`.
//! - `synth:ROOT`: the output of `pixl synth` (`ROOT/scenes.json` + `ROOT/<scene>/*.png` each with
//!   its exact `*.intrinsics.exr`), or a folder of such outputs (`ROOT/<set>/scenes.json`; scenes
//!   named `<set>/<scene>`; sets without a manifest yet are left out, so a set that grows by
//!   new `pixl synth` runs is read again with what has finished since).
//!
//! Splits for the datasets without an official one (BigTime, VIDIT, folder): if `ROOT/test.txt`
//! exists it lists the test scenes (one name a line); otherwise, over the sorted scene names, every
//! tenth scene (index 9, 19, …) is test. Synthetic sets carry their split in `scenes.json`.
//!
//! Scenes are sorted by name and images within a scene by file name (MIIW: by light direction
//! number), so the order is deterministic. [`open`] skips scenes with fewer than two images (they
//! cannot form a pair; with a warning); [`scenes_all`] and [`list_images`] keep them: every image
//! of every split, in the same order.
//!
//! **Target intrinsics** ([`load_intrinsics`]), in order: the entry's exact renderer intrinsics
//! (synthetic sets), else the cached file `<image stem>.intrinsics.exr` beside the image
//! ([`ct_cache_path`]; e.g. `scene/dir_3_mip2.jpg` → `scene/dir_3_mip2.intrinsics.exr`; any
//! external decomposer can fill this cache), else an error saying how to produce it.
//! `pixl synth --coarse` also writes coarse-reconstruction C_T beside a target
//! ([`coarse_ct_path`]); every `*.intrinsics.exr` is a C_T, never an image of the dataset.
//!
//! Errors are [`DataError`]s; images are [`pixl_core::Image`] (sRGB RGB in [0, 1]), C_T are
//! [`Ct`] or 9-channel HWC images `[albedo; shading; residual]`.
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;
use std::path::{Path, PathBuf};

mod bigtime;
pub mod error;
pub mod folder;
mod miiw;
mod spec;
mod vidit;

pub use bigtime::BigTime;
pub use error::{DataError, Result};
pub use folder::{CoarseAlbedo, Folder, Synth, Tone};
pub use miiw::Miiw;
pub use spec::{list_images, open, scenes_all};
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
    type Err = DataError;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "train" => Ok(Split::Train),
            "test" => Ok(Split::Test),
            "all" => Ok(Split::All),
            _ => Err(DataError::UnknownSplit(s.to_string())),
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

/// Where the cached target intrinsics of an image live: `<dir>/<image stem>.intrinsics.exr`
/// beside it (`scene/dir_3_mip2.jpg` → `scene/dir_3_mip2.intrinsics.exr`).
pub fn ct_cache_path(image: &Path) -> PathBuf {
    let stem = image.file_stem().and_then(|s| s.to_str()).unwrap_or("image");
    image.with_file_name(format!("{stem}.intrinsics.exr"))
}

/// Where `pixl synth --coarse` writes the C_T of relighting `source` to the lighting of
/// `target` (both image paths of one scene) in the inference setting:
/// `<target stem>.from_<source stem>.intrinsics.exr` beside the target.
pub fn coarse_ct_path(source: &Path, target: &Path) -> PathBuf {
    let stem = |p: &Path| {
        p.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    target.with_file_name(format!("{}.from_{}.intrinsics.exr", stem(target), stem(source)))
}

/// Where `pixl synth --coarse` writes the path-traced render of that coarse scene under the
/// target's lights, shown as the set's images are: `<target stem>.from_<source stem>.path_traced.png`.
pub fn coarse_render_path(source: &Path, target: &Path) -> PathBuf {
    let ct = coarse_ct_path(source, target);
    let name = ct
        .file_name()
        .map(|n| n.to_string_lossy().replace(".intrinsics.exr", ".path_traced.png"))
        .unwrap_or_default();
    ct.with_file_name(name)
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
    let rd = std::fs::read_dir(dir).map_err(|e| DataError::io(dir, e))?;
    let mut out = Vec::new();
    for entry in rd {
        out.push(entry.map_err(|e| DataError::io(dir, e))?.path());
    }
    out.sort();
    Ok(out)
}

/// An entry whose intrinsics field is filled when the cached file exists.
pub(crate) fn entry_with_cache(image: PathBuf) -> ImageEntry {
    let cached = ct_cache_path(&image);
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
        let text = std::fs::read_to_string(&list).map_err(|e| DataError::io(&list, e))?;
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
        return Err(DataError::Dataset {
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
    let cached = ct_cache_path(&entry.image);
    if cached.is_file() {
        return Ok(cached);
    }
    Err(DataError::MissingIntrinsics {
        image: entry.image.clone(),
        expected: cached,
    })
}

/// The target intrinsics of `entry` (exact renderer C_T for synthetic sets, else the cached
/// `<stem>.intrinsics.exr`), or [`DataError::MissingIntrinsics`] saying how to produce them.
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ct_cache_path_is_beside_the_image() {
        assert_eq!(
            ct_cache_path(Path::new("scene/dir_3_mip2.jpg")),
            Path::new("scene/dir_3_mip2.intrinsics.exr")
        );
        assert_eq!(
            coarse_ct_path(Path::new("s/light_0.png"), Path::new("s/light_1.png")),
            Path::new("s/light_1.from_light_0.intrinsics.exr")
        );
    }
}
