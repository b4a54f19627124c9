//! Relighting from a reference photograph: the target lighting is read off another photo of the
//! same view instead of being rendered from lights placed in a reconstructed scene. No depth,
//! mesh or render is involved.
//!
//! **Contract.** `C_T` of a target photo is built exactly as the paper builds the training
//! conditioning from a target photograph (§3.3), and as `pixl estimate lighting` and `pixl
//! prepare-targets` write it:
//! 1. a [`LightingEstimator`] (Marigold-IID-Lighting: [`crate::estimators::MarigoldLighting`])
//!    decomposes the target (RGB, sRGB-encoded values in `[0, 1]`) into linear albedo, diffuse
//!    shading and non-diffuse residual at the target's own size ([`Decomposition`]);
//! 2. App. B's rule, `pixl_intrinsics::compose::ct_from_decomposition`: A clipped to `[0, 1]`,
//!    S and R made finite and ≥ 0, then the joint 98th-percentile rescale of S and R with one
//!    shared cutoff τ, computed over the whole target (as the training targets are, before the
//!    sampler crops and resizes them);
//! 3. resized to the source's size by the tent filter the training sampler resizes `C_T` with
//!    (`pixl_core::resample::resize`; identity at the same size), then clamped to `[0, 1]`
//!    against the filter's rounding.
//!
//! The result ([`LikeCt`]) is 9 channels at the requested size, the representation
//! `relight::ct_at_working_size` and the network take. A target of another aspect ratio is
//! stretched to the source's frame: the two photos should show the same view. A difference
//! above [`ASPECT_TOLERANCE`] is reported ([`LikeCt::aspect_mismatch`], and a log warning).
//! [`relight_like`] then relights the source with it through [`crate::relight::relight`].
use crate::error::{PipelineError, Result};
use crate::observe::{Observer, Stage};
use crate::photo::Photo;
use crate::relight::{ct_at_working_size, relight, Network};
use candle_core::Device;
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;
use std::path::Path;

/// Relative difference of aspect ratios above which a target is reported as not matching the
/// source's frame (3 %: a few pixels of cropping, not another framing).
pub const ASPECT_TOLERANCE: f64 = 0.03;
/// Smallest side of a target photo (one latent pixel of Marigold's VAE).
pub const MIN_TARGET_SIDE: usize = 8;
/// Denoising steps of Marigold-IID-Lighting for a target's `C_T`: one, as the paper computes
/// the training conditioning (§3.3).
pub const LIKE_STEPS: usize = 1;

/// An intrinsic decomposition of a photo in the image-formation model of Marigold-IID-Lighting:
/// `I = A ⊙ S + R`, all linear RGB at the photo's size.
#[derive(Clone, Debug)]
pub struct Decomposition {
    pub albedo: Image,
    /// Diffuse shading.
    pub shading: Image,
    /// Non-diffuse residual.
    pub residual: Image,
}

impl Decomposition {
    /// Refuses maps that are not RGB at `size`; `by` names the estimator.
    pub fn check(&self, size: (usize, usize), by: &str) -> Result<()> {
        for (name, img) in [
            ("albedo", &self.albedo),
            ("shading", &self.shading),
            ("residual", &self.residual),
        ] {
            if (img.width, img.height, img.channels) != (size.0, size.1, 3) {
                return Err(PipelineError::input(format!(
                    "{by} returned a {}x{}x{} {name} map for a {}x{} photo (expected {}x{}x3)",
                    img.width, img.height, img.channels, size.0, size.1, size.0, size.1
                )));
            }
        }
        Ok(())
    }
}

/// An estimator of a photo's lighting intrinsics, plugged in by the caller (`pixl relight
/// --like` and `pixl studio` plug in [`crate::estimators::MarigoldLighting`]).
pub trait LightingEstimator: Send + Sync {
    /// A short name for messages ("Marigold-IID Lighting (marigold-lighting)").
    fn name(&self) -> String;
    /// The decomposition of `photo` (RGB, sRGB-encoded values in `[0, 1]`) at its size. Progress
    /// goes to `observer` as [`Stage::Intrinsics`] (the caller begins and ends the stage).
    fn decompose(&self, photo: &Image, observer: &dyn Observer) -> Result<Decomposition>;
}

/// A target's `C_T` at the size it was asked for, and how it was made.
#[derive(Clone, Debug)]
pub struct LikeCt {
    pub ct: Ct,
    /// The shared cutoff of the joint p98 rescale (in the estimator's linear units).
    pub tau: f32,
    /// The target photo's size.
    pub target_size: (usize, usize),
    /// Relative difference of the two aspect ratios (0: the same frame shape).
    pub aspect_mismatch: f64,
    /// The estimator's name.
    pub estimator: String,
}

