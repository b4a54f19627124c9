//! The photo-like scenes of `pixl synth` (`--style photo`, the default): furnished rooms and
//! table-tops made of boxes, cylinders, spheres and planes with procedural materials
//! ([`super::textures`]: wood, stone, fabric, paint, prints, tiles, metal; plus plain glossy,
//! dark, metal and glass objects), lit by 1–3 lights of every kind at powers derived from a
//! plausible irradiance at the subject, with a dim sky-tinted world.
//!
//! **Rooms** (half the scenes): floor, four walls (the camera stands in front of the fourth),
//! a ceiling in half of them (then no sun); a table with things on it, a sofa, a cabinet with
//! things on it, a rug, a floor lamp, a plant, balls and pictures on the back wall, each present
//! by chance and placed without overlaps. **Table-tops**: a table slab in a room corner seen from
//! close by, 3–8 cups, bottles, bowls, fruit, books, boxes, vases and cans on it.
//!
//! Everything is a pure function of `(seed, scene index)` for the scene and `(seed, scene index,
//! lighting index)` for the lights; textures are written under `textures/` as PNGs (colour sRGB,
//! roughness as a grey map).
use super::textures::{household_color, hsv, surface, Family};
use crate::error::Result;
use pixl_core::output::Provisional;
use pixl_core::Rng;
use pixl_render::scene::AreaShape;
use pixl_render::{Camera, Color, Light, Material, Object, Scene, Shape, Transform, World};
use std::path::{Path, PathBuf};

/// Where the subject is and how the room is bounded: what the lights are placed from.
#[derive(Clone, Debug)]
pub struct Layout {
    /// Room interior: `x ∈ [−w/2, w/2]`, `z ∈ [−d/2, d/2]`, floor at 0, walls `h` high.
    pub w: f32,
    pub d: f32,
    pub h: f32,
    pub ceiling: bool,
    /// The point the camera looks at, and a radius of interest around it (metres).
    pub focus: [f32; 3],
    pub radius: f32,
    pub tabletop: bool,
}

/// An axis-aligned footprint on a support: centre and half sizes in x, z.
#[derive(Clone, Copy)]
struct Footprint {
    x: f32,
    z: f32,
    hx: f32,
    hz: f32,
}

impl Footprint {
    fn overlaps(&self, o: &Footprint, gap: f32) -> bool {
        (self.x - o.x).abs() < self.hx + o.hx + gap && (self.z - o.z).abs() < self.hz + o.hz + gap
    }
}

/// A rectangle to place things on (top at `y`) and what is already there.
struct Support {
    y: f32,
    x0: f32,
    x1: f32,
    z0: f32,
    z1: f32,
    taken: Vec<Footprint>,
}

impl Support {
    fn new(y: f32, x0: f32, x1: f32, z0: f32, z1: f32) -> Self {
        Support {
            y,
            x0,
            x1,
            z0,
            z1,
            taken: Vec::new(),
        }
    }

    /// A free spot for a footprint of half sizes `(hx, hz)`, or `None` after a few tries.
    fn place(&mut self, rng: &mut Rng, hx: f32, hz: f32) -> Option<(f32, f32)> {
        if self.x1 - self.x0 < 2.0 * hx || self.z1 - self.z0 < 2.0 * hz {
            return None;
        }
        for _ in 0..24 {
            let f = Footprint {
                x: rng.uniform(self.x0 + hx, self.x1 - hx),
                z: rng.uniform(self.z0 + hz, self.z1 - hz),
                hx,
                hz,
            };
            if !self.taken.iter().any(|t| t.overlaps(&f, 0.02)) {
                self.taken.push(f);
                return Some((f.x, f.z));
            }
        }
        None
    }
}

/// Makes objects and their materials; textures go to `textures/scene<NNNN>_<k>_*.png`.
struct Builder<'a> {
    rng: Rng,
    index: usize,
    out: &'a Path,
    made: &'a mut Provisional,
    tex_size: usize,
    next: usize,
    objects: Vec<Object>,
}

