//! The session: one photo, its coarse geometry, the lights, the undo history and the latest
//! results — behind one `Mutex`, held only for short, non-blocking sections (reading or
//! replacing values); every heavy step (decoding, meshing, previews, renders, the network) runs
//! on values copied out of it, and its result is stored only if it is still the newest.
//!
//! **Generations.** Every change of the lights or the geometry increments `generation`. A
//! preview, a render stage or a relit image is stored with the generation it was computed for,
//! and dropped if a newer one is already stored. The background worker ([`Studio::new`] starts
//! it) waits until the lights have stopped changing for `settle_ms`, then runs the progressive
//! stages (`StudioConfig::stages`, e.g. 4 spp at half size, then 16 spp at the working size);
//! a newer generation cancels the running stage at its next row.
//!
//! **Undo / redo** keep snapshots of the light list. A change sent with `coalesce` (a drag, a
//! slider) merges into the previous undo step when that step changed the same light.
//!
//! **Light like a photo** ([`Studio::relight_like_bytes`]) is apart from the lights: the
//! reference photo's `C_T` (`pixl_pipeline::like::target_ct`, at the working size) and the
//! network on the photo at the working size; the result is kept until the next one or a new
//! photo, and never touches the lights, their history or the generation.
use crate::error::{Result, StudioError};
use crate::geometry::{Coarse, DepthEstimator, DepthKind, GeometrySource};
use crate::lights::{environment, LightKind, LightPatch, StudioLight};
use crate::pipeline::{self, Stage, StageError, StageOutput};
use crate::preview::{self, GBuffer};
use pixl_core::Image;
use pixl_pipeline::like::LightingEstimator;
use pixl_render::Scene;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

// The bundled demo weights (the `dim128-p8` demo model; `assets/demo-weights/README.md`), as `pixl relight`
// loads them.

/// How the studio works; [`StudioConfig::default`] is what `pixl studio` uses.
#[derive(Clone)]
pub struct StudioConfig {
    /// Long side of the working size (the coarse scene's camera, the final render, the network).
    pub work_side: usize,
    /// Long side of the quick preview.
    pub preview_side: usize,
    /// Progressive render stages, in order; each side is capped at `work_side`.
    pub stages: Vec<Stage>,
    /// Path-tracing bounces.
    pub max_bounces: u32,
    /// Shadow rays in the quick preview.
    pub preview_shadows: bool,
    /// How long the lights must stay unchanged before the render starts (ms).
    pub settle_ms: u64,
    /// Vertical field of view assumed for photos (degrees).
    pub fov_y_deg: f32,
    /// Largest upload accepted (bytes).
    pub max_upload_bytes: usize,
    /// Largest photo or depth map accepted (pixels).
    pub max_pixels: usize,
    /// Network weights (safetensors); `None`: the bundled demo weights.
    pub weights: Option<PathBuf>,
    /// 8-bit linear layers in the network where the CPU has AVX-512 VNNI
    /// ([`pixl_model::PixlRelight::quantize_int8`]); f32 elsewhere.
    pub int8: bool,
    /// Where "save" and "export" write.
    pub out_dir: PathBuf,
    /// A monocular depth estimator, used for photos given without a depth map.
    pub estimator: Option<Arc<dyn DepthEstimator>>,
    /// The intrinsics estimator behind "light like this photo" (Marigold-IID-Lighting); without
    /// one that request is refused with a message saying how to get it.
    pub lighting: Option<Arc<dyn LightingEstimator>>,
}

impl Default for StudioConfig {
    fn default() -> Self {
        StudioConfig {
            work_side: 512,
            preview_side: 128,
            stages: vec![Stage { side: 256, spp: 4 }, Stage { side: 512, spp: 16 }],
            max_bounces: 4,
            preview_shadows: true,
            settle_ms: 250,
            fov_y_deg: 50.0,
            max_upload_bytes: 64 << 20,
            max_pixels: 40_000_000,
            weights: None,
            int8: false,
            out_dir: PathBuf::from("studio-out"),
            estimator: None,
            lighting: None,
        }
    }
}

/// The photo at full size and at the working size.
pub struct Photo {
    pub name: String,
    pub full: Image,
    pub work: Image,
    work_png: Vec<u8>,
}

/// A stored image result.
struct Shown {
    generation: u64,
    png: Vec<u8>,
    mean: [f32; 3],
    width: usize,
    height: usize,
}

impl Shown {
    fn new(generation: u64, img: &Image) -> Result<Shown> {
        Ok(Shown {
            generation,
            png: pipeline::png_bytes(img)?,
            mean: pipeline::mean_rgb(img),
            width: img.width,
            height: img.height,
        })
    }

    fn json(&self) -> Value {
        json!({"generation": self.generation, "width": self.width, "height": self.height, "mean": self.mean})
    }
}

/// The newest finished render stage and what was made of it.
struct Rendered {
    generation: u64,
    stage: usize,
    spp: u32,
    out: Arc<StageOutput>,
    render: Shown,
    albedo: Shown,
    shading: Shown,
    residual: Shown,
    relit: Shown,
}

/// The photo relit like a reference photo.
struct Liked {
    /// Counts results (the page's cache key).
    id: u64,
    reference: String,
    like: pixl_pipeline::like::LikeCt,
    relit: Shown,
}

impl Liked {
    fn json(&self) -> Value {
        json!({
            "id": self.id,
            "reference": self.reference,
            "width": self.relit.width,
            "height": self.relit.height,
            "mean": self.relit.mean,
            "reference_size": [self.like.target_size.0, self.like.target_size.1],
            "aspect_mismatch": self.like.aspect_mismatch,
            "aspect_differs": self.like.aspect_differs(),
            "tau": self.like.tau,
            "estimator": self.like.estimator,
        })
    }
}

