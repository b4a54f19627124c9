//! Marigold-IID v1.1 (paper §3.3 training targets, §3.4 materials): intrinsic image
//! decomposition of a photo with the official diffusers-format checkpoints, loaded unchanged.
//!
//! - **Appearance** (`prs-eth/marigold-iid-appearance-v1-1`, UNet 12 → 8 latent channels):
//!   albedo (**sRGB**-encoded) and material (R = roughness, G = metallicity, linear).
//! - **Lighting** (`prs-eth/marigold-iid-lighting-v1-1`, 16 → 12): albedo, diffuse shading and
//!   non-diffuse residual, all **linear** — the paper's A, S, R.
//!
//! Contract of [`Marigold::predict`]: a photo ([`Image`], values in [0, 1] as read from an 8-bit
//! file, 1–4 channels; RGB is used) → one 3-channel map per target at the photo's size, values
//! in [0, 1], in the target's own colour space ([`Target::space`]). The pipeline is diffusers'
//! `MarigoldIntrinsicsPipeline`, step by step:
//! 1. ×2 − 1, antialiased bilinear resize of the longest side to the processing resolution
//!    (`h·res // max(h, w)`), replicate-pad right/bottom to a multiple of the VAE factor (8);
//! 2. VAE posterior **mode** × `scaling_factor` ([`vae`]);
//! 3. per ensemble member, from Gaussian noise: `steps` DDIM updates ([`scheduler`]) of the UNet
//!    (diffusers' SD2-family `UNet2DConditionModel`, widened input/output, [`unet`]) on
//!    `cat[image_latent, target_latents]` with the empty-prompt embedding ([`text`]);
//! 4. each target's 4 latent channels decoded by the VAE, clipped to [−1, 1], `(x + 1)/2`,
//!    padding removed;
//! 5. ensemble members reduced per pixel by the median (the lower one for an even count, as
//!    `torch.median`) or the mean;
//! 6. bilinear resize (no antialiasing) back to the photo's size.
//!
//! A Marigold **normals** checkpoint (`MarigoldNormalsPipeline`, [`PipelineKind::Normals`]) loads
//! through the same [`Marigold::load`] (one target, UNet 8 → 4); its decoding and ensembling are
//! [`normals`]'s, and [`Marigold::predict`] refuses it.
//!
//! Noise comes from [`pixl_core::rng::Rng`] seeded by [`MarigoldOptions::seed`] (the same seed
//! gives the same maps); [`Marigold::predict_with_noise`] takes it from the caller instead (the
//! parity tests feed the official pipeline's noise). Everything runs in f32; `.fp16.safetensors`
//! weight variants are upcast on load ([`weights`]: memory-mapped, converted in parallel).
pub mod config;
pub mod normals;
pub mod scheduler;
pub mod text;
pub mod unet;
pub mod vae;
pub mod weights;

pub use config::{PipelineConfig, PipelineKind, PredictionSpace, Target, TextConfig, UnetConfig, VaeConfig};
pub use scheduler::{Ddim, SchedulerConfig};

use crate::error::EstimateError;
use crate::resize;
use candle_core::{Device, Tensor};
use candle_nn::VarBuilder;
use pixl_core::Image;
use std::path::{Path, PathBuf};

/// Which IID model a checkpoint is, from its target names.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IidVariant {
    /// Targets `albedo`, `material`.
    Appearance,
    /// Targets `albedo`, `shading`, `residual`.
    Lighting,
}

impl IidVariant {
    pub fn target_names(self) -> &'static [&'static str] {
        match self {
            IidVariant::Appearance => &["albedo", "material"],
            IidVariant::Lighting => &["albedo", "shading", "residual"],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            IidVariant::Appearance => "appearance",
            IidVariant::Lighting => "lighting",
        }
    }

    fn from_targets(names: &[&str]) -> Option<Self> {
        [IidVariant::Appearance, IidVariant::Lighting]
            .into_iter()
            .find(|v| v.target_names() == names)
    }
}

/// How ensemble members are combined.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Reduction {
    /// Per-pixel median (lower median for an even count), diffusers' default.
    Median,
    Mean,
}