impl Builder<'_> {
    fn write_tex(&mut self, img: &pixl_core::Image, what: &str) -> Result<PathBuf> {
        let name = format!("scene{:04}_{}_{what}.png", self.index, self.next);
        let path = self.out.join("textures").join(&name);
        self.made.add_new_file(&path);
        pixl_core::io::write_png(&path, img, pixl_core::io::PngDepth::Eight)?;
        Ok(PathBuf::from("textures").join(name))
    }

    /// A textured material of `family` covering about `extent` metres.
    fn textured(&mut self, family: Family, extent: f32) -> Result<Material> {
        self.next += 1;
        let maps = surface(family, &mut self.rng, self.tex_size, extent);
        let mut m = Material::diffuse([1.0; 3]);
        m.base_color_texture = Some(self.write_tex(&maps.color, "color")?);
        m.roughness_texture = Some(self.write_tex(&maps.roughness, "rough")?);
        m.metallic = maps.metallic;
        m.specular_ior_level = self.rng.uniform(0.3, 0.6);
        Ok(m)
    }

    /// An untextured material: glossy or matte plastic/ceramic, a dark one, metal, or glass.
    fn plain(&mut self, glass_ok: bool) -> Material {
        let rng = &mut self.rng;
        let mut m = Material::diffuse(srgb_to_linear3(household_color(rng)));
        m.specular_ior_level = 0.5;
        match rng.below(10) {
            0..=3 => m.roughness = rng.uniform(0.05, 0.35), // glossy ceramic / plastic
            4..=5 => m.roughness = rng.uniform(0.5, 1.0),   // matte
            6 => {
                m.base_color = Color::Rgb(srgb_to_linear3(hsv(
                    rng.f32(),
                    rng.uniform(0.0, 0.4),
                    rng.uniform(0.02, 0.08),
                )));
                m.roughness = rng.uniform(0.1, 0.7); // dark
            }
            7..=8 => {
                m.base_color = Color::Rgb(srgb_to_linear3(hsv(
                    rng.uniform(0.05, 0.15),
                    rng.uniform(0.0, 0.5),
                    rng.uniform(0.6, 0.95),
                )));
                m.metallic = 1.0;
                m.roughness = rng.uniform(0.1, 0.45);
            }
            _ if glass_ok => {
                m.base_color = Color::Rgb(srgb_to_linear3(hsv(rng.f32(), rng.uniform(0.0, 0.3), 1.0)));
                m.transmission = 1.0;
                m.roughness = rng.uniform(0.0, 0.1);
            }
            _ => m.roughness = rng.uniform(0.2, 0.6),
        }
        m
    }

    /// A textured material of one of `families` (or a plain one with probability `p_plain`).
    fn any(&mut self, families: &[Family], extent: f32, p_plain: f32) -> Result<Material> {
        if self.rng.bernoulli(p_plain) {
            return Ok(self.plain(false));
        }
        let f = families[self.rng.below(families.len())];
        self.textured(f, extent)
    }

    fn push(&mut self, name: &str, shape: Shape, translate: [f32; 3], rotate_deg: [f32; 3], material: Material) {
        let transform = Transform {
            translate,
            rotate_deg,
            ..Default::default()
        };
        self.push_transformed(name, shape, transform, material);
    }

    fn push_scaled(&mut self, name: &str, shape: Shape, translate: [f32; 3], scale: [f32; 3], material: Material) {
        let transform = Transform {
            translate,
            scale,
            ..Default::default()
        };
        self.push_transformed(name, shape, transform, material);
    }

    /// Adds an object named `<name><index>`.
    fn push_transformed(&mut self, name: &str, shape: Shape, transform: Transform, material: Material) {
        self.objects.push(Object {
            name: format!("{name}{}", self.objects.len()),
            shape,
            transform,
            material,
        });
    }

    fn cuboid(&mut self, name: &str, size: [f32; 3], bottom_centre: [f32; 3], yaw: f32, m: Material) {
        let t = [bottom_centre[0], bottom_centre[1] + 0.5 * size[1], bottom_centre[2]];
        self.push(name, Shape::Cuboid { size }, t, [0.0, yaw, 0.0], m);
    }

    fn cylinder(&mut self, name: &str, radius: f32, height: f32, bottom_centre: [f32; 3], m: Material) {
        let t = [bottom_centre[0], bottom_centre[1] + 0.5 * height, bottom_centre[2]];
        self.push(name, Shape::Cylinder { radius, height }, t, [0.0; 3], m);
    }

    fn quad(&mut self, name: &str, size: [f32; 2], translate: [f32; 3], rotate_deg: [f32; 3], m: Material) {
        self.push(name, Shape::Quad { size }, translate, rotate_deg, m);
    }

    /// Floor, walls and maybe a ceiling of a `w × d × h` room.
    fn room(&mut self, w: f32, d: f32, h: f32, ceiling: bool) -> Result<()> {
        let floor = self.any(
            &[Family::Wood, Family::Wood, Family::Tiles, Family::Stone, Family::Fabric],
            w.max(d),
            0.0,
        )?;
        self.quad("floor", [w, d], [0.0, 0.0, 0.0], [-90.0, 0.0, 0.0], floor);
        let walls = [
            Family::Paint,
            Family::Paint,
            Family::Paint,
            Family::Print,
            Family::Tiles,
            Family::Wood,
        ];
        let main = self.any(&walls, w, 0.0)?;
        let side = if self.rng.bernoulli(0.6) {
            main.clone()
        } else {
            self.any(&walls, d, 0.0)?
        };
        self.quad("wall_back", [w, h], [0.0, h / 2.0, -d / 2.0], [0.0; 3], main.clone());
        self.quad(
            "wall_left",
            [d, h],
            [-w / 2.0, h / 2.0, 0.0],
            [0.0, 90.0, 0.0],
            side.clone(),
        );
        self.quad("wall_right", [d, h], [w / 2.0, h / 2.0, 0.0], [0.0, -90.0, 0.0], side);
        self.quad("wall_front", [w, h], [0.0, h / 2.0, d / 2.0], [0.0, 180.0, 0.0], main);
        if ceiling {
            let c = self.plain(false);
            self.quad(
                "ceiling",
                [w, d],
                [0.0, h, 0.0],
                [90.0, 0.0, 0.0],
                Material { metallic: 0.0, ..c },
            );
        }
        Ok(())
    }

    /// A small thing standing on `s` (cup, bottle, bowl, fruit, books, box, vase, can).
    fn small_thing(&mut self, s: &mut Support, scale: f32) -> Result<()> {
        let kind = self.rng.below(8);
        let r = self.rng.uniform(0.03, 0.06) * scale;
        match kind {
            0 | 7 => {
                // cup or can
                let Some((x, z)) = s.place(&mut self.rng, r, r) else {
                    return Ok(());
                };
                let h = r * self.rng.uniform(1.6, 2.6);
                let m = if kind == 7 && self.rng.bernoulli(0.6) {
                    self.textured(Family::Print, 2.0 * std::f32::consts::PI * r)?
                } else {
                    self.plain(false)
                };
                self.cylinder("cup", r, h, [x, s.y, z], m);
            }
            1 => {
                // bottle: body and neck
                let Some((x, z)) = s.place(&mut self.rng, r, r) else {
                    return Ok(());
                };
                let h = r * self.rng.uniform(3.5, 6.0);
                let m = self.plain(true);
                self.cylinder("bottle", r, h, [x, s.y, z], m.clone());
                self.cylinder("neck", r * 0.35, h * 0.3, [x, s.y + h, z], m);
            }
            2 => {
                // bowl: a flattened sphere sunk to its middle
                let rb = r * 1.8;
                let Some((x, z)) = s.place(&mut self.rng, rb, rb) else {
                    return Ok(());
                };
                let m = self.plain(false);
                self.push_scaled("bowl", Shape::Sphere { radius: rb }, [x, s.y, z], [1.0, 0.45, 1.0], m);
            }
            3 => {
                // fruit: a few spheres
                for _ in 0..1 + self.rng.below(3) {
                    let rf = r * self.rng.uniform(0.6, 0.9);
                    let Some((x, z)) = s.place(&mut self.rng, rf, rf) else {
                        return Ok(());
                    };
                    let mut m = Material::diffuse(srgb_to_linear3(hsv(
                        self.rng.uniform(-0.05, 0.3),
                        self.rng.uniform(0.6, 0.95),
                        self.rng.uniform(0.4, 0.9),
                    )));
                    m.roughness = self.rng.uniform(0.25, 0.6);
                    self.push("fruit", Shape::Sphere { radius: rf }, [x, s.y + rf, z], [0.0; 3], m);
                }
            }
            4 => {
                // a stack of books
                let (bw, bd) = (
                    self.rng.uniform(0.12, 0.22) * scale,
                    self.rng.uniform(0.16, 0.28) * scale,
                );
                let Some((x, z)) = s.place(&mut self.rng, bw * 0.7, bd * 0.7) else {
                    return Ok(());
                };
                let mut y = s.y;
                for _ in 0..1 + self.rng.below(4) {
                    let t = self.rng.uniform(0.015, 0.05) * scale;
                    let m = self.any(&[Family::Print, Family::Paint, Family::Fabric], bw, 0.3)?;
                    let yaw = self.rng.uniform(-15.0, 15.0);
                    self.cuboid("book", [bw, t, bd], [x, y, z], yaw, m);
                    y += t;
                }
            }
            5 => {
                let sz = [
                    r * self.rng.uniform(1.5, 4.0),
                    r * self.rng.uniform(1.0, 4.0),
                    r * self.rng.uniform(1.5, 4.0),
                ];
                let Some((x, z)) = s.place(&mut self.rng, sz[0] * 0.7, sz[2] * 0.7) else {
                    return Ok(());
                };
                let m = self.any(&[Family::Print, Family::Wood, Family::Paint, Family::Metal], sz[0], 0.4)?;
                let yaw = self.rng.uniform(0.0, 90.0);
                self.cuboid("box", sz, [x, s.y, z], yaw, m);
            }
            _ => {
                // vase
                let Some((x, z)) = s.place(&mut self.rng, r, r) else {
                    return Ok(());
                };
                let h = r * self.rng.uniform(3.0, 7.0);
                let m = self.any(&[Family::Stone, Family::Print], 2.0 * std::f32::consts::PI * r, 0.6)?;
                self.cylinder("vase", r, h, [x, s.y, z], m);
            }
        }
        Ok(())
    }
}

