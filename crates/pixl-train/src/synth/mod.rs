//! `pixl synth`: a synthetic multi-illumination data set with **exact** target intrinsics — the
//! "simulated multi-illumination renders" the paper names as future work.
//!
//! Two scene generators ([`SynthStyle`]): **photo** ([`photo`], the default) — furnished rooms
//! and table-tops with wood, stone, fabric, paint, printed, tiled and metal materials, glossy,
//! dark and glass objects, 1–3 lights of every kind at plausible powers; and **boxes**
//! ([`boxes`]) — the first generator, rooms of random boxes and spheres, kept so that older sets
//! can be made again. Each scene is rendered under `lights` lightings. For every rendering the
//! native path tracer's passes (at `spp`: C_T keeps the noise of a quick render) are composed
//! into C_T with `pixl_intrinsics::compose` (the code behind `pixl compose`, App. B, p98
//! rescale) and written beside the image as `<scene>/light_<k>.intrinsics.exr`; the image
//! `<scene>/light_<k>.png` is the `Combined` pass of a render at `image_spp` (clean targets;
//! photo style: a separate render with its own sample streams, cleaned by the guided median of
//! [`pixl_render::denoise`]) shown with the style's [`Tone`] ([`show`]): a camera's
//! (auto-exposure, filmic curve, sRGB; [`pixl_core::image::tonemap_camera`]) for photo, Reinhard
//! for boxes. `scenes.json` lists every scene, its split and its images
//! ([`pixl_data::Synth`] reads it; [`pixl_data::folder::SynthManifest`] is its format, which
//! records the style and the tone).
//!
//! With `coarse` (`pixl synth --coarse`), every scene also gets the C_T of the paper's inference
//! setting for each pair `i → j = i + 1 (mod lightings)` (the evaluation pairs) and `i → i`
//! (the source's own lighting, for the light-response score of `pixl eval`): the coarse
//! reconstruction of image `i` alone (its Depth pass → mesh, DiffCol → albedo texture, one
//! estimated material; [`pixl_render::reconstruct::coarse_scene`]) rendered under lighting `j`
//! and composed — `light_<j>.from_light_<i>.intrinsics.exr` ([`pixl_data::coarse_ct_path`]),
//! beside that render shown like the images (`….path_traced.png`, [`pixl_data::coarse_render_path`]). `pixl eval --ct coarse` reads those of
//! the test scenes; training can condition on those of the train scenes
//! (`[data.sampler] coarse_ct`, `coarse_pair_share`). With `coarse_albedo = photo` the
//! reconstruction is textured with image `i` itself instead of its DiffCol pass (what `pixl
//! reconstruct` does without an albedo map): the setting of a user with no albedo estimator.
//!
//! Everything is a pure function of `(seed, scene index, lighting index)`: same seed, same set.
//! A failed or interrupted [`generate`] leaves nothing it created behind.
use crate::error::{Result, TrainError};
use pixl_core::output::Provisional;
use pixl_core::Image;
use pixl_data::folder::{CoarseAlbedo, SynthImageRecord, SynthManifest, SynthSceneRecord, Tone, MANIFEST};
use pixl_data::{coarse_ct_path, Split};
use pixl_intrinsics::compose::{compose_film, ComposeOptions};
use pixl_render::{Film, RenderOptions, Scene};
use std::path::Path;

pub mod boxes;
pub mod estimated;
pub mod photo;
pub mod textures;

/// Which scene generator `pixl synth` uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SynthStyle {
    /// Furnished rooms and table-tops, shown with a camera's tone curve ([`photo`]).
    Photo,
    /// Rooms of random boxes and spheres, shown with Reinhard ([`boxes`]).
    Boxes,
}

impl SynthStyle {
    pub fn name(self) -> &'static str {
        match self {
            SynthStyle::Photo => "photo",
            SynthStyle::Boxes => "boxes",
        }
    }

    /// How the style shows its renders.
    pub fn tone(self) -> Tone {
        match self {
            SynthStyle::Photo => Tone::Camera,
            SynthStyle::Boxes => Tone::Reinhard,
        }
    }
}

