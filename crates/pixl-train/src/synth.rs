//! `pixl synth`: a synthetic multi-illumination data set with **exact** target intrinsics — the
//! "simulated multi-illumination renders" the paper names as future work.
//!
//! Each scene is a procedural room (floor, back and side walls; textured) holding 2–5 random
//! spheres and boxes with random colours, procedural checker / value-noise textures (written as
//! PNGs under `textures/`), roughness and metallic. It is rendered under `lights` random
//! lightings, each of 1–2 lights drawn from {point, spot, area, sun} plus a random environment
//! (world) strength, with random colour temperatures. For every rendering the native path
//! tracer's passes are composed into C_T with `pixl_intrinsics::compose` (the code behind
//! `pixl compose`, App. B, p98 rescale), and written beside the image as
//! `<scene>/light_<k>.intrinsics.exr`; the image `<scene>/light_<k>.png` is the `Combined` pass
//! shown with the display convention (`Film::combined_srgb`: Reinhard, auto-exposure, sRGB).
//! `scenes.json` lists every scene, its split and its images ([`pixl_data::Synth`] reads it;
//! [`pixl_data::folder::SynthManifest`] is its format).
//!
//! With `coarse` (`pixl synth --coarse`), every scene also gets the C_T of the paper's inference
//! setting for each pair `i → j = i + 1 (mod lightings)` (the evaluation pairs): the coarse
//! reconstruction of image `i` alone (its Depth pass → mesh, DiffCol → albedo texture, one
//! estimated material; [`pixl_render::reconstruct::coarse_scene`]) rendered under lighting `j`
//! and composed — `light_<j>.from_light_<i>.intrinsics.exr` ([`pixl_data::coarse_ct_path`]), beside that
//! render shown like the images (`….path_traced.png`). `pixl eval --ct coarse` reads those of
//! the test scenes; training can condition on those of the train scenes
//! (`[data.sampler] coarse_ct`, `coarse_pair_share`). With `coarse_albedo = photo` the
//! reconstruction is textured with image `i` itself instead of its DiffCol pass (what `pixl
//! reconstruct` does without an albedo map): the setting of a user with no albedo estimator.
//!
//! Everything is a pure function of `(seed, scene index, lighting index)`: same seed, same set.
//! A failed or interrupted [`generate`] leaves nothing it created behind.
use crate::error::{Result, TrainError};
use pixl_core::output::Provisional;
use pixl_core::{Image, Rng};
use pixl_data::folder::{CoarseAlbedo, SynthImageRecord, SynthManifest, SynthSceneRecord, MANIFEST};
use pixl_data::{coarse_ct_path, Split};
use pixl_intrinsics::compose::{compose, ComposeOptions, PassSet};
use pixl_render::scene::AreaShape;
use pixl_render::{Camera, Color, Light, Material, Object, RenderOptions, Scene, Shape, Transform, World};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug)]
pub struct SynthOptions {
    pub scenes: usize,
    pub lights: usize,
    /// Square image side in pixels.
    pub size: u32,
    pub spp: u32,
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
            scenes: 100,
            lights: 6,
            size: 256,
            spp: 16,
            max_bounces: 2,
            seed: 0,
            test_every: 10,
            coarse: false,
            coarse_albedo: CoarseAlbedo::Diffcol,
        }
    }
}

const STREAM_SCENE: u64 = 0x5CE;
const STREAM_LIGHT: u64 = 0x116;

fn rgb(rng: &mut Rng, lo: f32, hi: f32) -> [f32; 3] {
    [rng.uniform(lo, hi), rng.uniform(lo, hi), rng.uniform(lo, hi)]
}