/// sRGB-encoded colour to linear (materials take linear base colours).
fn srgb_to_linear3(c: [f32; 3]) -> [f32; 3] {
    c.map(pixl_core::image::srgb_to_linear)
}

/// Scene `index` of the photo style: camera, geometry, materials (no lights), and its layout.
pub fn build(
    seed: u64,
    stream: u64,
    index: usize,
    size: u32,
    out: &Path,
    made: &mut Provisional,
) -> Result<(Scene, Layout)> {
    let mut b = Builder {
        rng: Rng::for_stream(seed, &[stream, index as u64]),
        index,
        out,
        made,
        // Textures at twice the image's side (64–512 px): detail to spare, no waste at 32 px.
        tex_size: (2 * size as usize).clamp(64, 512),
        next: 0,
        objects: Vec::new(),
    };
    let tabletop = b.rng.bernoulli(0.5);
    let layout = if tabletop {
        tabletop_scene(&mut b)?
    } else {
        room_scene(&mut b)?
    };
    let (cam_pos, fov) = camera_for(&mut b.rng, &layout);
    let mut cam = Camera::new(size, size, fov);
    cam.position = cam_pos;
    cam.look_at = Some(layout.focus);
    let mut scene = Scene::new(cam);
    scene.base_dir = out.to_owned();
    scene.objects = b.objects;
    Ok((scene, layout))
}