/// What the last change did, for coalescing undo steps.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Action {
    Edit(u64),
    Other,
}

struct State {
    photo: Option<Arc<Photo>>,
    coarse: Option<Arc<Coarse>>,
    gbuf: Option<Arc<GBuffer>>,
    /// Sequence number of the geometry now installed (a slower, older load never replaces it).
    geometry_seq: u64,
    lights: Vec<StudioLight>,
    next_id: u64,
    undo: Vec<Vec<StudioLight>>,
    redo: Vec<Vec<StudioLight>>,
    last_action: Option<Action>,
    generation: u64,
    changed_at: Instant,
    preview: Option<Shown>,
    rendered: Option<Rendered>,
    busy: Option<String>,
    error: Option<String>,
    notes: Vec<String>,
    like: Option<Liked>,
    like_count: u64,
    /// The clip whose reference frame is the photo (lights are authored on it; "export video"
    /// relights every frame).
    video: Option<PathBuf>,
}

pub(crate) struct Shared {
    pub(crate) config: StudioConfig,
    state: Mutex<State>,
    /// Wakes the worker (changes) and waiters (new results).
    wake: Condvar,
    /// Mirror of `State::generation` for lock-free cancellation checks.
    generation: AtomicU64,
    seq: AtomicU64,
    model: pixl_model::PixlRelight,
    model_name: String,
    /// Threads of their own for the quick preview, so it never queues behind the render's and
    /// the network's work in rayon's global pool.
    preview_pool: rayon::ThreadPool,
    workdir: tempfile::TempDir,
}

/// A studio session (cheap to clone: all clones share it).
#[derive(Clone)]
pub struct Studio {
    pub(crate) shared: Arc<Shared>,
}

/// Which result [`Studio::wait`] waits for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WaitFor {
    Preview,
    /// Any render stage.
    Render,
    /// The last stage.
    Final,
}

impl WaitFor {
    pub fn parse(s: &str) -> Option<WaitFor> {
        match s {
            "preview" => Some(WaitFor::Preview),
            "render" | "relit" => Some(WaitFor::Render),
            "final" => Some(WaitFor::Final),
            _ => None,
        }
    }
}

/// Names of the images [`Studio::image_png`] serves.
pub const IMAGES: &[&str] = &[
    "photo", "preview", "render", "albedo", "shading", "residual", "relit", "like",
];

impl Studio {
    /// Loads the network and starts the background worker.
    pub fn new(mut config: StudioConfig) -> Result<Studio> {
        if config.work_side < 8 || config.preview_side < 4 || config.stages.is_empty() {
            return Err(StudioError::BadRequest(
                "work_side must be at least 8, preview_side at least 4, and there must be a render stage".into(),
            ));
        }
        for s in &mut config.stages {
            s.side = s.side.clamp(8, config.work_side);
        }
        let dev = candle_core::Device::Cpu;
        // Ours or the paper's released checkpoint (its licence goes into the model's name, which
        // the page shows), the same loader as `pixl relight`.
        let net = pixl_pipeline::relight::Network::load(
            config.weights.as_deref(),
            candle_core::DType::F32,
            &dev,
            config.int8,
        )?;
        let model_name = net.describe().trim_start_matches("weights: ").to_string();
        let model = net.model;
        let workdir = tempfile::Builder::new()
            .prefix("pixl-studio-")
            .tempdir()
            .map_err(|e| StudioError::io(&std::env::temp_dir(), e))?;
        let preview_pool = rayon::ThreadPoolBuilder::new()
            .num_threads(
                std::thread::available_parallelism()
                    .map(|n| n.get())
                    .unwrap_or(2)
                    .min(4),
            )
            .thread_name(|i| format!("pixl-studio-preview-{i}"))
            .build()
            .map_err(|e| StudioError::Internal(format!("starting the preview threads: {e}")))?;
        let shared = Arc::new(Shared {
            preview_pool,
            config,
            state: Mutex::new(State {
                photo: None,
                coarse: None,
                gbuf: None,
                geometry_seq: 0,
                lights: Vec::new(),
                next_id: 1,
                undo: Vec::new(),
                redo: Vec::new(),
                last_action: None,
                generation: 0,
                changed_at: Instant::now(),
                preview: None,
                rendered: None,
                busy: None,
                error: None,
                notes: Vec::new(),
                like: None,
                like_count: 0,
                video: None,
            }),
            wake: Condvar::new(),
            generation: AtomicU64::new(0),
            seq: AtomicU64::new(0),
            model,
            model_name,
            workdir,
        });
        let weak = Arc::downgrade(&shared);
        std::thread::Builder::new()
            .name("pixl-studio-render".into())
            .spawn(move || worker(weak))
            .map_err(|e| StudioError::Internal(format!("starting the render thread: {e}")))?;
        Ok(Studio { shared })
    }

