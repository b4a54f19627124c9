//! Relighting like a reference photo, through the library, on the bundled demo scene
//! (`assets/demo/scene.toml`, the scene `pixl demo` uses) rendered under the paper's presets:
//!
//! - with an estimator that returns a render's exact intrinsics (its passes, unrescaled), the
//!   `C_T` the `--like` path builds from the target render is the one `compose` makes from the
//!   same passes (App. B), bit for bit, at the same size and resized; and relighting with it
//!   gives exactly what the render path gives with that `C_T`;
//! - with the bundled demo weights, two targets lit by two presets give two different relit
//!   images, each nearer its own target than the other's;
//! - with Marigold-IID-Lighting (the tiny random checkpoint of `fixtures/marigold/lighting`), the
//!   `C_T` equals App. B's rule applied to the model's own prediction of the target.
use candle_core::{DType, Device};
use pixl_core::Image;
use pixl_intrinsics::compose::{compose_film, ComposeOptions};
use pixl_intrinsics::ct::Ct;
use pixl_pipeline::estimators::MarigoldLighting;
use pixl_pipeline::exif::{Focal, FocalSource};
use pixl_pipeline::like::{relight_like, target_ct, Decomposition, LightingEstimator, LIKE_STEPS};
use pixl_pipeline::relight::{ct_at_working_size, relight, Network};
use pixl_pipeline::{Observer, Photo, Result, Silent};
use pixl_render::{Film, RenderOptions, Scene};

const DEMO_SCENE: &str = include_str!("../../../assets/demo/scene.toml");

/// The demo scene under `preset` (its own light replaced), rendered at `size`.
fn render(preset: &str, size: (usize, usize)) -> Film {
    let mut scene = Scene::from_toml_str(DEMO_SCENE).unwrap();
    pixl_render::presets::apply_preset(&mut scene, preset, true).unwrap();
    let opts = RenderOptions {
        spp: 16,
        width: Some(size.0 as u32),
        height: Some(size.1 as u32),
        seed: 0,
        max_bounces: 4,
    };
    pixl_render::render(&scene, &opts, &|_, _| {}).unwrap()
}

/// A render's exact decomposition: its passes composed without the rescale (A, S, R in HDR).
fn exact_decomposition(film: &Film) -> Decomposition {
    let raw = compose_film(
        film,
        &ComposeOptions {
            rescale: false,
            sanitize: false,
        },
    )
    .unwrap()
    .ct;
    Decomposition {
        albedo: raw.albedo,
        shading: raw.shading,
        residual: raw.residual,
    }
}

/// An estimator that knows the renders it will be shown: it returns the exact decomposition of
/// the render whose picture it is handed, and refuses any other image (so the `--like` path
/// must hand it the target photo unchanged).
struct Oracle(Vec<(Image, Decomposition)>);

impl Oracle {
    fn of(films: &[&Film]) -> Oracle {
        Oracle(
            films
                .iter()
                .map(|f| (f.combined_srgb(), exact_decomposition(f)))
                .collect(),
        )
    }
}

impl LightingEstimator for Oracle {
    fn name(&self) -> String {
        "oracle".into()
    }
    fn decompose(&self, photo: &Image, _observer: &dyn Observer) -> Result<Decomposition> {
        self.0
            .iter()
            .find(|(img, _)| img.width == photo.width && img.height == photo.height && img.data == photo.data)
            .map(|(_, d)| d.clone())
            .ok_or_else(|| pixl_pipeline::PipelineError::input("the oracle was shown an image it does not know"))
    }
}

fn photo(img: Image) -> Photo {
    let h = img.height as f64;
    Photo::from_image(
        img,
        Focal {
            px: 0.5 * h / 25f64.to_radians().tan(),
            source: FocalSource::Default(50.0),
        },
    )
}

fn same_ct(a: &Ct, b: &Ct) -> bool {
    (a.width(), a.height()) == (b.width(), b.height())
        && a.to_chw()
            .iter()
            .zip(b.to_chw())
            .all(|(x, y)| x.to_bits() == y.to_bits())
}

fn mean_abs(a: &Image, b: &Image) -> f64 {
    assert_eq!((a.width, a.height, a.channels), (b.width, b.height, b.channels));
    a.data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| (x - y).abs() as f64)
        .sum::<f64>()
        / a.data.len() as f64
}