fn room_scene(b: &mut Builder) -> Result<Layout> {
    let (w, d, h) = (
        b.rng.uniform(3.5, 6.0),
        b.rng.uniform(3.5, 6.0),
        b.rng.uniform(2.6, 3.4),
    );
    let ceiling = b.rng.bernoulli(0.5);
    b.room(w, d, h, ceiling)?;
    // Furniture stands in front of the camera (which is near the front wall).
    let mut floor = Support::new(0.0, -w / 2.0 + 0.1, w / 2.0 - 0.1, -d / 2.0 + 0.05, d / 2.0 - 1.6);
    let mut focus = [0.0, 0.6, -d / 4.0];
    if b.rng.bernoulli(0.5) {
        // rug first, flat on the floor (others may stand on it)
        let (rw, rd) = (b.rng.uniform(1.2, 2.6), b.rng.uniform(0.9, 2.0));
        let m = b.any(&[Family::Fabric, Family::Print], rw, 0.0)?;
        let x = b.rng.uniform(-w / 4.0, w / 4.0);
        let z = b.rng.uniform(-d / 4.0, 0.0);
        b.cuboid("rug", [rw, 0.012, rd], [x, 0.0, z], 0.0, m);
    }
    if b.rng.bernoulli(0.8) {
        // table with things on it
        let (tw, td, th) = (
            b.rng.uniform(0.7, 1.6),
            b.rng.uniform(0.5, 1.0),
            b.rng.uniform(0.45, 0.8),
        );
        if let Some((x, z)) = floor.place(&mut b.rng, tw / 2.0, td / 2.0) {
            let m = b.any(&[Family::Wood, Family::Wood, Family::Stone, Family::Paint], tw, 0.15)?;
            b.cuboid("table", [tw, 0.04, td], [x, th - 0.04, z], 0.0, m.clone());
            for (sx, sz) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                let leg = [x + sx * (tw / 2.0 - 0.05), 0.0, z + sz * (td / 2.0 - 0.05)];
                b.cylinder("leg", 0.025, th - 0.04, leg, m.clone());
            }
            let mut top = Support::new(
                th,
                x - tw / 2.0 + 0.03,
                x + tw / 2.0 - 0.03,
                z - td / 2.0 + 0.03,
                z + td / 2.0 - 0.03,
            );
            for _ in 0..1 + b.rng.below(4) {
                b.small_thing(&mut top, 1.0)?;
            }
            focus = [x, th, z];
        }
    }
    if b.rng.bernoulli(0.5) {
        // sofa against the back wall
        let (sw, sd) = (b.rng.uniform(1.4, 2.2), b.rng.uniform(0.8, 0.95));
        let z0 = -d / 2.0 + sd / 2.0 + 0.02;
        let mut back_row = Support::new(0.0, -w / 2.0 + 0.1, w / 2.0 - 0.1, z0 - 0.01, z0 + 0.01);
        if let Some((x, _)) = back_row.place(&mut b.rng, sw / 2.0, 0.005) {
            let fp = Footprint {
                x,
                z: z0,
                hx: sw / 2.0,
                hz: sd / 2.0,
            };
            if !floor.taken.iter().any(|t| t.overlaps(&fp, 0.05)) {
                floor.taken.push(fp);
                let m = b.textured(Family::Fabric, sw)?;
                b.cuboid("seat", [sw, 0.42, sd], [x, 0.0, z0], 0.0, m.clone());
                b.cuboid(
                    "backrest",
                    [sw, 0.45, 0.2],
                    [x, 0.42, z0 - sd / 2.0 + 0.1],
                    0.0,
                    m.clone(),
                );
                for sx in [-1.0, 1.0] {
                    b.cuboid(
                        "arm",
                        [0.18, 0.22, sd],
                        [x + sx * (sw / 2.0 - 0.09), 0.42, z0],
                        0.0,
                        m.clone(),
                    );
                }
            }
        }
    }
    if b.rng.bernoulli(0.6) {
        // cabinet or shelf, things on top
        let (cw, cd, ch) = (
            b.rng.uniform(0.5, 1.5),
            b.rng.uniform(0.35, 0.5),
            b.rng.uniform(0.5, 1.8),
        );
        let fp_z = -d / 2.0 + cd / 2.0 + 0.01;
        let x = b.rng.uniform(-w / 2.0 + cw / 2.0 + 0.05, w / 2.0 - cw / 2.0 - 0.05);
        let fp = Footprint {
            x,
            z: fp_z,
            hx: cw / 2.0,
            hz: cd / 2.0,
        };
        if !floor.taken.iter().any(|t| t.overlaps(&fp, 0.05)) {
            floor.taken.push(fp);
            let m = b.any(&[Family::Wood, Family::Paint, Family::Metal], cw, 0.3)?;
            b.cuboid("cabinet", [cw, ch, cd], [x, 0.0, fp_z], 0.0, m);
            let mut top = Support::new(
                ch,
                x - cw / 2.0 + 0.03,
                x + cw / 2.0 - 0.03,
                fp_z - cd / 2.0 + 0.03,
                fp_z + cd / 2.0 - 0.03,
            );
            for _ in 0..b.rng.below(3) {
                b.small_thing(&mut top, 1.0)?;
            }
        }
    }
    for _ in 0..b.rng.below(3) {
        // pictures on the back wall
        let (pw, ph) = (b.rng.uniform(0.3, 1.1), b.rng.uniform(0.3, 0.8));
        let m = b.textured(Family::Print, pw)?;
        let x = b.rng.uniform(-w / 2.0 + pw, w / 2.0 - pw);
        let y = b.rng.uniform(1.1, (h - ph / 2.0 - 0.2).max(1.2));
        b.push(
            "picture",
            Shape::Cuboid { size: [pw, ph, 0.03] },
            [x, y, -d / 2.0 + 0.016],
            [0.0; 3],
            m,
        );
    }
    if b.rng.bernoulli(0.4) {
        // floor lamp (the shade is a material, not a light)
        if let Some((x, z)) = floor.place(&mut b.rng, 0.2, 0.2) {
            let metal = b.textured(Family::Metal, 0.2)?;
            let shade = b.textured(Family::Fabric, 1.0)?;
            b.cylinder("lamp_base", 0.15, 0.03, [x, 0.0, z], metal.clone());
            b.cylinder("lamp_pole", 0.015, 1.4, [x, 0.03, z], metal);
            b.cylinder("lamp_shade", 0.2, 0.28, [x, 1.35, z], shade);
        }
    }
    if b.rng.bernoulli(0.4) {
        // plant: pot and foliage
        if let Some((x, z)) = floor.place(&mut b.rng, 0.22, 0.22) {
            let pot = b.plain(false);
            let ph = b.rng.uniform(0.25, 0.45);
            b.cylinder("pot", 0.17, ph, [x, 0.0, z], pot);
            let mut leaves = Material::diffuse(srgb_to_linear3(hsv(
                b.rng.uniform(0.22, 0.38),
                b.rng.uniform(0.4, 0.8),
                b.rng.uniform(0.2, 0.5),
            )));
            leaves.roughness = 0.6;
            let r = b.rng.uniform(0.25, 0.4);
            b.push(
                "foliage",
                Shape::Sphere { radius: r },
                [x, ph + r * 0.8, z],
                [0.0; 3],
                leaves,
            );
        }
    }
    for _ in 0..b.rng.below(3) {
        // balls on the floor
        let r = b.rng.uniform(0.08, 0.3);
        if let Some((x, z)) = floor.place(&mut b.rng, r, r) {
            let m = b.any(&[Family::Print, Family::Stone, Family::Metal], 2.0 * r, 0.5)?;
            b.push("ball", Shape::Sphere { radius: r }, [x, r, z], [0.0; 3], m);
        }
    }
    Ok(Layout {
        w,
        d,
        h,
        ceiling,
        focus,
        radius: 1.5,
        tabletop: false,
    })
}

