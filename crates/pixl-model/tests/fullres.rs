//! Working-resolution relighting (`pixl_model::fullres`) against independent f64 code: the
//! bilinear resize-and-apply of gain and bias (the area downsampling is tested in pixl-core),
//! the staged forward against the plain one, and the whole chain with networks whose gain and
//! bias are known.
use candle_core::{DType, Device, Tensor};
use pixl_core::{Image, Rng};
use pixl_model::fullres::{apply_gain_bias, area_resize_to_chw, gain_bias_staged, relight_full, working_size};
use pixl_model::{build_trainable, freeze, Config};

fn image_from(rng: &mut Rng, w: usize, h: usize, c: usize, lo: f32, hi: f32) -> Image {
    let data: Vec<f32> = (0..w * h * c).map(|_| rng.uniform(lo, hi)).collect();
    Image::from_vec(w, h, c, data).unwrap()
}

/// A planar `(3, mh, mw)` map.
struct Planes<'a> {
    data: &'a [f32],
    mw: usize,
    mh: usize,
}

/// Naive bilinear sample of channel `c` of a planar map at output pixel `(x, y)` of a `w × h`
/// image, f64, half-pixel centres (`align_corners = false`), edges clamped.
fn naive_bilinear(map: &Planes, c: usize, (x, y): (usize, usize), (w, h): (usize, usize)) -> f64 {
    let Planes { data: map, mw, mh } = *map;
    let coord = |o: usize, n_in: usize, n_out: usize| {
        let s = ((o as f64 + 0.5) * n_in as f64 / n_out as f64 - 0.5).max(0.0);
        let i0 = (s.floor() as usize).min(n_in - 1);
        let i1 = (i0 + 1).min(n_in - 1);
        (i0, i1, (s - i0 as f64).min(1.0))
    };
    let (x0, x1, fx) = coord(x, mw, w);
    let (y0, y1, fy) = coord(y, mh, h);
    let at = |xx: usize, yy: usize| map[(c * mh + yy) * mw + xx] as f64;
    (1.0 - fy) * ((1.0 - fx) * at(x0, y0) + fx * at(x1, y0)) + fy * ((1.0 - fx) * at(x0, y1) + fx * at(x1, y1))
}

/// The area resize is pixl-core's (tested there against an f64 integral), with this module's
/// error type.
#[test]
fn area_resize_is_pixl_cores() {
    let mut rng = Rng::new(3);
    let img = image_from(&mut rng, 37, 23, 3, 0.0, 1.0);
    let want = pixl_core::resample::area_resize_to_chw(&img, 10, 7).unwrap();
    assert_eq!(area_resize_to_chw(&img, 10, 7).unwrap(), want);
    let e = area_resize_to_chw(&img, 0, 4).unwrap_err();
    assert!(matches!(e, pixl_model::fullres::FullResError::Size(_)), "{e}");
}

#[test]
fn apply_gain_bias_matches_a_naive_f64_bilinear() {
    let mut rng = Rng::new(17);
    // Upsampling by a non-integer factor, by an integer one, the same size, and downsampling.
    for (gw, gh, w, h) in [
        (7, 5, 53, 29),
        (4, 3, 16, 12),
        (9, 6, 9, 6),
        (12, 10, 5, 4),
        (1, 1, 3, 2),
    ] {
        let photo = image_from(&mut rng, w, h, 3, 0.0, 1.0);
        let gain: Vec<f32> = (0..3 * gw * gh).map(|_| rng.uniform(-0.8, 0.8)).collect();
        let bias: Vec<f32> = (0..3 * gw * gh).map(|_| rng.uniform(-0.3, 0.3)).collect();
        let mut out = photo.clone();
        apply_gain_bias(&mut out, &gain, &bias, gw, gh).unwrap();
        let mut clipped = 0;
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let g = naive_bilinear(
                        &Planes {
                            data: &gain,
                            mw: gw,
                            mh: gh,
                        },
                        c,
                        (x, y),
                        (w, h),
                    );
                    let b = naive_bilinear(
                        &Planes {
                            data: &bias,
                            mw: gw,
                            mh: gh,
                        },
                        c,
                        (x, y),
                        (w, h),
                    );
                    let raw = (1.0 + g) * photo.get(x, y, c) as f64 + b;
                    clipped += usize::from(!(0.0..=1.0).contains(&raw));
                    let want = raw.clamp(0.0, 1.0);
                    let got = out.get(x, y, c) as f64;
                    assert!(
                        (got - want).abs() < 1e-6,
                        "{gw}x{gh}->{w}x{h} at ({x},{y},{c}): {got} vs {want}"
                    );
                }
            }
        }
        if w * h > 50 {
            assert!(clipped > 0, "the test values should reach the clip");
        }
    }
    // Zero gain and bias leave the photo bitwise unchanged, at any size.
    let photo = image_from(&mut rng, 41, 27, 3, 0.0, 1.0);
    let mut out = photo.clone();
    apply_gain_bias(&mut out, &[0.0; 3 * 6 * 4], &[0.0; 3 * 6 * 4], 6, 4).unwrap();
    assert!(out
        .data
        .iter()
        .zip(&photo.data)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    // Wrong sizes are errors, not panics.
    let mut out = photo.clone();
    assert!(apply_gain_bias(&mut out, &[0.0; 5], &[0.0; 5], 6, 4).is_err());
    let mut grey = Image::new(4, 4, 1);
    assert!(apply_gain_bias(&mut grey, &[0.0; 3], &[0.0; 3], 1, 1).is_err());
}

