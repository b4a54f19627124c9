//! Marigold-IID against diffusers' `MarigoldIntrinsicsPipeline` on tiny random models
//! (`fixtures/marigold`, made by `scripts/fixtures/marigold.py`): scheduler tables, the
//! empty-prompt embedding, preprocessing, the image latent, every UNet output and DDIM step,
//! the decoded maps and the final prediction, for ensembles of 1 and 3; Appearance from f32
//! files, Lighting from `.fp16` files only, and `groups8` (a UNet with 8 GroupNorm groups,
//! 1×1-convolution projections, three levels, per-block transformer depths; a text encoder
//! saved without `text_model.`).
//!
//! Tolerances: both sides compute in f32 with the exact GELU, so what remains is rounding.
//! Measured (max abs): UNet outputs 6.5e-6 (appearance), 6.8e-6 (lighting), 2.4e-5 (groups8);
//! latents after a step 6.9e-6, 8.0e-6, 1.2e-5; final maps 2.7e-6, 2.1e-6, 3.5e-6.
mod marigold_common;

use candle_core::{DType, Device, Tensor};
use marigold_common::{copy_dir, f32s, fixtures, load, max_abs, photo};
use pixl_estimate::marigold::{reduce, Ddim, IidVariant, Marigold, MarigoldOptions, Reduction, SchedulerConfig};

fn close(what: &str, got: &Tensor, want: &Tensor, tol: f64) {
    assert_eq!(got.dims(), want.dims(), "{what}: shape");
    let e = max_abs(&f32s(got), &f32s(want));
    eprintln!("{what}: max abs error {e:.2e}");
    assert!(e <= tol, "{what}: max abs error {e:.3e} > {tol:.0e}");
}

#[test]
fn scheduler_tables_match_diffusers() {
    let text = std::fs::read_to_string(fixtures().join("appearance/scheduler/scheduler_config.json")).unwrap();
    let d = Ddim::new(SchedulerConfig::from_json(&text).unwrap());
    let t = load("scheduler_tables.safetensors");
    // PyTorch's f32 sqrt is not always correctly rounded (1 ulp on some values). ᾱ, which is
    // what the step uses, agrees to 1e-6; the last betas are 1 − ᾱ_t/ᾱ_{t−1} of tiny ᾱ values,
    // where such an ulp becomes ~3e-6 (β₉₈₉ = 0.177290 vs 0.177287).
    let e = max_abs(&d.betas, &f32s(&t["betas"]));
    assert!(e <= 5e-6, "betas: {e:.2e}");
    let e = max_abs(&d.alphas_cumprod, &f32s(&t["alphas_cumprod"]));
    assert!(e <= 1e-6, "alphas_cumprod: {e:.2e}");
    assert!((d.final_alpha_cumprod - f32s(&t["final_alpha_cumprod"])[0]).abs() <= 1e-7);
    for n in [1usize, 3, 4, 10, 16] {
        let want: Vec<i64> = t[&format!("n{n}.timesteps")]
            .to_dtype(DType::I64)
            .unwrap()
            .to_vec1()
            .unwrap();
        let got: Vec<i64> = d.timesteps(n).unwrap().iter().map(|&x| x as i64).collect();
        assert_eq!(got, want, "timesteps for {n} steps");
        let at = f32s(&t[&format!("n{n}.alpha_t")]);
        let ap = f32s(&t[&format!("n{n}.alpha_prev")]);
        for (k, &ts) in d.timesteps(n).unwrap().iter().enumerate() {
            let a = d.alphas(ts, n);
            assert!((a.alpha_prod_t - at[k]).abs() <= 1e-6, "n={n} step {k}: ᾱ_t");
            assert!((a.alpha_prod_t_prev - ap[k]).abs() <= 1e-6, "n={n} step {k}: ᾱ_prev");
        }
    }
}

/// Largest UNet output error of all steps and members allowed.
const UNET_TOL: f64 = 1e-4;
/// Largest latent error after a DDIM step (errors accumulate over the 4 steps).
const LATENT_TOL: f64 = 1e-4;
/// Largest error of a final map (values in [0, 1]).
const MAP_TOL: f64 = 3e-5;

