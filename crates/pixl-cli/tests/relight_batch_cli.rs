//! `pixl relight` over many photos, through the real binary: a folder of 12 photos with depth maps
//! relit with one model load, outputs under the same relative names, each the single-photo
//! command's output bit for bit; a run killed part-way resumes with the rest only; shards are
//! disjoint and cover everything (also as a local "cluster" of processes reading
//! `JOB_COMPLETION_INDEX`); a corrupt photo is reported and the others done; a manifest gives
//! each photo its own lighting.
mod common;
use common::{cmd, pixl_q, s, write_depth, write_file, write_image};
use pixl_core::Image;
use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Stdio;

/// 12 photos (`a00.png` … `a07.png`, `sub/b00.png` … `sub/b03.png`) of `w × h` and their depth
/// maps under `depths/` with the same relative names (`.exr`).
fn shoot(dir: &Path, w: usize, h: usize) -> (PathBuf, PathBuf) {
    let (shots, depths) = (dir.join("shots"), dir.join("depths"));
    std::fs::create_dir_all(shots.join("sub")).unwrap();
    std::fs::create_dir_all(depths.join("sub")).unwrap();
    for i in 0..12 {
        let rel = if i < 8 {
            format!("a{i:02}")
        } else {
            format!("sub/b{:02}", i - 8)
        };
        let img = Image::from_fn(w, h, 3, |x, y, c| {
            (0.15 + 0.04 * i as f32 + 0.4 * x as f32 / w as f32 + 0.1 * c as f32 + 0.05 * ((x / 3 + y / 3) % 2) as f32)
                .min(1.0)
        });
        write_image(&shots.join(format!("{rel}.png")), &img);
        write_depth(&depths.join(format!("{rel}.exr")), w, h, |x, _| {
            2.5 + (x + i) as f32 / w as f32
        });
    }
    (shots, depths)
}

/// The images under `dir` (relative paths), log and hidden files aside.
fn outputs(dir: &Path) -> BTreeSet<String> {
    common::tree(dir)
        .into_iter()
        .filter(|p| p.ends_with(".png") && !p.rsplit('/').next().unwrap_or("").starts_with('.'))
        .collect()
}