fn rand_tensor(rng: &mut Rng, shape: &[usize], lo: f32, hi: f32) -> Tensor {
    let n: usize = shape.iter().product();
    let v: Vec<f32> = (0..n).map(|_| rng.uniform(lo, hi)).collect();
    Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
}

/// A `tiny` network (patch `patch`) whose modulation conv has the given weight scale and bias.
fn network(patch: usize, weight_scale: f32, bias: Option<[f32; 6]>, seed: u64) -> (Config, pixl_model::PixlRelight) {
    let mut cfg = Config::tiny();
    cfg.patch = patch;
    let (vm, _) = build_trainable(&cfg, seed, &Device::Cpu).unwrap();
    let mut rng = Rng::new(seed + 100);
    {
        let data = vm.data().lock().unwrap();
        let w = &data["modulation.conv.weight"];
        w.set(&rand_tensor(&mut rng, w.dims(), -weight_scale, weight_scale))
            .unwrap();
        if let Some(b) = bias {
            data["modulation.conv.bias"]
                .set(&Tensor::new(&b, &Device::Cpu).unwrap())
                .unwrap();
        }
    }
    let model = freeze(&cfg, &vm, DType::F32, &Device::Cpu).unwrap();
    (cfg, model)
}

#[test]
fn staged_gain_bias_is_bitwise_the_plain_one() {
    let (_cfg, model) = network(8, 0.1, None, 4);
    let mut rng = Rng::new(8);
    let (h, w) = (27, 45);
    let src = rand_tensor(&mut rng, &[1, 3, h, w], 0.0, 1.0);
    let ct = rand_tensor(&mut rng, &[1, 9, h, w], 0.0, 1.0);
    let (g1, b1) = model.gain_bias(&src, &ct).unwrap();
    let mut calls = Vec::new();
    let (g2, b2) = gain_bias_staged(&model, &src, &ct, &mut |d, t, s: &str| {
        calls.push((d, t, s.to_string()))
    })
    .unwrap();
    let v = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    assert!(
        v(&g1).iter().any(|x| *x != 0.0),
        "the test network must have a non-zero gain"
    );
    assert_eq!(
        v(&g1).iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
        v(&g2).iter().map(|x| x.to_bits()).collect::<Vec<_>>()
    );
    assert_eq!(
        v(&b1).iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
        v(&b2).iter().map(|x| x.to_bits()).collect::<Vec<_>>()
    );
    // tiny: 2 source blocks, the intrinsics encoder, 4 trunk blocks, the head.
    let total = 2 + 1 + 4 + 1;
    assert_eq!(calls.len(), total);
    assert!(calls.iter().enumerate().all(|(i, c)| c.0 == i + 1 && c.1 == total));
    assert_eq!(calls.last().unwrap().2, "head");
}

