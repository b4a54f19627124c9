//! Marigold Normals against diffusers' `MarigoldNormalsPipeline` on a tiny random model
//! (`fixtures/marigold/normals`, `.fp16` files only, made by `scripts/fixtures/marigold_normals.py`):
//! the empty-prompt embedding, every member's DDIM latents, the decoded unit normals, and the final
//! normals for an ensemble of 1, an ensemble of 3 reduced by "closest" (with the uncertainty) and
//! by "mean", and a checkpoint with `use_full_z_range` false. The ensembling and the final resize
//! are also run on diffusers' own decoded members, apart from any network difference. "Closest"
//! keeps one member per pixel: where diffusers' two best are closer than our rounding can tell
//! apart, the output pixels resampled from there are left out of the final comparison
//! ([`closest_picks`]).
mod marigold_common;

use candle_core::{Device, Tensor};
use marigold_common::{copy_dir, f32s, fixtures, load, max_abs, photo};
use pixl_core::Image;
use pixl_estimate::marigold::normals::{
    ensemble, normals_to_size, uncertainty_to_size, MarigoldNormals, NormalsOptions, NormalsReduction,
};
use pixl_estimate::marigold::{Marigold, MarigoldOptions};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The fixture's processing resolution and steps.
const RES: usize = 32;
const STEPS: usize = 4;
/// Latents, decoded members and final normals against diffusers (observed: below 1e-5).
const TOL: f64 = 1e-4;

fn case() -> HashMap<String, Tensor> {
    load("normals_case.safetensors")
}

/// Asserts `got` within `tol` of `want` and returns the error.
fn close(what: &str, got: &[f32], want: &[f32], tol: f64) -> f64 {
    let e = max_abs(got, want);
    eprintln!("{what}: max abs error {e:.2e}");
    assert!(e <= tol, "{what}: max abs error {e:.3e} > {tol:.0e}");
    e
}

/// An interleaved image as planar values, the layout of the reference tensors.
fn planar(img: &Image) -> Vec<f32> {
    let (w, h, c) = (img.width, img.height, img.channels);
    (0..c * h * w)
        .map(|j| img.data[(j % (h * w)) * c + j / (h * w)])
        .collect()
}

/// A copy of the fixture folder `name` (loading caches the text embedding beside the weights),
/// with `edit` applied to its `model_index.json`.
fn fixture_copy(tmp: &Path, name: &str, edit: impl Fn(String) -> String) -> PathBuf {
    let dir = tmp.join(name);
    copy_dir(&fixtures().join(name), &dir);
    let idx = dir.join("model_index.json");
    std::fs::write(&idx, edit(std::fs::read_to_string(&idx).unwrap())).unwrap();
    dir
}

/// A copy of the normals fixture with `edit` applied to its `model_index.json`.
fn checkpoint(tmp: &Path, edit: impl Fn(String) -> String) -> PathBuf {
    fixture_copy(tmp, "normals", edit)
}

fn opts(ensemble: usize, reduction: NormalsReduction, uncertainty: bool) -> NormalsOptions {
    NormalsOptions {
        steps: Some(STEPS),
        ensemble,
        resolution: Some(RES),
        reduction,
        seed: 0,
        uncertainty,
    }
}