fn batch<'a>(shots: &'a Path, depths: &'a Path, out: &'a Path, extra: &[&'a str]) -> Vec<&'a str> {
    let base = [
        "relight",
        s(shots),
        "--depth-dir",
        s(depths),
        "--preset",
        "cool-side-flash",
        "--bounces",
        "1",
        "-o",
        s(out),
    ];
    let spp: &[&str] = if extra.contains(&"--spp") { &[] } else { &["--spp", "2"] };
    [&base[..], spp, extra].concat()
}

#[test]
fn a_folder_is_relit_with_one_model_load_as_each_photo_alone() {
    let dir = common::tempdir();
    let (shots, depths) = shoot(dir.path(), 24, 16);
    let out = dir.path().join("relit");
    let run = pixl_q(&batch(&shots, &depths, &out, &["--json"])).ok();
    let j = run.json();
    assert_eq!((j["total"].as_u64(), j["done"].as_u64()), (Some(12), Some(12)), "{j}");
    assert_eq!(j["network_loads"].as_u64(), Some(1), "{j}");
    let names = outputs(&out);
    assert_eq!(names.len(), 12, "{names:?}");
    assert!(names.contains("sub/b03.png") && names.contains("a00.png"), "{names:?}");
    // Each output is what the one-photo command writes.
    for rel in ["a03", "sub/b01"] {
        let one = dir.path().join(format!("{}.png", rel.replace('/', "_")));
        let photo = shots.join(format!("{rel}.png"));
        let depth = depths.join(format!("{rel}.exr"));
        pixl_q(&[
            "relight",
            s(&photo),
            "--depth",
            s(&depth),
            "--preset",
            "cool-side-flash",
            "--spp",
            "2",
            "--bounces",
            "1",
            "-o",
            s(&one),
        ])
        .ok();
        let a = pixl_core::io::read_image(&one).unwrap();
        let b = pixl_core::io::read_image(&out.join(format!("{rel}.png"))).unwrap();
        assert_eq!(a.data, b.data, "{rel}: batch and single differ");
    }
    // A log line per photo.
    let log = std::fs::read_to_string(out.join("pixl-batch.jsonl")).unwrap();
    let done = log.lines().filter(|l| l.contains("\"status\":\"done\"")).count();
    assert_eq!(done, 12, "{log}");
    // Run again: all skipped; with --force: all redone.
    let again = pixl_q(&batch(&shots, &depths, &out, &["--json"])).ok().json();
    assert_eq!(
        (again["done"].as_u64(), again["skipped"].as_u64()),
        (Some(0), Some(12)),
        "{again}"
    );
    // The same folder spelt another way: still done.
    let spelt = out.join(".");
    let again = pixl_q(&batch(&shots, &depths, &spelt, &["--json"])).ok().json();
    assert_eq!(again["skipped"].as_u64(), Some(12), "{again}");
    // Another lighting is another set-up: redone.
    let other = pixl_q(
        &[
            &batch(&shots, &depths, &out, &["--json"])[..],
            &["--light", "--type point --from left"],
        ]
        .concat(),
    )
    .ok()
    .json();
    assert_eq!(other["done"].as_u64(), Some(12), "{other}");
    let forced = pixl_q(&batch(&shots, &depths, &out, &["--json", "--force"]))
        .ok()
        .json();
    assert_eq!(forced["done"].as_u64(), Some(12), "{forced}");
}

#[test]
fn a_killed_batch_resumes_with_the_photos_not_done() {
    let dir = common::tempdir();
    let (shots, depths) = shoot(dir.path(), 240, 180);
    let out = dir.path().join("relit");
    let args = batch(&shots, &depths, &out, &["--spp", "16", "--quiet"]);
    let mut child = cmd()
        .args(&args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let start = std::time::Instant::now();
    loop {
        if outputs(&out).len() >= 5 {
            break;
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!("the batch ended ({status}) before 5 outputs");
        }
        assert!(start.elapsed().as_secs() < 300, "no 5 outputs in 300 s");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let before = outputs(&out);
    let k = before.len();
    assert!((5..12).contains(&k), "killed after {k} outputs");
    let args = batch(&shots, &depths, &out, &["--json", "--spp", "16"]);
    let j = pixl_q(&args).ok().json();
    assert_eq!(j["skipped"].as_u64(), Some(k as u64), "{j}");
    assert_eq!(j["done"].as_u64(), Some(12 - k as u64), "{j}");
    assert_eq!(outputs(&out).len(), 12);
}

#[test]
fn shards_are_disjoint_and_cover_every_photo_also_as_a_local_cluster() {
    let dir = common::tempdir();
    let (shots, depths) = shoot(dir.path(), 24, 16);
    let (a, b) = (dir.path().join("s0"), dir.path().join("s1"));
    pixl_q(&batch(&shots, &depths, &a, &["--shard", "0/2"])).ok();
    pixl_q(&batch(&shots, &depths, &b, &["--shard", "1/2"])).ok();
    let (sa, sb) = (outputs(&a), outputs(&b));
    assert!(sa.is_disjoint(&sb), "{sa:?} {sb:?}");
    assert_eq!(sa.len() + sb.len(), 12);
    assert!(a.join("pixl-batch.0-of-2.jsonl").is_file());

    // Three processes at once into one folder, as an Indexed Job's pods would run.
    let out = dir.path().join("cluster");
    let args = batch(
        &shots,
        &depths,
        &out,
        &["--shard", "auto", "--shard-count", "3", "--quiet"],
    );
    let children: Vec<_> = (0..3)
        .map(|i| {
            cmd()
                .args(&args)
                .env("JOB_COMPLETION_INDEX", i.to_string())
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for c in children {
        let o = c.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    assert_eq!(outputs(&out), &sa | &sb);
    // Without an index or a count, auto is refused with what to set.
    let o = pixl_q(&batch(&shots, &depths, &out, &["--shard", "auto"]));
    o.fails(&["JOB_COMPLETION_INDEX"]);
    pixl_q(&batch(&shots, &depths, &out, &["--shard", "2/2"])).fails(&["does not exist"]);
}

#[test]
fn a_corrupt_photo_is_reported_and_the_others_are_relit() {
    let dir = common::tempdir();
    let (shots, depths) = shoot(dir.path(), 24, 16);
    write_file(&shots.join("a04.png"), b"\x89PNG\r\n\x1a\nnot really");
    let out = dir.path().join("relit");
    let o = pixl_q(&batch(&shots, &depths, &out, &[]));
    let err = o.fails(&["1 of 12 photos failed", "pixl-batch.jsonl"]);
    assert!(!err.contains("panicked"), "{err}");
    let names = outputs(&out);
    assert_eq!(names.len(), 11);
    assert!(!names.contains("a04.png"));
    let log = std::fs::read_to_string(out.join("pixl-batch.jsonl")).unwrap();
    let failed: Vec<_> = log.lines().filter(|l| l.contains("\"status\":\"failed\"")).collect();
    assert_eq!(failed.len(), 1, "{log}");
    assert!(
        failed[0].contains("a04.png") && failed[0].contains("\"error\""),
        "{}",
        failed[0]
    );
}

#[test]
fn a_manifest_gives_each_photo_its_lighting_and_bad_rows_are_refused_before_any_work() {
    let dir = common::tempdir();
    let (shots, depths) = shoot(dir.path(), 24, 16);
    let manifest = write_file(
        &dir.path().join("jobs.csv"),
        "photo,preset,light,depth\n\
         shots/a00.png,warm-overhead-flash,,depths/a00.exr\n\
         shots/a01.png,,\"--type point --at-pixel 12,8 --power 20; --type sun --azimuth 40 --elevation 50\",depths/a01.exr\n\
         shots/sub/b00.png,,,depths/sub/b00.exr\n",
    );
    let out = dir.path().join("relit");
    // The third row has no lighting of its own: the flags' preset.
    let j = pixl_q(&[
        "relight",
        "--manifest",
        s(&manifest),
        "--preset",
        "cool-side-flash",
        "--spp",
        "2",
        "-o",
        s(&out),
        "--json",
    ])
    .ok()
    .json();
    assert_eq!(j["done"].as_u64(), Some(3), "{j}");
    let names = outputs(&out);
    assert_eq!(
        names,
        ["shots/a00.png", "shots/a01.png", "shots/sub/b00.png"]
            .map(String::from)
            .into()
    );
    // The row's preset, not the flags': the same as the single command with that preset.
    let one = dir.path().join("one.png");
    pixl_q(&[
        "relight",
        s(&shots.join("a00.png")),
        "--depth",
        s(&depths.join("a00.exr")),
        "--preset",
        "warm-overhead-flash",
        "--spp",
        "2",
        "-o",
        s(&one),
    ])
    .ok();
    let a = pixl_core::io::read_image(&one).unwrap();
    let b = pixl_core::io::read_image(&out.join("shots/a00.png")).unwrap();
    assert_eq!(a.data, b.data);

    let bad = write_file(&dir.path().join("bad.csv"), "photo,preset\nshots/a00.png,moonlight\n");
    let out2 = dir.path().join("none");
    pixl_q(&["relight", "--manifest", s(&bad), "-o", s(&out2)]).fails(&["moonlight"]);
    assert!(!out2.exists(), "nothing written");
    // An output that would be the photo itself is refused.
    pixl_q(&batch(&shots, &depths, &shots, &[])).fails(&["the photo itself"]);
}