#[test]
fn full_resolution_output_of_known_networks() {
    let mut rng = Rng::new(21);
    let (w, h) = (203, 131);
    let work = working_size(w, h, 64);
    assert_eq!(work, (64, 41));
    let photo = image_from(&mut rng, w, h, 3, 0.0, 1.0);
    let ct: Vec<f32> = (0..9 * work.0 * work.1).map(|_| rng.uniform(0.0, 1.0)).collect();
    let mut none = |_: usize, _: usize, _: &str| {};

    // Fresh weights: g = b = 0, the output is the photo exactly, at full size.
    let (_, fresh) = network(16, 0.0, None, 1);
    let out = relight_full(&fresh, photo.clone(), &ct, work, &Device::Cpu, &mut none).unwrap();
    assert_eq!((out.width, out.height), (w, h));
    assert!(out
        .data
        .iter()
        .zip(&photo.data)
        .all(|(a, b)| a.to_bits() == b.to_bits()));

    // Zero modulation weight, bias (g, b) per channel: constant maps, known output everywhere.
    let gb = [0.5, -0.25, 0.0, 0.05, 0.1, -0.2];
    let (_, constant) = network(16, 0.0, Some(gb), 2);
    let out = relight_full(&constant, photo.clone(), &ct, work, &Device::Cpu, &mut none).unwrap();
    for (i, (o, s)) in out.data.iter().zip(&photo.data).enumerate() {
        let c = i % 3;
        let want = ((1.0 + gb[c] as f64) * *s as f64 + gb[3 + c] as f64).clamp(0.0, 1.0);
        assert!((*o as f64 - want).abs() < 1e-6, "sample {i}: {o} vs {want}");
    }

    // A general network: the full-size output is the working-size gain and bias, computed on the
    // area-averaged photo, bilinearly resized and applied (naive f64 here).
    let (_, general) = network(8, 0.2, None, 3);
    let src_w = area_resize_to_chw(&photo, work.0, work.1).unwrap();
    let src_t = Tensor::from_vec(src_w, (1, 3, work.1, work.0), &Device::Cpu).unwrap();
    let ct_t = Tensor::from_vec(ct.clone(), (1, 9, work.1, work.0), &Device::Cpu).unwrap();
    let (g, b) = general.gain_bias(&src_t, &ct_t).unwrap();
    let v = |t: &Tensor| t.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let (g, b) = (v(&g), v(&b));
    assert!(g.iter().any(|x| x.abs() > 1e-3));
    let out = relight_full(&general, photo.clone(), &ct, work, &Device::Cpu, &mut none).unwrap();
    for y in (0..h).step_by(7) {
        for x in (0..w).step_by(5) {
            for c in 0..3 {
                let gg = naive_bilinear(
                    &Planes {
                        data: &g,
                        mw: work.0,
                        mh: work.1,
                    },
                    c,
                    (x, y),
                    (w, h),
                );
                let bb = naive_bilinear(
                    &Planes {
                        data: &b,
                        mw: work.0,
                        mh: work.1,
                    },
                    c,
                    (x, y),
                    (w, h),
                );
                let want = ((1.0 + gg) * photo.get(x, y, c) as f64 + bb).clamp(0.0, 1.0);
                assert!((out.get(x, y, c) as f64 - want).abs() < 1e-5, "({x},{y},{c})");
            }
        }
    }

    // At the working size itself the result is the network's own forward pass, bitwise.
    let small = image_from(&mut rng, 40, 24, 3, 0.0, 1.0);
    let ct_small: Vec<f32> = (0..9 * 40 * 24).map(|_| rng.uniform(0.0, 1.0)).collect();
    let out = relight_full(&general, small.clone(), &ct_small, (40, 24), &Device::Cpu, &mut none).unwrap();
    let src_t = Tensor::from_vec(small.to_chw(), (1, 3, 24, 40), &Device::Cpu).unwrap();
    let ct_t = Tensor::from_vec(ct_small, (1, 9, 24, 40), &Device::Cpu).unwrap();
    let fwd = Image::from_chw(40, 24, 3, &v(&general.forward(&src_t, &ct_t).unwrap())).unwrap();
    assert!(out.data.iter().zip(&fwd.data).all(|(a, b)| a.to_bits() == b.to_bits()));

    // A C_T of the wrong size is an error.
    assert!(relight_full(&general, small, &[0.0; 9], (40, 24), &Device::Cpu, &mut none).is_err());
}