/// Options of [`Marigold::predict`].
#[derive(Clone, Debug, PartialEq)]
pub struct MarigoldOptions {
    /// Denoising steps (`None`: the checkpoint's default, 4 for v1.1).
    pub steps: Option<usize>,
    /// Ensemble members (≥ 1).
    pub ensemble: usize,
    /// Longest side processed (`None`: the checkpoint's default, 768; must be a multiple of 8).
    pub resolution: Option<usize>,
    pub reduction: Reduction,
    /// Seed of the initial noise.
    pub seed: u64,
    /// Also the members' spread per pixel ([`uncertainty`]; needs an ensemble of 2 or more).
    pub uncertainty: bool,
}

impl Default for MarigoldOptions {
    fn default() -> Self {
        Self {
            steps: None,
            ensemble: 1,
            resolution: None,
            reduction: Reduction::Median,
            seed: 0,
            uncertainty: false,
        }
    }
}

/// Where [`Marigold::predict`] is (for a progress bar): one tick per UNet step and per decode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Progress {
    pub done: usize,
    pub total: usize,
}

/// Output of [`Marigold::predict`].
#[derive(Clone, Debug)]
pub struct IidPrediction {
    /// One RGB map per target at the photo's size, values in [0, 1], in latent order.
    pub maps: Vec<(Target, Image)>,
    /// Resized (unpadded) network input `(width, height)`.
    pub processed_size: (usize, usize),
    pub steps: usize,
    pub ensemble: usize,
    /// With [`MarigoldOptions::uncertainty`]: per target, the members' spread at the photo's size.
    pub uncertainty: Vec<(Target, Image)>,
}

impl IidPrediction {
    /// The map of the target called `name`.
    pub fn get(&self, name: &str) -> Option<&Image> {
        self.maps.iter().find(|(t, _)| t.name == name).map(|(_, m)| m)
    }
}

/// The preprocessed photo: `(1, 3, PH + ph, PW + pw)` in [−1, 1], and its sizes.
#[derive(Clone, Debug)]
pub struct Preprocessed {
    pub image: Tensor,
    /// Resized size `(height, width)` before padding.
    pub resized: (usize, usize),
    /// Padding added at the bottom and right `(ph, pw)`.
    pub padding: (usize, usize),
}

/// The files of a diffusers-format checkpoint folder, with the `.fp16` variant when only it
/// is present.
#[derive(Clone, Debug)]
pub struct CheckpointFiles {
    pub model_index: PathBuf,
    pub scheduler: PathBuf,
    pub unet_config: PathBuf,
    pub unet: PathBuf,
    pub vae_config: PathBuf,
    pub vae: PathBuf,
    pub text_config: PathBuf,
    /// `None` when the weights are absent but an empty-prompt embedding is cached.
    pub text: Option<PathBuf>,
    pub tokenizer: PathBuf,
    pub text_dir: PathBuf,
}

impl CheckpointFiles {
    /// Finds the files under `dir`; a missing one is an error naming it.
    pub fn find(dir: &Path) -> Result<Self, EstimateError> {
        let need = |rel: &str| -> Result<PathBuf, EstimateError> {
            let p = dir.join(rel);
            if p.is_file() {
                Ok(p)
            } else {
                Err(EstimateError::Config {
                    path: dir.to_owned(),
                    reason: format!(
                        "not a Marigold checkpoint folder: `{rel}` is missing (expected the diffusers layout: \
model_index.json, scheduler/, unet/, vae/, text_encoder/, tokenizer/)"
                    ),
                })
            }
        };
        let weights = |sub: &str, stem: &str| -> Option<PathBuf> {
            [
                format!("{sub}/{stem}.safetensors"),
                format!("{sub}/{stem}.fp16.safetensors"),
            ]
            .into_iter()
            .map(|r| dir.join(r))
            .find(|p| p.is_file())
        };
        let missing_weights = |sub: &str, stem: &str| EstimateError::Config {
            path: dir.to_owned(),
            reason: format!("`{sub}/{stem}.safetensors` (or its `.fp16` variant) is missing"),
        };
        let model_index = need("model_index.json")?;
        let text_dir = dir.join("text_encoder");
        let text = weights("text_encoder", "model");
        if text.is_none() && !text_dir.join(text::CACHE_FILE).is_file() {
            return Err(missing_weights("text_encoder", "model"));
        }
        Ok(Self {
            model_index,
            scheduler: need("scheduler/scheduler_config.json")?,
            unet_config: need("unet/config.json")?,
            unet: weights("unet", "diffusion_pytorch_model")
                .ok_or_else(|| missing_weights("unet", "diffusion_pytorch_model"))?,
            vae_config: need("vae/config.json")?,
            vae: weights("vae", "diffusion_pytorch_model")
                .ok_or_else(|| missing_weights("vae", "diffusion_pytorch_model"))?,
            text_config: need("text_encoder/config.json")?,
            text,
            tokenizer: dir.join("tokenizer"),
            text_dir,
        })
    }
}