    pub fn config(&self) -> &StudioConfig {
        &self.shared.config
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding the lock cannot leave a half-made change (changes are made on
        // copies and swapped in), so a poisoned lock is still usable.
        self.shared.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    // ----- photo and geometry -------------------------------------------------------------

    /// Decodes a PNG or JPEG photo (limits checked from the header first) and builds its
    /// geometry with the estimator, else the fallback. Replaces the lights and the history.
    pub fn load_photo_bytes(&self, bytes: &[u8], name: &str) -> Result<()> {
        let full = self.decode_photo(bytes, name)?;
        self.install_photo(full, name)
    }

    /// [`Studio::load_photo_bytes`] from a file.
    pub fn load_photo_file(&self, path: &Path) -> Result<()> {
        let bytes = std::fs::read(path).map_err(|e| StudioError::io(path, e))?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        self.load_photo_bytes(&bytes, &name)
    }

    /// Opens a clip (any container FFmpeg reads, or an image-sequence pattern): its reference
    /// frame — the median of its first frames, `pixl_pipeline::video::reference_frame` — becomes
    /// the photo the lights are placed on; [`Studio::export_video`] relights every frame.
    pub fn load_video_file(&self, path: &Path) -> Result<()> {
        let ff = pixl_pipeline::video::Ffmpeg::find()?;
        let (frame, _) = pixl_pipeline::video::reference_frame(&ff, path)?;
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        self.check_pixels(&name, frame.width, frame.height)?;
        self.install_photo(frame, &name)?;
        self.lock().video = Some(path.to_owned());
        Ok(())
    }

    /// Relights every frame of the loaded clip under the current lights' final `C_T` (a static
    /// camera: `pixl_pipeline::video::relight_frames`) into `<clip stem>-relit.mp4` (a sequence:
    /// `<stem>-relit/%05d.png`) in the output folder; waits up to `timeout` for the final render.
    /// Returns the file and the frame count.
    pub fn export_video(&self, timeout: Duration) -> Result<(PathBuf, u64)> {
        let clip = self
            .lock()
            .video
            .clone()
            .ok_or_else(|| StudioError::NotFound("no clip is loaded (open a video to export one)".into()))?;
        let (out, _) = self.final_output(timeout)?;
        let dir = self.out_dir()?;
        let stem = clip
            .file_stem()
            .map(|s| s.to_string_lossy().replace('%', ""))
            .unwrap_or_else(|| "clip".into());
        let dest = if pixl_pipeline::video::is_sequence(&clip) {
            let d = dir.join(format!("{stem}-relit"));
            std::fs::create_dir_all(&d).map_err(|e| StudioError::io(&d, e))?;
            d.join("%05d.png")
        } else {
            dir.join(format!("{stem}-relit.mp4"))
        };
        let ff = pixl_pipeline::video::Ffmpeg::find()?;
        let work = (out.ct.width(), out.ct.height());
        let (frames, _) = pixl_pipeline::video::relight_frames(
            &ff,
            &self.shared.model,
            &clip,
            &dest,
            &out.ct.to_chw(),
            work,
            &candle_core::Device::Cpu,
            &pixl_pipeline::Silent,
        )?;
        Ok((dest, frames))
    }

    fn check_upload(&self, len: usize) -> Result<()> {
        let max = self.shared.config.max_upload_bytes;
        if len > max {
            return Err(StudioError::TooLarge(format!(
                "the upload is {} bytes; the limit is {max} bytes ({} MiB)",
                len,
                max >> 20
            )));
        }
        Ok(())
    }

    fn decode_photo(&self, bytes: &[u8], name: &str) -> Result<Image> {
        self.check_upload(bytes.len())?;
        let reader = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| StudioError::BadRequest(format!("{name}: cannot read: {e}")))?;
        match reader.format() {
            Some(image::ImageFormat::Png) | Some(image::ImageFormat::Jpeg) => {}
            _ => {
                return Err(StudioError::BadRequest(format!(
                    "{name}: not a PNG or JPEG image (the studio opens .png and .jpg photos)"
                )))
            }
        }
        let (w, h) = reader
            .into_dimensions()
            .map_err(|e| StudioError::BadRequest(format!("{name}: cannot read the image header: {e}")))?;
        self.check_pixels(name, w as usize, h as usize)?;
        let decode = |e: image::ImageError| StudioError::BadRequest(format!("{name}: cannot decode: {e}"));
        let mut decoder = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| StudioError::BadRequest(format!("{name}: cannot read: {e}")))?
            .into_decoder()
            .map_err(decode)?;
        // Upright as a viewer shows it (phone photos are often stored sideways with a tag).
        let orientation = {
            use image::ImageDecoder;
            decoder
                .orientation()
                .unwrap_or(image::metadata::Orientation::NoTransforms)
        };
        let mut img = image::DynamicImage::from_decoder(decoder).map_err(decode)?;
        img.apply_orientation(orientation);
        let rgb = img.to_rgb32f();
        let (w, h) = rgb.dimensions();
        Ok(Image::from_vec(w as usize, h as usize, 3, rgb.into_raw())?)
    }

    fn check_pixels(&self, name: &str, w: usize, h: usize) -> Result<()> {
        let max = self.shared.config.max_pixels;
        if w == 0 || h == 0 {
            return Err(StudioError::BadRequest(format!("{name}: the image is empty ({w}x{h})")));
        }
        if w.saturating_mul(h) > max {
            return Err(StudioError::TooLarge(format!(
                "{name}: the image is {w}x{h} = {} pixels; the limit is {max} pixels",
                w.saturating_mul(h)
            )));
        }
        Ok(())
    }

    fn next_dir(&self) -> (u64, PathBuf) {
        let seq = self.shared.seq.fetch_add(1, Ordering::SeqCst) + 1;
        (seq, self.shared.workdir.path().join(format!("geometry-{seq}")))
    }

    fn install_photo(&self, full: Image, name: &str) -> Result<()> {
        let cfg = &self.shared.config;
        let (ww, wh) = pixl_model::fullres::working_size(full.width, full.height, cfg.work_side);
        let work = pixl_core::resample::area_resize(&full, ww, wh)?;
        let (seq, dir) = self.next_dir();
        let mut notes = Vec::new();
        let coarse = match &cfg.estimator {
            Some(est) => match est.estimate(
                &work,
                0.5 * wh as f64 / (0.5 * (cfg.fov_y_deg as f64).to_radians()).tan(),
            ) {
                Ok(d) => {
                    let metric = crate::geometry::metric_at(&d.depth, d.kind, ww, wh)?;
                    Some(Coarse::from_depth(
                        &work,
                        &metric,
                        cfg.fov_y_deg,
                        GeometrySource::Estimator { name: est.name() },
                        &dir,
                    )?)
                }
                Err(e) => {
                    notes.push(format!("the depth estimator failed ({e}); using the fallback geometry"));
                    None
                }
            },
            None => None,
        };
        let coarse = match coarse {
            Some(c) => c,
            None => {
                let depth = crate::geometry::fallback_depth(ww, wh, cfg.fov_y_deg)?;
                Coarse::from_depth(&work, &depth, cfg.fov_y_deg, GeometrySource::Fallback, &dir)?
            }
        };
        let photo = Photo {
            name: name.to_string(),
            work_png: pipeline::png_bytes(&work)?,
            full,
            work,
        };
        self.install(seq, Some(photo), coarse, Some(Vec::new()), notes)
    }

