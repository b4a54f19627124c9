//! Dataset loaders on tiny fake trees: pairing, mip levels, splits, masks and cached intrinsics
//! excluded, cached C_T found, bad specs explained.
use pixl_core::exrio::{write_exr_channels, ExrChannels};
use pixl_core::{io::write_image, Image};
use pixl_data::{self as data, SceneEntry, Split};
use std::path::Path;

fn png(path: &Path, w: usize, h: usize, v: f32) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    write_image(
        path,
        &Image::from_fn(w, h, 3, |x, _, c| (v + 0.01 * (x + c) as f32).min(1.0)),
    )
    .unwrap();
}

fn names(ds: &dyn data::Dataset) -> Vec<String> {
    ds.scenes().iter().map(|s| s.name.clone()).collect()
}

fn files(s: &SceneEntry) -> Vec<String> {
    s.images
        .iter()
        .map(|e| e.image.file_name().unwrap().to_string_lossy().into_owned())
        .collect()
}

#[test]
fn miiw_pairs_mip_level_and_everett_split() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path();
    for scene in ["everett_kitchen1", "main_livingroom", "summer_bath"] {
        for d in [0, 1, 10, 24] {
            png(&r.join(scene).join(format!("dir_{d}_mip2.jpg")), 6, 4, 0.5);
            png(&r.join(scene).join(format!("dir_{d}_mip3.jpg")), 3, 2, 0.5);
        }
        png(&r.join(scene).join("materials_mip2.png"), 6, 4, 0.1);
    }
    // one scene with a single image cannot pair and is skipped
    png(&r.join("lonely").join("dir_0_mip2.jpg"), 6, 4, 0.5);
    let spec = format!("miiw:{}", r.display());
    let test = data::open(&spec, Split::Test).unwrap();
    assert_eq!(test.kind(), "miiw");
    assert_eq!(names(test.as_ref()), ["everett_kitchen1"]);
    let train = data::open(&spec, Split::Train).unwrap();
    assert_eq!(names(train.as_ref()), ["main_livingroom", "summer_bath"]);
    // sorted by direction number, not by string
    assert_eq!(
        files(&train.scenes()[0]),
        ["dir_0_mip2.jpg", "dir_1_mip2.jpg", "dir_10_mip2.jpg", "dir_24_mip2.jpg"]
    );
    let mip3 = data::open(&format!("miiw@3:{}", r.display()), Split::All).unwrap();
    assert_eq!(mip3.scenes().len(), 3);
    assert!(files(&mip3.scenes()[0]).iter().all(|f| f.ends_with("_mip3.jpg")));
}

#[test]
fn bigtime_ignores_masks_and_accepts_flat_scenes() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path();
    for f in ["a.jpg", "b.png", "a_mask.png", "b_skymask.png"] {
        png(&r.join("0001/data").join(f), 4, 4, 0.3);
    }
    for f in ["x.jpg", "y.jpg", "z.jpg"] {
        png(&r.join("0002").join(f), 4, 4, 0.3);
    }
    let ds = data::open(&format!("bigtime:{}", r.display()), Split::All).unwrap();
    assert_eq!(names(ds.as_ref()), ["0001", "0002"]);
    assert_eq!(files(&ds.scenes()[0]), ["a.jpg", "b.png"]);
    assert_eq!(files(&ds.scenes()[1]), ["x.jpg", "y.jpg", "z.jpg"]);
}

#[test]
fn vidit_groups_by_image_number() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path();
    for n in ["000", "001"] {
        for (t, d) in [(2500, "N"), (4500, "NE"), (6500, "W")] {
            png(&r.join(format!("Image{n}_{t}_{d}.png")), 4, 4, 0.2);
        }
    }
    png(&r.join("readme.png"), 4, 4, 0.2);
    let ds = data::open(&format!("vidit:{}", r.display()), Split::All).unwrap();
    assert_eq!(names(ds.as_ref()), ["Image000", "Image001"]);
    assert_eq!(
        files(&ds.scenes()[1]),
        ["Image001_2500_N.png", "Image001_4500_NE.png", "Image001_6500_W.png"]
    );
}

fn write_ct(path: &Path, w: usize, h: usize, f: impl Fn(usize, usize, usize) -> f32) {
    let mut ch = ExrChannels::new(w, h);
    for (c, name) in ["albedo", "shading", "residual"]
        .iter()
        .flat_map(|g| ["R", "G", "B"].map(|x| format!("{g}.{x}")))
        .enumerate()
    {
        ch.push(name, (0..w * h).map(|p| f(p % w, p / w, c)).collect()).unwrap();
    }
    write_exr_channels(path, &ch).unwrap();
}