fn read_text(path: &Path) -> Result<String, EstimateError> {
    std::fs::read_to_string(path).map_err(|source| EstimateError::Io {
        path: path.to_owned(),
        source,
    })
}

fn config<T>(path: &Path, parse: impl FnOnce(&str) -> Result<T, String>) -> Result<T, EstimateError> {
    parse(&read_text(path)?).map_err(|reason| EstimateError::Config {
        path: path.to_owned(),
        reason,
    })
}

fn var_builder(path: &Path, device: &Device) -> Result<VarBuilder<'static>, EstimateError> {
    weights::load(path, device)
}

/// Maps a candle error while building a network to one naming the weight file.
fn building(path: &Path) -> impl Fn(candle_core::Error) -> EstimateError + '_ {
    move |e| EstimateError::Weights {
        path: path.to_owned(),
        reason: e.to_string(),
    }
}

/// A loaded Marigold checkpoint: IID, or normals ([`PipelineConfig::kind`]).
pub struct Marigold {
    pipeline: PipelineConfig,
    variant: Option<IidVariant>,
    unet: unet::UNet2DConditionModel,
    unet_cfg: UnetConfig,
    encoder: vae::VaeEncoder,
    decoder: vae::VaeDecoder,
    vae_cfg: VaeConfig,
    scheduler: Ddim,
    empty: Tensor,
    device: Device,
}

impl Marigold {
    /// Loads a diffusers-format folder. All configs are checked before any weight is read.
    pub fn load(dir: &Path, device: &Device) -> Result<Self, EstimateError> {
        let f = CheckpointFiles::find(dir)?;
        let pipeline = config(&f.model_index, PipelineConfig::from_json)?;
        let sched = config(&f.scheduler, SchedulerConfig::from_json)?;
        let unet_cfg = config(&f.unet_config, UnetConfig::from_json)?;
        let vae_cfg = config(&f.vae_config, VaeConfig::from_json)?;
        let text_cfg = config(&f.text_config, TextConfig::from_json)?;
        let t = pipeline.targets.len();
        let l = vae_cfg.latent_channels;
        if unet_cfg.in_channels != (t + 1) * l || unet_cfg.out_channels != t * l {
            return Err(EstimateError::Config {
                path: f.unet_config.clone(),
                reason: format!(
                    "the UNet maps {} → {} channels, but {t} targets of {l} latent channels need {} → {}",
                    unet_cfg.in_channels,
                    unet_cfg.out_channels,
                    (t + 1) * l,
                    t * l
                ),
            });
        }
        if unet_cfg.cross_attention_dim != text_cfg.hidden_size {
            return Err(EstimateError::Config {
                path: f.unet_config.clone(),
                reason: format!(
                    "cross_attention_dim {} differs from the text encoder's hidden_size {}",
                    unet_cfg.cross_attention_dim, text_cfg.hidden_size
                ),
            });
        }
        let empty = match text::read_cache(&f.text_dir, Some(text_cfg.hidden_size), device) {
            Some(e) => e,
            None => {
                let ids = text::empty_prompt_ids(&f.tokenizer)?;
                let tp = f.text.clone().ok_or_else(|| EstimateError::Config {
                    path: dir.to_owned(),
                    reason: "`text_encoder/model.safetensors` is missing".into(),
                })?;
                let enc = text::TextEncoder::new(text_cfg.clone(), var_builder(&tp, device)?).map_err(building(&tp))?;
                let e = enc.forward(&ids).map_err(building(&tp))?;
                text::write_cache(&f.text_dir, &e);
                e
            }
        };
        let unet =
            unet::UNet2DConditionModel::new(&unet_cfg, var_builder(&f.unet, device)?).map_err(building(&f.unet))?;
        let vb = var_builder(&f.vae, device)?;
        let encoder = vae::VaeEncoder::new(&vae_cfg, vb.clone()).map_err(building(&f.vae))?;
        let decoder = vae::VaeDecoder::new(&vae_cfg, vb).map_err(building(&f.vae))?;
        let variant = IidVariant::from_targets(&pipeline.target_names());
        Ok(Self {
            pipeline,
            variant,
            unet,
            unet_cfg,
            encoder,
            decoder,
            vae_cfg,
            scheduler: Ddim::new(sched),
            empty,
            device: device.clone(),
        })
    }