    /// Rebuilds the geometry from a depth map (EXR, 16-bit PNG or `.npy`; `name`'s extension
    /// says which) of `kind`, resampled to the working size. Lights anchored to the photo
    /// follow the new surface.
    pub fn load_depth_bytes(&self, bytes: &[u8], name: &str, kind: DepthKind) -> Result<()> {
        self.check_upload(bytes.len())?;
        let photo = self
            .lock()
            .photo
            .clone()
            .ok_or_else(|| StudioError::BadRequest("load a photo before its depth map".into()))?;
        let ext = pixl_core::io::extension(Path::new(name));
        if !["exr", "png", "npy"].contains(&ext.as_str()) {
            return Err(StudioError::BadRequest(format!(
                "{name}: a depth map must be .exr, .png (16-bit) or .npy"
            )));
        }
        let (seq, dir) = self.next_dir();
        std::fs::create_dir_all(&dir).map_err(|e| StudioError::io(&dir, e))?;
        let file = dir.join(format!("depth-upload.{ext}"));
        std::fs::write(&file, bytes).map_err(|e| StudioError::io(&file, e))?;
        let depth = pixl_render::depth::read_depth(&file, pixl_render::depth::DEFAULT_DEPTH_SCALE).map_err(|e| {
            // Name the upload, not the temporary file.
            StudioError::BadRequest(format!(
                "{name}: {}",
                e.to_string().replace(&file.display().to_string(), "depth map")
            ))
        })?;
        let _ = std::fs::remove_file(&file);
        self.check_pixels(name, depth.width, depth.height)?;
        let (ww, wh) = (photo.work.width, photo.work.height);
        let metric = crate::geometry::metric_at(&depth, kind, ww, wh)?;
        let source = GeometrySource::Depth {
            depth_kind: kind,
            file: name.to_string(),
        };
        let coarse = Coarse::from_depth(&photo.work, &metric, self.shared.config.fov_y_deg, source, &dir)?;
        self.install(seq, None, coarse, None, Vec::new())
    }

    /// Opens a scene file: its objects are the geometry, its render under its own lights (at
    /// the working size, the last stage's samples) is the photo, its lights the first lights.
    pub fn open_scene_file(&self, path: &Path) -> Result<()> {
        let scene = Scene::load(path)?;
        let cfg = &self.shared.config;
        let (w, h) =
            pixl_model::fullres::working_size(scene.camera.width as usize, scene.camera.height as usize, cfg.work_side);
        let spp = cfg.stages.last().map(|s| s.spp).unwrap_or(16);
        let opts = pixl_render::RenderOptions {
            spp,
            width: Some(w as u32),
            height: Some(h as u32),
            seed: 0,
            max_bounces: cfg.max_bounces,
        };
        let photo = pixl_render::render(&scene, &opts, &|_, _| {})?.combined_srgb();
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let coarse = Coarse::from_scene(&scene, &name)?;
        let distance = 0.3 * coarse.radius;
        let lights: Vec<StudioLight> = scene
            .lights
            .iter()
            .map(|l| StudioLight::from_render(l, distance))
            .collect();
        let mut lights = lights;
        if let Some(w) = &scene.world {
            let mut env = LightKind::Environment.defaults(distance, coarse.radius);
            env.name = "world".into();
            env.color = w.color;
            env.power = w.strength;
            lights.push(env);
        }
        let (seq, _) = self.next_dir();
        let p = Photo {
            name: format!("{name} (rendered)"),
            work_png: pipeline::png_bytes(&photo)?,
            full: photo.clone(),
            work: photo,
        };
        self.install(seq, Some(p), coarse, Some(lights), Vec::new())
    }

    /// Installs new geometry (and photo, and lights when given) unless a newer load already did.
    fn install(
        &self,
        seq: u64,
        photo: Option<Photo>,
        coarse: Coarse,
        lights: Option<Vec<StudioLight>>,
        notes: Vec<String>,
    ) -> Result<()> {
        let gbuf = GBuffer::build(&coarse, self.shared.config.preview_side);
        {
            let mut st = self.lock();
            if seq < st.geometry_seq {
                return Err(StudioError::Superseded(
                    "a newer photo or depth map was loaded meanwhile".into(),
                ));
            }
            st.geometry_seq = seq;
            st.coarse = Some(Arc::new(coarse));
            st.gbuf = Some(Arc::new(gbuf));
            if let Some(p) = photo {
                st.photo = Some(Arc::new(p));
                st.like = None;
                st.video = None;
            }
            if let Some(mut ls) = lights {
                st.undo.clear();
                st.redo.clear();
                st.last_action = None;
                st.next_id = 1;
                for l in &mut ls {
                    l.id = st.next_id;
                    st.next_id += 1;
                }
                st.lights = ls;
            }
            let coarse = st.coarse.clone();
            if let Some(c) = coarse {
                for l in &mut st.lights {
                    l.resolve(|u, v| c.pick(u, v), |u, v, t| c.along_ray(u, v, t));
                }
            }
            st.rendered = None;
            st.preview = None;
            st.error = None;
            st.notes = notes;
            self.bump(&mut st);
        }
        self.refresh_preview()
    }