fn tabletop_scene(b: &mut Builder) -> Result<Layout> {
    let (w, d, h) = (
        b.rng.uniform(3.0, 5.0),
        b.rng.uniform(3.0, 5.0),
        b.rng.uniform(2.6, 3.2),
    );
    let ceiling = b.rng.bernoulli(0.5);
    b.room(w, d, h, ceiling)?;
    // The table stands against the back wall, its top at th.
    let (tw, td, th) = (
        b.rng.uniform(1.2, 2.2),
        b.rng.uniform(0.8, 1.2),
        b.rng.uniform(0.7, 0.8),
    );
    let z = -d / 2.0 + td / 2.0 + b.rng.uniform(0.0, 0.6);
    let m = b.any(
        &[
            Family::Wood,
            Family::Stone,
            Family::Fabric,
            Family::Paint,
            Family::Tiles,
            Family::Print,
        ],
        tw,
        0.1,
    )?;
    b.cuboid("table", [tw, 0.05, td], [0.0, th - 0.05, z], 0.0, m);
    let mut top = Support::new(
        th,
        -tw / 2.0 + 0.05,
        tw / 2.0 - 0.05,
        z - td / 2.0 + 0.05,
        z + td / 2.0 - 0.15,
    );
    for _ in 0..3 + b.rng.below(6) {
        b.small_thing(&mut top, 1.0)?;
    }
    // The camera looks at the middle of what is on the table.
    let (mut cx, mut cz, n) = (0.0, 0.0, top.taken.len().max(1) as f32);
    for t in &top.taken {
        cx += t.x / n;
        cz += t.z / n;
    }
    if top.taken.is_empty() {
        cz = z;
    }
    Ok(Layout {
        w,
        d,
        h,
        ceiling,
        focus: [cx, th + 0.05, cz],
        radius: 0.5,
        tabletop: true,
    })
}