#[test]
fn folder_split_excludes_intrinsics_and_finds_cache() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path();
    for s in 0..12 {
        let sd = r.join(format!("s{s:02}"));
        png(&sd.join("l0.png"), 4, 4, 0.1);
        png(&sd.join("l1.png"), 4, 4, 0.2);
        write_ct(&sd.join("l1.intrinsics.exr"), 4, 4, |x, y, c| {
            (x + 10 * y + 100 * c) as f32
        });
    }
    let spec = format!("folder:{}", r.display());
    let all = data::open(&spec, Split::All).unwrap();
    assert_eq!(all.scenes().len(), 12);
    assert_eq!(files(&all.scenes()[0]), ["l0.png", "l1.png"]);
    let test = data::open(&spec, Split::Test).unwrap();
    assert_eq!(names(test.as_ref()), ["s09"]); // every tenth sorted scene
    assert_eq!(data::open(&spec, Split::Train).unwrap().scenes().len(), 11);
    std::fs::write(r.join("test.txt"), "s03\n# comment\ns07\n").unwrap();
    assert_eq!(names(data::open(&spec, Split::Test).unwrap().as_ref()), ["s03", "s07"]);

    let s0 = &all.scenes()[0];
    assert_eq!(
        s0.images[1].intrinsics.as_deref(),
        Some(r.join("s00/l1.intrinsics.exr").as_path())
    );
    let ct = data::load_intrinsics_image(&s0.images[1]).unwrap();
    assert_eq!((ct.width, ct.height, ct.channels), (4, 4, 9));
    assert_eq!(ct.get(3, 2, 7), (3 + 20 + 700) as f32);
    let err = data::load_intrinsics_image(&s0.images[0]).unwrap_err().to_string();
    assert!(
        err.contains("l0.png") && err.contains("l0.intrinsics.exr") && err.contains("pixl compose"),
        "{err}"
    );
}

#[test]
fn bad_specs_are_explained() {
    for spec in ["nonsense", "foo:/tmp", "miiw:", "vidit@2:/tmp"] {
        let e = data::open(spec, Split::All).err().expect(spec).to_string();
        assert!(e.contains(spec), "{e}");
    }
    let e = data::open("folder:/definitely/not/here", Split::All)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("/definitely/not/here"), "{e}");
}

/// Writes a minimal `pixl synth` output at `root`: `scenes` scenes of two lightings each, scene
/// `i` test when `test(i)`.
fn fake_synth_set(root: &Path, scenes: usize, test: impl Fn(usize) -> bool) {
    let mut records = Vec::new();
    for i in 0..scenes {
        let name = format!("scene{i:04}");
        let mut images = Vec::new();
        for k in 0..2 {
            let (img, ct) = (
                format!("{name}/light_{k}.png"),
                format!("{name}/light_{k}.intrinsics.exr"),
            );
            png(&root.join(&img), 4, 4, 0.1 * k as f32);
            write_ct(&root.join(&ct), 4, 4, |_, _, c| c as f32);
            images.push(serde_json::json!({"image": img, "intrinsics": ct, "lighting": "sun"}));
        }
        let split = if test(i) { "test" } else { "train" };
        records.push(serde_json::json!({"name": name, "split": split, "images": images}));
    }
    let manifest = serde_json::json!({"version": 1, "seed": 0, "size": 4, "spp": 1, "scenes": records});
    std::fs::write(root.join("scenes.json"), manifest.to_string()).unwrap();
}

/// A folder of `pixl synth` outputs reads as one set whose scenes are prefixed by their
/// subfolder; a subfolder still being written (no manifest) is left out until it has one.
#[test]
fn synth_folder_of_sets_grows_as_sets_finish() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path();
    let spec = format!("synth:{}", r.display());
    let e = data::open(&spec, Split::All).err().unwrap().to_string();
    assert!(e.contains("scenes.json"), "{e}");

    fake_synth_set(&r.join("b"), 2, |i| i == 1);
    png(&r.join("a/scene0000/light_0.png"), 4, 4, 0.3); // a set at work: no manifest yet
    assert_eq!(
        names(data::open(&spec, Split::All).unwrap().as_ref()),
        ["b/scene0000", "b/scene0001"]
    );
    assert_eq!(
        names(data::open(&spec, Split::Train).unwrap().as_ref()),
        ["b/scene0000"]
    );

    fake_synth_set(&r.join("a"), 1, |_| false);
    let all = data::open(&spec, Split::All).unwrap();
    assert_eq!(names(all.as_ref()), ["a/scene0000", "b/scene0000", "b/scene0001"]);
    assert_eq!(all.scenes()[0].images[1].image, r.join("a/scene0000/light_1.png"));
    assert_eq!(
        all.scenes()[2].images[0].intrinsics.as_deref(),
        Some(r.join("b/scene0001/light_0.intrinsics.exr").as_path())
    );
    assert_eq!(names(data::open(&spec, Split::Test).unwrap().as_ref()), ["b/scene0001"]);
}
