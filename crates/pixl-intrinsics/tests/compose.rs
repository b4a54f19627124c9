//! Compose (paper App. B) against hand-derived answers, an f64 reference, and real Cycles renders.
use pixl_core::exrio::{read_exr_channels, write_exr_channels, ExrChannels};
use pixl_core::io::write_image;
use pixl_core::Image;
use pixl_intrinsics::compose::{compose, percentile, ComposeOptions, PassSet, TAU_EPS};
use pixl_intrinsics::IntrinsicsError;
use std::path::PathBuf;

fn constant(w: usize, h: usize, v: [f32; 3]) -> Image {
    Image::from_fn(w, h, 3, |_, _, c| v[c])
}

fn set_of(passes: &[(&str, Image)]) -> PassSet {
    let mut set = PassSet::new("test");
    for (n, img) in passes {
        set.insert(n, img.clone()).unwrap();
    }
    set
}

/// numpy's default percentile, in f64 with a full sort: the independent reference.
fn naive_percentile(values: &[f32], q: f64) -> f64 {
    let mut v: Vec<f64> = values.iter().map(|&x| x as f64).collect();
    v.sort_by(f64::total_cmp);
    let h = q / 100.0 * (v.len() - 1) as f64;
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(v.len() - 1);
    v[lo] + (h - lo as f64) * (v[hi] - v[lo])
}

#[test]
fn constants_give_hand_derived_ct() {
    let (w, h) = (4, 3);
    let set = set_of(&[
        ("DiffCol", constant(w, h, [1.5, 0.5, -0.2])),
        ("DiffDir", constant(w, h, [0.3, 0.1, -1.0])),
        ("DiffInd", constant(w, h, [0.2, 0.1, 0.5])),
        ("GlossCol", constant(w, h, [0.5, 0.5, 0.5])),
        ("GlossDir", constant(w, h, [1.0, 2.0, 0.0])),
        ("GlossInd", constant(w, h, [1.0, 0.0, 0.0])),
        ("Emit", constant(w, h, [0.0, 0.0, 0.25])),
    ]);
    let raw = compose(
        &set,
        &ComposeOptions {
            rescale: false,
            sanitize: false,
        },
    )
    .unwrap();
    // A = clip(DiffCol,0,1); S = max(DD+DI,0); R = max(0.5*(GD+GI) + Emit, 0)
    let (a, s, r) = ([1.0, 0.5, 0.0], [0.5, 0.2, 0.0], [1.0, 1.0, 0.25]);
    for p in 0..w * h {
        for c in 0..3 {
            assert!((raw.ct.albedo.data[p * 3 + c] - a[c]).abs() < 1e-6);
            assert!((raw.ct.shading.data[p * 3 + c] - s[c]).abs() < 1e-6);
            assert!((raw.ct.residual.data[p * 3 + c] - r[c]).abs() < 1e-6);
        }
    }
    assert_eq!(raw.tau, None);
    assert_eq!(
        raw.missing,
        vec!["TransCol", "TransDir", "TransInd", "VolumeDir", "VolumeInd"]
    );

    // Rescaled: p98(S) over {0.5,0.2,0}×12 = 0.5, p98(R) over {1,1,0.25}×12 = 1 -> τ = 1.
    let out = compose(&set, &ComposeOptions::default()).unwrap();
    assert!((out.tau.unwrap() - 1.0).abs() < 1e-6);
    assert!((out.ct.shading.get(0, 0, 0) - 0.5).abs() < 1e-6);
    assert!((out.ct.residual.get(0, 0, 2) - 0.25).abs() < 1e-6);
}

