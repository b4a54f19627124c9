//! The pair sampler's invariants: pairing, epochs, crop aspect bounds, identical crop / flip on
//! source, target and C_T, coarse C_T where it exists.
use pixl_core::resample::crop_resize;
use pixl_core::Image;
use pixl_data::{ImageEntry, SceneEntry};
use pixl_train::sampler::{flip_horizontal, Loader, Sampler, SamplerConfig};

/// Every image of scene `s`, light `l` is a horizontal ramp plus a light-specific offset; C_T is
/// the same ramp in all 9 channels plus the light id, so crops and flips can be traced.
struct RampLoader {
    w: usize,
    h: usize,
}

fn ramp(w: usize, h: usize, ch: usize, offset: f32) -> Image {
    Image::from_fn(w, h, ch, |x, y, c| {
        offset + x as f32 + 0.001 * y as f32 + 1000.0 * c as f32
    })
}

fn light_id(e: &ImageEntry) -> f32 {
    e.image
        .file_stem()
        .unwrap()
        .to_string_lossy()
        .trim_start_matches('l')
        .parse::<f32>()
        .unwrap()
}

impl Loader for RampLoader {
    fn image(&self, e: &ImageEntry) -> pixl_train::Result<Image> {
        Ok(ramp(self.w, self.h, 3, 100.0 * light_id(e)))
    }
    fn intrinsics(&self, e: &ImageEntry) -> pixl_train::Result<Image> {
        Ok(ramp(self.w, self.h, 9, 100.0 * light_id(e)))
    }
}

fn fake_scenes(n: usize, lights: usize) -> Vec<SceneEntry> {
    (0..n)
        .map(|s| SceneEntry {
            name: format!("s{s}"),
            images: (0..lights)
                .map(|l| ImageEntry {
                    image: format!("s{s}/l{l}.png").into(),
                    intrinsics: None,
                })
                .collect(),
        })
        .collect()
}

#[test]
fn sampler_pairs_are_distinct_and_cover_scenes_per_epoch() {
    let loader = RampLoader { w: 40, h: 30 };
    let cfg = SamplerConfig {
        long_side: 16,
        multiple: 4,
        ..Default::default()
    };
    let sampler = Sampler::new(fake_scenes(5, 3), cfg, 2, 7).unwrap();
    let mut seen = Vec::new();
    let mut roles = std::collections::HashSet::new();
    for step in 0..15 {
        for s in sampler.batch(step, &loader).unwrap() {
            assert_ne!(s.source_index, s.target_index);
            roles.insert((s.source_index, s.target_index));
            // source and target come from the right lights: pixel value offset identifies the light
            let src_light = ((s.source.data[0] - 0.0) / 100.0).floor() as usize;
            assert!(s.source.data.iter().all(|v| v.is_finite()));
            assert!(src_light <= 2);
            seen.push(s.scene);
        }
    }
    // each epoch (5 consecutive global samples) visits every scene exactly once
    for epoch in seen.chunks(5) {
        let mut e = epoch.to_vec();
        e.sort();
        assert_eq!(e, ["s0", "s1", "s2", "s3", "s4"]);
    }
    assert_eq!(roles.len(), 6, "all ordered pairs of 3 lights occur: {roles:?}");
    // deterministic: same (seed, step, index) → same sample
    let a = sampler.sample(3, 1, &loader).unwrap();
    let b = sampler.sample(3, 1, &loader).unwrap();
    assert_eq!((a.crop, a.flipped, a.source_index), (b.crop, b.flipped, b.source_index));
    assert_eq!(a.source, b.source);
}

#[test]
fn crops_respect_aspect_bounds_and_size() {
    let loader = RampLoader { w: 120, h: 80 };
    let cfg = SamplerConfig {
        long_side: 32,
        multiple: 4,
        min_scale: 0.5,
        ..Default::default()
    };
    let sampler = Sampler::new(fake_scenes(2, 2), cfg, 1, 3).unwrap();
    let (mut portrait, mut landscape, mut min_aspect) = (0, 0, 1.0f32);
    for step in 0..200 {
        let s = sampler.sample(step, 0, &loader).unwrap();
        let (w, h) = (s.source.width, s.source.height);
        assert_eq!(w.max(h), 32);
        assert_eq!((w % 4, h % 4), (0, 0));
        let out_aspect = w.min(h) as f32 / w.max(h) as f32;
        assert!((0.33..=1.0).contains(&out_aspect), "output aspect {out_aspect}");
        let c = s.crop;
        assert!(c.x + c.width <= 120 && c.y + c.height <= 80);
        let crop_aspect = c.width.min(c.height) as f32 / c.width.max(c.height) as f32;
        // integer rounding of the crop moves the aspect by at most one pixel on the short side
        let tol = 1.0 / c.width.max(c.height) as f32;
        assert!(crop_aspect >= 0.33 - tol && crop_aspect <= 1.0, "crop {c:?}");
        if w != h {
            assert_eq!(
                w > h,
                c.width > c.height,
                "crop orientation follows the output: {c:?} vs {w}x{h}"
            );
        }
        min_aspect = min_aspect.min(out_aspect);
        if h > w {
            portrait += 1;
        } else if w > h {
            landscape += 1;
        }
    }
    assert!(
        portrait > 20 && landscape > 20,
        "both orientations: {portrait} / {landscape}"
    );
    assert!(min_aspect < 0.5, "narrow crops occur: {min_aspect}");
}

