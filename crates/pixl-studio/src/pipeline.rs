//! One progressive stage of the relighting pipeline, cancelable: path-trace the coarse scene
//! under the session's lights (the native renderer, rows in parallel, each row checking a
//! cancel flag first), compose `C_T` from the passes (App. B), and run the network on the photo
//! at the stage's size (paper §3.2). The network's gain and bias are kept, so the relit image
//! can be produced at any size later (the display size now, the photo's full size on export).
use crate::error::{Result, StudioError};
use candle_core::{DType, Device, Tensor};
use pixl_core::Image;
use pixl_intrinsics::compose::{compose_film, ComposeOptions};
use pixl_intrinsics::ct::Ct;
use pixl_model::fullres;
use pixl_render::film::PixelSum;
use pixl_render::integrator::Renderer;
use pixl_render::{Film, RenderOptions, Scene};
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, Ordering};

/// A rendering stage: long side of the render and samples per pixel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Stage {
    pub side: usize,
    pub spp: u32,
}

/// What a finished stage produced.
pub struct StageOutput {
    pub width: usize,
    pub height: usize,
    /// The path-traced render (display: Reinhard, sRGB).
    pub render: Image,
    pub ct: Ct,
    /// Planar `3 × h × w` gain and bias of the network.
    pub gain: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Whether the stage was abandoned because newer work replaced it.
pub enum StageError {
    Cancelled,
    Failed(Box<StudioError>),
}

impl<E: Into<StudioError>> From<E> for StageError {
    fn from(e: E) -> Self {
        StageError::Failed(Box::new(e.into()))
    }
}

/// Renders `scene` (lights set) at `stage`, composes C_T and runs `model` on `photo` (RGB,
/// sRGB values in [0, 1], any size: area-averaged to the render's size). `cancel` is polled
/// before each row and before the network. `cached` holds the renderer of an earlier stage of
/// the same scene (taken and put back; `None` the first time).
#[allow(clippy::too_many_arguments)]
pub fn run_stage(
    cached: &mut Option<Renderer>,
    scene: &Scene,
    stage: Stage,
    max_bounces: u32,
    seed: u64,
    photo: &Image,
    model: &pixl_model::PixlRelight,
    cancel: &(dyn Fn() -> bool + Sync),
) -> std::result::Result<StageOutput, StageError> {
    let cam = &scene.camera;
    let (w, h) = fullres::working_size(cam.width as usize, cam.height as usize, stage.side);
    let opts = RenderOptions {
        spp: stage.spp.max(1),
        width: Some(w as u32),
        height: Some(h as u32),
        seed,
        max_bounces,
    };
    // The BVH and the lights do not depend on the image size: a later stage of the same scene
    // reuses them with new camera rays.
    let renderer = match cached.take() {
        Some(mut r) => {
            r.camera = pixl_render::camera::CameraRays::new(&scene.camera, w as u32, h as u32);
            r.width = w as u32;
            r.height = h as u32;
            r.opts = opts.clone();
            r
        }
        None => Renderer::new(scene, &opts)?,
    };
    let stopped = AtomicBool::new(false);
    let r = &renderer;
    let rows: Vec<Vec<PixelSum>> = (0..h)
        .into_par_iter()
        .map(|y| {
            if stopped.load(Ordering::Relaxed) || cancel() {
                stopped.store(true, Ordering::Relaxed);
                return Vec::new();
            }
            (0..w).map(|x| r.render_pixel(x, y)).collect()
        })
        .collect();
    if stopped.load(Ordering::Relaxed) {
        return Err(StageError::Cancelled);
    }
    let sums: Vec<PixelSum> = rows.into_iter().flatten().collect();
    let film = Film::from_sums(w, h, opts.spp, &sums);
    drop(sums);
    *cached = Some(renderer);
    let render = film.combined_srgb();
    let ct = compose_film(&film, &ComposeOptions::default())?.ct;
    drop(film);
    if cancel() {
        return Err(StageError::Cancelled);
    }
    let (gain, bias) = gain_bias(model, photo, &ct)?;
    Ok(StageOutput {
        width: w,
        height: h,
        render,
        ct,
        gain,
        bias,
    })
}

/// The network's gain and bias for `photo` under `ct` (at C_T's size).
pub fn gain_bias(model: &pixl_model::PixlRelight, photo: &Image, ct: &Ct) -> Result<(Vec<f32>, Vec<f32>)> {
    let (w, h) = (ct.width(), ct.height());
    let dev = Device::Cpu;
    let src = fullres::area_resize_to_chw(photo, w, h)?;
    let src = Tensor::from_vec(src, (1, 3, h, w), &dev)?;
    let ct_t = Tensor::from_vec(ct.to_chw(), (1, 9, h, w), &dev)?;
    let (g, b) = fullres::gain_bias_staged(model, &src, &ct_t, &mut |_, _, _| {})?;
    let flat =
        |t: &Tensor| -> candle_core::Result<Vec<f32>> { t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>() };
    Ok((flat(&g)?, flat(&b)?))
}

/// `photo` relit by a stage's gain and bias (resized bilinearly to the photo's size).
pub fn relight(photo: &Image, out: &StageOutput) -> Result<Image> {
    let mut img = photo.clone();
    fullres::apply_gain_bias(&mut img, &out.gain, &out.bias, out.width, out.height)?;
    Ok(img)
}

/// 8-bit PNG bytes of an image with values in [0, 1] (fast compression: sent at every change).
pub fn png_bytes(img: &Image) -> Result<Vec<u8>> {
    Ok(pixl_core::io::encode_png(
        img,
        pixl_core::io::PngDepth::Eight,
        pixl_core::io::PngCompression::Fast,
    )?)
}

/// Mean of each of the first three channels.
pub fn mean_rgb(img: &Image) -> [f32; 3] {
    let mut s = [0.0f64; 3];
    let n = img.num_pixels().max(1) as f64;
    for px in img.data.chunks_exact(img.channels.max(1)) {
        for (c, sum) in s.iter_mut().enumerate() {
            *sum += px.get(c).or(px.first()).copied().unwrap_or(0.0) as f64;
        }
    }
    s.map(|v| (v / n) as f32)
}

/// The C_T groups for display, sRGB-encoded as `pixl demo` shows them.
pub fn ct_panels(ct: &Ct) -> [Image; 3] {
    ct.groups()
        .map(|g| g.map(|v| pixl_core::image::linear_to_srgb(v.max(0.0))))
}