#[test]
fn ramp_has_known_p98_and_shared_cutoff() {
    // DiffDir holds 0, 1, …, 299 over all pixels and channels: p98 = 0.98·299 = 293.02.
    let (w, h) = (10, 10);
    let ramp = Image::from_vec(w, h, 3, (0..300).map(|i| i as f32).collect()).unwrap();
    let half = constant(w, h, [0.5, 0.5, 0.5]);
    let set = set_of(&[
        ("DiffCol", half.clone()),
        ("DiffDir", ramp),
        ("DiffInd", constant(w, h, [0.0; 3])),
    ]);
    let out = compose(&set, &ComposeOptions::default()).unwrap();
    let tau = out.tau.unwrap() as f64;
    assert!((tau - 293.02).abs() < 1e-3, "tau {tau}");
    for (i, v) in out.ct.shading.data.iter().enumerate() {
        let want = (i as f64).min(293.02) / 293.02;
        assert!((*v as f64 - want).abs() < 1e-5, "{i}: {v} vs {want}");
    }
    assert!(out.ct.residual.data.iter().all(|&v| v == 0.0));
    assert_eq!(out.missing.len(), 9);

    // A residual brighter than the shading sets τ for both (one shared cutoff).
    let set = set_of(&[
        ("DiffCol", half.clone()),
        ("DiffDir", constant(w, h, [1.0; 3])),
        ("DiffInd", constant(w, h, [1.0; 3])),
        ("Emit", constant(w, h, [8.0; 3])),
    ]);
    let out = compose(&set, &ComposeOptions::default()).unwrap();
    assert!((out.tau.unwrap() - 8.0).abs() < 1e-6);
    assert!((out.ct.shading.get(3, 3, 1) - 0.25).abs() < 1e-6);
    assert!((out.ct.residual.get(3, 3, 1) - 1.0).abs() < 1e-6);

    // All black: τ = ε, no division by zero.
    let zero = constant(w, h, [0.0; 3]);
    let set = set_of(&[("DiffCol", half), ("DiffDir", zero.clone()), ("DiffInd", zero)]);
    let out = compose(&set, &ComposeOptions::default()).unwrap();
    assert_eq!(out.tau, Some(TAU_EPS));
    assert!(out.ct.shading.data.iter().all(|&v| v == 0.0));
}

#[test]
fn percentile_matches_sorting_reference() {
    let mut rng = pixl_core::Rng::new(7);
    for n in [1usize, 2, 3, 10, 51, 1000, 4097] {
        let vals: Vec<f32> = (0..n)
            .map(|i| if i % 5 == 0 { 0.25 } else { rng.normal() * 3.0 })
            .collect();
        for q in [0.0, 2.0, 50.0, 98.0, 100.0] {
            let got = percentile(&mut vals.clone(), q) as f64;
            let want = naive_percentile(&vals, q);
            assert!(
                (got - want).abs() <= 1e-5 * (1.0 + want.abs()),
                "n={n} q={q}: {got} vs {want}"
            );
        }
    }
}

#[test]
fn roundtrip_without_rescale_returns_a_s_r() {
    let (w, h) = (9, 7);
    let a = Image::from_fn(w, h, 3, |x, y, c| ((x * 3 + y * 5 + c * 7) % 11) as f32 / 10.0);
    let s = Image::from_fn(w, h, 3, |x, y, c| (x as f32 * 0.7 + y as f32 * 0.3 + c as f32) * 1.7);
    let r = Image::from_fn(w, h, 3, |x, y, c| ((x + y + c) % 4) as f32 * 2.5);
    let set = set_of(&[
        ("Diffuse Color", a.clone()),
        ("DiffDir", s.map(|v| v * 0.6)),
        ("Diffuse Indirect", s.map(|v| v * 0.4)),
        ("GlossCol", constant(w, h, [0.5; 3])),
        ("Glossy Direct", r.clone()),
        ("GlossInd", r.clone()),
    ]);
    let out = compose(
        &set,
        &ComposeOptions {
            rescale: false,
            sanitize: false,
        },
    )
    .unwrap();
    let close = |x: &Image, y: &Image| {
        x.data
            .iter()
            .zip(&y.data)
            .all(|(p, q)| (p - q).abs() <= 1e-5 * (1.0 + q.abs()))
    };
    assert!(close(&out.ct.albedo, &a));
    assert!(close(&out.ct.shading, &s));
    assert!(close(&out.ct.residual, &r));
}

#[test]
fn non_finite_is_located_or_sanitized() {
    let (w, h) = (5, 4);
    let mut dd = constant(w, h, [0.5; 3]);
    dd.set(3, 2, 1, f32::NAN);
    dd.set(4, 3, 0, f32::INFINITY);
    let mut col = constant(w, h, [0.8; 3]);
    col.set(1, 1, 2, f32::NEG_INFINITY);
    let set = set_of(&[
        ("DiffCol", col),
        ("DiffDir", dd),
        ("DiffInd", constant(w, h, [0.25; 3])),
    ]);
    let e = compose(&set, &ComposeOptions::default()).unwrap_err();
    match &e {
        IntrinsicsError::NonFinitePasses {
            count,
            pass,
            x,
            y,
            channel,
            ..
        } => {
            assert_eq!(
                (*count, pass.as_str(), *x, *y, channel.as_str()),
                (3, "DiffCol", 1, 1, "B")
            );
        }
        other => panic!("unexpected {other}"),
    }
    assert!(e.to_string().contains("--sanitize"));

    let out = compose(
        &set,
        &ComposeOptions {
            rescale: false,
            sanitize: true,
        },
    )
    .unwrap();
    assert_eq!(out.sanitized, 3);
    assert_eq!(out.ct.albedo.get(1, 1, 2), 0.0);
    assert!((out.ct.shading.get(3, 2, 1) - 0.25).abs() < 1e-7);
    assert!((out.ct.shading.get(4, 3, 0) - 0.25).abs() < 1e-7);
    assert!((out.ct.shading.get(0, 0, 0) - 0.75).abs() < 1e-7);
    assert!(out.ct.to_chw().iter().all(|v| v.is_finite()));
}