    /// Appearance, Lighting, or `None` for another target set.
    pub fn variant(&self) -> Option<IidVariant> {
        self.variant
    }

    pub fn pipeline(&self) -> &PipelineConfig {
        &self.pipeline
    }

    pub fn scheduler(&self) -> &Ddim {
        &self.scheduler
    }

    pub fn vae_config(&self) -> &VaeConfig {
        &self.vae_cfg
    }

    /// The empty-prompt embedding `(1, tokens, hidden)`.
    pub fn empty_embedding(&self) -> &Tensor {
        &self.empty
    }

    /// Latent channels of all targets together.
    pub fn target_latent_channels(&self) -> usize {
        self.unet_cfg.out_channels
    }

    /// The checkpoint's defaults resolved: `(steps, resolution)`.
    pub fn resolve(&self, opts: &MarigoldOptions) -> Result<(usize, usize), EstimateError> {
        let steps = opts.steps.or(self.pipeline.default_steps).unwrap_or(4);
        let res = opts.resolution.or(self.pipeline.default_resolution).unwrap_or(768);
        let f = self.vae_cfg.scale_factor();
        if steps == 0 || steps > self.scheduler.config.num_train_timesteps {
            return Err(EstimateError::Input(format!(
                "steps {steps}: must be between 1 and {}",
                self.scheduler.config.num_train_timesteps
            )));
        }
        if res == 0 || !res.is_multiple_of(f) {
            return Err(EstimateError::Input(format!(
                "processing resolution {res}: must be a positive multiple of {f}"
            )));
        }
        if opts.ensemble == 0 {
            return Err(EstimateError::Input("the ensemble size must be at least 1".into()));
        }
        if opts.uncertainty && opts.ensemble < 2 {
            return Err(EstimateError::Input(
                "the uncertainty is the spread of an ensemble: give an ensemble of 2 or more (3 or more to be useful)"
                    .into(),
            ));
        }
        Ok((steps, res))
    }

    /// Approximate work of one [`Marigold::predict`] in TFLOP (2 × multiply-adds) for the
    /// released SD2-size networks, `None` for other sizes: per 768² pixels, VAE encoding 2.6,
    /// one UNet step 2.14, one target's VAE decoding 5.75 (analytic counts of the SD2 UNet and VAE).
    pub fn approx_tflop(&self, width: usize, height: usize, opts: &MarigoldOptions) -> Option<f64> {
        let released = self.unet_cfg.block_out_channels.first() == Some(&320)
            && self.vae_cfg.block_out_channels.first() == Some(&128);
        if !released {
            return None;
        }
        let (steps, res) = self.resolve(opts).ok()?;
        let f = self.vae_cfg.scale_factor();
        let (nh, nw) = resized_size(width, height, res).ok()?;
        let (nh, nw) = (nh.div_ceil(f) * f, nw.div_ceil(f) * f);
        let area = (nh * nw) as f64 / (768.0 * 768.0);
        let t = self.pipeline.targets.len() as f64;
        Some(area * (2.6 + opts.ensemble as f64 * (steps as f64 * 2.14 + t * 5.75)))
    }

