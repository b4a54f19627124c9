//! Marigold Normals v1.1 (`prs-eth/marigold-normals-v1-1`, Apache-2.0): the surface normals of a
//! photo, with the official diffusers-format checkpoint loaded unchanged (the folder layout,
//! `.fp16` variants and the SD2 networks of [`super::Marigold`]; UNet 8 → 4 latent channels).
//!
//! Contract of [`MarigoldNormals::predict`]: a photo ([`Image`], values in [0, 1], 1–4
//! channels; RGB is used) → a 3-channel map at the photo's size whose pixels are **unit**
//! normals, each component in [−1, 1], in Marigold's **camera frame: x right, y up, z towards
//! the viewer** (R, G, B = x, y, z; a wall facing the camera is (0, 0, 1)). Sources for the
//! frame: diffusers' `visualize_normals` documents x "right", y "top" and z "facing the
//! observer", and Marigold's training flips a sample left–right by negating x alone. It is the
//! frame of the reconstructed scene (`pixl_render::depth`: camera at the origin looking down −Z,
//! +X right, +Y up), so the map needs no change of axes there.
//!
//! The pipeline is diffusers' `MarigoldNormalsPipeline`, step by step:
//! 1. –3. as IID ([`super`]): preprocessing to the processing resolution, the image latent, and
//!    per ensemble member `steps` DDIM updates of a 4-channel latent from Gaussian noise;
//! 4. decoding: the VAE's output clipped to [−1, 1]; when the checkpoint's `use_full_z_range` is
//!    false, `z ← z/2 + 1/2`; each pixel divided by `max(|n|, 1e-6)`; padding removed;
//! 5. with 2 or more members ([`ensemble`]): `m` = the members' mean, normalised; per pixel
//!    `c_e = clamp(m · n_e, −1, 1)`; [`NormalsReduction::Closest`] (the default) keeps the member
//!    with the largest `c_e` (the first on ties, as `argmax`), [`NormalsReduction::Mean`] keeps
//!    `m`; the uncertainty is `mean_e(arccos c_e) / π`, in [0, 1];
//! 6. bilinear resize (no antialiasing) to the photo's size, then every pixel normalised again;
//!    the uncertainty is resized the same way.
//!
//! Noise comes from [`pixl_core::rng::Rng`] seeded by [`NormalsOptions::seed`];
//! [`MarigoldNormals::predict_with_noise`] takes it from the caller (`(ensemble, 4, h/8, w/8)`).
//! Everything runs in f32.
use super::{resized_size, Marigold, MarigoldOptions, PipelineKind, Progress};
use crate::error::EstimateError;
use crate::resize;
use candle_core::{Device, Tensor};
use pixl_core::Image;
use std::path::Path;

/// How ensemble members are combined (diffusers' `ensembling_kwargs["reduction"]`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NormalsReduction {
    /// Per pixel, the member closest in angle to the normalised mean (diffusers' default).
    Closest,
    /// The normalised mean.
    Mean,
}

/// Options of [`MarigoldNormals::predict`].
#[derive(Clone, Debug, PartialEq)]
pub struct NormalsOptions {
    /// Denoising steps (`None`: the checkpoint's default, 4 for v1.1).
    pub steps: Option<usize>,
    /// Ensemble members (≥ 1).
    pub ensemble: usize,
    /// Longest side processed (`None`: the checkpoint's default, 768; a multiple of 8).
    pub resolution: Option<usize>,
    pub reduction: NormalsReduction,
    /// Seed of the initial noise.
    pub seed: u64,
    /// Also the ensemble's angular spread per pixel (needs an ensemble of 2 or more).
    pub uncertainty: bool,
}

impl Default for NormalsOptions {
    fn default() -> Self {
        Self {
            steps: None,
            ensemble: 1,
            resolution: None,
            reduction: NormalsReduction::Closest,
            seed: 0,
            uncertainty: false,
        }
    }
}

impl NormalsOptions {
    /// The options the shared checks ([`Marigold::resolve`]) and estimates read.
    fn shared(&self) -> MarigoldOptions {
        MarigoldOptions {
            steps: self.steps,
            ensemble: self.ensemble,
            resolution: self.resolution,
            seed: self.seed,
            uncertainty: self.uncertainty,
            ..Default::default()
        }
    }
}