#[derive(Clone, Debug)]
pub struct SynthOptions {
    pub style: SynthStyle,
    pub scenes: usize,
    pub lights: usize,
    /// Square image side in pixels.
    pub size: u32,
    /// Samples per pixel of the passes C_T is composed from.
    pub spp: u32,
    /// Samples per pixel of the images; `None`: 4 × `spp` for photo, `spp` for boxes (one
    /// render for both, as the first generator did).
    pub image_spp: Option<u32>,
    pub max_bounces: u32,
    pub seed: u64,
    /// Every `test_every`-th scene (index `test_every − 1`, `2·test_every − 1`, …) is test.
    pub test_every: usize,
    /// Also write the coarse-reconstruction C_T of every pair `i → i+1` (see the module docs).
    pub coarse: bool,
    /// The coarse reconstruction's albedo texture.
    pub coarse_albedo: CoarseAlbedo,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            style: SynthStyle::Photo,
            scenes: 100,
            lights: 6,
            size: 256,
            spp: 16,
            image_spp: None,
            max_bounces: 2,
            seed: 0,
            test_every: 10,
            coarse: false,
            coarse_albedo: CoarseAlbedo::Diffcol,
        }
    }
}

impl SynthOptions {
    /// The images' samples per pixel (see [`SynthOptions::image_spp`]).
    pub fn image_spp(&self) -> u32 {
        self.image_spp.unwrap_or(match self.style {
            SynthStyle::Photo => 4 * self.spp,
            SynthStyle::Boxes => self.spp,
        })
    }
}

/// The photo style's scene and light streams (the boxes style keeps its own).
const STREAM_PHOTO_SCENE: u64 = 0x9407_05CE;
const STREAM_PHOTO_LIGHT: u64 = 0x9407_0116;
/// Seed offset of the image render when it is separate from the passes' render.
const IMAGE_SEED: u64 = 0x1_3A6E;

/// Radius of the guided median ([`pixl_render::denoise`]) the photo style cleans its images with.
pub const DENOISE_RADIUS: usize = 2;

/// Shows a linear render as the style's images are shown: boxes — `Combined` with Reinhard;
/// photo — the guided median of its light (radius [`DENOISE_RADIUS`]) with a camera's tone curve.
pub fn show(film: &Film, style: SynthStyle) -> Image {
    match style {
        SynthStyle::Boxes => film.combined_srgb(),
        SynthStyle::Photo => match pixl_render::denoise::guided_median(film, DENOISE_RADIUS) {
            Some(clean) => pixl_core::image::tonemap_camera(&clean),
            None => Image::new(film.width, film.height, 3),
        },
    }
}

fn render(opts: &SynthOptions, scene: &Scene, spp: u32, seed: u64) -> Result<Film> {
    let ropts = RenderOptions {
        spp,
        width: Some(opts.size),
        height: Some(opts.size),
        seed,
        max_bounces: opts.max_bounces,
    };
    pixl_render::render(scene, &ropts, &|_, _| {}).map_err(|e| TrainError::Other(format!("render: {e}")))
}

/// Renders one lighting: composes C_T from a render at `spp` and writes it to `ct_path`; writes
/// the image (a render at `image_spp`, the same one when the counts are equal) to `img_path`.
/// Returns the image's render and the image.
fn render_one(
    opts: &SynthOptions,
    image_spp: u32,
    seed: u64,
    scene: &Scene,
    img_path: &Path,
    ct_path: &Path,
) -> Result<(Film, Image)> {
    let passes_film = render(opts, scene, opts.spp, seed)?;
    let composed = compose_film(&passes_film, &ComposeOptions::default())?;
    pixl_intrinsics::ct::write_ct(ct_path, &composed.ct)?;
    let film = if image_spp == opts.spp {
        passes_film
    } else {
        render(opts, scene, image_spp, seed ^ IMAGE_SEED)?
    };
    let image = show(&film, opts.style);
    pixl_core::io::write_png(img_path, &image, pixl_core::io::PngDepth::Eight)?;
    Ok((film, image))
}