#[test]
fn normals_match_diffusers() {
    let tmp = tempfile::tempdir().unwrap();
    let m = MarigoldNormals::load(&checkpoint(tmp.path(), |s| s), &Device::Cpu).unwrap();
    assert!(m.use_full_z_range());
    let case = case();
    close(
        "empty embedding",
        &f32s(m.model().empty_embedding()),
        &f32s(&case["empty_embedding"]),
        1e-5,
    );
    let img = photo(&case);
    let pre = m.model().preprocess(&img, RES).unwrap();
    let lat = m.model().encode(&pre.image).unwrap();
    let (nh, nw) = pre.resized;
    let mut worst = 0f64;
    for e in [1usize, 3] {
        let noise = &case[&format!("e{e}.noise")];
        // Every member's latents after each step, and its decoded normals.
        let mut ours: Vec<Vec<f32>> = Vec::new();
        for k in 0..e {
            let mut steps: Vec<Tensor> = Vec::new();
            let z = noise.narrow(0, k, 1).unwrap();
            let last = m
                .model()
                .denoise(&lat, &z, STEPS, &mut |_, l| steps.push(l.clone()))
                .unwrap();
            for (s, l) in steps.iter().enumerate() {
                let want = case[&format!("e{e}.step{s}.latent")].narrow(0, k, 1).unwrap();
                close(&format!("e{e} member {k} step {s} latent"), &f32s(l), &f32s(&want), TOL);
            }
            let d = m
                .decode(&last)
                .unwrap()
                .narrow(2, 0, nh)
                .unwrap()
                .narrow(3, 0, nw)
                .unwrap();
            let want = case[&format!("e{e}.decoded")].narrow(0, k, 1).unwrap();
            close(&format!("e{e} member {k} decoded"), &f32s(&d), &f32s(&want), TOL);
            ours.push(f32s(&d));
        }
        // Where "closest" may pick another member than diffusers (see `closest_picks`), the final
        // normals are compared apart.
        let skip = if e > 1 {
            let theirs = f32s(&case[&format!("e{e}.decoded")]);
            let theirs: Vec<&[f32]> = theirs.chunks(3 * nh * nw).collect();
            let ours: Vec<&[f32]> = ours.iter().map(Vec::as_slice).collect();
            closest_picks(&ours, &theirs, (nh, nw), (img.height, img.width))
        } else {
            vec![false; img.width * img.height]
        };
        let reductions: &[(NormalsReduction, &str)] = if e == 1 {
            &[(NormalsReduction::Closest, "prediction")]
        } else {
            &[
                (NormalsReduction::Closest, "prediction"),
                (NormalsReduction::Mean, "prediction_mean"),
            ]
        };
        for &(how, key) in reductions {
            let with_u = e > 1 && how == NormalsReduction::Closest;
            let pred = m
                .predict_with_noise(&img, &opts(e, how, with_u), noise, &mut |_| {})
                .unwrap();
            let n = &pred.normals;
            assert_eq!((n.width, n.height, n.channels), (img.width, img.height, 3));
            assert_eq!(pred.processed_size, (nw, nh));
            let (got, want) = (planar(n), f32s(&case[&format!("e{e}.{key}")]));
            let keep = |v: &[f32]| -> Vec<f32> {
                let hw = img.width * img.height;
                (0..v.len())
                    .filter(|&j| how == NormalsReduction::Mean || !skip[j % hw])
                    .map(|j| v[j])
                    .collect()
            };
            worst = worst.max(close(
                &format!("e{e} {how:?} final normals"),
                &keep(&got),
                &keep(&want),
                TOL,
            ));
            let off_unit = n
                .data
                .chunks_exact(3)
                .map(|p| ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 1.0).abs())
                .fold(0f32, f32::max);
            assert!(off_unit < 1e-5, "not unit length: {off_unit}");
            match &pred.uncertainty {
                Some(u) if with_u => {
                    assert_eq!(u.channels, 1);
                    close(
                        &format!("e{e} uncertainty"),
                        &u.data,
                        &f32s(&case["e3.uncertainty"]),
                        TOL,
                    );
                }
                None if !with_u => {}
                other => panic!("uncertainty {:?} with uncertainty={with_u}", other.is_some()),
            }
        }
    }
    eprintln!("final normals: worst max abs error {worst:.2e} over all cases");
}

/// Per pixel of planar `(3, n)` unit-normal members, each member's cosine to their normalised mean
/// (what "closest" ranks them by).
fn cosines(members: &[&[f32]]) -> Vec<Vec<f32>> {
    let n = members[0].len() / 3;
    (0..n)
        .map(|i| {
            let v = |m: &[f32]| [m[i], m[n + i], m[2 * n + i]];
            let s = members.iter().fold([0.0f64; 3], |a, m| {
                let x = v(m);
                [a[0] + x[0] as f64, a[1] + x[1] as f64, a[2] + x[2] as f64]
            });
            let l = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
            members
                .iter()
                .map(|m| {
                    let x = v(m);
                    ((s[0] * x[0] as f64 + s[1] * x[1] as f64 + s[2] * x[2] as f64) / l) as f32
                })
                .collect()
        })
        .collect()
}