/// A procedural texture: checker or smooth value noise between two colours, sRGB PNG.
fn texture(rng: &mut Rng, size: usize) -> Image {
    let (a, b) = (rgb(rng, 0.1, 0.95), rgb(rng, 0.1, 0.95));
    if rng.bernoulli(0.5) {
        let cells = 2 + rng.below(7);
        Image::from_fn(size, size, 3, |x, y, c| {
            if (x * cells / size + y * cells / size).is_multiple_of(2) {
                a[c]
            } else {
                b[c]
            }
        })
    } else {
        let g = 4 + rng.below(6);
        let grid: Vec<f32> = (0..(g + 1) * (g + 1)).map(|_| rng.f32()).collect();
        Image::from_fn(size, size, 3, |x, y, c| {
            let (fx, fy) = (x as f32 / size as f32 * g as f32, y as f32 / size as f32 * g as f32);
            let (ix, iy) = (fx as usize, fy as usize);
            let (tx, ty) = (fx - ix as f32, fy - iy as f32);
            let at = |i: usize, j: usize| grid[j.min(g) * (g + 1) + i.min(g)];
            let v = (at(ix, iy) * (1.0 - tx) + at(ix + 1, iy) * tx) * (1.0 - ty)
                + (at(ix, iy + 1) * (1.0 - tx) + at(ix + 1, iy + 1) * tx) * ty;
            a[c] * (1.0 - v) + b[c] * v
        })
    }
}

fn material(rng: &mut Rng, tex_dir: &Path, tex_name: &str, tex_rel: &str, made: &mut Provisional) -> Result<Material> {
    let mut m = Material::diffuse(rgb(rng, 0.1, 0.9));
    m.roughness = rng.uniform(0.15, 1.0);
    m.specular_ior_level = rng.uniform(0.2, 0.6);
    if rng.bernoulli(0.2) {
        m.metallic = rng.uniform(0.5, 1.0);
    }
    if rng.bernoulli(0.5) {
        made.add_new_file(&tex_dir.join(tex_name));
        pixl_core::io::write_png(
            &tex_dir.join(tex_name),
            &texture(rng, 64),
            pixl_core::io::PngDepth::Eight,
        )?;
        m.base_color_texture = Some(PathBuf::from(tex_rel));
        m.base_color = Color::Rgb([1.0; 3]);
    }
    Ok(m)
}

fn quad(name: &str, size: [f32; 2], translate: [f32; 3], rotate_deg: [f32; 3], material: Material) -> Object {
    Object {
        name: name.into(),
        shape: Shape::Quad { size },
        transform: Transform {
            translate,
            rotate_deg,
            ..Default::default()
        },
        material,
    }
}

/// The static part of scene `index`: camera, room and objects (no lights); its textures are
/// written under `out/textures/`.
pub fn build_scene(opts: &SynthOptions, index: usize, out: &Path) -> Result<Scene> {
    let mut made = Provisional::new();
    let scene = build_scene_in(opts, index, out, &mut made)?;
    made.keep();
    Ok(scene)
}

/// [`build_scene`], adding the folders and textures it creates to `made`.
fn build_scene_in(opts: &SynthOptions, index: usize, out: &Path, made: &mut Provisional) -> Result<Scene> {
    let mut rng = Rng::for_stream(opts.seed, &[STREAM_SCENE, index as u64]);
    let tex_dir = out.join("textures");
    made.create_dir_all(&tex_dir)?;
    let mut mat = |rng: &mut Rng, k: usize| {
        let name = format!("scene{index:04}_{k}.png");
        material(rng, &tex_dir, &name, &format!("textures/{name}"), made)
    };
    let (w, d, h) = (rng.uniform(3.0, 5.0), rng.uniform(3.0, 5.0), rng.uniform(2.5, 3.5));
    let mut cam = Camera::new(opts.size, opts.size, rng.uniform(45.0, 65.0));
    cam.position = [rng.uniform(-0.4, 0.4), rng.uniform(1.0, 1.6), d / 2.0 - 0.2];
    cam.look_at = Some([rng.uniform(-0.5, 0.5), rng.uniform(0.3, 0.8), -d / 4.0]);
    let mut scene = Scene::new(cam);
    scene.base_dir = out.to_owned();
    let objs = &mut scene.objects;
    objs.push(quad(
        "floor",
        [w, d],
        [0.0, 0.0, 0.0],
        [-90.0, 0.0, 0.0],
        mat(&mut rng, 0)?,
    ));
    objs.push(quad(
        "back",
        [w, h],
        [0.0, h / 2.0, -d / 2.0],
        [0.0, 0.0, 0.0],
        mat(&mut rng, 1)?,
    ));
    objs.push(quad(
        "left",
        [d, h],
        [-w / 2.0, h / 2.0, 0.0],
        [0.0, 90.0, 0.0],
        mat(&mut rng, 2)?,
    ));
    objs.push(quad(
        "right",
        [d, h],
        [w / 2.0, h / 2.0, 0.0],
        [0.0, -90.0, 0.0],
        mat(&mut rng, 3)?,
    ));
    for k in 0..2 + rng.below(4) {
        let pos = [rng.uniform(-w / 3.0, w / 3.0), 0.0, rng.uniform(-d / 2.5, d / 8.0)];
        let m = mat(&mut rng, 4 + k)?;
        let obj = if rng.bernoulli(0.5) {
            let r = rng.uniform(0.2, 0.6);
            Object {
                name: format!("sphere{k}"),
                shape: Shape::Sphere { radius: r },
                transform: Transform {
                    translate: [pos[0], r, pos[2]],
                    ..Default::default()
                },
                material: m,
            }
        } else {
            let s = [rng.uniform(0.3, 1.0), rng.uniform(0.3, 1.2), rng.uniform(0.3, 1.0)];
            Object {
                name: format!("box{k}"),
                shape: Shape::Cuboid { size: s },
                transform: Transform {
                    translate: [pos[0], s[1] / 2.0, pos[2]],
                    rotate_deg: [0.0, rng.uniform(0.0, 90.0), 0.0],
                    ..Default::default()
                },
                material: m,
            }
        };
        objs.push(obj);
    }
    Ok(scene)
}

