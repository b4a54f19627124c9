//! One relighting job, end to end: a [`Photo`] and a [`Lighting`] set-up → the relit photo at
//! its full size, with the intermediates written to a folder only when asked ([`Job::keep`]).
//! `pixl relight` runs one job; a batch runs one per photo with the network and estimators
//! loaded once.
//!
//! **Contract.** [`run`] checks the memory plan first ([`crate::relight::check_budget`]; nothing
//! is computed for a request that does not fit), then, by lighting:
//! - [`Lighting::Lights`]: depth ([`DepthSource`]) → [`crate::reconstruct::reconstruct`] in
//!   memory, with a mesh stride that keeps it near the working size → the lights (preset, then
//!   each [`LightSpec`], then fixed lights, in that order) → [`crate::render::render_intrinsics`]
//!   at the working size → the network. Needs a depth source.
//! - [`Lighting::Intrinsics`]: a `C_T` file at the photo's size or at the working size.
//! - [`Lighting::Like`]: the `C_T` of a reference photo ([`crate::like::target_ct`]).
//!
//! The photo is not decoded again; the scene is written (as `scene/`) only with `keep`. What
//! `keep` holds is [`KEPT`] or [`KEPT_LIKE`]; the caller checks the folder before the job (it
//! is created here). Notes for the user (a light's placement, where intermediates went) go to
//! the observer.
use crate::depth::{read_depth_file, DepthEstimator, DepthFile};
use crate::error::{PipelineError, Result};
use crate::lights::LightSpec;
use crate::like::{target_ct, LightingEstimator, LikeCt};
use crate::observe::Observer;
use crate::photo::Photo;
use crate::reconstruct::{reconstruct, Maps, MeshFormat, MeshSettings};
use crate::relight::{check_budget, ct_at_working_size, relight, Budget, Network};
use crate::render::{render_intrinsics, RenderSettings};
use candle_core::Device;
use pixl_core::io::{write_png, PngDepth};
use pixl_core::resample::area_resize;
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;
use pixl_render::depth::DepthMap;
use pixl_render::presets::apply_preset;
use pixl_render::scene::Light;
use std::borrow::Cow;
use std::path::{Path, PathBuf};

/// The files `keep` receives from a job with lights (`scene` is a folder).
pub const KEPT: &[&str] = &[
    "scene",
    "passes.exr",
    "CT.exr",
    "CT_sheet.png",
    "render.png",
    "before_after.png",
];
/// The files `keep` receives from a [`Lighting::Like`] job.
pub const KEPT_LIKE: &[&str] = &["CT.exr", "CT_sheet.png", "before_after.png"];

/// What a [`Lighting`] is, before its estimator is loaded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightingKind {
    Lights,
    Intrinsics,
    Like,
}

impl LightingKind {
    /// Full-size bytes per photo pixel beside the network: the photo (f32) and the encoded
    /// output, and a full-size `C_T` (9 f32 + its EXR decode) or the target's (9 f32 + one map
    /// being resized).
    pub fn bytes_per_px(self) -> u64 {
        12 + 8
            + match self {
                LightingKind::Lights => 0,
                LightingKind::Intrinsics => 72,
                LightingKind::Like => 36 + 12,
            }
    }
}

/// The memory plan of a job of `kind` on a `size` photo, refused above `max_memory`
/// ([`crate::relight::check_budget`]); a caller can check it before loading any estimator.
pub fn check(
    net: &Network,
    size: (usize, usize),
    max_side: usize,
    max_memory: Option<u64>,
    kind: LightingKind,
) -> Result<Budget> {
    check_budget(net, size, max_side, kind.bytes_per_px(), max_memory)
}

/// The lights of a job, as the user gave them.
#[derive(Clone, Debug, Default)]
pub struct LightSet {
    /// One of the paper's presets (`pixl_render::presets::PRESETS`).
    pub preset: Option<String>,
    /// Lights placed in the reconstructed scene, each with the words it was given as (for messages).
    pub placed: Vec<(String, LightSpec)>,
    /// Lights in the reconstructed scene's coordinates (a lights file's `[[lights]]`).
    pub fixed: Vec<Light>,
}

impl LightSet {
    pub fn is_empty(&self) -> bool {
        self.preset.is_none() && self.placed.is_empty() && self.fixed.is_empty()
    }

