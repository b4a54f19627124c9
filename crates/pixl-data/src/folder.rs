//! Generic folders (`ROOT/<scene>/*.(png|jpg|jpeg|exr)`, minus `*.intrinsics.exr`) and the
//! synthetic sets written by `pixl synth` (same layout plus `ROOT/scenes.json`, whose entries
//! carry the split and point at the exact renderer intrinsics of every image). This module owns
//! the manifest's format ([`SynthManifest`]); `pixl_train::synth` writes it.
//!
//! Folders: scenes and images sorted by name, no official split. Synthetic sets: scenes sorted
//! by name, images in manifest order; a manifest entry whose files are missing is an error.
use super::{default_split, entry_with_cache, is_intrinsics_file, keep_pairable, non_empty, sorted_dir};
use super::{Dataset, ImageEntry, SceneEntry, Split};
use crate::error::{DataError, Result};
use std::path::Path;

pub struct Folder {
    scenes: Vec<SceneEntry>,
}

fn is_image(path: &Path) -> bool {
    path.is_file()
        && matches!(pixl_core::io::extension(path).as_str(), "png" | "jpg" | "jpeg" | "exr")
        && !is_intrinsics_file(path)
}

impl Folder {
    /// Every scene directory under `root`, sorted by name, with its images (possibly fewer than two).
    pub(crate) fn scan(root: &Path) -> Result<Vec<SceneEntry>> {
        let mut scenes = Vec::new();
        for dir in sorted_dir(root)?.into_iter().filter(|p| p.is_dir()) {
            let Some(name) = dir.file_name().and_then(|n| n.to_str()).map(String::from) else {
                continue;
            };
            let images = sorted_dir(&dir)?
                .into_iter()
                .filter(|p| is_image(p))
                .map(entry_with_cache)
                .collect();
            scenes.push(SceneEntry { name, images });
        }
        Ok(scenes)
    }

    pub fn open(root: &Path, split: Split) -> Result<Self> {
        let scenes = default_split(root, keep_pairable(root, Self::scan(root)?), split)?;
        Ok(Self {
            scenes: non_empty(root, split, scenes)?,
        })
    }
}

impl Dataset for Folder {
    fn kind(&self) -> &'static str {
        "folder"
    }
    fn scenes(&self) -> &[SceneEntry] {
        &self.scenes
    }
}

/// The manifest `pixl synth` writes as `ROOT/scenes.json`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SynthManifest {
    /// Format version (1).
    pub version: u32,
    pub seed: u64,
    pub size: usize,
    pub spp: u32,
    /// With `pixl synth --coarse`: where the coarse reconstruction's albedo came from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coarse_albedo: Option<CoarseAlbedo>,
    /// The scene generator (`photo` or `boxes`); absent in sets made before there were two
    /// (those are `boxes`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub style: Option<String>,
    /// How the images show the renders; absent: [`Tone::Reinhard`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tone: Option<Tone>,
    /// Samples per pixel of the images when they differ from `spp` (that of the C_T passes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_spp: Option<u32>,
    pub scenes: Vec<SynthSceneRecord>,
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SynthSceneRecord {
    pub name: String,
    pub split: Split,
    /// One per lighting: paths relative to ROOT.
    pub images: Vec<SynthImageRecord>,
}

#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct SynthImageRecord {
    pub image: String,
    pub intrinsics: String,
    /// A short description of the lighting (kinds of lights used).
    pub lighting: String,
}

/// Where the coarse reconstruction of `pixl synth --coarse` takes its albedo texture from.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum CoarseAlbedo {
    /// The source render's `DiffCol` pass: a perfect albedo estimator.
    #[default]
    Diffcol,
    /// The source image itself (`pixl reconstruct` without `--albedo`): no estimator, the source's
    /// shading and shadows stay in the texture.
    Photo,
    /// `DiffCol` with an estimator's errors drawn per source: part of the source's shading left
    /// in, blur, a tint (`pixl_train::synth::estimated`).
    Estimated,
}