#[test]
fn crop_and_flip_are_identical_for_source_target_and_ct() {
    let (w, h) = (50, 36);
    let loader = RampLoader { w, h };
    let cfg = SamplerConfig {
        long_side: 24,
        multiple: 4,
        min_scale: 0.6,
        ..Default::default()
    };
    let sampler = Sampler::new(fake_scenes(3, 4), cfg, 4, 11).unwrap();
    let (mut flips, mut total) = (0, 0);
    for step in 0..10 {
        for s in sampler.batch(step, &loader).unwrap() {
            total += 1;
            let (ow, oh) = (s.source.width, s.source.height);
            let reference = |img: Image| {
                let out = crop_resize(&img, s.crop, ow, oh).unwrap();
                if s.flipped {
                    flip_horizontal(&out)
                } else {
                    out
                }
            };
            let (ls, lt) = (s.source_index as f32, s.target_index as f32);
            // independent reference: the same crop/flip applied by hand to the originals
            assert_eq!(s.source, reference(ramp(w, h, 3, 100.0 * ls)));
            assert_eq!(s.target, reference(ramp(w, h, 3, 100.0 * lt)));
            assert_eq!(s.ct, reference(ramp(w, h, 9, 100.0 * lt)));
            // geometry agrees: target − source is the constant light offset everywhere
            for (a, b) in s.target.data.iter().zip(&s.source.data) {
                assert!((a - b - 100.0 * (lt - ls)).abs() < 1e-3);
            }
            // the ramp increases with x in the original; flipped samples decrease along rows
            let row = &s.ct.data[..ow * 9];
            let (first, last) = (row[0], row[(ow - 1) * 9]);
            assert_eq!(
                s.flipped,
                first > last,
                "flip {} but row goes {first} -> {last}",
                s.flipped
            );
            // the crop's left edge (or right, when flipped) shows up in the values
            let left = if s.flipped { last } else { first };
            assert!((left - 100.0 * lt - s.crop.x as f32).abs() < 2.0 * s.crop.width as f32 / ow as f32);
            flips += s.flipped as usize;
        }
    }
    assert!(flips > 5 && flips < total - 5, "{flips} of {total} flipped");
}

/// A loader that marks C_T by where it comes from: the light id of the target, + 50 when the
/// entry names an explicit (coarse) C_T file.
struct MarkLoader;

impl Loader for MarkLoader {
    fn image(&self, e: &ImageEntry) -> pixl_train::Result<Image> {
        Ok(ramp(24, 16, 3, 100.0 * light_id(e)))
    }
    fn intrinsics(&self, e: &ImageEntry) -> pixl_train::Result<Image> {
        let coarse = e
            .intrinsics
            .as_ref()
            .is_some_and(|p| p.to_string_lossy().contains(".from_"));
        Ok(Image::new(24, 16, 9).map(|_| light_id(e) + if coarse { 50.0 } else { 0.0 }))
    }
}

/// One scene `s0` of three images `l0..l2` under `root`, where only the pair l0 -> l1 has a
/// coarse C_T (a marker file: [`MarkLoader`] never reads it).
fn scene_with_one_coarse_pair(root: &std::path::Path) -> (std::path::PathBuf, Vec<SceneEntry>) {
    let scene_dir = root.join("s0");
    std::fs::create_dir_all(&scene_dir).unwrap();
    std::fs::write(scene_dir.join("l1.from_l0.intrinsics.exr"), b"marker").unwrap();
    let scenes = vec![SceneEntry {
        name: "s0".into(),
        images: (0..3)
            .map(|l| ImageEntry {
                image: scene_dir.join(format!("l{l}.png")),
                intrinsics: None,
            })
            .collect(),
    }];
    (scene_dir, scenes)
}