    /// The lights in `scene` (its own lights replaced), validated.
    pub fn apply(&self, scene: &mut pixl_render::Scene, observer: &dyn Observer) -> Result<()> {
        scene.lights.clear();
        if let Some(p) = &self.preset {
            apply_preset(scene, p, false)?;
        }
        for (words, spec) in &self.placed {
            let (light, notes) = spec.build(scene).map_err(|e| e.context(format!("--light '{words}'")))?;
            for n in notes {
                observer.note(&n);
            }
            scene.lights.push(light);
        }
        scene.lights.extend(self.fixed.iter().cloned());
        scene.validate()?;
        Ok(())
    }
}

/// Where the photo's depth comes from (for [`Lighting::Lights`]).
pub enum DepthSource<'a> {
    /// A depth file of the photo, read as `how` says.
    File { path: PathBuf, how: DepthFile },
    /// An estimator run on the photo.
    Estimate(&'a dyn DepthEstimator),
    /// Metric z-depth at the photo's size, already read or estimated.
    Given(DepthMap),
}

/// Where the target lighting comes from.
pub enum Lighting<'a> {
    /// Lights placed in the photo's reconstructed scene.
    Lights {
        lights: &'a LightSet,
        depth: DepthSource<'a>,
    },
    /// A `C_T` file (`albedo.*`, `shading.*`, `residual.*`), at the photo's size or the working size.
    Intrinsics(&'a Path),
    /// The lighting of a reference photo of the same view (RGB, sRGB-encoded, in `[0, 1]`).
    Like {
        target: &'a Image,
        estimator: &'a dyn LightingEstimator,
    },
}

impl Lighting<'_> {
    pub fn kind(&self) -> LightingKind {
        match self {
            Lighting::Lights { .. } => LightingKind::Lights,
            Lighting::Intrinsics(_) => LightingKind::Intrinsics,
            Lighting::Like { .. } => LightingKind::Like,
        }
    }
}

/// One photo to relight.
pub struct Job<'a> {
    pub photo: Photo,
    pub lighting: Lighting<'a>,
    /// Longest side the network works at.
    pub max_side: usize,
    /// The render `C_T` is composed from (lights only).
    pub render: RenderSettings,
    /// Most bytes the job may plan to use (default: the memory available now).
    pub max_memory: Option<u64>,
    /// A folder for the intermediates ([`KEPT`], [`KEPT_LIKE`]).
    pub keep: Option<PathBuf>,
}

/// A relit photo.
pub struct Relit {
    /// At the photo's full size.
    pub image: Image,
    pub budget: Budget,
    /// The files written to `keep`.
    pub kept: Vec<PathBuf>,
    /// With [`Lighting::Like`]: the reference's `C_T` and how it was made.
    pub like: Option<LikeCt>,
}

/// Runs `job` with `net` on `device` (see the module docs).
pub fn run(net: &Network, job: Job, device: &Device, observer: &dyn Observer) -> Result<Relit> {
    let size = job.photo.size();
    let budget = check(net, size, job.max_side, job.max_memory, job.lighting.kind())?;
    let work = budget.work;
    let mut kept = Vec::new();
    let mut like = None;
    let ct_work = match &job.lighting {
        Lighting::Lights { lights, depth } => {
            let ct = lit_ct(&job, lights, depth, work, &mut kept, observer)?;
            ct_at_working_size(&ct, work)?
        }
        Lighting::Intrinsics(path) => {
            let ct = pixl_intrinsics::ct::read_ct(path)?;
            let ct_size = (ct.width(), ct.height());
            if ct_size != size && ct_size != work {
                return Err(PipelineError::input(format!(
                    "{} is {}x{} but intrinsics {} are {}x{}; give C_T at the photo's size or at the working size {}x{} \
                     (--max-side {})",
                    job.photo.name(),
                    size.0,
                    size.1,
                    path.display(),
                    ct_size.0,
                    ct_size.1,
                    work.0,
                    work.1,
                    job.max_side
                )));
            }
            ct_at_working_size(&ct, work)?
        }
        Lighting::Like { target, estimator } => {
            let liked = target_ct(*estimator, target, size, observer)?;
            let ct_work = ct_at_working_size(&liked.ct, work)?;
            like = Some(liked);
            ct_work
        }
    };

    let before = job
        .keep
        .as_ref()
        .map(|_| area_resize(&job.photo.image, work.0, work.1))
        .transpose()?;
    let image = relight(net, job.photo.image, &ct_work, work, device, observer)?;
    if let (Some(dir), Some(before)) = (&job.keep, before) {
        if let Some(liked) = &like {
            create_dir(dir)?;
            kept.extend(write_ct(dir, &liked.ct)?);
        }
        let after = area_resize(&image, work.0, work.1)?;
        let path = dir.join("before_after.png");
        write_png(&path, &Image::hstack(&[&before, &after])?, PngDepth::Eight)?;
        kept.push(path);
        observer.note(&format!("intermediates in {}", dir.display()));
    }
    Ok(Relit {
        image,
        budget,
        kept,
        like,
    })
}

