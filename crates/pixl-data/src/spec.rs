//! The `KIND:ROOT` dataset spec (the kinds and layouts are listed in the crate docs): parsing it
//! once, then either opening the scenes of one split that can form pairs ([`open`], for training
//! and evaluation) or listing every scene and image of every split ([`scenes_all`],
//! [`list_images`], for commands that process each image once). Both orders are deterministic
//! and agree: scenes by name, images as each loader sorts them.
use crate::error::{DataError, Result};
use crate::{miiw, BigTime, Dataset, Folder, Miiw, SceneEntry, Split, Synth, Vidit};
use std::path::{Path, PathBuf};

/// A parsed `KIND:ROOT` spec.
#[derive(Clone, Debug, PartialEq, Eq)]
enum Spec<'a> {
    Miiw { root: &'a Path, mip: u32 },
    BigTime(&'a Path),
    Vidit(&'a Path),
    Folder(&'a Path),
    Synth(&'a Path),
}

impl<'a> Spec<'a> {
    fn parse(spec: &'a str) -> Result<Self> {
        let bad = |reason: &str| DataError::Spec {
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
                Spec::Miiw { root, mip }
            }
            "bigtime" => Spec::BigTime(root),
            "vidit" => Spec::Vidit(root),
            "folder" => Spec::Folder(root),
            "synth" => Spec::Synth(root),
            _ => {
                return Err(bad(&format!(
                    "unknown dataset kind {kind:?} (expected miiw, bigtime, vidit, folder, synth)"
                )))
            }
        })
    }

    fn root(&self) -> &'a Path {
        match *self {
            Spec::Miiw { root, .. }
            | Spec::BigTime(root)
            | Spec::Vidit(root)
            | Spec::Folder(root)
            | Spec::Synth(root) => root,
        }
    }
}

/// Opens a dataset from a `KIND:ROOT` spec (see the module docs): the scenes of `split` that
/// hold at least two images; an error if there are none.
pub fn open(spec: &str, split: Split) -> Result<Box<dyn Dataset>> {
    Ok(match Spec::parse(spec)? {
        Spec::Miiw { root, mip } => Box::new(Miiw::open(root, split, mip)?),
        Spec::BigTime(root) => Box::new(BigTime::open(root, split)?),
        Spec::Vidit(root) => Box::new(Vidit::open(root, split)?),
        Spec::Folder(root) => Box::new(Folder::open(root, split)?),
        Spec::Synth(root) => Box::new(Synth::open(root, split)?),
    })
}

/// Every scene of the dataset named by `spec` that holds at least one image: all splits, scenes
/// with a single image included, in [`open`]'s order (sorted by scene name, images within a
/// scene as [`open`] orders them). An error if the dataset holds no image at all.
pub fn scenes_all(spec: &str) -> Result<Vec<SceneEntry>> {
    let parsed = Spec::parse(spec)?;
    let scenes = match parsed {
        Spec::Miiw { root, mip } => Miiw::scan(root, mip, Split::All)?,
        Spec::BigTime(root) => BigTime::scan(root)?,
        Spec::Vidit(root) => Vidit::scan(root)?,
        Spec::Folder(root) => Folder::scan(root)?,
        Spec::Synth(root) => Synth::scan(root, Split::All)?,
    };
    let scenes: Vec<SceneEntry> = scenes.into_iter().filter(|s| !s.images.is_empty()).collect();
    if scenes.is_empty() {
        return Err(DataError::Dataset {
            root: parsed.root().to_owned(),
            reason: "no image found".into(),
        });
    }
    Ok(scenes)
}

/// Every image of the dataset named by `spec` ([`scenes_all`], flattened): all splits, single
/// images included, each once, in a deterministic order.
pub fn list_images(spec: &str) -> Result<Vec<PathBuf>> {
    Ok(scenes_all(spec)?
        .into_iter()
        .flat_map(|s| s.images)
        .map(|e| e.image)
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Empty files are enough: listing never decodes an image.
    fn touch(root: &Path, rel: &str) {
        let path = root.join(rel);
        std::fs::create_dir_all(path.parent().expect("a file under root")).expect("mkdir");
        std::fs::write(&path, b"").expect("write");
    }

    fn rel(root: &Path, images: &[PathBuf]) -> Vec<String> {
        images
            .iter()
            .map(|p| p.strip_prefix(root).expect("under root").to_string_lossy().into_owned())
            .collect()
    }

    #[test]
    fn list_images_covers_every_split_and_single_image_scenes_of_miiw() {
        let dir = tempfile::tempdir().expect("tempdir");
        let r = dir.path();
        for f in [
            "dir_10_mip2.jpg",
            "dir_2_mip2.jpg",
            "dir_2_mip2.intrinsics.exr",
            "dir_3_mip3.jpg",
        ] {
            touch(r, &format!("main_room/{f}"));
        }
        touch(r, "everett_hall/dir_0_mip2.exr");
        touch(r, "everett_hall/dir_1_mip2.jpg");
        touch(r, "lonely/dir_5_mip2.jpg");
        touch(r, "materials/materials_mip2.png");
        let spec = format!("miiw:{}", r.display());
        let want = [
            "everett_hall/dir_0_mip2.exr",
            "everett_hall/dir_1_mip2.jpg",
            "lonely/dir_5_mip2.jpg",
            "main_room/dir_2_mip2.jpg",
            "main_room/dir_10_mip2.jpg",
        ];
        assert_eq!(rel(r, &list_images(&spec).expect("list")), want);
        // `open` sees the same images minus the unpairable scene, split by split.
        let test = open(&spec, Split::Test).expect("test split");
        assert_eq!(test.scenes().len(), 1);
        let scenes = scenes_all(&spec).expect("scenes");
        let names: Vec<&str> = scenes.iter().map(|s| s.name.as_str()).collect();
        assert_eq!(names, ["everett_hall", "lonely", "main_room"]);
        assert_eq!(
            scenes[2].images[0].intrinsics.as_deref(),
            Some(r.join("main_room/dir_2_mip2.intrinsics.exr").as_path())
        );
        let mip3 = list_images(&format!("miiw@3:{}", r.display())).expect("mip 3");
        assert_eq!(rel(r, &mip3), ["main_room/dir_3_mip3.jpg"]);
    }

    #[test]
    fn list_images_covers_every_scene_of_a_folder_and_refuses_an_empty_one() {
        let dir = tempfile::tempdir().expect("tempdir");
        let r = dir.path();
        for s in 0..11 {
            touch(r, &format!("s{s:02}/b.png"));
            touch(r, &format!("s{s:02}/a.jpg"));
        }
        touch(r, "s03/a.intrinsics.exr");
        touch(r, "s03/notes.txt");
        touch(r, "single/only.exr");
        std::fs::create_dir_all(r.join("empty")).expect("mkdir");
        let spec = format!("folder:{}", r.display());
        let images = list_images(&spec).expect("list");
        assert_eq!(images.len(), 23);
        assert_eq!(rel(r, &images[..2]), ["s00/a.jpg", "s00/b.png"]);
        assert_eq!(rel(r, &images[22..]), ["single/only.exr"]);
        // every split together: the test scene s09 is listed too, and the order does not change
        assert!(images.contains(&r.join("s09/a.jpg")));
        assert_eq!(list_images(&spec).expect("again"), images);

        let none = tempfile::tempdir().expect("tempdir");
        std::fs::create_dir_all(none.path().join("scene")).expect("mkdir");
        let err = list_images(&format!("folder:{}", none.path().display()))
            .expect_err("no image")
            .to_string();
        assert!(
            err.contains("no image found") && err.contains(&none.path().display().to_string()),
            "{err}"
        );
        let err = list_images("folder").expect_err("bad spec").to_string();
        assert!(err.starts_with("dataset spec \"folder\""), "{err}");
    }
}