/// A camera position (inside the room, in front of the subject) and vertical field of view.
fn camera_for(rng: &mut Rng, l: &Layout) -> ([f32; 3], f32) {
    if l.tabletop {
        let dist = rng.uniform(0.6, 1.3);
        let az = rng.uniform(-0.6, 0.6);
        let el = rng.uniform(0.25, 0.7);
        let p = [
            l.focus[0] + dist * el.cos() * az.sin(),
            l.focus[1] + dist * el.sin(),
            l.focus[2] + dist * el.cos() * az.cos(),
        ];
        (clamp_inside(l, p), rng.uniform(35.0, 55.0))
    } else {
        let p = [
            rng.uniform(-l.w / 4.0, l.w / 4.0),
            rng.uniform(1.1, 1.7),
            l.d / 2.0 - rng.uniform(0.2, 0.5),
        ];
        (clamp_inside(l, p), rng.uniform(50.0, 70.0))
    }
}

fn clamp_inside(l: &Layout, p: [f32; 3]) -> [f32; 3] {
    let m = 0.1;
    [
        p[0].clamp(-l.w / 2.0 + m, l.w / 2.0 - m),
        p[1].clamp(0.1, l.h - m),
        p[2].clamp(-l.d / 2.0 + m, l.d / 2.0 - m),
    ]
}