/// Runs one checkpoint against its case file.
fn parity(folder: &str, case_file: &str, variant: IidVariant) {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join(folder);
    copy_dir(&fixtures().join(folder), &dir);
    let dev = Device::Cpu;
    let m = Marigold::load(&dir, &dev).unwrap();
    assert_eq!(m.variant(), Some(variant));
    let case = load(case_file);
    close("empty embedding", m.empty_embedding(), &case["empty_embedding"], 1e-5);
    // The embedding was cached: a second load reads it (and gives the same).
    assert!(dir.join("text_encoder/pixl-empty-embedding.safetensors").is_file());
    let again = Marigold::load(&dir, &dev).unwrap();
    close("cached embedding", again.empty_embedding(), m.empty_embedding(), 0.0);

    let img = photo(&case);
    let res = 32;
    let pre = m.preprocess(&img, res).unwrap();
    close("preprocessed image", &pre.image, &case["image_processed"], 1e-5);
    let pad: Vec<i64> = case["padding"].to_dtype(DType::I64).unwrap().to_vec1().unwrap();
    assert_eq!((pre.padding.0 as i64, pre.padding.1 as i64), (pad[0], pad[1]));
    let lat = m.encode(&pre.image).unwrap();
    close("image latent", &lat, &case["image_latent"], 1e-4);

    for e in [1usize, 3] {
        let noise = &case[&format!("e{e}.noise")];
        // The UNet output of every step, all members together, on the reference's input latent
        // of that step (so that each step is checked on its own).
        let il = lat.repeat((e, 1, 1, 1)).unwrap();
        for (s, &t) in m.scheduler().timesteps(4).unwrap().iter().enumerate() {
            let input = match s {
                0 => noise.clone(),
                _ => case[&format!("e{e}.step{}.latent", s - 1)].clone(),
            };
            let out = m.unet(&il, &input, t).unwrap();
            close(
                &format!("e{e} step {s} UNet output"),
                &out,
                &case[&format!("e{e}.step{s}.unet_out")],
                UNET_TOL,
            );
        }
        // Every step's latent, member by member.
        for k in 0..e {
            let mut steps: Vec<Tensor> = Vec::new();
            let z = noise.narrow(0, k, 1).unwrap();
            m.denoise(&lat, &z, 4, &mut |_, l| steps.push(l.clone())).unwrap();
            assert_eq!(steps.len(), 4);
            for (s, l) in steps.iter().enumerate() {
                let want = case[&format!("e{e}.step{s}.latent")].narrow(0, k, 1).unwrap();
                close(&format!("e{e} member {k} step {s} latent"), l, &want, LATENT_TOL);
            }
        }
        let opts = MarigoldOptions {
            steps: Some(4),
            ensemble: e,
            resolution: Some(res),
            ..Default::default()
        };
        let pred = m.predict_with_noise(&img, &opts, noise, &mut |_| {}).unwrap();
        let want = &case[&format!("e{e}.prediction")];
        let (t, _, h, w) = want.dims4().unwrap();
        assert_eq!(pred.maps.len(), t);
        for (i, (target, map)) in pred.maps.iter().enumerate() {
            assert_eq!(target.name, variant.target_names()[i]);
            assert_eq!((map.width, map.height, map.channels), (w, h, 3));
            let planar: Vec<f32> = (0..3 * h * w)
                .map(|j| {
                    let (c, p) = (j / (h * w), j % (h * w));
                    map.data[p * 3 + c]
                })
                .collect();
            let e_ = max_abs(&planar, &f32s(&want.narrow(0, i, 1).unwrap()));
            eprintln!("e{e} prediction {}: max abs error {e_:.2e}", target.name);
            assert!(e_ <= MAP_TOL, "e{e} {}: max abs error {e_:.3e}", target.name);
        }
    }
}

#[test]
fn appearance_matches_diffusers() {
    parity("appearance", "appearance_case.safetensors", IidVariant::Appearance);
}

#[test]
fn lighting_from_fp16_files_matches_diffusers() {
    parity("lighting", "lighting_case.safetensors", IidVariant::Lighting);
}

#[test]
fn groups8_unet_matches_diffusers() {
    let unet = std::fs::read_to_string(fixtures().join("groups8/unet/config.json")).unwrap();
    let cfg = pixl_estimate::marigold::UnetConfig::from_json(&unet).unwrap();
    assert_eq!((cfg.norm_num_groups, cfg.use_linear_projection), (8, false));
    parity("groups8", "groups8_case.safetensors", IidVariant::Appearance);
}

#[test]
fn ensemble_reduction_matches_torch() {
    let case = load("appearance_case.safetensors");
    let x = &case["ensemble.input"];
    let n = x.dim(0).unwrap();
    let members: Vec<Vec<f32>> = (0..n).map(|i| f32s(&x.narrow(0, i, 1).unwrap())).collect();
    let refs: Vec<&[f32]> = members.iter().map(Vec::as_slice).collect();
    let med = reduce(&refs, Reduction::Median);
    assert_eq!(max_abs(&med, &f32s(&case["ensemble.median"])), 0.0, "median");
    let mean = reduce(&refs, Reduction::Mean);
    assert!(max_abs(&mean, &f32s(&case["ensemble.mean"])) <= 1e-6, "mean");
}
