//! DA3 preprocessing pieces against their references: cv2.resize byte for byte
//! (`fixtures/da3/resize.safetensors`, opencv-python 5.1.0), the official size rules by hand.
mod da3_common;

use candle_core::Device;
use da3_common::fixtures;
use pixl_estimate::da3::resize::{cv2_resize_u8, Cv2Filter};

#[test]
fn cv2_resize_matches_opencv_byte_for_byte() {
    let t = candle_core::safetensors::load(fixtures().join("resize.safetensors"), &Device::Cpu).unwrap();
    let mut names: Vec<&str> = t.keys().filter_map(|k| k.strip_suffix(".src")).collect();
    names.sort_unstable();
    assert!(names.len() >= 8, "{names:?}");
    let mut failures = Vec::new();
    for name in names {
        let src = &t[&format!("{name}.src")];
        let dst = &t[&format!("{name}.dst")];
        let (sh, sw, cn) = src.dims3().unwrap();
        let (dh, dw, _) = dst.dims3().unwrap();
        let filter = if name.starts_with("cubic") {
            Cv2Filter::Cubic
        } else {
            Cv2Filter::Area
        };
        let src = src.flatten_all().unwrap().to_vec1::<u8>().unwrap();
        let want = dst.flatten_all().unwrap().to_vec1::<u8>().unwrap();
        let got = cv2_resize_u8(&src, sw, sh, cn, dw, dh, filter);
        let bad: Vec<usize> = (0..want.len()).filter(|&i| got[i] != want[i]).collect();
        if !bad.is_empty() {
            let show: Vec<String> = bad
                .iter()
                .take(6)
                .map(|&i| {
                    format!(
                        "[y{} x{} c{}] {} vs {}",
                        i / (dw * cn),
                        (i / cn) % dw,
                        i % cn,
                        got[i],
                        want[i]
                    )
                })
                .collect();
            failures.push(format!(
                "{name} {sw}x{sh}->{dw}x{dh}: {} of {} differ: {}",
                bad.len(),
                want.len(),
                show.join(", ")
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The official size rules, by hand: longest side to `process_res` with Python's
/// round-half-to-even, then each side to the nearest multiple of 14 with ties upward.
#[test]
fn process_sizes_follow_the_official_rules() {
    use pixl_estimate::da3::resize::Cv2Filter::{Area, Cubic};
    use pixl_estimate::da3::ProcessPlan;
    let p = |w, h, r| ProcessPlan::new(w, h, r).unwrap();
    // 640x480 -> 504x378 (378 = 27·14): one INTER_AREA resize, nothing to round.
    let a = p(640, 480, 504);
    assert_eq!(
        (a.bounded, a.processed, a.first_filter(), a.second_filter()),
        ((504, 378), (504, 378), Some(Area), None)
    );
    // 1008x25: 12.5 rounds to 12 (half to even), then 12 -> 14 (nearest multiple, enlarging: cubic).
    let b = p(1008, 25, 504);
    assert_eq!(
        (b.bounded, b.processed, b.second_filter()),
        ((504, 12), (504, 14), Some(Cubic))
    );
    // 1008x42: 21 lies halfway between 14 and 28: ties go up.
    assert_eq!(p(1008, 42, 504).processed, (504, 28));
    // 1008x54: 27 -> 28; 1008x50: 25 -> 28; 1008x38: 19 -> 14 (shrinks: INTER_AREA).
    assert_eq!(p(1008, 54, 504).processed, (504, 28));
    assert_eq!(p(1008, 50, 504).processed, (504, 28));
    let c = p(1008, 38, 504);
    assert_eq!((c.processed, c.second_filter()), ((504, 14), Some(Area)));
    // Already at process_res: no first resize.
    let d = p(504, 300, 504);
    assert_eq!(
        (d.bounded, d.first_filter(), d.processed),
        ((504, 300), None, (504, 294))
    );
    // Upscaling a small photo: INTER_CUBIC.
    assert_eq!(p(100, 50, 504).first_filter(), Some(Cubic));
    // Refused: empty, too small a process_res, too elongated.
    assert!(ProcessPlan::new(0, 10, 504).is_err());
    assert!(ProcessPlan::new(10, 10, 13).is_err());
    assert!(ProcessPlan::new(5000, 6, 504).is_err());
}

/// `torch.quantile(x, q)` (linear interpolation) by hand, and the sky rule's guards.
#[test]
fn quantile_and_sky_rule_by_hand() {
    use pixl_estimate::da3::postprocess::{apply_sky_rule, quantile_linear};
    // Values 0..=100: rank 0.99·100 = 99 -> 99; 0..=10: rank 9.9 -> 9.9.
    let mut v: Vec<f32> = (0..=100).rev().map(|i| i as f32).collect();
    assert_eq!(quantile_linear(&mut v, 0.99), 99.0);
    let mut v: Vec<f32> = (0..=10).map(|i| i as f32).collect();
    assert!((quantile_linear(&mut v, 0.99) - 9.9).abs() < 1e-5);
    // 20 ground pixels of depth 1..=20, 12 sky pixels: sky takes q0.99 = 19 + 0.81 = 19.81.
    let mut depth: Vec<f32> = (1..=20)
        .map(|i| i as f32)
        .chain(std::iter::repeat_n(100.0, 12))
        .collect();
    let sky: Vec<f32> = std::iter::repeat_n(0.0, 20)
        .chain(std::iter::repeat_n(0.3, 12))
        .collect();
    let q = apply_sky_rule(&mut depth, &sky).unwrap().unwrap();
    assert!((q - 19.81).abs() < 1e-4, "{q}");
    assert!(depth[20..].iter().all(|&d| d == q) && depth[..20].iter().zip(1..).all(|(&d, i)| d == i as f32));
    // Only 10 sky pixels: unchanged (the official rule needs more than 10 of each).
    let mut depth: Vec<f32> = vec![1.0; 30];
    let sky: Vec<f32> = (0..30).map(|i| if i < 10 { 0.9 } else { 0.0 }).collect();
    assert_eq!(apply_sky_rule(&mut depth, &sky).unwrap(), None);
    assert!(depth.iter().all(|&d| d == 1.0));
}

/// Metric scaling by hand: a 1000x500 photo with f = 800 px processed at 504x252 gives
/// fx = 800·504/1000 = 403.2, fy = 800·252/500 = 403.2, scale 403.2/300.
#[test]
fn metric_scale_by_hand() {
    use pixl_estimate::da3::postprocess::metric_scale;
    let s = metric_scale(800.0, (1000, 500), (504, 252));
    assert!((s - 403.2 / 300.0).abs() < 1e-12);
    // Unequal side ratios (rounding to multiples of 14): the mean of fx and fy.
    let s = metric_scale(300.0, (100, 100), (98, 112));
    assert!((s - (294.0 + 336.0) / 2.0 / 300.0).abs() < 1e-12);
}

/// Bad photos are refused with an input error, not a panic.
#[test]
fn bad_photos_are_refused() {
    use pixl_estimate::da3::preprocess::{preprocess, to_rgb8};
    let mut img = pixl_core::Image::new(20, 10, 3);
    img.data[7] = f32::NAN;
    let err = to_rgb8(&img).unwrap_err().to_string();
    assert!(err.contains("non-finite") && err.contains("x=2"), "{err}");
    let five = pixl_core::Image::new(4, 4, 5);
    assert!(to_rgb8(&five).is_err());
    let empty = pixl_core::Image::new(0, 0, 3);
    assert!(preprocess(&empty, 504, &Device::Cpu).is_err());
    // Grey and RGBA are accepted: grey replicated, alpha dropped.
    let grey = pixl_core::Image::from_fn(2, 1, 1, |x, _, _| x as f32);
    assert_eq!(to_rgb8(&grey).unwrap(), vec![0, 0, 0, 255, 255, 255]);
    let rgba = pixl_core::Image::from_fn(1, 1, 4, |_, _, c| [0.2, 0.4, 0.6, 0.0][c]);
    assert_eq!(to_rgb8(&rgba).unwrap(), vec![51, 102, 153]);
}