/// `coarse_ct = 1` conditions on `pixl synth --coarse`'s C_T exactly for the pairs that have one
/// (here only l0 → l1) and changes nothing else of a sample; `coarse_ct = 0` never does.
#[test]
fn coarse_ct_is_used_where_it_exists_and_keeps_the_random_stream() {
    let dir = tempfile::tempdir().unwrap();
    let (scene_dir, scenes) = scene_with_one_coarse_pair(dir.path());
    let cfg = |p: f32| SamplerConfig {
        long_side: 16,
        multiple: 4,
        coarse_ct: p,
        ..Default::default()
    };
    let plain = Sampler::new(scenes.clone(), cfg(0.0), 4, 5).unwrap();
    let coarse = Sampler::new(scenes.clone(), cfg(1.0), 4, 5).unwrap();
    // 3 images: 6 ordered pairs, one of which (l0 -> l1) has a coarse C_T.
    assert_eq!(coarse.coarse_pairs(), (1, 6));
    assert_eq!(plain.coarse_pairs(), (0, 0));
    let mut used = 0;
    for step in 0..10 {
        for (a, b) in plain
            .batch(step, &MarkLoader)
            .unwrap()
            .into_iter()
            .zip(coarse.batch(step, &MarkLoader).unwrap())
        {
            assert_eq!(
                (a.source_index, a.target_index, a.crop, a.flipped),
                (b.source_index, b.target_index, b.crop, b.flipped)
            );
            assert_eq!(a.ct.data[0], a.target_index as f32, "coarse_ct = 0 used a coarse C_T");
            let want = if (b.source_index, b.target_index) == (0, 1) {
                50.0
            } else {
                0.0
            };
            assert_eq!(b.ct.data[0], b.target_index as f32 + want);
            assert_eq!(
                b.coarse_ct,
                want > 0.0,
                "the sample's coarse flag disagrees with its C_T"
            );
            assert!(!a.coarse_ct);
            used += (want > 0.0) as usize;
        }
    }
    assert!(used > 0, "pair l0 -> l1 never drawn: the test proves nothing");
    assert!(cfg(1.5).validate().is_err());
    // Asking for coarse C_T on a set that has none would silently train on exact C_T only.
    std::fs::remove_file(scene_dir.join("l1.from_l0.intrinsics.exr")).unwrap();
    let err = Sampler::new(scenes.clone(), cfg(0.5), 4, 5)
        .err()
        .expect("no coarse file: must refuse");
    assert!(err.to_string().contains("pixl synth --coarse"), "{err}");
    assert!(Sampler::new(scenes, cfg(0.0), 4, 5).is_ok());
}

/// `coarse_pair_share = p` makes a fraction p of the samples the pair with a coarse C_T (l0 -> l1
/// here), conditioned on it, keeps every other draw of the sample (crop, flip) and, for the
/// other samples, the pair too; the measured fraction matches [`Sampler::coarse_fraction`],
/// checked against the closed form by hand.
#[test]
fn coarse_pair_share_draws_the_pairs_that_have_a_coarse_ct() {
    let dir = tempfile::tempdir().unwrap();
    let (_, scenes) = scene_with_one_coarse_pair(dir.path());
    let cfg = |ct: f32, share: f32| SamplerConfig {
        long_side: 16,
        multiple: 4,
        coarse_ct: ct,
        coarse_pair_share: share,
        ..Default::default()
    };
    let plain = Sampler::new(scenes.clone(), cfg(0.0, 0.0), 4, 5).unwrap();
    let all = Sampler::new(scenes.clone(), cfg(0.0, 1.0), 4, 5).unwrap();
    let half = Sampler::new(scenes.clone(), cfg(0.5, 0.5), 4, 5).unwrap();
    // By hand: 1 of 6 pairs has a coarse C_T. share 1 -> 1; share 0.5, ct 0.5 -> 0.5 + 0.5 * 0.5 / 6.
    assert!((all.coarse_fraction() - 1.0).abs() < 1e-12);
    let want = 0.5 + 0.5 * 0.5 / 6.0;
    assert!(
        (half.coarse_fraction() - want).abs() < 1e-12,
        "{}",
        half.coarse_fraction()
    );
    assert_eq!(plain.coarse_fraction(), 0.0);
    let (mut n, mut coarse_half) = (0usize, 0usize);
    for step in 0..250 {
        let p = plain.batch(step, &MarkLoader).unwrap();
        let a = all.batch(step, &MarkLoader).unwrap();
        let h = half.batch(step, &MarkLoader).unwrap();
        for ((p, a), h) in p.iter().zip(&a).zip(&h) {
            assert_eq!((a.source_index, a.target_index), (0, 1));
            // (The marker value passes through the crop's resampling: equal up to rounding.)
            assert!(
                (a.ct.data[0] - 51.0).abs() < 1e-3,
                "share 1 did not condition on the coarse C_T"
            );
            assert_eq!((a.crop, a.flipped), (p.crop, p.flipped), "other draws changed");
            let is_coarse = h.ct.data[0] >= 50.0;
            if !is_coarse {
                assert_eq!(
                    (h.source_index, h.target_index, h.crop),
                    (p.source_index, p.target_index, p.crop)
                );
            }
            coarse_half += is_coarse as usize;
            n += 1;
        }
    }
    // 1000 samples: the binomial standard deviation is ~0.016; allow 4 of them.
    let frac = coarse_half as f64 / n as f64;
    assert!((frac - want).abs() < 0.064, "measured {frac}, expected {want}");
    assert!(cfg(0.0, -0.1).validate().is_err());
}