/// Output of [`MarigoldNormals::predict`].
#[derive(Clone, Debug)]
pub struct NormalsPrediction {
    /// Unit normals at the photo's size, 3 channels (x right, y up, z towards the viewer).
    pub normals: Image,
    /// With [`NormalsOptions::uncertainty`]: one channel in [0, 1], the members' mean angle to
    /// their mean normal divided by π.
    pub uncertainty: Option<Image>,
    /// Resized (unpadded) network input `(width, height)`.
    pub processed_size: (usize, usize),
    pub steps: usize,
    pub ensemble: usize,
}

/// A loaded Marigold normals checkpoint.
pub struct MarigoldNormals {
    net: Marigold,
}

impl MarigoldNormals {
    /// Loads a diffusers-format folder; one of another Marigold pipeline (IID) is refused.
    pub fn load(dir: &Path, device: &Device) -> Result<Self, EstimateError> {
        Self::new(Marigold::load(dir, device)?).map_err(|reason| EstimateError::Config {
            path: dir.join("model_index.json"),
            reason,
        })
    }

    /// Wraps a loaded checkpoint; `Err` says what it predicts instead of normals.
    pub fn new(net: Marigold) -> Result<Self, String> {
        if net.pipeline().kind != PipelineKind::Normals {
            return Err(format!(
                "a {} predicting {}, not a Marigold normals checkpoint (MarigoldNormalsPipeline)",
                net.pipeline().kind.class_name(),
                net.pipeline().target_names().join(", ")
            ));
        }
        Ok(Self { net })
    }

    /// The shared networks, scheduler and configs.
    pub fn model(&self) -> &Marigold {
        &self.net
    }

    /// Whether the decoded z spans [−1, 1] (the checkpoint's `use_full_z_range`).
    pub fn use_full_z_range(&self) -> bool {
        self.net.pipeline().use_full_z_range
    }

    /// The checkpoint's defaults resolved and the options checked: `(steps, resolution)`.
    pub fn resolve(&self, opts: &NormalsOptions) -> Result<(usize, usize), EstimateError> {
        self.net.resolve(&opts.shared())
    }

    /// Approximate work of one [`MarigoldNormals::predict`] in TFLOP for the released network
    /// sizes ([`Marigold::approx_tflop`] with one target), `None` for other sizes.
    pub fn approx_tflop(&self, width: usize, height: usize, opts: &NormalsOptions) -> Option<f64> {
        self.net.approx_tflop(width, height, &opts.shared())
    }

    /// Step 4 for one latent `(1, 4, h, w)`: `(1, 3, 8h, 8w)` unit normals (padding kept).
    pub fn decode(&self, latent: &Tensor) -> Result<Tensor, EstimateError> {
        let x = self.net.decode_raw(latent)?.clamp(-1f32, 1f32)?;
        let x = if self.use_full_z_range() {
            x
        } else {
            let z = ((x.narrow(1, 2, 1)? * 0.5)? + 0.5)?;
            Tensor::cat(&[&x.narrow(1, 0, 2)?, &z], 1)?
        };
        let norm = x.sqr()?.sum_keepdim(1)?.sqrt()?.clamp(NORM_EPS, f32::MAX)?;
        Ok(x.broadcast_div(&norm)?)
    }