impl LikeCt {
    /// Whether the aspect ratios differ by more than [`ASPECT_TOLERANCE`].
    pub fn aspect_differs(&self) -> bool {
        self.aspect_mismatch > ASPECT_TOLERANCE
    }
}

/// `max(a, b) / min(a, b) − 1` of the aspect ratios (width / height) of two sizes.
pub fn aspect_mismatch(a: (usize, usize), b: (usize, usize)) -> f64 {
    let ra = a.0.max(1) as f64 / a.1.max(1) as f64;
    let rb = b.0.max(1) as f64 / b.1.max(1) as f64;
    ra.max(rb) / ra.min(rb) - 1.0
}

/// Reads a target photo for the estimator: PNG/JPEG as stored, EXR (linear) sRGB-encoded;
/// values clamped to `[0, 1]` (non-finite values refused); at least [`MIN_TARGET_SIDE`] pixels
/// on each side.
pub fn read_target(path: &Path) -> Result<Image> {
    let img =
        pixl_core::io::read_rgb_finite(path).map_err(|e| PipelineError::from(e).context("reading the target photo"))?;
    let img = if pixl_core::io::extension(path) == "exr" {
        img.map(|v| pixl_core::image::linear_to_srgb(v.clamp(0.0, 1.0)))
    } else {
        img.map(|v| v.clamp(0.0, 1.0))
    };
    check_target(&img)?;
    Ok(img)
}

fn check_target(target: &Image) -> Result<()> {
    if target.channels != 3 {
        return Err(PipelineError::input(format!(
            "the target photo has {} channels; an RGB image is needed",
            target.channels
        )));
    }
    if target.width < MIN_TARGET_SIDE || target.height < MIN_TARGET_SIDE {
        return Err(PipelineError::input(format!(
            "the target photo is {}x{}; it needs at least {MIN_TARGET_SIDE}x{MIN_TARGET_SIDE} pixels",
            target.width, target.height
        )));
    }
    Ok(())
}

/// `C_T` from a decomposition at its own size by App. B's rule, then resized to `size` (steps
/// 2 and 3 of the module's contract). Returns `C_T` and τ.
pub fn ct_from_decomposition(d: &Decomposition, size: (usize, usize)) -> Result<(Ct, f32)> {
    if size.0 == 0 || size.1 == 0 {
        return Err(PipelineError::input(format!(
            "cannot make C_T of size {}x{}",
            size.0, size.1
        )));
    }
    let (ct, tau) = pixl_intrinsics::compose::ct_from_decomposition(&d.albedo, &d.shading, &d.residual)?;
    if (ct.width(), ct.height()) == size {
        return Ok((ct, tau));
    }
    let resize = |img: &Image| -> Result<Image> {
        Ok(pixl_core::resample::resize(img, size.0, size.1)?.map(|v| v.clamp(0.0, 1.0)))
    };
    let ct = Ct::new(resize(&ct.albedo)?, resize(&ct.shading)?, resize(&ct.residual)?)?;
    Ok((ct, tau))
}

/// The `C_T` of `target` (RGB, sRGB-encoded values in `[0, 1]`, any size) at `size` — the
/// source photo's size — by the module's contract; progress of the estimator goes to
/// `observer`.
pub fn target_ct(
    estimator: &dyn LightingEstimator,
    target: &Image,
    size: (usize, usize),
    observer: &dyn Observer,
) -> Result<LikeCt> {
    check_target(target)?;
    let target_size = (target.width, target.height);
    let mismatch = aspect_mismatch(size, target_size);
    if mismatch > ASPECT_TOLERANCE {
        tracing::warn!(
            "the target photo is {}x{} and the source {}x{}: aspect ratios {:.0} % apart; the target's lighting is \
             stretched to the source's frame (the two photos should show the same view)",
            target_size.0,
            target_size.1,
            size.0,
            size.1,
            100.0 * mismatch
        );
    }
    let name = estimator.name();
    observer.begin(Stage::Intrinsics, 0);
    let d = estimator.decompose(target, observer);
    observer.end(Stage::Intrinsics);
    let d = d.map_err(|e| e.context(format!("estimating the target photo's intrinsics with {name}")))?;
    d.check(target_size, &name)?;
    let (ct, tau) = ct_from_decomposition(&d, size)?;
    Ok(LikeCt {
        ct,
        tau,
        target_size,
        aspect_mismatch: mismatch,
        estimator: name,
    })
}