#[test]
fn missing_required_pass_is_named() {
    let img = constant(3, 3, [0.5; 3]);
    let set = set_of(&[("DiffCol", img.clone()), ("Diffuse Direct", img)]);
    let e = compose(&set, &ComposeOptions::default()).unwrap_err().to_string();
    assert!(e.contains("DiffInd") && !e.contains("missing: DiffCol"), "{e}");
}

#[test]
fn mismatched_sizes_are_refused() {
    let mut set = PassSet::new("test");
    set.insert("DiffCol", constant(4, 4, [0.5; 3])).unwrap();
    let e = set.insert("DiffDir", constant(4, 5, [0.5; 3])).unwrap_err().to_string();
    assert!(e.contains("DiffDir is 4x5") && e.contains("DiffCol is 4x4"), "{e}");

    let dir = tempfile::tempdir().unwrap();
    write_image(&dir.path().join("DiffCol.exr"), &constant(4, 4, [0.5; 3])).unwrap();
    write_image(&dir.path().join("Diffuse Direct.exr"), &constant(6, 4, [0.5; 3])).unwrap();
    write_image(&dir.path().join("DiffInd.exr"), &constant(4, 4, [0.5; 3])).unwrap();
    let e = PassSet::read(dir.path(), None).unwrap_err().to_string();
    assert!(e.contains("must share one size"), "{e}");
}

#[test]
fn folder_of_single_pass_files() {
    let dir = tempfile::tempdir().unwrap();
    write_image(&dir.path().join("Diffuse Color.exr"), &constant(4, 4, [0.5; 3])).unwrap();
    write_image(&dir.path().join("DiffDir.exr"), &constant(4, 4, [2.0; 3])).unwrap();
    write_image(&dir.path().join("DiffInd.exr"), &constant(4, 4, [1.0; 3])).unwrap();
    write_image(&dir.path().join("Emission.exr"), &constant(4, 4, [0.5; 3])).unwrap();
    write_image(&dir.path().join("notes.exr"), &constant(2, 2, [0.5; 3])).unwrap();
    let set = PassSet::read(dir.path(), None).unwrap();
    assert_eq!(set.names(), vec!["DiffCol", "DiffDir", "DiffInd", "Emit"]);
    let out = compose(
        &set,
        &ComposeOptions {
            rescale: false,
            sanitize: false,
        },
    )
    .unwrap();
    assert_eq!(out.ct.shading.get(1, 1, 0), 3.0);
    assert_eq!(out.ct.residual.get(1, 1, 0), 0.5);
}

fn channels(layers: &[&str], pass_names: &[&str], w: usize, h: usize) -> ExrChannels {
    let mut ch = ExrChannels::new(w, h);
    for l in layers {
        for (k, p) in pass_names.iter().enumerate() {
            for c in ["R", "G", "B"] {
                let name = if l.is_empty() {
                    format!("{p}.{c}")
                } else {
                    format!("{l}.{p}.{c}")
                };
                ch.push(name, vec![0.1 * (k + 1) as f32; w * h]).unwrap();
            }
        }
        let name = if l.is_empty() {
            "Depth.Z".to_string()
        } else {
            format!("{l}.Depth.Z")
        };
        ch.push(name, vec![1e10; w * h]).unwrap();
    }
    ch
}