    /// The whole pipeline with noise from [`NormalsOptions::seed`].
    pub fn predict(
        &self,
        photo: &Image,
        opts: &NormalsOptions,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<NormalsPrediction, EstimateError> {
        let (_, res) = self.resolve(opts)?;
        let vae = self.net.vae_config();
        let f = vae.scale_factor();
        let (nh, nw) = resized_size(photo.width, photo.height, res)?;
        let (lh, lw, c) = (nh.div_ceil(f), nw.div_ceil(f), vae.latent_channels);
        let mut rng = pixl_core::rng::Rng::new(opts.seed);
        let noise: Vec<f32> = (0..opts.ensemble * c * lh * lw).map(|_| rng.normal()).collect();
        let noise = Tensor::from_vec(noise, (opts.ensemble, c, lh, lw), self.net.empty_embedding().device())?;
        self.predict_with_noise(photo, opts, &noise, progress)
    }

    /// The whole pipeline with the initial latents given: `(ensemble, 4, h/8, w/8)`. Progress:
    /// one tick for the encoding, one per UNet step and one per decoding.
    pub fn predict_with_noise(
        &self,
        photo: &Image,
        opts: &NormalsOptions,
        noise: &Tensor,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<NormalsPrediction, EstimateError> {
        let (steps, res) = self.resolve(opts)?;
        let m = &self.net;
        let pre = m.preprocess(photo, res)?;
        let (_, _, hh, ww) = pre.image.dims4()?;
        let f = m.vae_config().scale_factor();
        let want = (opts.ensemble, m.vae_config().latent_channels, hh / f, ww / f);
        if noise.dims4()? != want {
            return Err(EstimateError::Input(format!(
                "initial latents have shape {:?}, expected {want:?}",
                noise.dims()
            )));
        }
        let total = opts.ensemble * (steps + 1) + 1;
        let mut done = 0;
        let mut tick = |done: &mut usize| {
            *done += 1;
            progress(Progress { done: *done, total });
        };
        let image_latent = m.encode(&pre.image)?;
        tick(&mut done);
        let (nh, nw) = pre.resized;
        // members[e]: member e's unit normals, planar (3, nh, nw).
        let mut members: Vec<Vec<f32>> = Vec::with_capacity(opts.ensemble);
        for e in 0..opts.ensemble {
            let z = noise.narrow(0, e, 1)?;
            let mut on_step = |_: usize, _: &Tensor| tick(&mut done);
            let lat = m.denoise(&image_latent, &z, steps, &mut on_step)?;
            let d = self.decode(&lat)?.narrow(2, 0, nh)?.narrow(3, 0, nw)?;
            members.push(d.flatten_all()?.to_vec1::<f32>()?);
            tick(&mut done);
        }
        let refs: Vec<&[f32]> = members.iter().map(Vec::as_slice).collect();
        let (reduced, spread) = if refs.len() == 1 {
            (members[0].clone(), None)
        } else {
            let (n, u) = ensemble(&refs, opts.reduction);
            (n, opts.uncertainty.then_some(u))
        };
        let size = (photo.width, photo.height);
        Ok(NormalsPrediction {
            normals: normals_to_size(reduced, (nw, nh), size)?,
            uncertainty: spread.map(|u| uncertainty_to_size(u, (nw, nh), size)).transpose()?,
            processed_size: (nw, nh),
            steps,
            ensemble: opts.ensemble,
        })
    }
}

/// diffusers' `normalize_normals` floor on the length.
const NORM_EPS: f32 = 1e-6;

/// Step 6: planar `(3, h, w)` normals at the processed size `from = (w, h)` → an RGB image of
/// unit normals at `to = (width, height)`.
pub fn normals_to_size(planar: Vec<f32>, from: (usize, usize), to: (usize, usize)) -> Result<Image, EstimateError> {
    let mut img = to_size(planar, 3, from, to)?;
    normalize_pixels(&mut img.data);
    Ok(img)
}

/// Step 6 for the uncertainty: `(h, w)` at the processed size `from = (w, h)` → one channel at
/// `to = (width, height)`.
pub fn uncertainty_to_size(u: Vec<f32>, from: (usize, usize), to: (usize, usize)) -> Result<Image, EstimateError> {
    to_size(u, 1, from, to)
}

/// Planar `(c, h, w)` → an interleaved `c`-channel image at `to = (width, height)`, bilinear
/// without antialiasing (PyTorch's `interpolate(mode="bilinear", align_corners=False)`).
fn to_size(v: Vec<f32>, c: usize, from: (usize, usize), to: (usize, usize)) -> Result<Image, EstimateError> {
    let ((fw, fh), (w, h)) = (from, to);
    if v.len() != c * fw * fh {
        return Err(EstimateError::Input(format!(
            "{} values for a {c}-channel {fw}x{fh} map",
            v.len()
        )));
    }
    let small = Tensor::from_vec(v, (1, c, fh, fw), &Device::Cpu)?;
    let planar = resize::bilinear_half_pixel(&small, h, w)?
        .flatten_all()?
        .to_vec1::<f32>()?;
    Ok(Image::from_fn(w, h, c, |x, y, k| planar[(k * h + y) * w + x]))
}

/// Divides each interleaved RGB triple by `max(|n|, 1e-6)`.
fn normalize_pixels(data: &mut [f32]) {
    for n in data.chunks_exact_mut(3) {
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(NORM_EPS);
        n.iter_mut().for_each(|v| *v /= len);
    }
}

/// Step 5 on planar `(3, n)` unit-normal maps of 2 or more members: the reduced map (planar
/// `(3, n)`) and the uncertainty (`(n)`, mean angle to the normalised mean over π), as diffusers'
/// `ensemble_normals` computes them (see the module docs).
pub fn ensemble(members: &[&[f32]], how: NormalsReduction) -> (Vec<f32>, Vec<f32>) {
    let e = members.len();
    let n = members.first().map_or(0, |m| m.len() / 3);
    let mut out = vec![0.0f32; 3 * n];
    let mut spread = vec![0.0f32; n];
    let mut cos = vec![0.0f32; e];
    for i in 0..n {
        let mut mean = [0.0f32; 3];
        for (c, mc) in mean.iter_mut().enumerate() {
            *mc = members.iter().map(|m| m[c * n + i]).sum::<f32>() / e as f32;
        }
        let len = (mean[0] * mean[0] + mean[1] * mean[1] + mean[2] * mean[2])
            .sqrt()
            .max(NORM_EPS);
        mean.iter_mut().for_each(|v| *v /= len);
        for (ce, m) in cos.iter_mut().zip(members) {
            *ce = (mean[0] * m[i] + mean[1] * m[n + i] + mean[2] * m[2 * n + i]).clamp(-1.0, 1.0);
        }
        spread[i] = cos.iter().map(|c| c.acos()).sum::<f32>() / e as f32 / std::f32::consts::PI;
        let pick: [f32; 3] = match how {
            NormalsReduction::Mean => mean,
            NormalsReduction::Closest => {
                // The first largest, as `argmax`.
                let best = (1..e).fold(0, |b, k| if cos[k] > cos[b] { k } else { b });
                let m = members[best];
                [m[i], m[n + i], m[2 * n + i]]
            }
        };
        for (c, v) in pick.into_iter().enumerate() {
            out[c * n + i] = v;
        }
    }
    (out, spread)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two pixels, three members, worked by hand.
    #[test]
    fn ensemble_keeps_the_member_nearest_the_mean_or_the_mean() {
        let s = std::f32::consts::FRAC_1_SQRT_2;
        // Pixel 0: +z, +z, +x → mean (1, 0, 2)/√5; cosines 2/√5, 2/√5, 1/√5 → the first +z member.
        // Pixel 1: (s, 0, s), +z, (s, 0, s) → mean ∝ (2s, 0, 2s + 1); the (s, 0, s) members are
        // nearer than +z (the mean leans to x), and the first of them is kept.
        let a = [0.0, s, 0.0, 0.0, 1.0, s]; // planar x0 x1 | y0 y1 | z0 z1
        let b = [0.0, 0.0, 0.0, 0.0, 1.0, 1.0];
        let c = [1.0, s, 0.0, 0.0, 0.0, s];
        let (closest, u) = ensemble(&[&a, &b, &c], NormalsReduction::Closest);
        assert_eq!(closest, vec![0.0, s, 0.0, 0.0, 1.0, s]);
        let (mean, _) = ensemble(&[&a, &b, &c], NormalsReduction::Mean);
        let r5 = 5f32.sqrt();
        for (got, want) in mean[..].iter().step_by(2).zip([1.0 / r5, 0.0, 2.0 / r5]) {
            assert!((got - want).abs() < 1e-6, "{mean:?}");
        }
        // Uncertainty of pixel 0: (2·acos(2/√5) + acos(1/√5)) / 3 / π.
        let want = (2.0 * (2.0 / r5).acos() + (1.0 / r5).acos()) / 3.0 / std::f32::consts::PI;
        assert!((u[0] - want).abs() < 1e-6, "{u:?} vs {want}");
        // Identical members: no spread.
        let (_, u) = ensemble(&[&b, &b], NormalsReduction::Closest);
        assert!(u.iter().all(|v| v.abs() < 1e-3), "{u:?}");
    }

    #[test]
    fn pixels_are_scaled_to_unit_length_and_zero_stays_zero() {
        let mut d = vec![3.0, 0.0, 4.0, 0.0, 0.0, 0.0];
        normalize_pixels(&mut d);
        assert_eq!(d, vec![0.6, 0.0, 0.8, 0.0, 0.0, 0.0]);
    }
}