/// The member with the largest cosine (the first on ties) and its margin over the runner-up.
fn best(cos: &[f32]) -> (usize, f32) {
    let k = (1..cos.len()).fold(0, |b, k| if cos[k] > cos[b] { k } else { b });
    let second = (0..cos.len())
        .filter(|&j| j != k)
        .map(|j| cos[j])
        .fold(f32::MIN, f32::max);
    (k, cos[k] - second)
}

/// "Closest" is a discontinuous choice: our members differ from diffusers' by the network's
/// rounding (up to ~1e-5 here), so our cosines differ from theirs by up to some `d`, and at a pixel where
/// diffusers' two best members are within `2d` of each other we may rightly keep the runner-up.
/// Checks that elsewhere we keep diffusers' member, and returns the output pixels whose bilinear
/// footprint holds such a near-tie, to leave out of the comparison of the final normals.
fn closest_picks(ours: &[&[f32]], theirs: &[&[f32]], (nh, nw): (usize, usize), (h, w): (usize, usize)) -> Vec<bool> {
    let (co, ct) = (cosines(ours), cosines(theirs));
    let d = co
        .iter()
        .flatten()
        .zip(ct.iter().flatten())
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    let mut near_tie = vec![false; nh * nw];
    for (i, (o, t)) in co.iter().zip(&ct).enumerate() {
        let ((ko, _), (kt, gap)) = (best(o), best(t));
        if gap <= 2.0 * d {
            near_tie[i] = true;
        } else {
            assert_eq!(
                ko, kt,
                "pixel {i}: a clear choice (margin {gap:.1e} > 2 × {d:.1e}) differs"
            );
        }
    }
    // PyTorch's bilinear taps (align_corners=False): floor(src) and the next, src clamped at 0.
    let taps = |o: usize, n_out: usize, n_in: usize| {
        let src = ((o as f32 + 0.5) * n_in as f32 / n_out as f32 - 0.5).max(0.0);
        let i0 = (src as usize).min(n_in - 1);
        [i0, (i0 + 1).min(n_in - 1)]
    };
    let skip: Vec<bool> = (0..h * w)
        .map(|j| {
            let (y, x) = (j / w, j % w);
            taps(y, h, nh)
                .iter()
                .any(|&sy| taps(x, w, nw).iter().any(|&sx| near_tie[sy * nw + sx]))
        })
        .collect();
    let n_tie = near_tie.iter().filter(|a| **a).count();
    let n_skip = skip.iter().filter(|s| **s).count();
    eprintln!(
        "closest: cosines within {d:.1e} of diffusers'; {n_tie} of {} processed pixels within {:.1e} of a tie; \
{n_skip} of {} output pixels left out",
        nh * nw,
        2.0 * d,
        h * w
    );
    assert!(2 * n_skip < h * w, "too few output pixels left to compare");
    skip
}

#[test]
fn ensembling_and_resize_match_diffusers_on_its_own_members() {
    let case = case();
    let img = photo(&case);
    let d = &case["e3.decoded"];
    let (e, _, nh, nw) = d.dims4().unwrap();
    let members: Vec<Vec<f32>> = (0..e).map(|k| f32s(&d.narrow(0, k, 1).unwrap())).collect();
    let refs: Vec<&[f32]> = members.iter().map(Vec::as_slice).collect();
    let size = (img.width, img.height);
    for (how, key) in [
        (NormalsReduction::Closest, "e3.prediction"),
        (NormalsReduction::Mean, "e3.prediction_mean"),
    ] {
        let (reduced, u) = ensemble(&refs, how);
        let n = normals_to_size(reduced, (nw, nh), size).unwrap();
        close(
            &format!("{how:?} from diffusers' members"),
            &planar(&n),
            &f32s(&case[key]),
            1e-5,
        );
        if how == NormalsReduction::Closest {
            let u = uncertainty_to_size(u, (nw, nh), size).unwrap();
            close(
                "uncertainty from diffusers' members",
                &u.data,
                &f32s(&case["e3.uncertainty"]),
                1e-5,
            );
        }
    }
    // An ensemble of 1 is only resized and normalised.
    let d1 = f32s(&case["e1.decoded"]);
    let n = normals_to_size(d1, (nw, nh), size).unwrap();
    close(
        "e1 from diffusers' decode",
        &planar(&n),
        &f32s(&case["e1.prediction"]),
        1e-5,
    );
}