/// A light colour: mostly a blackbody of household temperatures, sometimes a coloured gel.
fn light_color(rng: &mut Rng) -> Color {
    if rng.bernoulli(0.15) {
        Color::Rgb(srgb_to_linear3(hsv(rng.f32(), rng.uniform(0.4, 0.9), 1.0)))
    } else {
        Color::Blackbody {
            kelvin: rng.uniform(2400.0, 7000.0),
        }
    }
}

/// Lighting `k` of a photo-style scene: a key light and up to two fills (point, spot, area or —
/// without a ceiling — sun), placed around the subject, with powers set so that each delivers a
/// drawn irradiance at the subject (the key 5–40 W/m², fills 5–50 % of it), and a dim world.
pub fn draw_lighting(seed: u64, stream: u64, index: usize, k: usize, l: &Layout) -> (Vec<Light>, World, String) {
    let mut rng = Rng::for_stream(seed, &[stream, index as u64, k as u64]);
    let key_e = rng.uniform(5.0, 40.0);
    let n = 1 + rng.below(3);
    let mut lights = Vec::new();
    let mut kinds = Vec::new();
    for i in 0..n {
        let e = if i == 0 { key_e } else { key_e * rng.uniform(0.05, 0.5) };
        let kinds_ok = if l.ceiling { 3 } else { 4 };
        let kind = rng.below(kinds_ok);
        // Direction from the subject to the light.
        let az = rng.uniform(-std::f32::consts::PI, std::f32::consts::PI);
        let el = rng.uniform(0.2, 1.35);
        let dir = [el.cos() * az.sin(), el.sin(), el.cos() * az.cos()];
        let dist = if l.tabletop {
            rng.uniform(0.4, 1.6)
        } else {
            rng.uniform(1.0, 2.8)
        };
        let pos = clamp_inside(
            l,
            [
                l.focus[0] + dist * dir[0],
                l.focus[1] + dist * dir[1],
                l.focus[2] + dist * dir[2],
            ],
        );
        let to = |p: [f32; 3]| {
            ((p[0] - l.focus[0]).powi(2) + (p[1] - l.focus[1]).powi(2) + (p[2] - l.focus[2]).powi(2)).sqrt()
        };
        let d2 = to(pos).max(0.2).powi(2);
        let aim = [
            l.focus[0] + rng.uniform(-0.3, 0.3) * l.radius,
            l.focus[1],
            l.focus[2] + rng.uniform(-0.3, 0.3) * l.radius,
        ];
        let color = light_color(&mut rng);
        let (light, name) = match kind {
            0 => (
                Light::Point {
                    name: "point".into(),
                    position: pos,
                    // E = P / (4π d²)
                    power: e * 4.0 * std::f32::consts::PI * d2,
                    radius: rng.uniform(0.02, 0.15),
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
                    look_at: Some(aim),
                    power: e * 4.0 * std::f32::consts::PI * d2,
                    spot_size_deg: rng.uniform(25.0, 100.0),
                    blend: rng.uniform(0.05, 0.6),
                    radius: rng.uniform(0.01, 0.1),
                    color,
                    visible_to_camera: false,
                },
                "spot",
            ),
            2 => {
                let shape = [AreaShape::Square, AreaShape::Rectangle, AreaShape::Disk][rng.below(3)];
                let size = rng.uniform(0.2, 1.5);
                (
                    Light::Area {
                        name: "area".into(),
                        position: pos,
                        direction: None,
                        look_at: Some(aim),
                        shape,
                        size,
                        size_y: (shape == AreaShape::Rectangle).then(|| rng.uniform(0.2, 1.5)),
                        // on axis E ≈ P / (π d²) for a small emitter
                        power: e * std::f32::consts::PI * d2,
                        color,
                        visible_to_camera: false,
                    },
                    "area",
                )
            }
            _ => (
                Light::Sun {
                    name: "sun".into(),
                    direction: Some(dir.map(|c| -c)),
                    strength: e,
                    angle_deg: rng.uniform(0.5, 8.0),
                    color,
                },
                "sun",
            ),
        };
        lights.push(light);
        kinds.push(name);
    }
    let sky = srgb_to_linear3(hsv(rng.uniform(0.5, 0.65), rng.uniform(0.0, 0.4), 1.0));
    let world = World {
        color: Color::Rgb(sky),
        strength: key_e * rng.uniform(0.0, 0.03),
        ..Default::default()
    };
    (lights, world, kinds.join("+"))
}