/// Lighting `k` of a scene with room size from its camera: 1–2 lights of random kinds, a random
/// environment strength, random colour temperatures. Returns the lights and a description.
pub fn draw_lighting(opts: &SynthOptions, index: usize, k: usize) -> (Vec<Light>, World, String) {
    let mut rng = Rng::for_stream(opts.seed, &[STREAM_LIGHT, index as u64, k as u64]);
    let mut lights = Vec::new();
    let mut kinds = Vec::new();
    for _ in 0..1 + rng.below(2) {
        let color = Color::Blackbody {
            kelvin: rng.uniform(2500.0, 7500.0),
        };
        let pos = [rng.uniform(-1.8, 1.8), rng.uniform(0.5, 2.4), rng.uniform(-1.5, 1.8)];
        let target = [rng.uniform(-0.8, 0.8), 0.2, rng.uniform(-1.2, 0.3)];
        let (light, kind) = match rng.below(4) {
            0 => (
                Light::Point {
                    name: "point".into(),
                    position: pos,
                    power: rng.uniform(150.0, 600.0),
                    radius: 0.05,
                    color,
                    visible_to_camera: false,
                },
                "point",
            ),
            1 => (
                Light::Spot {
                    name: "spot".into(),
                    position: pos,
                    direction: None,
                    look_at: Some(target),
                    power: rng.uniform(400.0, 1500.0),
                    spot_size_deg: rng.uniform(30.0, 90.0),
                    blend: rng.uniform(0.1, 0.5),
                    radius: 0.05,
                    color,
                    visible_to_camera: false,
                },
                "spot",
            ),
            2 => (
                Light::Area {
                    name: "area".into(),
                    position: pos,
                    direction: None,
                    look_at: Some(target),
                    shape: AreaShape::Square,
                    size: rng.uniform(0.3, 1.2),
                    size_y: None,
                    power: rng.uniform(150.0, 600.0),
                    color,
                    visible_to_camera: false,
                },
                "area",
            ),
            _ => {
                let dir = [rng.uniform(-0.7, 0.7), -rng.uniform(0.4, 1.0), rng.uniform(-0.7, 0.4)];
                (
                    Light::Sun {
                        name: "sun".into(),
                        direction: Some(dir),
                        strength: rng.uniform(2.0, 6.0),
                        angle_deg: 2.0,
                        color,
                    },
                    "sun",
                )
            }
        };
        lights.push(light);
        kinds.push(kind);
    }
    let world = World {
        strength: rng.uniform(0.0, 1.0),
        ..Default::default()
    };
    (lights, world, kinds.join("+"))
}

