//! The resamplers (`pixl_core::resample`) against independent f64 code: the tent filter as a
//! sum over every input pixel, the area average as an integral over each output footprint.
use pixl_core::resample::{area_resize, area_resize_to_chw, crop_resize, resize, CropRect};
use pixl_core::{Image, Rng};

fn image_from(rng: &mut Rng, w: usize, h: usize, c: usize, lo: f32, hi: f32) -> Image {
    let data: Vec<f32> = (0..w * h * c).map(|_| rng.uniform(lo, hi)).collect();
    Image::from_vec(w, h, c, data).unwrap()
}

/// Normalised tent weights of every input sample `0..limit` for output `o`, in f64.
fn naive_tent(offset: usize, n_in: usize, n_out: usize, limit: usize, o: usize) -> Vec<f64> {
    let scale = n_in as f64 / n_out as f64;
    let support = scale.max(1.0);
    let center = offset as f64 + (o as f64 + 0.5) * scale - 0.5;
    let ws: Vec<f64> = (0..limit)
        .map(|x| (1.0 - (x as f64 - center).abs() / support).max(0.0))
        .collect();
    let sum: f64 = ws.iter().sum();
    ws.iter().map(|w| w / sum).collect()
}

#[test]
fn tent_resize_matches_a_naive_f64_sum() {
    let mut rng = Rng::new(4);
    for (w, h, rect, ow, oh) in [
        (37, 23, CropRect::whole(37, 23), 10, 7),
        (37, 23, CropRect::whole(37, 23), 50, 31),
        (
            50,
            36,
            CropRect {
                x: 7,
                y: 3,
                width: 30,
                height: 20,
            },
            12,
            8,
        ),
        (
            50,
            36,
            CropRect {
                x: 0,
                y: 16,
                width: 9,
                height: 20,
            },
            16,
            5,
        ),
        (9, 5, CropRect::whole(9, 5), 9, 5),
    ] {
        let img = image_from(&mut rng, w, h, 3, 0.0, 1.0);
        let got = crop_resize(&img, rect, ow, oh).unwrap();
        assert_eq!((got.width, got.height, got.channels), (ow, oh, 3));
        let mut err = 0f64;
        for oy in 0..oh {
            let wy = naive_tent(rect.y, rect.height, oh, h, oy);
            for ox in 0..ow {
                let wx = naive_tent(rect.x, rect.width, ow, w, ox);
                for c in 0..3 {
                    let mut want = 0f64;
                    for (y, ty) in wy.iter().enumerate().filter(|(_, t)| **t > 0.0) {
                        for (x, tx) in wx.iter().enumerate().filter(|(_, t)| **t > 0.0) {
                            want += ty * tx * img.get(x, y, c) as f64;
                        }
                    }
                    err = err.max((got.get(ox, oy, c) as f64 - want).abs());
                }
            }
        }
        assert!(err < 2e-6, "{w}x{h} {rect:?} -> {ow}x{oh}: max error {err}");
    }
}

#[test]
fn tent_resize_of_a_constant_is_constant_and_of_a_ramp_is_linear() {
    let img = Image::from_fn(30, 20, 1, |x, _, _| 2.0 * x as f32 + 1.0);
    let rect = CropRect {
        x: 4,
        y: 2,
        width: 20,
        height: 10,
    };
    // 2× downsampling: the tent of radius 2 over a linear function returns its centre value
    let out = crop_resize(&img, rect, 10, 5).unwrap();
    for x in 1..9 {
        let centre = 4.0 + (x as f32 + 0.5) * 2.0 - 0.5;
        assert!(
            (out.get(x, 2, 0) - (2.0 * centre + 1.0)).abs() < 1e-4,
            "x {x}: {}",
            out.get(x, 2, 0)
        );
    }
    let flat = resize(&Image::from_fn(9, 9, 2, |_, _, c| 0.25 + c as f32), 13, 4).unwrap();
    assert!(flat
        .data
        .chunks(2)
        .all(|p| (p[0] - 0.25).abs() < 1e-6 && (p[1] - 1.25).abs() < 1e-6));
}

#[test]
fn tent_resize_refuses_empty_sizes_and_crops_outside_the_image() {
    let img = Image::new(8, 6, 3);
    assert!(crop_resize(&img, CropRect::whole(8, 6), 0, 4).is_err());
    assert!(crop_resize(
        &img,
        CropRect {
            x: 2,
            y: 0,
            width: 7,
            height: 6
        },
        4,
        4
    )
    .is_err());
    assert!(crop_resize(
        &img,
        CropRect {
            x: 0,
            y: 0,
            width: 0,
            height: 6
        },
        4,
        4
    )
    .is_err());
    assert!(resize(&Image::new(0, 6, 3), 4, 4).is_err());
}

/// Naive area average in f64: the integral of the piecewise-constant image over the output
/// pixel's footprint, divided by the footprint's area.
fn naive_area(img: &Image, ow: usize, oh: usize) -> Vec<f64> {
    let (w, h, ch) = (img.width, img.height, img.channels);
    let (sx, sy) = (w as f64 / ow as f64, h as f64 / oh as f64);
    let mut out = vec![0f64; ch * ow * oh];
    for c in 0..ch {
        for oy in 0..oh {
            for ox in 0..ow {
                let (x0, x1) = (ox as f64 * sx, (ox + 1) as f64 * sx);
                let (y0, y1) = (oy as f64 * sy, (oy + 1) as f64 * sy);
                let mut acc = 0.0;
                for y in 0..h {
                    let oy_len = (y1.min(y as f64 + 1.0) - y0.max(y as f64)).max(0.0);
                    if oy_len == 0.0 {
                        continue;
                    }
                    for x in 0..w {
                        let ox_len = (x1.min(x as f64 + 1.0) - x0.max(x as f64)).max(0.0);
                        acc += ox_len * oy_len * img.get(x, y, c) as f64;
                    }
                }
                out[(c * oh + oy) * ow + ox] = acc / ((x1 - x0) * (y1 - y0));
            }
        }
    }
    out
}

#[test]
fn area_resize_matches_a_naive_f64_integral() {
    let mut rng = Rng::new(3);
    for (w, h, ow, oh) in [
        (37, 23, 10, 7),
        (16, 16, 5, 3),
        (9, 5, 9, 5),
        (7, 4, 12, 9),
        (40, 3, 13, 1),
    ] {
        let img = image_from(&mut rng, w, h, 3, 0.0, 1.0);
        let got = area_resize_to_chw(&img, ow, oh).unwrap();
        let want = naive_area(&img, ow, oh);
        assert_eq!(got.len(), want.len());
        let err = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (*a as f64 - b).abs())
            .fold(0f64, f64::max);
        assert!(err < 2e-6, "{w}x{h} -> {ow}x{oh}: max error {err}");
        let interleaved = area_resize(&img, ow, oh).unwrap();
        assert_eq!(interleaved, Image::from_chw(ow, oh, 3, &got).unwrap());
    }
    // A constant image stays constant; the same size is the planar copy.
    let flat = Image::from_fn(31, 17, 9, |_, _, c| 0.1 * c as f32);
    let got = area_resize_to_chw(&flat, 8, 5).unwrap();
    for c in 0..9 {
        assert!(got[c * 40..(c + 1) * 40]
            .iter()
            .all(|v| (v - 0.1 * c as f32).abs() < 1e-6));
    }
    let img = image_from(&mut rng, 6, 4, 3, 0.0, 1.0);
    assert_eq!(area_resize_to_chw(&img, 6, 4).unwrap(), img.to_chw());
    assert!(area_resize_to_chw(&img, 0, 4).is_err());
}