#[test]
fn a_half_z_range_checkpoint_maps_the_decoded_z_to_the_front_half() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = checkpoint(tmp.path(), |s| {
        assert!(s.contains("\"use_full_z_range\": true"));
        s.replace("\"use_full_z_range\": true", "\"use_full_z_range\": false")
    });
    let m = MarigoldNormals::load(&dir, &Device::Cpu).unwrap();
    assert!(!m.use_full_z_range());
    let case = case();
    let img = photo(&case);
    let pred = m
        .predict_with_noise(
            &img,
            &opts(1, NormalsReduction::Closest, false),
            &case["e1.noise"],
            &mut |_| {},
        )
        .unwrap();
    close(
        "half z range final normals",
        &planar(&pred.normals),
        &f32s(&case["e1.prediction_half_z"]),
        TOL,
    );
    assert!(pred.normals.data.chunks_exact(3).all(|p| p[2] >= 0.0));
}

#[test]
fn seeded_runs_repeat_and_count_their_progress() {
    let tmp = tempfile::tempdir().unwrap();
    let m = MarigoldNormals::load(&checkpoint(tmp.path(), |s| s), &Device::Cpu).unwrap();
    let img = photo(&case());
    let o = NormalsOptions {
        seed: 7,
        ..opts(2, NormalsReduction::Closest, true)
    };
    let mut ticks = Vec::new();
    let a = m.predict(&img, &o, &mut |p| ticks.push((p.done, p.total))).unwrap();
    // Encoding, 2 × (4 steps + 1 decode).
    assert_eq!(ticks.len(), 11);
    assert!(ticks.iter().enumerate().all(|(i, &(d, t))| d == i + 1 && t == 11));
    let b = m.predict(&img, &o, &mut |_| {}).unwrap();
    assert_eq!(a.normals.data, b.normals.data);
    let u = a.uncertainty.expect("asked for");
    assert!(u.data.iter().all(|v| (0.0..=1.0).contains(v)));
    let c = m.predict(&img, &NormalsOptions { seed: 8, ..o }, &mut |_| {}).unwrap();
    assert_ne!(a.normals.data, c.normals.data);
}

#[test]
fn each_pipeline_refuses_the_others_checkpoint() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = checkpoint(tmp.path(), |s| s);
    let img = photo(&case());
    // The normals checkpoint through the IID pipeline.
    let m = Marigold::load(&dir, &Device::Cpu).unwrap();
    assert_eq!(m.variant(), None);
    let opts = MarigoldOptions {
        resolution: Some(RES),
        ..Default::default()
    };
    let e = m.predict(&img, &opts, &mut |_| {}).expect_err("refused").to_string();
    assert!(e.contains("normals"), "{e}");
    // An IID checkpoint through the normals pipeline.
    let e = MarigoldNormals::load(&fixture_copy(tmp.path(), "lighting", |s| s), &Device::Cpu)
        .err()
        .expect("refused")
        .to_string();
    assert!(
        e.contains("MarigoldIntrinsicsPipeline") && e.contains("not a Marigold normals checkpoint"),
        "{e}"
    );
    // A folder whose index names the wrong prediction type.
    let dir = checkpoint(&tmp.path().join("b"), |s| {
        s.replace("\"prediction_type\": \"normals\"", "\"prediction_type\": \"depth\"")
    });
    let e = MarigoldNormals::load(&dir, &Device::Cpu)
        .err()
        .expect("refused")
        .to_string();
    assert!(e.contains("prediction_type") && e.contains("depth"), "{e}");
}