/// How a synthetic set shows its linear renders as images.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Tone {
    /// Reinhard with auto-exposure ([`pixl_core::image::tonemap_reinhard`]).
    #[default]
    Reinhard,
    /// A camera's: auto-exposure, filmic curve ([`pixl_core::image::tonemap_camera`]).
    Camera,
}

pub const MANIFEST: &str = "scenes.json";

pub struct Synth {
    scenes: Vec<SceneEntry>,
}

/// Where the coarse reconstructions of the `pixl synth --coarse` set at `root` took their albedo
/// from, as its manifest records it (`None`: no manifest, an unreadable one, or a set made before
/// the field existed or without `--coarse`).
pub fn synth_coarse_albedo(root: &Path) -> Option<CoarseAlbedo> {
    let text = std::fs::read_to_string(root.join(MANIFEST)).ok()?;
    serde_json::from_str::<SynthManifest>(&text).ok()?.coarse_albedo
}

impl Synth {
    /// The scenes of `split` listed in the manifest under `root`, sorted by name, each with every
    /// image it lists (possibly fewer than two); an error if a listed file is missing.
    ///
    /// A `root` without a manifest is read as a *folder of sets*: every subfolder that holds a
    /// `scenes.json` is one `pixl synth` output, its scenes named `<subfolder>/<scene>` (sorted
    /// by subfolder, then scene). Subfolders without a manifest yet — a `pixl synth` still at
    /// work — are left out, so reading the folder again later finds the sets finished since.
    pub(crate) fn scan(root: &Path, split: Split) -> Result<Vec<SceneEntry>> {
        if !root.join(MANIFEST).exists() && root.is_dir() {
            let sets: Vec<_> = sorted_dir(root)?
                .into_iter()
                .filter(|p| p.join(MANIFEST).is_file())
                .collect();
            if sets.is_empty() {
                return Err(DataError::Dataset {
                    root: root.to_owned(),
                    reason: format!(
                        "no {MANIFEST}: neither a `pixl synth` output nor a folder of them (none of its \
                         subfolders has a finished set yet)"
                    ),
                });
            }
            let mut scenes = Vec::new();
            for set in sets {
                let prefix = set.file_name().and_then(|n| n.to_str()).unwrap_or("set").to_string();
                for mut s in Self::scan_set(&set, split)? {
                    s.name = format!("{prefix}/{}", s.name);
                    scenes.push(s);
                }
            }
            return Ok(scenes);
        }
        Self::scan_set(root, split)
    }

    /// One `pixl synth` output (see [`Synth::scan`]).
    fn scan_set(root: &Path, split: Split) -> Result<Vec<SceneEntry>> {
        let path = root.join(MANIFEST);
        let text = std::fs::read_to_string(&path).map_err(|e| DataError::io(&path, e))?;
        let manifest: SynthManifest = serde_json::from_str(&text).map_err(|e| DataError::File {
            path: path.clone(),
            reason: format!("not a `pixl synth` manifest: {e}"),
        })?;
        let mut records = manifest.scenes;
        records.sort_by(|a, b| a.name.cmp(&b.name));
        let mut scenes = Vec::new();
        for rec in records.into_iter().filter(|r| split.keeps(r.split == Split::Test)) {
            let mut images = Vec::new();
            for im in rec.images {
                let (image, intrinsics) = (root.join(&im.image), root.join(&im.intrinsics));
                if !image.is_file() || !intrinsics.is_file() {
                    return Err(DataError::File {
                        path: path.clone(),
                        reason: format!(
                            "scene {} lists {} / {} which do not exist",
                            rec.name, im.image, im.intrinsics
                        ),
                    });
                }
                images.push(ImageEntry {
                    image,
                    intrinsics: Some(intrinsics),
                });
            }
            scenes.push(SceneEntry { name: rec.name, images });
        }
        Ok(scenes)
    }

    pub fn open(root: &Path, split: Split) -> Result<Self> {
        let scenes = Self::scan(root, split)?;
        Ok(Self {
            scenes: non_empty(root, split, keep_pairable(root, scenes))?,
        })
    }
}

impl Dataset for Synth {
    fn kind(&self) -> &'static str {
        "synth"
    }
    fn scenes(&self) -> &[SceneEntry] {
        &self.scenes
    }
}