/// The photo's metric depth at its size.
fn depth_map<'a>(photo: &Photo, depth: &'a DepthSource) -> Result<Cow<'a, DepthMap>> {
    match depth {
        DepthSource::File { path, how } => read_depth_file(path, how, photo.size()).map(Cow::Owned),
        DepthSource::Estimate(est) => est
            .estimate(&photo.srgb(), photo.focal.px)
            .and_then(|d| d.to_metric(photo.size()))
            .map(Cow::Owned),
        DepthSource::Given(map) if (map.width, map.height) == photo.size() => Ok(Cow::Borrowed(map)),
        DepthSource::Given(map) => Err(PipelineError::input(format!(
            "the depth is {}x{}, the photo {}x{}",
            map.width,
            map.height,
            photo.size().0,
            photo.size().1
        ))),
    }
    .map_err(|e| e.context("reconstructing the scene"))
}

/// Reconstruct → lights → render → `C_T` at the working size (kept files appended to `kept`).
fn lit_ct(
    job: &Job,
    lights: &LightSet,
    depth: &DepthSource,
    work: (usize, usize),
    kept: &mut Vec<PathBuf>,
    observer: &dyn Observer,
) -> Result<Ct> {
    let photo = &job.photo;
    let size = photo.size();
    let depth_name = match depth {
        DepthSource::File { path, .. } => path.display().to_string(),
        DepthSource::Estimate(_) => "the estimated depth".to_string(),
        DepthSource::Given(_) => "the photo's depth".to_string(),
    };
    let map = depth_map(photo, depth)?;
    // The mesh needs no more vertices than the render has pixels.
    let settings = MeshSettings {
        stride: Some(size.0.max(size.1).div_ceil(work.0.max(work.1)).max(1)),
        ..Default::default()
    };
    let geometry = reconstruct(photo, &map, &depth_name, &Maps::default(), &settings, observer)
        .map_err(|e| e.context("reconstructing the scene"))?;
    drop(map);

    let mut scene = geometry.scene.clone();
    lights.apply(&mut scene, observer)?;
    let scene_name = match &job.keep {
        Some(dir) => {
            create_dir(dir)?;
            let path = geometry.write(&dir.join("scene"), MeshFormat::Glb, &scene.lights)?;
            kept.push(dir.join("scene"));
            path.display().to_string()
        }
        None => "the reconstructed scene".to_string(),
    };
    drop(geometry);

    let (film, composed) = render_intrinsics(&scene, work, &job.render, observer)
        .map_err(|e| e.context(format!("rendering {scene_name}")))?;
    if let Some(dir) = &job.keep {
        let passes = dir.join("passes.exr");
        film.write_exr(&passes)?;
        let render = dir.join("render.png");
        write_png(&render, &film.combined_srgb(), PngDepth::Eight)?;
        kept.push(passes);
        kept.extend(write_ct(dir, &composed.ct)?);
        kept.push(render);
    }
    Ok(composed.ct)
}

/// Writes `CT.exr` and its preview `CT_sheet.png` in `dir`.
fn write_ct(dir: &Path, ct: &Ct) -> Result<[PathBuf; 2]> {
    let exr = dir.join("CT.exr");
    pixl_intrinsics::ct::write_ct(&exr, ct)?;
    let sheet = dir.join("CT_sheet.png");
    write_png(&sheet, &pixl_intrinsics::preview::preview_sheet(ct)?, PngDepth::Eight)?;
    Ok([exr, sheet])
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| PipelineError::io(dir, e))
}