    fn bump(&self, st: &mut State) {
        st.generation += 1;
        st.changed_at = Instant::now();
        self.shared.generation.store(st.generation, Ordering::SeqCst);
        self.shared.wake.notify_all();
    }

    // ----- lights ---------------------------------------------------------------------------

    /// Runs a change of the light list: on success it becomes one undo step (or merges into
    /// the previous one, see the module docs), the generation advances and the preview is
    /// recomputed; on error nothing changes.
    fn change<T>(&self, action: Action, coalesce: bool, f: impl FnOnce(&mut State, &Coarse) -> Result<T>) -> Result<T> {
        let out = {
            let mut st = self.lock();
            let coarse = st
                .coarse
                .clone()
                .ok_or_else(|| StudioError::BadRequest("load a photo first".into()))?;
            let before = st.lights.clone();
            let out = match f(&mut st, &coarse) {
                Ok(v) => v,
                Err(e) => {
                    st.lights = before;
                    return Err(e);
                }
            };
            let merge = coalesce && matches!(action, Action::Edit(_)) && st.last_action == Some(action);
            if !merge {
                st.undo.push(before);
                if st.undo.len() > 200 {
                    st.undo.remove(0);
                }
            }
            st.redo.clear();
            st.last_action = Some(action);
            self.bump(&mut st);
            out
        };
        self.refresh_preview()?;
        Ok(out)
    }

    /// Adds a light: `patch.kind` (default point) with its defaults, then the patch. With an
    /// anchor and no distance, the distance is 30 % of the scene's bounding radius.
    pub fn add_light(&self, patch: &LightPatch) -> Result<StudioLight> {
        self.change(Action::Other, false, |st, c| {
            let distance = patch.distance.unwrap_or(0.3 * c.radius);
            let mut l = patch.kind.unwrap_or(LightKind::Point).defaults(distance, c.radius);
            l.id = st.next_id;
            if patch.anchor.is_none() && patch.position.is_none() {
                // Unplaced: in front of the scene's centre, towards the camera.
                l.anchor = Some([0.5, 0.5]);
            }
            l.apply(patch)?;
            l.resolve(|u, v| c.pick(u, v), |u, v, t| c.along_ray(u, v, t));
            st.next_id += 1;
            st.lights.push(l.clone());
            Ok(l)
        })
    }

    /// Changes light `id`.
    pub fn update_light(&self, id: u64, patch: &LightPatch) -> Result<StudioLight> {
        self.change(Action::Edit(id), patch.coalesce, |st, c| {
            let l = st
                .lights
                .iter_mut()
                .find(|l| l.id == id)
                .ok_or_else(|| StudioError::NotFound(format!("there is no light {id}")))?;
            l.apply(patch)?;
            l.resolve(|u, v| c.pick(u, v), |u, v, t| c.along_ray(u, v, t));
            Ok(l.clone())
        })
    }

    /// Removes light `id`.
    pub fn delete_light(&self, id: u64) -> Result<()> {
        self.change(Action::Other, false, |st, _| {
            let n = st.lights.len();
            st.lights.retain(|l| l.id != id);
            if st.lights.len() == n {
                return Err(StudioError::NotFound(format!("there is no light {id}")));
            }
            Ok(())
        })
    }

    /// Replaces every light by the given ones (each a patch on its kind's defaults).
    pub fn set_lights(&self, patches: &[LightPatch]) -> Result<Vec<StudioLight>> {
        if patches.len() > 64 {
            return Err(StudioError::BadRequest("at most 64 lights".into()));
        }
        self.change(Action::Other, false, |st, c| {
            let mut out = Vec::new();
            for (i, p) in patches.iter().enumerate() {
                let mut l = p
                    .kind
                    .unwrap_or(LightKind::Point)
                    .defaults(p.distance.unwrap_or(0.3 * c.radius), c.radius);
                l.id = st.next_id + i as u64;
                l.apply(p)
                    .map_err(|e| StudioError::BadRequest(format!("light {i}: {e}")))?;
                l.resolve(|u, v| c.pick(u, v), |u, v, t| c.along_ray(u, v, t));
                out.push(l);
            }
            st.next_id += patches.len() as u64;
            st.lights = out.clone();
            Ok(out)
        })
    }

    /// Replaces the lights by one of the paper's five presets (§4.2), placed from the coarse
    /// scene's bounds.
    pub fn apply_preset(&self, name: &str) -> Result<Vec<StudioLight>> {
        self.change(Action::Other, false, |st, c| {
            let lights = pixl_render::presets::preset_lights(&c.scene, name)?;
            let out: Vec<StudioLight> = lights
                .iter()
                .enumerate()
                .map(|(i, l)| {
                    let mut s = StudioLight::from_render(l, 0.3 * c.radius);
                    s.id = st.next_id + i as u64;
                    s
                })
                .collect();
            st.next_id += out.len() as u64;
            st.lights = out.clone();
            Ok(out)
        })
    }

    /// Takes the lights (and the world, as an environment light) of a scene file's text
    /// (`.toml` or, with `json`, `.json`); the geometry stays.
    pub fn load_lights_from_scene_text(&self, text: &str, json: bool) -> Result<Vec<StudioLight>> {
        let scene = if json {
            Scene::from_json_str(text)?
        } else {
            Scene::from_toml_str(text)?
        };
        self.change(Action::Other, false, |st, c| {
            let d = 0.3 * c.radius;
            let mut out: Vec<StudioLight> = scene.lights.iter().map(|l| StudioLight::from_render(l, d)).collect();
            if let Some(w) = &scene.world {
                let mut env = LightKind::Environment.defaults(d, c.radius);
                env.name = "world".into();
                env.color = w.color;
                env.power = w.strength;
                out.push(env);
            }
            for (i, l) in out.iter_mut().enumerate() {
                l.id = st.next_id + i as u64;
            }
            st.next_id += out.len() as u64;
            st.lights = out.clone();
            Ok(out)
        })
    }