/// Renders and composes one lighting; writes the PNG and the C_T EXR; returns the passes.
fn render_one(
    opts: &SynthOptions,
    seed: u64,
    scene: &Scene,
    img_path: &Path,
    ct_path: &Path,
) -> Result<pixl_render::Film> {
    let ropts = RenderOptions {
        spp: opts.spp,
        width: Some(opts.size),
        height: Some(opts.size),
        seed,
        max_bounces: opts.max_bounces,
    };
    let film = pixl_render::render(scene, &ropts, &|_, _| {}).map_err(|e| TrainError::Other(format!("render: {e}")))?;
    let passes = PassSet::from_exr_channels(&film.to_exr_channels(), None)?;
    let composed = compose(&passes, &ComposeOptions::default())?;
    pixl_core::io::write_png(img_path, &film.combined_srgb(), pixl_core::io::PngDepth::Eight)?;
    pixl_intrinsics::ct::write_ct(ct_path, &composed.ct)?;
    Ok(film)
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
    let n_coarse = if opts.coarse { opts.scenes * opts.lights } else { 0 };
    let total = opts.scenes * opts.lights + n_coarse;
    let mut done = 0;
    let mut records = Vec::new();
    for i in 0..opts.scenes {
        let name = format!("scene{i:04}");
        let dir = out.join(&name);
        made.create_dir_all(&dir)?;
        let base = build_scene_in(opts, i, out, &mut made)?;
        let mut images = Vec::new();
        let mut lit = Vec::new();
        for k in 0..opts.lights {
            let (lights, world, desc) = draw_lighting(opts, i, k);
            let mut scene = base.clone();
            scene.lights = lights;
            scene.world = Some(world);
            let (img, ct) = (
                format!("{name}/light_{k}.png"),
                format!("{name}/light_{k}.intrinsics.exr"),
            );
            made.add_new_file(&out.join(&img));
            made.add_new_file(&out.join(&ct));
            let film = render_one(opts, opts.seed, &scene, &out.join(&img), &out.join(&ct))?;
            if opts.coarse {
                lit.push((scene, film));
            }
            images.push(SynthImageRecord {
                image: img,
                intrinsics: ct,
                lighting: desc,
            });
            done += 1;
            progress(done, total);
        }
        for (k, (source_scene, source_film)) in lit.iter().enumerate() {
            let j = (k + 1) % opts.lights;
            let recon_dir = dir.join(format!("coarse_from_light_{k}"));
            made.create_dir_all(&recon_dir)?;
            let photo = match opts.coarse_albedo {
                CoarseAlbedo::Diffcol => None,
                CoarseAlbedo::Photo => Some(source_film.combined_srgb()),
            };
            let mut relit = pixl_render::reconstruct::coarse_scene_textured(
                source_film,
                source_scene,
                &pixl_render::reconstruct::estimated_material(),
                photo.as_ref(),
                &recon_dir,
            )
            .map_err(|e| TrainError::Other(format!("coarse reconstruction of {name}/light_{k}: {e}")))?;
            relit.lights = lit[j].0.lights.clone();
            relit.world = lit[j].0.world.clone();
            let (src_img, tgt_img) = (out.join(&images[k].image), out.join(&images[j].image));
            let ct_path = coarse_ct_path(&src_img, &tgt_img);
            let traced = ct_path.with_file_name(
                ct_path
                    .file_name()
                    .map(|n| n.to_string_lossy().replace(".intrinsics.exr", ".path_traced.png"))
                    .unwrap_or_default(),
            );
            made.add_new_file(&traced);
            made.add_new_file(&ct_path);
            // Its own sample streams: the coarse render must not share the target's noise.
            render_one(opts, opts.seed ^ 0xC0A4_5E00, &relit, &traced, &ct_path)?;
            done += 1;
            progress(done, total);
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
        scenes: records,
    };
    let json = serde_json::to_string_pretty(&manifest).map_err(|e| TrainError::Other(e.to_string()))?;
    pixl_core::io::atomic_write_bytes(&out.join(MANIFEST), json.as_bytes())?;
    made.keep();
    Ok(manifest)
}