/// A source relit like a target photo.
pub struct Liked {
    /// At the source's full size.
    pub relit: Image,
    /// The target's `C_T` at the source's size.
    pub ct: LikeCt,
}

/// Relights `source` under the lighting of `target` (RGB, sRGB-encoded values in `[0, 1]`):
/// the target's `C_T` at the source's size ([`target_ct`]), area-averaged to the working size
/// `work`, then the network ([`crate::relight::relight`]) applied at the source's full size.
pub fn relight_like(
    net: &Network,
    source: Photo,
    target: &Image,
    estimator: &dyn LightingEstimator,
    work: (usize, usize),
    device: &Device,
    observer: &dyn Observer,
) -> Result<Liked> {
    let ct = target_ct(estimator, target, source.size(), observer)?;
    let ct_work = ct_at_working_size(&ct.ct, work)?;
    let relit = relight(net, source.image, &ct_work, work, device, observer)?;
    Ok(Liked { relit, ct })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::observe::Silent;

    /// Returns fixed maps, whatever the photo.
    struct Fixed(Decomposition);

    impl LightingEstimator for Fixed {
        fn name(&self) -> String {
            "fixed".into()
        }
        fn decompose(&self, _photo: &Image, _observer: &dyn Observer) -> Result<Decomposition> {
            Ok(self.0.clone())
        }
    }

    fn decomposition(w: usize, h: usize) -> Decomposition {
        Decomposition {
            albedo: Image::from_fn(w, h, 3, |x, _, c| 0.1 * c as f32 + 0.5 * x as f32 / w as f32),
            shading: Image::from_fn(w, h, 3, |x, y, _| 4.0 * (x + y) as f32 / (w + h) as f32),
            residual: Image::from_fn(w, h, 3, |x, y, _| if (x + y) % 5 == 0 { 3.0 } else { 0.0 }),
        }
    }

    #[test]
    fn aspect_mismatch_is_symmetric_and_zero_for_the_same_shape() {
        assert_eq!(aspect_mismatch((640, 480), (320, 240)), 0.0);
        let a = aspect_mismatch((640, 480), (640, 360));
        assert!((a - (16.0 / 9.0) / (4.0 / 3.0) + 1.0).abs() < 1e-12, "{a}");
        assert_eq!(a, aspect_mismatch((640, 360), (640, 480)));
    }

    #[test]
    fn same_size_is_app_b_exactly_and_another_size_is_the_tent_resize_of_it() {
        let d = decomposition(24, 16);
        let (direct, tau) =
            pixl_intrinsics::compose::ct_from_decomposition(&d.albedo, &d.shading, &d.residual).unwrap();
        let (same, tau_same) = ct_from_decomposition(&d, (24, 16)).unwrap();
        assert_eq!(tau, tau_same);
        assert_eq!(same.to_chw(), direct.to_chw());
        // Half the size: the resize of the rescaled maps (τ from the whole target, not after).
        let (half, tau_half) = ct_from_decomposition(&d, (12, 8)).unwrap();
        assert_eq!(tau, tau_half);
        let expect = pixl_core::resample::resize(&direct.shading, 12, 8).unwrap();
        let worst = half
            .shading
            .data
            .iter()
            .zip(&expect.data)
            .map(|(a, b)| (a - b.clamp(0.0, 1.0)).abs())
            .fold(0f32, f32::max);
        assert_eq!(worst, 0.0);
        for g in half.groups() {
            assert!(g.data.iter().all(|v| (0.0..=1.0).contains(v)));
        }
    }

    #[test]
    fn a_wrong_sized_decomposition_and_a_tiny_target_are_refused() {
        let target = Image::from_fn(20, 10, 3, |_, _, _| 0.5);
        let e = target_ct(&Fixed(decomposition(10, 10)), &target, (20, 10), &Silent).unwrap_err();
        assert!(
            e.to_string()
                .contains("fixed returned a 10x10x3 albedo map for a 20x10 photo"),
            "{e}"
        );
        let tiny = Image::from_fn(4, 10, 3, |_, _, _| 0.5);
        let e = target_ct(&Fixed(decomposition(4, 10)), &tiny, (20, 10), &Silent).unwrap_err();
        assert!(e.to_string().contains("at least 8x8"), "{e}");
        let ok = target_ct(&Fixed(decomposition(20, 10)), &target, (40, 30), &Silent).unwrap();
        assert_eq!((ok.ct.width(), ok.ct.height()), (40, 30));
        assert!(ok.aspect_differs());
        assert_eq!(ok.target_size, (20, 10));
    }
}