    /// Undoes the last change of the lights; `false` if there is none.
    pub fn undo(&self) -> Result<bool> {
        self.history(true)
    }

    /// Redoes the last undone change; `false` if there is none.
    pub fn redo(&self) -> Result<bool> {
        self.history(false)
    }

    fn history(&self, undo: bool) -> Result<bool> {
        {
            let mut st = self.lock();
            let popped = if undo { st.undo.pop() } else { st.redo.pop() };
            let Some(lights) = popped else { return Ok(false) };
            let now = std::mem::replace(&mut st.lights, lights);
            if undo {
                st.redo.push(now);
            } else {
                st.undo.push(now);
            }
            st.last_action = None;
            self.bump(&mut st);
        }
        self.refresh_preview()?;
        Ok(true)
    }

    /// The lights now.
    pub fn lights(&self) -> Vec<StudioLight> {
        self.lock().lights.clone()
    }

    /// The lights in the scene format (enabled ones) and the world they make.
    fn render_scene(coarse: &Coarse, lights: &[StudioLight]) -> Scene {
        let mut scene = coarse.scene.clone();
        scene.lights = lights.iter().filter_map(StudioLight::to_render).collect();
        if let Some(w) = environment(lights) {
            scene.world = Some(w);
        }
        scene
    }

    /// The session's scene (geometry and lights) as the CLI's scene format.
    pub fn scene(&self) -> Result<Scene> {
        let st = self.lock();
        let c = st
            .coarse
            .as_ref()
            .ok_or_else(|| StudioError::NotFound("no photo is loaded".into()))?;
        Ok(Self::render_scene(c, &st.lights))
    }

    // ----- previews and results -------------------------------------------------------------

    /// Recomputes the quick preview for the current generation (kept only if still newest).
    fn refresh_preview(&self) -> Result<()> {
        let (generation, gbuf, coarse, lights) = {
            let st = self.lock();
            match (&st.gbuf, &st.coarse) {
                (Some(g), Some(c)) => (st.generation, g.clone(), c.clone(), st.lights.clone()),
                _ => return Ok(()),
            }
        };
        let scene = Self::render_scene(&coarse, &lights);
        let shadows = self.shared.config.preview_shadows;
        let lin = self
            .shared
            .preview_pool
            .install(|| preview::shade(&gbuf, &coarse.geom, &scene.lights, scene.world.as_ref(), shadows));
        let shown = Shown::new(generation, &pixl_core::image::tonemap_reinhard(&lin))?;
        let mut st = self.lock();
        if st.preview.as_ref().is_none_or(|p| p.generation < generation) {
            st.preview = Some(shown);
            self.shared.wake.notify_all();
        }
        Ok(())
    }

    /// PNG bytes and generation of one of [`IMAGES`].
    pub fn image_png(&self, name: &str) -> Result<(u64, Vec<u8>)> {
        let st = self.lock();
        let missing = || StudioError::NotFound(format!("no {name} image yet"));
        let r = st.rendered.as_ref();
        let pick = |s: Option<&Shown>| s.map(|s| (s.generation, s.png.clone())).ok_or_else(missing);
        match name {
            "photo" => st
                .photo
                .as_ref()
                .map(|p| (st.generation, p.work_png.clone()))
                .ok_or_else(missing),
            "preview" => pick(st.preview.as_ref()),
            "render" => pick(r.map(|r| &r.render)),
            "albedo" => pick(r.map(|r| &r.albedo)),
            "shading" => pick(r.map(|r| &r.shading)),
            "residual" => pick(r.map(|r| &r.residual)),
            "relit" => pick(r.map(|r| &r.relit)),
            "like" => pick(st.like.as_ref().map(|l| &l.relit)),
            _ => Err(StudioError::NotFound(format!(
                "no image named {name:?} (there are {})",
                IMAGES.join(", ")
            ))),
        }
    }

    /// Everything the page shows, as JSON (documented in the crate README).
    pub fn state_json(&self) -> Value {
        let st = self.lock();
        let coarse = st.coarse.clone();
        let lights: Vec<Value> = st
            .lights
            .iter()
            .map(|l| {
                let uv = match (&l.anchor, &coarse) {
                    (Some(a), _) => Some(*a),
                    (None, Some(c)) if l.kind != LightKind::Sun && l.kind != LightKind::Environment => {
                        c.project(l.position)
                    }
                    _ => None,
                };
                let mut v = serde_json::to_value(l).unwrap_or(Value::Null);
                if let Value::Object(m) = &mut v {
                    m.insert("uv".into(), json!(uv));
                }
                v
            })
            .collect();
        let stages = &self.shared.config.stages;
        let rendered = st.rendered.as_ref().map(|r| {
            json!({
                "generation": r.generation,
                "stage": r.stage,
                "stages": stages.len(),
                "final": r.stage + 1 == stages.len(),
                "spp": r.spp,
                "render": r.render.json(),
                "relit": r.relit.json(),
            })
        });
        json!({
            "photo": st.photo.as_ref().map(|p| json!({
                "name": p.name, "width": p.full.width, "height": p.full.height,
                "work": [p.work.width, p.work.height],
            })),
            "geometry": coarse.as_ref().map(|c| json!({
                "source": c.source,
                "label": c.source.label(),
                "fallback": c.source == GeometrySource::Fallback,
                "radius": c.radius,
            })),
            "lights": lights,
            "can_undo": !st.undo.is_empty(),
            "can_redo": !st.redo.is_empty(),
            "generation": st.generation,
            "preview": st.preview.as_ref().map(Shown::json),
            "rendered": rendered,
            "busy": st.busy,
            "error": st.error,
            "notes": st.notes,
            "presets": pixl_render::presets::PRESETS,
            "weights": self.shared.model_name,
            "like": st.like.as_ref().map(Liked::json),
            "video": st.video.as_ref().map(|p| p.display().to_string()),
            "can_like": self.shared.config.lighting.is_some(),
            "out_dir": self.shared.config.out_dir.display().to_string(),
            "stages": stages,
        })
    }

