//! BigTime time-lapses: `ROOT/<scene>/data/<frame>.(png|jpg)`, or frames directly in
//! `ROOT/<scene>/`. Masks (`*_mask.png`, `*_skymask.png`) and cached intrinsics are not frames.
//! Scenes and frames are sorted by name (frames under `data/` first); no official split.
use super::{default_split, entry_with_cache, is_intrinsics_file, is_ldr, keep_pairable, non_empty, sorted_dir};
use super::{Dataset, SceneEntry, Split};
use crate::error::Result;
use std::path::{Path, PathBuf};

pub struct BigTime {
    scenes: Vec<SceneEntry>,
}

fn is_frame(path: &Path) -> bool {
    let name = path
        .file_name()
        .and_then(|n| n.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    path.is_file()
        && is_ldr(path)
        && !name.ends_with("_mask.png")
        && !name.ends_with("_skymask.png")
        && !is_intrinsics_file(path)
}

impl BigTime {
    /// Every scene directory under `root`, sorted by name, with its frames (possibly fewer than two).
    pub(crate) fn scan(root: &Path) -> Result<Vec<SceneEntry>> {
        let mut scenes = Vec::new();
        for dir in sorted_dir(root)?.into_iter().filter(|p| p.is_dir()) {
            let Some(name) = dir.file_name().and_then(|n| n.to_str()).map(String::from) else {
                continue;
            };
            let data = dir.join("data");
            let mut frames: Vec<PathBuf> = Vec::new();
            if data.is_dir() {
                frames.extend(sorted_dir(&data)?.into_iter().filter(|p| is_frame(p)));
            }
            frames.extend(sorted_dir(&dir)?.into_iter().filter(|p| is_frame(p)));
            let images = frames.into_iter().map(entry_with_cache).collect();
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

impl Dataset for BigTime {
    fn kind(&self) -> &'static str {
        "bigtime"
    }
    fn scenes(&self) -> &[SceneEntry] {
        &self.scenes
    }
}