    /// Step 1: `(1, 3, H', W')` in [−1, 1], resized and padded.
    pub fn preprocess(&self, photo: &Image, resolution: usize) -> Result<Preprocessed, EstimateError> {
        let (w, h) = (photo.width, photo.height);
        let (nh, nw) = resized_size(w, h, resolution)?;
        let c = photo.channels;
        let mut planar = vec![0.0f32; 3 * h * w];
        for i in 0..h * w {
            for ch in 0..3 {
                let v = photo.data[i * c + ch.min(c.saturating_sub(1))];
                if !v.is_finite() {
                    return Err(EstimateError::Input("the photo has non-finite values".into()));
                }
                planar[ch * h * w + i] = v * 2.0 - 1.0;
            }
        }
        let resized = resize::bilinear_antialias(&planar, 3, h, w, nh, nw);
        let f = self.vae_cfg.scale_factor();
        let (ph, pw) = ((f - nh % f) % f, (f - nw % f) % f);
        let (hh, ww) = (nh + ph, nw + pw);
        let mut padded = vec![0.0f32; 3 * hh * ww];
        for ch in 0..3 {
            for y in 0..hh {
                let sy = y.min(nh - 1);
                for x in 0..ww {
                    padded[(ch * hh + y) * ww + x] = resized[(ch * nh + sy) * nw + x.min(nw - 1)];
                }
            }
        }
        let image = Tensor::from_vec(padded, (1, 3, hh, ww), &self.device)?;
        Ok(Preprocessed {
            image,
            resized: (nh, nw),
            padding: (ph, pw),
        })
    }

    /// Step 2: the image latent, `mode × scaling_factor`.
    pub fn encode(&self, image: &Tensor) -> Result<Tensor, EstimateError> {
        Ok((self.encoder.mode(image)? * self.vae_cfg.scaling_factor)?)
    }

    /// The UNet's prediction for `cat[image_latent, target_latent]` at timestep `t`.
    pub fn unet(&self, image_latent: &Tensor, target_latent: &Tensor, t: usize) -> Result<Tensor, EstimateError> {
        let x = Tensor::cat(&[image_latent, target_latent], 1)?;
        let b = x.dim(0)?;
        let ctx = self.empty.repeat((b, 1, 1))?;
        Ok(self.unet.forward(&x, t as f64, &ctx)?)
    }

    /// Step 3 for one member: `steps` DDIM updates from `noise`; `on_step(k, latent)` sees each.
    pub fn denoise(
        &self,
        image_latent: &Tensor,
        noise: &Tensor,
        steps: usize,
        on_step: &mut dyn FnMut(usize, &Tensor),
    ) -> Result<Tensor, EstimateError> {
        let ts = self.scheduler.timesteps(steps).map_err(EstimateError::Input)?;
        let mut lat = noise.clone();
        for (k, &t) in ts.iter().enumerate() {
            let out = self.unet(image_latent, &lat, t)?;
            lat = self.scheduler.step(&out, t, &lat, steps)?;
            on_step(k, &lat);
        }
        Ok(lat)
    }

    /// Step 4 for one target latent `(1, 4, h, w)`: `(1, 3, 8h, 8w)` in [0, 1].
    pub fn decode(&self, latent: &Tensor) -> Result<Tensor, EstimateError> {
        let x = self.decode_raw(latent)?;
        Ok(((x.clamp(-1f32, 1f32)? + 1.0)? / 2.0)?)
    }

    /// The VAE's decoding of one target latent `(1, 4, h, w)` as it comes: `(1, 3, 8h, 8w)`,
    /// not clipped.
    pub fn decode_raw(&self, latent: &Tensor) -> Result<Tensor, EstimateError> {
        Ok(self.decoder.decode(&(latent / self.vae_cfg.scaling_factor)?)?)
    }

