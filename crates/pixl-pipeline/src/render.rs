//! The coarse scene under the new lights → its render passes (Cycles names) → `C_T` (paper
//! App. B): [`render_intrinsics`] path-traces at the working size with the native renderer and
//! composes with `pixl_intrinsics::compose::compose_film`, the one way a render becomes C_T.
use crate::error::{PipelineError, Result};
use crate::observe::{Observer, Stage};
use pixl_intrinsics::compose::{compose_film, ComposeOptions, Composed};
use pixl_render::{Film, RenderOptions, Scene};

/// Path-tracing settings of the passes C_T is composed from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RenderSettings {
    /// Samples per pixel.
    pub spp: u32,
    /// Maximum bounces.
    pub bounces: u32,
    pub seed: u64,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings {
            spp: 64,
            bounces: 8,
            seed: 0,
        }
    }
}

/// Renders `scene` (its lights set) at `size` and composes C_T; progress over rows goes to
/// `observer`. Returns the render (for its passes and picture) and the composition.
pub fn render_intrinsics(
    scene: &Scene,
    size: (usize, usize),
    settings: &RenderSettings,
    observer: &dyn Observer,
) -> Result<(Film, Composed)> {
    let opts = RenderOptions {
        spp: settings.spp,
        width: Some(size.0 as u32),
        height: Some(size.1 as u32),
        seed: settings.seed,
        max_bounces: settings.bounces,
    };
    observer.begin(Stage::Render, size.1 as u64);
    let film = pixl_render::render(scene, &opts, &|done, total| {
        observer.progress(Stage::Render, done as u64, total as u64)
    });
    observer.end(Stage::Render);
    let film = film.map_err(|e| PipelineError::from(e).context("rendering the coarse scene"))?;
    let composed = compose_film(&film, &ComposeOptions::default())?;
    Ok((film, composed))
}
