//! The first generator of `pixl synth` (`--style boxes`): a room (floor, back and side walls;
//! textured) holding 2–5 random spheres and boxes with random colours, procedural checker /
//! value-noise textures, roughness and metallic, under 1–2 random lights of {point, spot, area,
//! sun} and a random world strength. Kept so that sets made with it (and the bundled demo
//! weights' training runs) can be made again: the same scenes and lights (the pixels follow the
//! renderer's sampling).
use crate::error::Result;
use pixl_core::output::Provisional;
use pixl_core::{Image, Rng};
use pixl_render::scene::AreaShape;
use pixl_render::{Camera, Color, Light, Material, Object, Scene, Shape, Transform, World};
use std::path::{Path, PathBuf};

use super::SynthOptions;

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
pub(super) fn build_scene_in(opts: &SynthOptions, index: usize, out: &Path, made: &mut Provisional) -> Result<Scene> {
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
