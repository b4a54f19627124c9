//! The contact sheet of `run_eval` (`EvalOptions::sheet_pairs`): its size, and the pixels of
//! its columns against values worked out here from what was written to disk.
use pixl_core::io::{write_png, PngDepth};
use pixl_core::Image;
use pixl_data::ImageEntry;
use pixl_eval::{contact_sheet, run_eval, Compose, EvalOptions, Identity, Method, Pair};
use pixl_intrinsics::ct::{write_ct, Ct};
use std::path::Path;

/// An 8-bit sample as the PNG stores it.
fn q8(v: f32) -> f32 {
    (v.clamp(0.0, 1.0) * 255.0).round() / 255.0
}

/// The sRGB OETF, written out here in f64.
fn srgb(v: f64) -> f64 {
    let v = v.clamp(0.0, 1.0);
    if v <= 0.0031308 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

struct Written {
    pair: Pair,
    source: Image,
    target: Image,
    ct: Ct,
}

/// A pair of `w`×`h` images (`seed` varies the pixels) with the target's C_T beside it.
fn write_pair(dir: &Path, scene: &str, w: usize, h: usize, seed: usize) -> Written {
    let dir = dir.join(scene);
    std::fs::create_dir_all(&dir).unwrap();
    let img = |k: usize| {
        Image::from_fn(w, h, 3, move |x, y, c| {
            0.1 + 0.8 * (((x * 7 + y * 5 + c * 3 + k * 11 + seed) % 17) as f32 / 16.0)
        })
    };
    let (source, target) = (img(0), img(1));
    let ct = Ct::new(
        Image::from_fn(w, h, 3, |x, y, c| ((x + y + c + seed) % 5) as f32 / 4.0),
        Image::from_fn(w, h, 3, |x, _, _| 0.3 * x as f32 / w as f32 + 0.9),
        Image::from_fn(w, h, 3, |_, y, c| 0.05 * (y + c) as f32 - 0.1),
    )
    .unwrap();
    let (sp, tp) = (dir.join("a.png"), dir.join("b.png"));
    write_png(&sp, &source, PngDepth::Eight).unwrap();
    write_png(&tp, &target, PngDepth::Eight).unwrap();
    let ctp = dir.join("b.intrinsics.exr");
    write_ct(&ctp, &ct).unwrap();
    Written {
        pair: Pair {
            scene: scene.into(),
            source: ImageEntry {
                image: sp,
                intrinsics: None,
            },
            target: ImageEntry {
                image: tp,
                intrinsics: Some(ctp),
            },
        },
        source: source.map(q8),
        target: target.map(q8),
        ct,
    }
}

fn opts(sheet_pairs: usize) -> EvalOptions {
    EvalOptions {
        runs: 0,
        sheet_pairs,
        ..EvalOptions::default()
    }
}

/// Three pairs (the second of another size), identity and compose, a sheet of the first two:
/// 2 rows × 7 columns (source, three C_T maps, two methods, target); the source and target
/// columns hold the PNGs' 8-bit values exactly, the albedo column sRGB(clip(A)), the identity
/// column the source after the per-channel scale correction; the narrower first row is padded.
#[test]
fn sheet_rows_hold_the_pairs_images_in_column_order() {
    let tmp = tempfile::tempdir().unwrap();
    let small = write_pair(tmp.path(), "s0", 16, 12, 0);
    let big = write_pair(tmp.path(), "s1", 20, 14, 3);
    let third = write_pair(tmp.path(), "s2", 16, 12, 5);
    let pairs = vec![small.pair.clone(), big.pair.clone(), third.pair.clone()];
    let methods: Vec<Box<dyn Method>> = vec![Box::new(Identity), Box::new(Compose::default())];
    let report = run_eval("test", &pairs, &methods, None, &opts(2), |_| {}).unwrap();
    assert_eq!(
        report.sheet_columns,
        [
            "source",
            "C_T albedo",
            "C_T shading",
            "C_T residual",
            "Identity (source)",
            "Compose (A⊙S+R of C_T)",
            "target"
        ]
    );
    assert_eq!(report.sheet_pairs, 2);
    assert_eq!(report.sheet_rows.len(), 2);
    let sheet = contact_sheet(&report.sheet_rows).unwrap();
    let cols = 7;
    assert_eq!((sheet.width, sheet.height, sheet.channels), (cols * 20, 12 + 14, 3));

    for (written, y0) in [(&small, 0), (&big, 12)] {
        let (w, h) = (written.source.width, written.source.height);
        // Per-channel least-squares scale of the source against the target, in f64.
        let scale: Vec<f64> = (0..3)
            .map(|c| {
                let (mut num, mut den) = (0f64, 0f64);
                for y in 0..h {
                    for x in 0..w {
                        let (p, g) = (written.source.get(x, y, c) as f64, written.target.get(x, y, c) as f64);
                        num += p * g;
                        den += p * p;
                    }
                }
                num / den
            })
            .collect();
        for y in 0..h {
            for x in 0..w {
                for (c, s) in scale.iter().enumerate() {
                    let at = |col: usize| sheet.get(col * w + x, y0 + y, c);
                    assert_eq!(at(0), written.source.get(x, y, c), "source ({x},{y},{c})");
                    assert_eq!(at(6), written.target.get(x, y, c), "target ({x},{y},{c})");
                    let albedo = srgb(written.ct.albedo.get(x, y, c) as f64);
                    assert!((at(1) as f64 - albedo).abs() < 1e-5, "albedo ({x},{y},{c})");
                    let identity = (s * written.source.get(x, y, c) as f64).clamp(0.0, 1.0);
                    assert!((at(4) as f64 - identity).abs() < 1e-5, "identity ({x},{y},{c})");
                }
            }
        }
    }
    // The 16-wide first row is padded to the 20-wide second one.
    assert_eq!(sheet.get(cols * 16, 0, 0), pixl_eval::sheet::PAD_GREY);
    assert_eq!(sheet.get(cols * 20 - 1, 11, 2), pixl_eval::sheet::PAD_GREY);
}

/// Without a method that reads C_T the sheet has no C_T columns (and C_T is not needed); with
/// `sheet_pairs` 0 nothing is kept and the report carries no sheet fields.
#[test]
fn no_ct_columns_without_ct_and_nothing_kept_by_default() {
    let tmp = tempfile::tempdir().unwrap();
    let mut p = write_pair(tmp.path(), "s0", 16, 12, 0);
    p.pair.target.intrinsics = Some(tmp.path().join("missing.exr"));
    let methods: Vec<Box<dyn Method>> = vec![Box::new(Identity)];
    let pairs = [p.pair.clone()];
    let report = run_eval("test", &pairs, &methods, None, &opts(5), |_| {}).unwrap();
    assert_eq!(report.sheet_columns, ["source", "Identity (source)", "target"]);
    let sheet = contact_sheet(&report.sheet_rows).unwrap();
    assert_eq!((sheet.width, sheet.height), (3 * 16, 12));
    assert_eq!(sheet.get(2 * 16 + 3, 4, 1), p.target.get(3, 4, 1));

    let report = run_eval("test", &pairs, &methods, None, &opts(0), |_| {}).unwrap();
    assert!(report.sheet_rows.is_empty() && report.sheet_columns.is_empty());
    let json = pixl_eval::report::json(&report).unwrap();
    assert!(!json.contains("sheet"), "{json}");
}

#[test]
fn two_methods_of_one_name_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let p = write_pair(tmp.path(), "s0", 16, 12, 0);
    let methods: Vec<Box<dyn Method>> = vec![Box::new(Identity), Box::new(Identity)];
    let e = run_eval("test", &[p.pair], &methods, None, &opts(0), |_| {})
        .unwrap_err()
        .to_string();
    assert!(e.contains("Identity (source)") && e.contains("twice"), "{e}");
}
