//! VIDIT: `ROOT/Image<NNN>_<temp>_<dir>.png` (temperatures 2500–6500 K, directions N…NW), one
//! scene per `<NNN>`; the scene is named `Image<NNN>`. Scenes and images are sorted by name; no
//! official split.
use super::{default_split, entry_with_cache, keep_pairable, non_empty, sorted_dir, Dataset, SceneEntry, Split};
use crate::error::Result;
use std::collections::BTreeMap;
use std::path::Path;

pub struct Vidit {
    scenes: Vec<SceneEntry>,
}

/// `Image012_4500_NE.png` → `Some("Image012")`.
fn scene_of(file_name: &str) -> Option<String> {
    let stem = file_name.strip_suffix(".png")?;
    let mut parts = stem.split('_');
    let image = parts.next()?;
    let temp = parts.next()?;
    let dir = parts.next()?;
    let digits = image.strip_prefix("Image")?;
    let valid = !digits.is_empty()
        && digits.bytes().all(|b| b.is_ascii_digit())
        && temp.parse::<u32>().is_ok()
        && !dir.is_empty()
        && dir.bytes().all(|b| b.is_ascii_alphabetic())
        && parts.next().is_none();
    valid.then(|| image.to_string())
}

impl Vidit {
    /// Every scene under `root` (grouped by image number), sorted by name, with its images (possibly
    /// only one).
    pub(crate) fn scan(root: &Path) -> Result<Vec<SceneEntry>> {
        let mut groups: BTreeMap<String, Vec<_>> = BTreeMap::new();
        for path in sorted_dir(root)?.into_iter().filter(|p| p.is_file()) {
            let Some(scene) = path.file_name().and_then(|n| n.to_str()).and_then(scene_of) else {
                continue;
            };
            groups.entry(scene).or_default().push(entry_with_cache(path));
        }
        Ok(groups
            .into_iter()
            .map(|(name, images)| SceneEntry { name, images })
            .collect())
    }

    pub fn open(root: &Path, split: Split) -> Result<Self> {
        let scenes = default_split(root, keep_pairable(root, Self::scan(root)?), split)?;
        Ok(Self {
            scenes: non_empty(root, split, scenes)?,
        })
    }
}

impl Dataset for Vidit {
    fn kind(&self) -> &'static str {
        "vidit"
    }
    fn scenes(&self) -> &[SceneEntry] {
        &self.scenes
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn parses_vidit_names() {
        assert_eq!(super::scene_of("Image012_4500_NE.png").as_deref(), Some("Image012"));
        assert_eq!(super::scene_of("Image012_4500.png"), None);
        assert_eq!(super::scene_of("Image012_warm_NE.png"), None);
        assert_eq!(super::scene_of("Photo012_4500_NE.png"), None);
    }
}