/// Generates the whole set under `out`; `progress(done, total)` after every rendering.
///
/// On failure (or interruption, see `pixl_core::output`) everything this call created is removed
/// again: the folders (`out` itself if it was new, scene folders, reconstructions, `textures/`)
/// and the files that did not exist before. Files it replaced in an existing set stay replaced.
pub fn generate(opts: &SynthOptions, out: &Path, progress: &dyn Fn(usize, usize)) -> Result<SynthManifest> {
    if opts.scenes == 0 || opts.lights < 2 || opts.size < 8 || opts.spp == 0 {
        return Err(TrainError::Config(format!(
            "synth needs scenes >= 1, lights >= 2 (a pair), size >= 8 and spp >= 1 (got {}, {}, {}, {})",
            opts.scenes, opts.lights, opts.size, opts.spp
        )));
    }
    let mut made = Provisional::new();
    made.create_dir_all(out)?;
    let n_coarse = if opts.coarse { 2 * opts.scenes * opts.lights } else { 0 };
    let total = opts.scenes * opts.lights + n_coarse;
    let mut done = 0;
    let mut records = Vec::new();
    for i in 0..opts.scenes {
        let name = format!("scene{i:04}");
        let dir = out.join(&name);
        made.create_dir_all(&dir)?;
        let (base, layout) = match opts.style {
            SynthStyle::Boxes => (boxes::build_scene_in(opts, i, out, &mut made)?, None),
            SynthStyle::Photo => {
                made.create_dir_all(&out.join("textures"))?;
                let (scene, layout) = photo::build(opts.seed, STREAM_PHOTO_SCENE, i, opts.size, out, &mut made)?;
                (scene, Some(layout))
            }
        };
        let mut images = Vec::new();
        let mut lit = Vec::new();
        for k in 0..opts.lights {
            let (lights, world, desc) = match &layout {
                None => boxes::draw_lighting(opts, i, k),
                Some(l) => photo::draw_lighting(opts.seed, STREAM_PHOTO_LIGHT, i, k, l),
            };
            let mut scene = base.clone();
            scene.lights = lights;
            scene.world = Some(world);
            let (img, ct) = (
                format!("{name}/light_{k}.png"),
                format!("{name}/light_{k}.intrinsics.exr"),
            );
            made.add_new_file(&out.join(&img));
            made.add_new_file(&out.join(&ct));
            let (film, image) = render_one(
                opts,
                opts.image_spp(),
                opts.seed,
                &scene,
                &out.join(&img),
                &out.join(&ct),
            )?;
            if opts.coarse {
                lit.push((scene, film, image));
            }
            images.push(SynthImageRecord {
                image: img,
                intrinsics: ct,
                lighting: desc,
            });
            done += 1;
            progress(done, total);
        }
        for (k, (source_scene, source_film, source_image)) in lit.iter().enumerate() {
            let recon_dir = dir.join(format!("coarse_from_light_{k}"));
            made.create_dir_all(&recon_dir)?;
            let estimated_texture;
            let texture = match opts.coarse_albedo {
                CoarseAlbedo::Diffcol => None,
                CoarseAlbedo::Photo => Some(source_image),
                CoarseAlbedo::Estimated => {
                    let pass = |p: &str| {
                        source_film
                            .pass_ref(p)
                            .ok_or_else(|| TrainError::Other(format!("{name}/light_{k}: the render has no {p} pass")))
                    };
                    let mut rng = pixl_core::Rng::for_stream(opts.seed, &[0x00A1_BED0, i as u64, k as u64]);
                    let errors = estimated::EstimatorErrors::draw(&mut rng);
                    estimated_texture =
                        estimated::estimated_albedo_srgb(pass("DiffCol")?, pass("DiffDir")?, pass("DiffInd")?, &errors)
                            .ok_or_else(|| TrainError::Other(format!("{name}/light_{k}: passes of different sizes")))?;
                    Some(&estimated_texture)
                }
            };
            let mut relit = pixl_render::reconstruct::coarse_scene_textured(
                source_film,
                source_scene,
                &pixl_render::reconstruct::estimated_material(),
                texture,
                &recon_dir,
            )
            .map_err(|e| TrainError::Other(format!("coarse reconstruction of {name}/light_{k}: {e}")))?;
            // The evaluation pair's target i+1, then the source's own lighting (for the
            // light-response score: the change between the two renders is what the lights do).
            for j in [(k + 1) % opts.lights, k] {
                relit.lights = lit[j].0.lights.clone();
                relit.world = lit[j].0.world.clone();
                let (src_img, tgt_img) = (out.join(&images[k].image), out.join(&images[j].image));
                let ct_path = coarse_ct_path(&src_img, &tgt_img);
                let traced = pixl_data::coarse_render_path(&src_img, &tgt_img);
                made.add_new_file(&traced);
                made.add_new_file(&ct_path);
                // Its own sample streams: the coarse render must not share the target's noise.
                // One render at `spp` serves C_T and the picture.
                render_one(opts, opts.spp, opts.seed ^ 0xC0A4_5E00, &relit, &traced, &ct_path)?;
                done += 1;
                progress(done, total);
            }
        }
        let is_test = opts.test_every > 0 && i % opts.test_every == opts.test_every - 1;
        records.push(SynthSceneRecord {
            name,
            split: if is_test { Split::Test } else { Split::Train },
            images,
        });
    }
    let manifest = SynthManifest {
        version: 1,
        seed: opts.seed,
        size: opts.size as usize,
        spp: opts.spp,
        coarse_albedo: opts.coarse.then_some(opts.coarse_albedo),
        style: Some(opts.style.name().to_string()),
        tone: Some(opts.style.tone()),
        image_spp: Some(opts.image_spp()),
        scenes: records,
    };
    let json = serde_json::to_string_pretty(&manifest).map_err(|e| TrainError::Other(e.to_string()))?;
    pixl_core::io::atomic_write_bytes(&out.join(MANIFEST), json.as_bytes())?;
    made.keep();
    Ok(manifest)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts(style: SynthStyle, scenes: usize, size: u32, spp: u32) -> SynthOptions {
        SynthOptions {
            style,
            scenes,
            lights: 2,
            size,
            spp,
            test_every: 2,
            ..Default::default()
        }
    }

    /// The photo style writes what the manifest lists, records its style, tone and image spp,
    /// and is a pure function of the seed: two runs give the same bytes, another seed differs.
    #[test]
    fn photo_sets_are_recorded_and_reproducible() {
        let dirs: Vec<_> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
        let mut o = opts(SynthStyle::Photo, 2, 24, 2);
        let m = generate(&o, dirs[0].path(), &|_, _| {}).unwrap();
        generate(&o, dirs[1].path(), &|_, _| {}).unwrap();
        o.seed = 9;
        generate(&o, dirs[2].path(), &|_, _| {}).unwrap();
        assert_eq!(m.style.as_deref(), Some("photo"));
        assert_eq!(m.tone, Some(Tone::Camera));
        assert_eq!(m.image_spp, Some(8));
        assert_eq!(m.scenes.len(), 2);
        assert_eq!(m.scenes[1].split, Split::Test);
        let bytes = |d: &tempfile::TempDir, f: &str| std::fs::read(d.path().join(f)).unwrap();
        let mut differs = false;
        for sc in &m.scenes {
            for im in &sc.images {
                assert_eq!(bytes(&dirs[0], &im.image), bytes(&dirs[1], &im.image), "{}", im.image);
                assert_eq!(bytes(&dirs[0], &im.intrinsics), bytes(&dirs[1], &im.intrinsics));
                differs |= bytes(&dirs[0], &im.image) != bytes(&dirs[2], &im.image);
                assert!(!im.lighting.is_empty());
            }
        }
        assert!(differs, "another seed must give other images");
    }

    /// Photo-style images are exposed like photographs: over a handful of scenes and lightings
    /// the mean sRGB level lies in [0.2, 0.75] for every image, fewer than 3 % of any image's
    /// pixels are blown out (≥ 254/255 in every channel), and black pixels (≤ 1/255 in every
    /// channel: deep shadow) are under 20 % of any image and 3 % of the set. (Six scenes at 40 px
    /// and 4 spp when written: means 0.22–0.58, blown ≤ 0.4 %, black ≤ 14 %, 2 % overall.)
    #[test]
    fn photo_images_are_neither_blown_out_nor_black() {
        let dir = tempfile::tempdir().unwrap();
        let o = opts(SynthStyle::Photo, 6, 40, 4);
        let m = generate(&o, dir.path(), &|_, _| {}).unwrap();
        let (mut black_sum, mut count) = (0.0, 0.0);
        for sc in &m.scenes {
            for im in &sc.images {
                let img = pixl_core::io::read_rgb(&dir.path().join(&im.image)).unwrap();
                let mean = img.data.iter().sum::<f32>() / img.data.len() as f32;
                let px = img.data.chunks_exact(3);
                let n = px.len() as f32;
                let blown = px.clone().filter(|p| p.iter().all(|&v| v >= 254.0 / 255.0)).count() as f32 / n;
                let black = px.filter(|p| p.iter().all(|&v| v <= 1.0 / 255.0)).count() as f32 / n;
                assert!((0.2..=0.75).contains(&mean), "{}: mean {mean}", im.image);
                assert!(
                    blown < 0.03 && black < 0.2,
                    "{}: blown {blown}, black {black}",
                    im.image
                );
                black_sum += black;
                count += 1.0;
            }
        }
        assert!(
            black_sum / count < 0.03,
            "black pixels: {} of the set",
            black_sum / count
        );
    }

    /// The boxes style still makes one render per image (image spp = spp) shown with Reinhard.
    #[test]
    fn boxes_style_keeps_one_render_and_reinhard() {
        let dir = tempfile::tempdir().unwrap();
        let m = generate(&opts(SynthStyle::Boxes, 1, 16, 2), dir.path(), &|_, _| {}).unwrap();
        assert_eq!(
            (m.style.as_deref(), m.tone, m.image_spp),
            (Some("boxes"), Some(Tone::Reinhard), Some(2))
        );
    }
}
