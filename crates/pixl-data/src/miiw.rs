//! MIT Multi-Illumination Images in the Wild: `ROOT/<scene>/dir_<0..24>_mip<N>.(jpg|exr)`.
//! When both a JPEG and an EXR exist for a light direction, the JPEG (sRGB) is used. Images of a
//! scene are ordered by direction number (`dir_2` before `dir_10`). Test split: the scenes whose
//! names start with `everett` (the official one).
use super::{entry_with_cache, keep_pairable, non_empty, sorted_dir, Dataset, SceneEntry, Split};
use crate::error::Result;
use std::path::Path;

/// Mip level used unless another is asked for (1500×1000 in the published set).
pub const DEFAULT_MIP: u32 = 2;
/// Number of flash directions per scene.
pub const DIRECTIONS: u32 = 25;

pub struct Miiw {
    scenes: Vec<SceneEntry>,
}

impl Miiw {
    /// Every scene directory of `split` under `root`, sorted by name, with the images it holds at
    /// mip level `mip` (possibly fewer than two, or none).
    pub(crate) fn scan(root: &Path, mip: u32, split: Split) -> Result<Vec<SceneEntry>> {
        let mut scenes = Vec::new();
        for dir in sorted_dir(root)?.into_iter().filter(|p| p.is_dir()) {
            let Some(name) = dir.file_name().and_then(|n| n.to_str()).map(String::from) else {
                continue;
            };
            let is_test = name.starts_with("everett");
            if !split.keeps(is_test) {
                continue;
            }
            let mut images = Vec::new();
            for d in 0..DIRECTIONS {
                let jpg = dir.join(format!("dir_{d}_mip{mip}.jpg"));
                let exr = dir.join(format!("dir_{d}_mip{mip}.exr"));
                if jpg.is_file() {
                    images.push(entry_with_cache(jpg));
                } else if exr.is_file() {
                    images.push(entry_with_cache(exr));
                }
            }
            scenes.push(SceneEntry { name, images });
        }
        Ok(scenes)
    }

    pub fn open(root: &Path, split: Split, mip: u32) -> Result<Self> {
        let scenes = Self::scan(root, mip, split)?;
        Ok(Self {
            scenes: non_empty(root, split, keep_pairable(root, scenes))?,
        })
    }
}

impl Dataset for Miiw {
    fn kind(&self) -> &'static str {
        "miiw"
    }
    fn scenes(&self) -> &[SceneEntry] {
        &self.scenes
    }
}