#[test]
fn ct_from_a_target_render_is_app_b_of_its_passes_and_relights_like_the_render_path() {
    let size = (80, 64); // the demo camera's 5:4
    let source = render("warm-overhead-flash", size);
    let target_b = render("cool-side-flash", size);
    let target_c = render("warm-interior-sun", size);
    let large_b = render("cool-side-flash", (160, 128));
    let oracle = Oracle::of(&[&source, &target_b, &target_c, &large_b]);
    let src_img = source.combined_srgb();

    // The C_T the --like path builds = compose's App. B C_T of the same passes, bit for bit.
    let like_b = target_ct(&oracle, &target_b.combined_srgb(), size, &Silent).unwrap();
    let composed_b = compose_film(&target_b, &ComposeOptions::default()).unwrap();
    assert!(
        same_ct(&like_b.ct, &composed_b.ct),
        "C_T of target B differs from compose's"
    );
    assert_eq!(Some(like_b.tau), composed_b.tau);
    assert_eq!(like_b.aspect_mismatch, 0.0);
    // A target twice the size: App. B at its size (τ of the whole target), then the tent resize.
    let like_large = target_ct(&oracle, &large_b.combined_srgb(), size, &Silent).unwrap();
    let composed_large = compose_film(&large_b, &ComposeOptions::default()).unwrap().ct;
    let resized = Ct::new(
        pixl_core::resample::resize(&composed_large.albedo, size.0, size.1).unwrap(),
        pixl_core::resample::resize(&composed_large.shading, size.0, size.1).unwrap(),
        pixl_core::resample::resize(&composed_large.residual, size.0, size.1).unwrap(),
    )
    .unwrap();
    let worst = like_large
        .ct
        .to_chw()
        .iter()
        .zip(resized.to_chw())
        .map(|(a, b)| (a - b.clamp(0.0, 1.0)).abs())
        .fold(0f32, f32::max);
    assert_eq!(worst, 0.0, "resized C_T");

    // Relit like target B = the render path's relight under compose's C_T of B, exactly.
    let dev = Device::Cpu;
    let net = Network::load(None, DType::F32, &dev, false).unwrap();
    let work = size;
    let liked_b = relight_like(
        &net,
        photo(src_img.clone()),
        &target_b.combined_srgb(),
        &oracle,
        work,
        &dev,
        &Silent,
    )
    .unwrap();
    let by_render = relight(
        &net,
        src_img.clone(),
        &ct_at_working_size(&composed_b.ct, work).unwrap(),
        work,
        &dev,
        &Silent,
    )
    .unwrap();
    assert_eq!((liked_b.relit.width, liked_b.relit.height), size);
    assert!(liked_b
        .relit
        .data
        .iter()
        .zip(&by_render.data)
        .all(|(a, b)| a.to_bits() == b.to_bits()));

    let liked_c = relight_like(
        &net,
        photo(src_img.clone()),
        &target_c.combined_srgb(),
        &oracle,
        work,
        &dev,
        &Silent,
    )
    .unwrap();
    let liked_a = relight_like(&net, photo(src_img.clone()), &src_img, &oracle, work, &dev, &Silent).unwrap();
    let (tb, tc) = (target_b.combined_srgb(), target_c.combined_srgb());
    // Measured with the weights bundled when this was written (mean absolute difference over
    // RGB in [0, 1]): relit B vs relit C 0.095; relit B to targets B / C 0.104 / 0.121; relit C
    // to C / B 0.052 / 0.123; relit under the source's own C_T to the source 0.044, under B and
    // C 0.073 and 0.085. A network that ignored C_T (or fresh weights: g = b = 0) gives 0 for
    // the first and fails every comparison below.
    let b_vs_c = mean_abs(&liked_b.relit, &liked_c.relit);
    assert!(b_vs_c > 0.02, "relit like B and like C barely differ: {b_vs_c}");
    let (b_to_b, b_to_c) = (mean_abs(&liked_b.relit, &tb), mean_abs(&liked_b.relit, &tc));
    assert!(b_to_b < b_to_c, "relit like B is nearer C ({b_to_c}) than B ({b_to_b})");
    let (c_to_c, c_to_b) = (mean_abs(&liked_c.relit, &tc), mean_abs(&liked_c.relit, &tb));
    assert!(c_to_c < c_to_b, "relit like C is nearer B ({c_to_b}) than C ({c_to_c})");
    // Target == source: not the identity with these weights (0.044 is about 11/255 on average),
    // but it changes the source less than either other lighting does.
    let own = mean_abs(&liked_a.relit, &src_img);
    let others = mean_abs(&liked_b.relit, &src_img).min(mean_abs(&liked_c.relit, &src_img));
    assert!(
        own < others,
        "relit under its own lighting moved {own}, under another {others}"
    );
}

#[test]
fn marigold_lighting_ct_is_app_b_of_its_own_prediction() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/marigold/lighting");
    let opts = pixl_estimate::marigold::MarigoldOptions {
        steps: Some(LIKE_STEPS),
        resolution: Some(32),
        ..Default::default()
    };
    let est = MarigoldLighting::load(&dir, opts.clone(), "marigold-lighting", &Device::Cpu).unwrap();
    let target = render("cool-side-flash", (40, 32)).combined_srgb();
    let pred = est.model().predict(&target, &opts, &mut |_| {}).unwrap();
    let (direct, tau) = pixl_intrinsics::compose::ct_from_decomposition(
        pred.get("albedo").unwrap(),
        pred.get("shading").unwrap(),
        pred.get("residual").unwrap(),
    )
    .unwrap();
    let like = target_ct(&est, &target, (40, 32), &Silent).unwrap();
    assert_eq!(like.tau, tau);
    assert!(
        same_ct(&like.ct, &direct),
        "Marigold C_T differs from App. B of its prediction"
    );
    assert!(like.estimator.contains("Marigold-IID Lighting"));
}