    /// The whole pipeline with noise from [`MarigoldOptions::seed`].
    pub fn predict(
        &self,
        photo: &Image,
        opts: &MarigoldOptions,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<IidPrediction, EstimateError> {
        let (_, res) = self.resolve(opts)?;
        let f = self.vae_cfg.scale_factor();
        let (nh, nw) = resized_size(photo.width, photo.height, res)?;
        let (lh, lw) = (nh.div_ceil(f), nw.div_ceil(f));
        let c = self.target_latent_channels();
        let mut rng = pixl_core::rng::Rng::new(opts.seed);
        let n = opts.ensemble * c * lh * lw;
        let noise: Vec<f32> = (0..n).map(|_| rng.normal()).collect();
        let noise = Tensor::from_vec(noise, (opts.ensemble, c, lh, lw), &self.device)?;
        self.predict_with_noise(photo, opts, &noise, progress)
    }

    /// The whole pipeline with the initial latents given: `(ensemble, T·4, h/8, w/8)`.
    pub fn predict_with_noise(
        &self,
        photo: &Image,
        opts: &MarigoldOptions,
        noise: &Tensor,
        progress: &mut dyn FnMut(Progress),
    ) -> Result<IidPrediction, EstimateError> {
        if self.pipeline.kind == PipelineKind::Normals {
            return Err(EstimateError::Input(
                "this is a Marigold normals checkpoint: run it with marigold::normals::MarigoldNormals".into(),
            ));
        }
        let (steps, res) = self.resolve(opts)?;
        let pre = self.preprocess(photo, res)?;
        let (_, _, hh, ww) = pre.image.dims4()?;
        let f = self.vae_cfg.scale_factor();
        let want = (opts.ensemble, self.target_latent_channels(), hh / f, ww / f);
        if noise.dims4()? != want {
            return Err(EstimateError::Input(format!(
                "initial latents have shape {:?}, expected {want:?}",
                noise.dims()
            )));
        }
        let t = self.pipeline.targets.len();
        let l = self.vae_cfg.latent_channels;
        let total = opts.ensemble * (steps + t) + 1;
        let mut done = 0;
        let mut tick = |done: &mut usize| {
            *done += 1;
            progress(Progress { done: *done, total });
        };
        let image_latent = self.encode(&pre.image)?;
        tick(&mut done);
        let (nh, nw) = pre.resized;
        // members[e][k]: target k of member e, planar (3, nh, nw).
        let mut members: Vec<Vec<Vec<f32>>> = Vec::with_capacity(opts.ensemble);
        for e in 0..opts.ensemble {
            let z = noise.narrow(0, e, 1)?;
            let mut on_step = |_: usize, _: &Tensor| tick(&mut done);
            let lat = self.denoise(&image_latent, &z, steps, &mut on_step)?;
            let mut maps = Vec::with_capacity(t);
            for k in 0..t {
                let d = self.decode(&lat.narrow(1, k * l, l)?)?;
                let d = d.narrow(2, 0, nh)?.narrow(3, 0, nw)?;
                maps.push(d.flatten_all()?.to_vec1::<f32>()?);
                tick(&mut done);
            }
            members.push(maps);
        }
        let (w, h) = (photo.width, photo.height);
        // Planar (3, nh, nw) → the photo's size, as diffusers resizes prediction and uncertainty.
        let to_photo = |v: Vec<f32>| -> Result<Image, EstimateError> {
            let small = Tensor::from_vec(v, (1, 3, nh, nw), &Device::Cpu)?;
            let full = resize::bilinear_half_pixel(&small, h, w)?;
            let planar = full.flatten_all()?.to_vec1::<f32>()?;
            Ok(Image::from_fn(w, h, 3, |x, y, c| planar[(c * h + y) * w + x]))
        };
        let (mut out, mut spread) = (Vec::with_capacity(t), Vec::new());
        for (k, target) in self.pipeline.targets.iter().enumerate() {
            let planes: Vec<&[f32]> = members.iter().map(|m| m[k].as_slice()).collect();
            let reduced = reduce(&planes, opts.reduction);
            if opts.uncertainty {
                spread.push((
                    target.clone(),
                    to_photo(uncertainty(&planes, &reduced, opts.reduction))?,
                ));
            }
            out.push((target.clone(), to_photo(reduced)?));
        }
        Ok(IidPrediction {
            maps: out,
            processed_size: (nw, nh),
            steps,
            ensemble: opts.ensemble,
            uncertainty: spread,
        })
    }
}

/// The photo's size `(height, width)` once its longest side is `res` (diffusers:
/// `h·res // max(h, w)`, before padding); an error for an empty photo or a side that rounds to 0.
fn resized_size(w: usize, h: usize, res: usize) -> Result<(usize, usize), EstimateError> {
    if w == 0 || h == 0 {
        return Err(EstimateError::Input("the photo is empty".into()));
    }
    let mx = w.max(h);
    let (nh, nw) = (h * res / mx, w * res / mx);
    if nh == 0 || nw == 0 {
        return Err(EstimateError::Input(format!(
            "extreme aspect ratio of the photo ({w}x{h}): one side would be 0 pixels at {res}"
        )));
    }
    Ok((nh, nw))
}

/// The members' spread per element, as diffusers' `ensemble_intrinsics` computes it: for the
/// median, the median (lower, as `torch.median`) of `|member − reduced|`; for the mean, the
/// standard deviation with Bessel's correction (`torch.std`). `reduced` is [`reduce`]'s output.
pub fn uncertainty(members: &[&[f32]], reduced: &[f32], how: Reduction) -> Vec<f32> {
    let n = members.len();
    let mut buf = vec![0.0f32; n];
    (0..reduced.len())
        .map(|i| {
            for (b, m) in buf.iter_mut().zip(members) {
                *b = m[i] - reduced[i];
            }
            match how {
                Reduction::Mean if n > 1 => {
                    (buf.iter().map(|d| (*d as f64).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt() as f32
                }
                Reduction::Mean => 0.0,
                Reduction::Median => {
                    buf.iter_mut().for_each(|d| *d = d.abs());
                    buf.sort_by(f32::total_cmp);
                    buf[(n - 1) / 2]
                }
            }
        })
        .collect()
}

/// Per-element median (lower median for an even count, as `torch.median`) or mean.
pub fn reduce(members: &[&[f32]], how: Reduction) -> Vec<f32> {
    let n = members.len();
    if n == 1 {
        return members[0].to_vec();
    }
    let len = members[0].len();
    let mut buf = vec![0.0f32; n];
    (0..len)
        .map(|i| {
            for (b, m) in buf.iter_mut().zip(members) {
                *b = m[i];
            }
            match how {
                Reduction::Mean => buf.iter().sum::<f32>() / n as f32,
                Reduction::Median => {
                    buf.sort_by(f32::total_cmp);
                    buf[(n - 1) / 2]
                }
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uncertainty_is_the_median_absolute_deviation_or_the_sample_std_as_diffusers_computes_it() {
        let (a, b, c) = ([0.1f32, 0.5], [0.4f32, 0.5], [0.2f32, 0.9]);
        let members: Vec<&[f32]> = vec![&a, &b, &c];
        // Median: element 0: members 0.1, 0.4, 0.2 → median 0.2, deviations 0.1, 0.2, 0 → median 0.1.
        let med = reduce(&members, Reduction::Median);
        let u = uncertainty(&members, &med, Reduction::Median);
        assert!(
            (med[0] - 0.2).abs() < 1e-7 && (u[0] - 0.1).abs() < 1e-6,
            "{med:?} {u:?}"
        );
        // Element 1: 0.5, 0.5, 0.9 → median 0.5, deviations 0, 0, 0.4 → 0.
        assert_eq!(u[1], 0.0);
        // Mean: element 1: mean 0.6333, sample std sqrt(((−0.1333)²·2 + 0.2667²) / 2) = 0.23094.
        let mean = reduce(&members, Reduction::Mean);
        let s = uncertainty(&members, &mean, Reduction::Mean);
        assert!((s[1] - 0.230_940_1).abs() < 1e-5, "{s:?}");
    }

    #[test]
    fn median_is_the_lower_one_for_even_counts() {
        let a = [1.0f32, 5.0];
        let b = [3.0f32, 2.0];
        let c = [2.0f32, 9.0];
        assert_eq!(reduce(&[&a, &b, &c], Reduction::Median), vec![2.0, 5.0]);
        assert_eq!(reduce(&[&a, &b], Reduction::Median), vec![1.0, 2.0]);
        assert_eq!(reduce(&[&a, &b], Reduction::Mean), vec![2.0, 3.5]);
    }
}
