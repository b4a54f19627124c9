//! A scene under its lights → its render passes (Cycles names) → `C_T` (paper App. B):
//! [`render_intrinsics`] path-traces at a given size with the native renderer and composes with
//! `pixl_intrinsics::compose::compose_film` ([`compose`]), the one way a render becomes C_T. Its
//! two steps are offered apart for callers that need the picture of every render but the C_T of
//! only some (a synthetic source photograph, a ground truth): [`render_film`] renders exactly as
//! `pixl_render::render` does with the same [`RenderSettings`], and [`compose`] turns a film's
//! passes into C_T.
use crate::error::Result;
use crate::observe::{Observer, Stage};
use pixl_intrinsics::compose::{compose_film, ComposeOptions, Composed};
use pixl_render::{Film, RenderOptions, Scene};

/// Path-tracing settings of a render (the passes C_T is composed from, or any other picture).
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

/// Renders `scene` (its lights set) at `size` with the native path tracer; progress over rows
/// goes to `observer`. The film holds every pass (`combined_srgb` for its picture).
pub fn render_film(
    scene: &Scene,
    size: (usize, usize),
    settings: &RenderSettings,
    observer: &dyn Observer,
) -> Result<Film> {
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
    Ok(film?)
}

/// Renders `scene` (its lights set) at `size` and composes C_T; progress over rows goes to
/// `observer`. Returns the render (for its passes and picture) and the composition.
pub fn render_intrinsics(
    scene: &Scene,
    size: (usize, usize),
    settings: &RenderSettings,
    observer: &dyn Observer,
) -> Result<(Film, Composed)> {
    let film = render_film(scene, size, settings, observer).map_err(|e| e.context("rendering the coarse scene"))?;
    let composed = compose(&film)?;
    Ok((film, composed))
}

/// C_T composed from the passes of `film` (a render with Cycles pass names), with the default
/// options (the joint 98th-percentile rescale).
pub fn compose(film: &Film) -> Result<Composed> {
    Ok(compose_film(film, &ComposeOptions::default())?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    /// A unit sphere 3 m in front of a 24×16 camera, lit by a point light.
    fn scene() -> Scene {
        Scene::from_toml_str(
            "[camera]\nwidth = 24\nheight = 16\nfov_y_deg = 40.0\nposition = [0.0, 0.0, 3.0]\n\n\
             [[objects]]\nshape = { type = \"sphere\", radius = 1.0 }\n\
             material = { base_color = [0.8, 0.4, 0.2], roughness = 0.4 }\n\n\
             [[lights]]\ntype = \"point\"\nposition = [1.0, 2.0, 2.0]\npower = 100.0\n",
        )
        .unwrap()
    }

    /// Records what the render stage says.
    #[derive(Default)]
    struct Log(Mutex<Vec<(Stage, &'static str, u64, u64)>>);

    impl Observer for Log {
        fn begin(&self, stage: Stage, total: u64) {
            self.0.lock().unwrap().push((stage, "begin", 0, total));
        }
        fn progress(&self, stage: Stage, done: u64, total: u64) {
            self.0.lock().unwrap().push((stage, "progress", done, total));
        }
        fn end(&self, stage: Stage) {
            self.0.lock().unwrap().push((stage, "end", 0, 0));
        }
    }

    #[test]
    fn the_stage_renders_and_composes_as_the_renderer_and_compose_do() {
        let scene = scene();
        let settings = RenderSettings {
            spp: 2,
            ..RenderSettings::default()
        };
        // The renderer at the camera's own size with its default bounces and seed.
        let direct = pixl_render::render(
            &scene,
            &RenderOptions {
                spp: 2,
                ..RenderOptions::default()
            },
            &|_, _| {},
        )
        .unwrap();
        let log = Log::default();
        let film = render_film(&scene, (24, 16), &settings, &log).unwrap();
        assert_eq!((film.width, film.height), (24, 16));
        assert_eq!(film.combined_srgb(), direct.combined_srgb());
        for pass in pixl_core::passes::ALL {
            assert_eq!(film.pass_ref(pass.short), direct.pass_ref(pass.short), "{}", pass.short);
        }
        assert!(film.pass_ref("Depth").is_some() && film.pass_ref("DiffDir").is_some());
        let log = log.0.into_inner().unwrap();
        assert_eq!(log.first(), Some(&(Stage::Render, "begin", 0, 16)));
        assert_eq!(log.last(), Some(&(Stage::Render, "end", 0, 0)));
        assert!(log.contains(&(Stage::Render, "progress", 16, 16)), "{log:?}");

        let (film2, composed) = render_intrinsics(&scene, (24, 16), &settings, &crate::Silent).unwrap();
        assert_eq!(film2.combined_srgb(), film.combined_srgb());
        let expected = compose_film(&direct, &ComposeOptions::default()).unwrap();
        assert_eq!(composed.ct, expected.ct);
        assert_eq!(compose(&film).unwrap().ct, expected.ct);
        assert!(
            composed.ct.shading.data.iter().any(|v| *v > 0.0),
            "the lit sphere has shading"
        );
    }
}