    /// Waits (up to `timeout`) until `what` exists for generation `generation` or newer (the
    /// current one when `None`), and returns whether it does.
    pub fn wait(&self, what: WaitFor, generation: Option<u64>, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        let last = self.shared.config.stages.len().saturating_sub(1);
        let mut st = self.lock();
        let target = generation.unwrap_or(st.generation);
        loop {
            let ok = match what {
                WaitFor::Preview => st.preview.as_ref().is_some_and(|p| p.generation >= target),
                WaitFor::Render => st.rendered.as_ref().is_some_and(|r| r.generation >= target),
                WaitFor::Final => st
                    .rendered
                    .as_ref()
                    .is_some_and(|r| r.generation >= target && r.stage == last),
            };
            let now = Instant::now();
            if ok || now >= deadline {
                return ok;
            }
            st = match self.shared.wake.wait_timeout(st, deadline - now) {
                Ok((g, _)) => g,
                Err(p) => p.into_inner().0,
            };
        }
    }

    /// The final stage's output for the current generation, waiting up to `timeout` for it.
    fn final_output(&self, timeout: Duration) -> Result<(Arc<StageOutput>, Arc<Photo>)> {
        if !self.wait(WaitFor::Final, None, timeout) {
            return Err(StudioError::Superseded(
                "the relit image for the current lights is not ready yet (the render is still running); try again"
                    .into(),
            ));
        }
        let st = self.lock();
        match (&st.rendered, &st.photo) {
            (Some(r), Some(p)) => Ok((r.out.clone(), p.clone())),
            _ => Err(StudioError::NotFound("no photo is loaded".into())),
        }
    }

    /// The relit photo at its full size (waits up to `timeout` for the final stage).
    pub fn relit_full(&self, timeout: Duration) -> Result<Image> {
        let (out, photo) = self.final_output(timeout)?;
        pipeline::relight(&photo.full, &out)
    }

    // ----- light like a photo ---------------------------------------------------------------

    /// Relights the photo (at the working size) with the lighting of a reference photo (PNG or
    /// JPEG bytes, the upload limits apply): its `C_T` by the plugged [`LightingEstimator`]
    /// (`pixl_pipeline::like::target_ct`), then the network. Returns the result's JSON (as in
    /// the state's `like`); the image is served as `like`.
    pub fn relight_like_bytes(&self, bytes: &[u8], name: &str) -> Result<Value> {
        let estimator = self.shared.config.lighting.clone().ok_or_else(|| {
            StudioError::NotFound(
                "no Marigold-IID-Lighting estimator is loaded, so lighting cannot be read off a photo: put its \
                 weights on disk (`pixl models fetch marigold-lighting`, or --models DIR) and restart the studio"
                    .into(),
            )
        })?;
        let photo =
            self.lock().photo.clone().ok_or_else(|| {
                StudioError::BadRequest("load a photo before a reference photo to light it like".into())
            })?;
        let reference = self.decode_photo(bytes, name)?;
        let size = (photo.work.width, photo.work.height);
        let like = pixl_pipeline::like::target_ct(estimator.as_ref(), &reference, size, &pixl_pipeline::Silent)?;
        let (gain, bias) = pipeline::gain_bias(&self.shared.model, &photo.work, &like.ct)?;
        let mut relit = photo.work.clone();
        pixl_model::fullres::apply_gain_bias(&mut relit, &gain, &bias, size.0, size.1)?;
        let mut st = self.lock();
        if !st.photo.as_ref().is_some_and(|p| Arc::ptr_eq(p, &photo)) {
            return Err(StudioError::Superseded(
                "another photo was loaded meanwhile; light it like the reference again".into(),
            ));
        }
        st.like_count += 1;
        let liked = Liked {
            id: st.like_count,
            reference: name.to_string(),
            relit: Shown::new(st.generation, &relit)?,
            like,
        };
        let out = liked.json();
        st.like = Some(liked);
        self.shared.wake.notify_all();
        Ok(out)
    }

    // ----- files ------------------------------------------------------------------------------

    fn out_dir(&self) -> Result<PathBuf> {
        let d = self.shared.config.out_dir.clone();
        std::fs::create_dir_all(&d).map_err(|e| StudioError::io(&d, e))?;
        Ok(d)
    }

    /// Writes `scene.toml` (the CLI's format: `pixl render` / `pixl relight --scene` read it) to
    /// the output folder, with the files it refers to copied beside it.
    pub fn save_scene(&self) -> Result<PathBuf> {
        let scene = self.scene()?;
        let dir = self.out_dir()?;
        let mut out = scene.clone();
        out.base_dir = dir.clone();
        let workdir = self.shared.workdir.path().to_owned();
        let relocate = |p: &mut PathBuf| -> Result<()> {
            let src = scene.resolve(p);
            if src.starts_with(&workdir) {
                let name = src.file_name().map(PathBuf::from).unwrap_or_else(|| p.clone());
                let dst = dir.join(&name);
                std::fs::copy(&src, &dst).map_err(|e| StudioError::io(&src, e))?;
                *p = name;
            } else {
                *p = std::path::absolute(&src).map_err(|e| StudioError::io(&src, e))?;
            }
            Ok(())
        };
        for o in &mut out.objects {
            if let pixl_render::Shape::Mesh { path } = &mut o.shape {
                relocate(path)?;
            }
            for t in [
                &mut o.material.base_color_texture,
                &mut o.material.roughness_texture,
                &mut o.material.metallic_texture,
            ]
            .into_iter()
            .flatten()
            {
                relocate(t)?;
            }
        }
        if let Some(img) = out.world.as_mut().and_then(|w| w.image.as_mut()) {
            relocate(img)?;
        }
        let path = dir.join("scene.toml");
        out.save(&path)?;
        Ok(path)
    }