#[test]
fn exr_channels_short_or_long_names_and_layers() {
    let long = channels(
        &["ViewLayer"],
        &["Diffuse Color", "Diffuse Direct", "Diffuse Indirect", "Glossy Color"],
        3,
        2,
    );
    let set = PassSet::from_exr_channels(&long, None).unwrap();
    assert_eq!(set.names(), vec!["DiffCol", "DiffDir", "DiffInd", "GlossCol"]);
    assert_eq!((set.width(), set.height()), (3, 2));
    assert!((set.get("Diffuse Indirect").unwrap().get(2, 1, 2) - 0.3).abs() < 1e-7);

    let two = channels(&["Front", "Back"], &["DiffCol", "DiffDir", "DiffInd"], 2, 2);
    let e = PassSet::from_exr_channels(&two, None).unwrap_err().to_string();
    assert!(
        e.contains("Front") && e.contains("Back") && e.contains("--layer"),
        "{e}"
    );
    assert_eq!(PassSet::from_exr_channels(&two, Some("Back")).unwrap().names().len(), 3);
    let e = PassSet::from_exr_channels(&two, Some("Side")).unwrap_err().to_string();
    assert!(
        e.contains("Side") && e.contains("Front, Back") || e.contains("Back, Front"),
        "{e}"
    );

    let bare = channels(&[""], &["DiffCol", "DiffDir", "DiffInd"], 2, 2);
    assert_eq!(PassSet::from_exr_channels(&bare, None).unwrap().names().len(), 3);

    let mut partial = channels(&["ViewLayer"], &["DiffCol", "DiffDir"], 2, 2);
    partial.push("ViewLayer.DiffInd.R", vec![0.0; 4]).unwrap();
    let e = PassSet::from_exr_channels(&partial, None).unwrap_err().to_string();
    assert!(e.contains("DiffInd") && e.contains("G, B"), "{e}");

    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("multi.exr");
    write_exr_channels(&p, &long).unwrap();
    assert_eq!(PassSet::read(&p, None).unwrap().names().len(), 4);
}

fn fixtures() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/cycles");
    if dir.join("scene256_multipart.exr").exists() {
        Some(dir)
    } else {
        println!("skipping: Cycles fixtures not found at {}", dir.display());
        None
    }
}

/// Real Blender 5 renders: both files compose; A ∈ [0,1], τ > 0, S, R ∈ [0,1]; and before the
/// rescale A⊙S+R agrees with Combined − Environment (the image-formation identity, up to the
/// negative noise the max(·,0) removes and DiffCol values above 1 that the clip removes).
#[test]
fn real_cycles_renders_compose() {
    let Some(dir) = fixtures() else { return };
    for file in ["scene256_multipart.exr", "scene256_singlepart_half.exr"] {
        let path = dir.join(file);
        let set = PassSet::read(&path, None).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert_eq!((set.width(), set.height()), (256, 256), "{file}");
        let out = compose(&set, &ComposeOptions::default()).unwrap_or_else(|e| panic!("{file}: {e}"));
        assert!(out.missing.is_empty(), "{file}: missing {:?}", out.missing);
        let tau = out.tau.unwrap();
        assert!(tau.is_finite() && tau > TAU_EPS, "{file}: tau {tau}");
        let chw = out.ct.to_chw();
        assert!(
            chw.iter().all(|v| (0.0..=1.0).contains(v)),
            "{file}: values outside [0,1]"
        );
        // S or R reaches 1 at ≥ 2 % of its samples (that is what p98 means).
        let n = 256 * 256 * 3;
        let at_one = |d: &[f32]| d.iter().filter(|&&v| v >= 1.0 - 1e-6).count() as f64 / n as f64;
        assert!(
            at_one(&out.ct.shading.data).max(at_one(&out.ct.residual.data)) >= 0.0199,
            "{file}"
        );

        let raw = compose(
            &set,
            &ComposeOptions {
                rescale: false,
                sanitize: false,
            },
        )
        .unwrap();
        let recomposed = raw.ct.recompose();
        let chans = read_exr_channels(&path).unwrap();
        let (mut err, mut total, mut worst) = (0f64, 0f64, Vec::with_capacity(n));
        for (c, comp) in ["R", "G", "B"].iter().enumerate() {
            let combined = chans.get(&format!("ViewLayer.Combined.{comp}")).expect("Combined");
            let env = chans
                .get(&format!("ViewLayer.Environment.{comp}"))
                .expect("Environment");
            for p in 0..256 * 256 {
                let want = (combined[p] - env[p]) as f64;
                let got = recomposed.data[p * 3 + c] as f64;
                err += (got - want).abs();
                total += want.abs();
                worst.push((got - want).abs() / (0.05 + want.abs()));
            }
        }
        worst.sort_by(f64::total_cmp);
        let rel = err / total;
        let p99 = worst[worst.len() * 99 / 100];
        println!("{file}: tau {tau:.4}, mean relative |A⊙S+R − (Combined − Env)| {rel:.2e}, p99 {p99:.2e}");
        assert!(
            rel < 2e-3,
            "{file}: recomposition differs from Combined - Environment by {rel}"
        );
        assert!(p99 < 5e-3, "{file}: p99 {p99}");
    }
}