    /// The session's scene as TOML text (geometry paths as in the session's folder).
    pub fn scene_toml(&self) -> Result<String> {
        self.scene()?
            .to_string_as(pixl_render::scene::SceneFormat::Toml)
            .map_err(StudioError::Internal)
    }

    /// Writes `what` to the output folder: `relit` (`relit.png`, the photo's full size, 16-bit),
    /// `ct` (`CT.exr`, at the working size), `blender` (`scene_blender.py` and its data folder,
    /// `pixl_render::blender`), `scene` ([`Studio::save_scene`]), `video` (with a clip open:
    /// [`Studio::export_video`]). Waits up to `timeout` for the
    /// final render when needed.
    pub fn export(&self, what: &str, timeout: Duration) -> Result<Vec<PathBuf>> {
        let dir = self.out_dir()?;
        match what {
            "relit" => {
                let img = self.relit_full(timeout)?;
                let p = dir.join("relit.png");
                pixl_core::io::write_png(&p, &img, pixl_core::io::PngDepth::Sixteen)?;
                Ok(vec![p])
            }
            "ct" => {
                let (out, _) = self.final_output(timeout)?;
                let p = dir.join("CT.exr");
                pixl_intrinsics::ct::write_ct(&p, &out.ct)?;
                Ok(vec![p])
            }
            "blender" => {
                let scene = self.scene()?;
                let p = dir.join("scene_blender.py");
                let e = pixl_render::blender::export_blender(&scene, &p)?;
                Ok(vec![e.script, e.data_dir])
            }
            "scene" => Ok(vec![self.save_scene()?]),
            "video" => Ok(vec![self.export_video(timeout)?.0]),
            other => Err(StudioError::BadRequest(format!(
                "cannot export {other:?}: give relit, ct, blender, scene or video"
            ))),
        }
    }
}

/// The background loop: wait for a settled change, run the stages, store what is newest.
fn worker(weak: Weak<Shared>) {
    let mut done: u64 = 0;
    loop {
        let Some(shared) = weak.upgrade() else { return };
        let studio = Studio { shared };
        let job = {
            let st = studio.lock();
            let settle = Duration::from_millis(studio.shared.config.settle_ms);
            let ready = st.generation > done && st.changed_at.elapsed() >= settle;
            match (&st.coarse, &st.photo) {
                (Some(c), Some(p)) if ready => Some((st.generation, c.clone(), p.clone(), st.lights.clone())),
                _ => {
                    if st.generation > done && st.coarse.is_none() {
                        done = st.generation;
                    }
                    let wait = if st.generation > done {
                        settle
                            .saturating_sub(st.changed_at.elapsed())
                            .max(Duration::from_millis(5))
                    } else {
                        Duration::from_millis(200)
                    };
                    let _ = studio.shared.wake.wait_timeout(st, wait);
                    None
                }
            }
        };
        let Some((generation, coarse, photo, lights)) = job else {
            continue;
        };
        done = generation;
        let scene = Studio::render_scene(&coarse, &lights);
        let stages = studio.shared.config.stages.clone();
        let mut renderer = None;
        for (i, stage) in stages.iter().enumerate() {
            let cancelled = || studio.shared.generation.load(Ordering::SeqCst) != generation;
            if cancelled() {
                break;
            }
            studio.lock().busy = Some(format!(
                "rendering stage {}/{} ({} spp, long side {})",
                i + 1,
                stages.len(),
                stage.spp,
                stage.side
            ));
            let result = pipeline::run_stage(
                &mut renderer,
                &scene,
                *stage,
                studio.shared.config.max_bounces,
                generation,
                &photo.work,
                &studio.shared.model,
                &cancelled,
            );
            match result {
                Ok(out) => {
                    if let Err(e) = studio.store(generation, i, stage.spp, out, &photo) {
                        studio.lock().error = Some(e.to_string());
                        break;
                    }
                }
                Err(StageError::Cancelled) => break,
                Err(StageError::Failed(e)) => {
                    tracing::warn!("render failed: {e}");
                    let mut st = studio.lock();
                    if st.generation == generation {
                        st.error = Some(format!("render failed: {e}"));
                    }
                    break;
                }
            }
        }
        let mut st = studio.lock();
        st.busy = None;
        studio.shared.wake.notify_all();
    }
}

impl Studio {
    fn store(&self, generation: u64, stage: usize, spp: u32, out: StageOutput, photo: &Photo) -> Result<()> {
        let relit = pipeline::relight(&photo.work, &out)?;
        let [a, s, r] = pipeline::ct_panels(&out.ct);
        let rendered = Rendered {
            generation,
            stage,
            spp,
            render: Shown::new(generation, &out.render)?,
            albedo: Shown::new(generation, &a)?,
            shading: Shown::new(generation, &s)?,
            residual: Shown::new(generation, &r)?,
            relit: Shown::new(generation, &relit)?,
            out: Arc::new(out),
        };
        let mut st = self.lock();
        let newer = st
            .rendered
            .as_ref()
            .is_none_or(|r| (r.generation, r.stage) < (generation, stage));
        if newer && st.generation == generation {
            st.rendered = Some(rendered);
            st.error = None;
        }
        self.shared.wake.notify_all();
        Ok(())
    }
}
