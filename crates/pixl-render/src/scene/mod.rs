//! The scene description: camera, objects (meshes and primitives) with Principled-BSDF-like
//! materials, lights in Blender's units, and the world (environment). Serialised as TOML or JSON
//! (chosen by the file extension, `.toml` or `.json`); paths inside a scene file are relative to
//! the file's directory.
//!
//! This folder holds the scene and what it is made of; it uses nothing of the crate but its error
//! type (the tracer, the reconstruction and the exporters all read it):
//! - this module: [`Scene`] and its parts, their serde format, loading, saving and validation;
//! - [`color`]: blackbody temperature → linear RGB, and luminance;
//! - [`mesh`]: triangle meshes (positions, normals, UVs), as mesh files and depth maps give them.
//!
//! # Coordinate conventions
//! - World space is right-handed, in metres, **+Y up** (OpenGL / glTF convention). The Blender
//!   bridge maps it to Blender's Z-up world by `(x, y, z) ↦ (x, −z, y)` (a +90° rotation about X,
//!   what Blender's glTF importer does).
//! - The camera looks down its local **−Z**, with local **+Y up** and **+X right** (Blender /
//!   OpenGL camera convention). Image row 0 is the *top* row.
//! - Lights that have a direction (spot, area, sun) emit along their local −Z, like Blender's;
//!   in this file that axis is given as `direction` (the way the light travels) or `look_at`.
//! - Equirectangular environment images: +Y is the zenith (image top row) and the image centre
//!   faces +X. For a world direction `d = (x, y, z)`: `u = 0.5 − atan2(−z, x) / 2π`,
//!   `v = 0.5 + atan2(y, hypot(x, z)) / π`, pixel column `u·W`, row `(1 − v)·H`. This is
//!   Blender's equirectangular mapping (`u = 0.5 − atan2(y_b, x_b)/2π`, `v = 0.5 +
//!   elevation/π`) composed with the Y-up → Z-up map above, so a world image looks the same in
//!   both renderers.
//!
//! # Units (as in Blender / Cycles)
//! - Point light: `power` in W; radiant intensity `I = power / 4π` W/sr (times `color`).
//!   `radius` (Blender's `shadow_soft_size`) makes it a sphere, as in Cycles: soft shadows, and
//!   a disk of radiance `I / (π r²)` in reflections and refractions.
//! - Spot light: as a point light of the same power (`I = power / 4π`), masked by the cone of
//!   full angle `spot_size_deg` with `blend` softening its edge; Cycles does *not* renormalise
//!   the power into the cone, and neither do we.
//! - Area light: `power` in W over area `A`, one-sided Lambertian emitter of radiance
//!   `L = power / (π A)`; shapes `rectangle` (`size` × `size_y`), `square`, `disk` (diameter
//!   `size`), `ellipse`. Camera rays look through it unless `visible_to_camera = true`
//!   (Blender's Ray Visibility ▸ Camera, off by default in Blender 4/5); the same key makes the
//!   sphere of a point or spot light with a `radius` visible to the camera (radiance
//!   `I / (π r²)`, times the spot's cone mask), as in Cycles. Sun lights are never seen by the
//!   camera. Rays that scattered always see area and sphere lights.
//! - Sun: `strength` is the irradiance in W/m² on a surface facing the sun; `angle_deg` its
//!   angular diameter (a cone of radiance `strength / Ω` that mirrors and glass reflect; below
//!   ~0.16°, e.g. 0, a delta light they do not).
//! - Emission (materials): radiance `emission_strength × emission_color` (W/m²/sr).
//! - World: radiance `strength × color` (or × the image's texel).
//! - Camera depth of field (`dof = { focus_distance = 2.0, aperture_fstop = 2.8 }`, Blender's
//!   names; off when absent): a thin lens whose focal length is that of Blender's camera with a
//!   24 mm sensor height, aperture radius `lens / (2 · f-stop)` as in Cycles (see [`Dof`]).
//!
//! Colours are linear Rec.709 RGB triples (`[1.0, 0.9, 0.8]`) or a blackbody temperature
//! (`{ kelvin = 3200 }`, see [`crate::scene::color::blackbody`]).
//!
//! # Example (TOML)
//! ```toml
//! [camera]
//! width = 640
//! height = 480
//! fov_y_deg = 50.0
//! position = [0.0, 1.0, 4.0]
//! look_at = [0.0, 0.5, 0.0]
//!
//! [[objects]]
//! name = "floor"
//! shape = { type = "quad", size = [10.0, 10.0] }
//! transform = { rotate_deg = [-90.0, 0.0, 0.0] }
//! material = { base_color = [0.8, 0.8, 0.8], roughness = 0.9 }
//!
//! [[objects]]
//! name = "photo"
//! shape = { type = "mesh", path = "mesh.glb" }
//! material = { base_color_texture = "albedo.png" }
//!
//! [[lights]]
//! type = "point"
//! position = [1.0, 3.0, 1.0]
//! power = 100.0
//! color = { kelvin = 3200 }
//!
//! [world]
//! color = [0.05, 0.05, 0.08]
//! strength = 1.0
//! ```
use crate::error::{RenderError, Result};
use color::blackbody;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub mod color;
pub mod mesh;

/// Current scene-format version (written by [`Scene::save`]).
pub const SCENE_VERSION: u32 = 1;

/// A whole scene. Relative paths inside are resolved against [`Scene::base_dir`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    #[serde(default = "default_version")]
    pub version: u32,
    pub camera: Camera,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub world: Option<World>,
    #[serde(default)]
    pub objects: Vec<Object>,
    #[serde(default)]
    pub lights: Vec<Light>,
    /// The directory relative paths are resolved against (the scene file's directory; `.` for
    /// scenes parsed from strings). Not serialised.
    #[serde(skip)]
    pub base_dir: PathBuf,
    /// Meshes and images held in memory, looked up by the paths the objects name before any
    /// file is read: a scene built in memory renders without touching the disk. Not serialised.
    #[serde(skip)]
    pub assets: Assets,
}

/// Meshes and images a [`Scene`] holds in memory, keyed by the path (as written in the scene)
/// that names them. An image's key decides its encoding as a file's name would: `.exr` is
/// linear, anything else sRGB-encoded (colour textures) or as stored (scalar textures).
#[derive(Clone, Default)]
pub struct Assets {
    pub meshes: std::collections::HashMap<PathBuf, std::sync::Arc<mesh::Mesh>>,
    pub images: std::collections::HashMap<PathBuf, std::sync::Arc<pixl_core::Image>>,
}

impl Assets {
    pub fn is_empty(&self) -> bool {
        self.meshes.is_empty() && self.images.is_empty()
    }
}

impl std::fmt::Debug for Assets {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let keys = |m: Vec<&PathBuf>| {
            let mut v: Vec<String> = m.into_iter().map(|p| p.display().to_string()).collect();
            v.sort();
            v
        };
        f.debug_struct("Assets")
            .field("meshes", &keys(self.meshes.keys().collect()))
            .field("images", &keys(self.images.keys().collect()))
            .finish()
    }
}

/// Equal when they hold the same keys with equal contents.
impl PartialEq for Assets {
    fn eq(&self, other: &Self) -> bool {
        fn same<T: PartialEq>(
            a: &std::collections::HashMap<PathBuf, std::sync::Arc<T>>,
            b: &std::collections::HashMap<PathBuf, std::sync::Arc<T>>,
        ) -> bool {
            a.len() == b.len()
                && a.iter()
                    .all(|(k, v)| b.get(k).is_some_and(|w| std::sync::Arc::ptr_eq(v, w) || **v == **w))
        }
        same(&self.meshes, &other.meshes) && same(&self.images, &other.images)
    }
}

fn default_version() -> u32 {
    SCENE_VERSION
}

/// A pinhole camera, or a thin lens with `dof`. Give exactly one of `fov_y_deg` and `focal_px`,
/// and either `position` + `look_at` (+ `up`) or `matrix`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Vertical field of view in degrees (full angle).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fov_y_deg: Option<f32>,
    /// Focal length in pixels (`fy = fx`); an alternative to `fov_y_deg`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub focal_px: Option<f32>,
    /// Principal point `(cx, cy)` in pixels from the top-left corner; default the image centre.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub principal_px: Option<[f32; 2]>,
    /// Camera position (world). Default the origin.
    #[serde(default)]
    pub position: [f32; 3],
    /// Point the camera looks at. Default `position + (0, 0, −1)`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub look_at: Option<[f32; 3]>,
    /// World up hint. Default `(0, 1, 0)`.
    #[serde(default = "default_up")]
    pub up: [f32; 3],
    /// Camera-to-world 4×4 matrix, row-major (`[[r00, r01, r02, tx], ...]`); columns 0..3 are the
    /// camera's +X, +Y, +Z axes. Overrides `position` / `look_at` / `up` when given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub matrix: Option<[[f32; 4]; 4]>,
    /// Thin-lens depth of field (Blender's camera ▸ Depth of Field). Absent (the default): a
    /// pinhole, everything sharp.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dof: Option<Dof>,
}

/// Thin-lens depth of field, named as Blender's camera DOF settings (the table's presence is
/// Blender's `use_dof`). The lens is the one the Blender bridge gives the camera — a 24 mm high
/// sensor, so focal length `lens = 12 mm / tan(fov_y / 2)` — and, as in Cycles, the aperture is
/// a disk of radius `lens / (2 · aperture_fstop)` (lens in metres) centred on the camera
/// position, in the plane of the image. Points at `focus_distance` along the viewing axis are
/// sharp; a point at depth `z` spreads over a disk of radius `f · A · |1/focus_distance − 1/z|`
/// pixels (`f` the focal length in pixels, `A` the aperture radius).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Dof {
    /// Distance from the camera to the plane in focus, along the viewing axis (metres).
    pub focus_distance: f32,
    /// F-number: the aperture's diameter is the focal length over it.
    pub aperture_fstop: f32,
}

fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}

impl Camera {
    /// A camera at the origin looking down −Z with the given image size and vertical FOV.
    pub fn new(width: u32, height: u32, fov_y_deg: f32) -> Self {
        Camera {
            width,
            height,
            fov_y_deg: Some(fov_y_deg),
            focal_px: None,
            principal_px: None,
            position: [0.0; 3],
            look_at: None,
            up: default_up(),
            matrix: None,
            dof: None,
        }
    }

    /// The focal length in millimetres of the camera Blender gets (24 mm sensor height).
    pub fn lens_mm(&self) -> f32 {
        12.0 / (0.5 * self.fov_y().to_radians()).tan()
    }

    /// Radius of the thin lens's aperture in metres (0 without depth of field): Cycles'
    /// `lens · 1e-3 / (2 · aperture_fstop)`.
    pub fn aperture_radius(&self) -> f32 {
        match &self.dof {
            Some(d) => self.lens_mm() * 1e-3 / (2.0 * d.aperture_fstop),
            None => 0.0,
        }
    }

    /// Focal length in pixels for an image of height `height` (the FOV is kept when the image
    /// is resized; a focal length in pixels is scaled with the height).
    pub fn focal_for_height(&self, height: u32) -> f32 {
        match (self.fov_y_deg, self.focal_px) {
            (Some(fov), _) => 0.5 * height as f32 / (0.5 * fov.to_radians()).tan(),
            (None, Some(f)) => f * height as f32 / self.height.max(1) as f32,
            (None, None) => 0.5 * height as f32 / (0.5 * 50f32.to_radians()).tan(),
        }
    }

    /// Vertical FOV in degrees.
    pub fn fov_y(&self) -> f32 {
        let f = self.focal_for_height(self.height);
        2.0 * (0.5 * self.height as f32 / f).atan().to_degrees()
    }

    /// Camera-to-world frame: `(origin, right (+X), up (+Y), back (+Z))`, orthonormal.
    pub fn frame(&self) -> ([f32; 3], [f32; 3], [f32; 3], [f32; 3]) {
        if let Some(m) = self.matrix {
            let col = |j: usize| normalize([m[0][j], m[1][j], m[2][j]]);
            return ([m[0][3], m[1][3], m[2][3]], col(0), col(1), col(2));
        }
        let target = self.look_at.unwrap_or(add(self.position, [0.0, 0.0, -1.0]));
        let back = normalize(sub(self.position, target));
        let mut right = cross(self.up, back);
        if length(right) < 1e-6 {
            // Looking along `up`: pick any perpendicular.
            right = cross(
                if back[0].abs() < 0.9 {
                    [1.0, 0.0, 0.0]
                } else {
                    [0.0, 0.0, 1.0]
                },
                back,
            );
        }
        let right = normalize(right);
        let up = cross(back, right);
        (self.position, right, up, back)
    }
}

/// A rigid-plus-scale transform: scale, then rotate (Euler XYZ in degrees, Blender's default
/// mode: `R = Rz · Ry · Rx`), then translate. Or an explicit 4×4 row-major object-to-world
/// matrix, which overrides the rest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Transform {
    #[serde(default)]
    pub translate: [f32; 3],
    #[serde(default)]
    pub rotate_deg: [f32; 3],
    #[serde(default = "ones")]
    pub scale: [f32; 3],
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub matrix: Option<[[f32; 4]; 4]>,
}

fn ones() -> [f32; 3] {
    [1.0; 3]
}

impl Default for Transform {
    fn default() -> Self {
        Transform {
            translate: [0.0; 3],
            rotate_deg: [0.0; 3],
            scale: ones(),
            matrix: None,
        }
    }
}

impl Transform {
    /// The object-to-world matrix (row-major 4×4).
    pub fn to_matrix(&self) -> [[f32; 4]; 4] {
        if let Some(m) = self.matrix {
            return m;
        }
        let [rx, ry, rz] = self.rotate_deg.map(f32::to_radians);
        let (sx, cx) = rx.sin_cos();
        let (sy, cy) = ry.sin_cos();
        let (sz, cz) = rz.sin_cos();
        // Rz · Ry · Rx
        let r = [
            [cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
            [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
            [-sy, cy * sx, cy * cx],
        ];
        let s = self.scale;
        let t = self.translate;
        let mut m = [[0.0; 4]; 4];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = r[i][j] * s[j];
            }
            m[i][3] = t[i];
        }
        m[3][3] = 1.0;
        m
    }
}

/// One object: a shape, where it is, and what it is made of.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Object {
    #[serde(default)]
    pub name: String,
    pub shape: Shape,
    #[serde(default)]
    pub transform: Transform,
    #[serde(default)]
    pub material: Material,
}

/// Geometry. Primitives are centred on the object origin (before the transform).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Shape {
    /// A triangle mesh file (`.obj`, `.ply`, `.glb`), relative to the scene file.
    Mesh { path: PathBuf },
    /// A sphere (tessellated finely, smooth-shaded).
    Sphere { radius: f32 },
    /// An axis-aligned box with edge lengths `size` (closed, normals outwards).
    Cuboid { size: [f32; 3] },
    /// A rectangle in the local XY plane, facing +Z (Blender's plane primitive), `size = [sx, sy]`.
    Quad { size: [f32; 2] },
    /// A closed cylinder along the local Y axis (up), from `−height/2` to `+height/2`: smooth
    /// side, flat caps (Blender's cylinder primitive turned Y-up).
    Cylinder { radius: f32, height: f32 },
}

/// Principled-BSDF-like material (maps 1:1 to Blender's Principled BSDF inputs of the same
/// names). Textures are sampled at the mesh UVs (`v = 0` at the image's top row); PNG/JPEG
/// textures are sRGB-decoded for colour and read as-is (first channel) for roughness/metallic;
/// EXR textures are linear.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    #[serde(default = "default_base")]
    pub base_color: Color,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub base_color_texture: Option<PathBuf>,
    #[serde(default = "default_roughness")]
    pub roughness: f32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roughness_texture: Option<PathBuf>,
    #[serde(default)]
    pub metallic: f32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metallic_texture: Option<PathBuf>,
    /// A tangent-space normal map, as Blender's Normal Map node (strength 1) feeding the
    /// Principled BSDF's Normal: texel `c` (read as stored, "Non-Color") is the normal
    /// `2c − 1` in the frame (tangent `T`, bitangent `B`, shading normal `N`), `T` along
    /// increasing `u`, `B` towards the texture's top row (Blender's increasing `v`), both made
    /// perpendicular to `N` (per triangle, from its UVs). Needs UVs. (Cycles also bends
    /// strongly tilted normals back towards the surface's, which we do not: `BENCHMARKS.md`.)
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normal_texture: Option<PathBuf>,
    /// Blender's "Transmission Weight".
    #[serde(default)]
    pub transmission: f32,
    #[serde(default = "default_ior")]
    pub ior: f32,
    /// Blender's "Specular IOR Level" in [0, 1]: 0.5 keeps the dielectric F0 given by `ior`
    /// (`F0 = ((ior − 1)/(ior + 1))² · 2 · level`), 0 removes the specular layer (pure Lambertian).
    #[serde(default = "default_specular_level")]
    pub specular_ior_level: f32,
    #[serde(default = "white")]
    pub emission_color: Color,
    #[serde(default)]
    pub emission_strength: f32,
}

fn default_base() -> Color {
    Color::Rgb([0.8, 0.8, 0.8])
}
fn default_roughness() -> f32 {
    0.5
}
fn default_ior() -> f32 {
    1.5
}
fn default_specular_level() -> f32 {
    0.5
}
fn white() -> Color {
    Color::Rgb([1.0, 1.0, 1.0])
}

impl Default for Material {
    fn default() -> Self {
        Material {
            base_color: default_base(),
            base_color_texture: None,
            roughness: default_roughness(),
            roughness_texture: None,
            metallic: 0.0,
            metallic_texture: None,
            normal_texture: None,
            transmission: 0.0,
            ior: default_ior(),
            specular_ior_level: default_specular_level(),
            emission_color: white(),
            emission_strength: 0.0,
        }
    }
}

impl Material {
    /// A pure Lambertian material of the given albedo (no specular layer).
    pub fn diffuse(rgb: [f32; 3]) -> Self {
        Material {
            base_color: Color::Rgb(rgb),
            roughness: 1.0,
            specular_ior_level: 0.0,
            ..Default::default()
        }
    }

    /// A black, purely emissive material of radiance `strength × rgb`.
    pub fn emissive(rgb: [f32; 3], strength: f32) -> Self {
        Material {
            base_color: Color::Rgb([0.0; 3]),
            specular_ior_level: 0.0,
            emission_color: Color::Rgb(rgb),
            emission_strength: strength,
            ..Default::default()
        }
    }
}

/// A linear RGB colour, or a blackbody temperature.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(
    untagged,
    expecting = "a colour: an RGB triple [r, g, b] or a temperature { kelvin = K }"
)]
pub enum Color {
    Rgb([f32; 3]),
    Blackbody { kelvin: f32 },
}

impl Default for Color {
    fn default() -> Self {
        white()
    }
}

impl Color {
    /// Linear RGB (a blackbody is normalised to luminance 1).
    pub fn rgb(&self) -> [f32; 3] {
        match *self {
            Color::Rgb(c) => c,
            Color::Blackbody { kelvin } => blackbody(kelvin),
        }
    }

    fn check(&self, what: &str) -> std::result::Result<(), String> {
        match *self {
            Color::Rgb(c) if c.iter().any(|v| !v.is_finite() || *v < 0.0) => {
                Err(format!("{what} {c:?} must be finite and non-negative"))
            }
            Color::Blackbody { kelvin } if !(kelvin.is_finite() && (800.0..=40000.0).contains(&kelvin)) => {
                Err(format!("{what} temperature {kelvin} K is outside [800, 40000] K"))
            }
            _ => Ok(()),
        }
    }
}

/// Shape of an area light (Blender's `shape`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum AreaShape {
    #[default]
    Square,
    Rectangle,
    Disk,
    Ellipse,
}

/// A light, in Blender's units (see the module docs). Directional lights take `direction`
/// (the way light travels) or `look_at` (a target point); default straight down (−Y).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Light {
    Point {
        #[serde(default)]
        name: String,
        position: [f32; 3],
        /// Watts.
        power: f32,
        #[serde(default)]
        radius: f32,
        #[serde(default)]
        color: Color,
        /// Whether camera rays see the light's sphere (Blender's Ray Visibility ▸ Camera; off by
        /// default). Only a light with a `radius` has a sphere to see.
        #[serde(default, skip_serializing_if = "is_false")]
        visible_to_camera: bool,
    },
    Spot {
        #[serde(default)]
        name: String,
        position: [f32; 3],
        #[serde(default, skip_serializing_if = "Option::is_none")]
        direction: Option<[f32; 3]>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        look_at: Option<[f32; 3]>,
        /// Watts (intensity `power / 4π` W/sr inside the cone).
        power: f32,
        /// Full cone angle in degrees (Blender's `spot_size`), in (0, 180].
        #[serde(default = "default_spot_size")]
        spot_size_deg: f32,
        /// Edge softness in [0, 1] (Blender's `spot_blend`).
        #[serde(default = "default_blend")]
        blend: f32,
        #[serde(default)]
        radius: f32,
        #[serde(default)]
        color: Color,
        /// As for point lights: camera rays see the sphere (masked by the cone) when asked.
        #[serde(default, skip_serializing_if = "is_false")]
        visible_to_camera: bool,
    },
    Area {
        #[serde(default)]
        name: String,
        /// Centre of the emitter.
        position: [f32; 3],
        #[serde(default, skip_serializing_if = "Option::is_none")]
        direction: Option<[f32; 3]>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        look_at: Option<[f32; 3]>,
        #[serde(default)]
        shape: AreaShape,
        /// Edge length (square/rectangle: local X) or diameter (disk/ellipse: local X), metres.
        #[serde(default = "default_area_size")]
        size: f32,
        /// Local-Y size for `rectangle` / `ellipse` (default `size`).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        size_y: Option<f32>,
        /// Watts.
        power: f32,
        #[serde(default)]
        color: Color,
        /// Whether camera rays see the emitter itself (Blender's Object ▸ Visibility ▸ Ray
        /// Visibility ▸ Camera). Off by default, as for a light added in Blender 4/5: it still
        /// lights the scene and shows in reflections, but the camera looks through it.
        #[serde(default, skip_serializing_if = "is_false")]
        visible_to_camera: bool,
    },
    Sun {
        #[serde(default)]
        name: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        direction: Option<[f32; 3]>,
        /// Irradiance in W/m² on a surface facing the sun.
        strength: f32,
        /// Angular diameter in degrees (Blender's `angle`).
        #[serde(default = "default_sun_angle")]
        angle_deg: f32,
        #[serde(default)]
        color: Color,
    },
}

fn is_false(b: &bool) -> bool {
    !*b
}
fn default_spot_size() -> f32 {
    45.0
}
fn default_blend() -> f32 {
    0.15
}
fn default_area_size() -> f32 {
    1.0
}
fn default_sun_angle() -> f32 {
    0.526
}

impl Light {
    pub fn name(&self) -> &str {
        match self {
            Light::Point { name, .. }
            | Light::Spot { name, .. }
            | Light::Area { name, .. }
            | Light::Sun { name, .. } => name,
        }
    }

    pub fn color(&self) -> Color {
        match self {
            Light::Point { color, .. }
            | Light::Spot { color, .. }
            | Light::Area { color, .. }
            | Light::Sun { color, .. } => *color,
        }
    }

    /// The unit direction light travels (spot, area, sun); `None` for point lights.
    pub fn direction(&self) -> Option<[f32; 3]> {
        let down = [0.0, -1.0, 0.0];
        match self {
            Light::Point { .. } => None,
            Light::Spot {
                position,
                direction,
                look_at,
                ..
            }
            | Light::Area {
                position,
                direction,
                look_at,
                ..
            } => Some(match (direction, look_at) {
                (Some(d), _) => normalize(*d),
                (None, Some(t)) => normalize(sub(*t, *position)),
                (None, None) => down,
            }),
            Light::Sun { direction, .. } => Some(direction.map(normalize).unwrap_or(down)),
        }
    }

    /// Area-light extents `(size_x, size_y)` in metres.
    pub fn area_size(&self) -> Option<(f32, f32)> {
        match self {
            Light::Area {
                shape, size, size_y, ..
            } => Some(match shape {
                AreaShape::Square | AreaShape::Disk => (*size, *size),
                AreaShape::Rectangle | AreaShape::Ellipse => (*size, size_y.unwrap_or(*size)),
            }),
            _ => None,
        }
    }

    fn check(&self) -> std::result::Result<(), String> {
        let finite3 = |v: &[f32; 3], what: &str| {
            if v.iter().all(|x| x.is_finite()) {
                Ok(())
            } else {
                Err(format!("{what} {v:?} is not finite"))
            }
        };
        let nonneg = |v: f32, what: &str| {
            if v.is_finite() && v >= 0.0 {
                Ok(())
            } else {
                Err(format!("{what} {v} must be finite and non-negative"))
            }
        };
        let dir = |d: &Option<[f32; 3]>, t: &Option<[f32; 3]>, p: &[f32; 3]| {
            if d.is_some() && t.is_some() {
                return Err("give either direction or look_at, not both".to_string());
            }
            if let Some(d) = d {
                finite3(d, "direction")?;
                if length(*d) < 1e-9 {
                    return Err("direction is the zero vector".into());
                }
            }
            if let Some(t) = t {
                finite3(t, "look_at")?;
                if length(sub(*t, *p)) < 1e-9 {
                    return Err("look_at equals the light's position".into());
                }
            }
            Ok(())
        };
        let seen_sphere = |visible: bool, radius: f32| {
            if visible && !(radius > 0.0) {
                Err("visible_to_camera needs a radius > 0 (a light without one has no sphere to see)".to_string())
            } else {
                Ok(())
            }
        };
        self.color().check("color")?;
        match self {
            Light::Point {
                position,
                power,
                radius,
                visible_to_camera,
                ..
            } => {
                finite3(position, "position")?;
                nonneg(*power, "power")?;
                nonneg(*radius, "radius")?;
                seen_sphere(*visible_to_camera, *radius)
            }
            Light::Spot {
                position,
                direction,
                look_at,
                power,
                spot_size_deg,
                blend,
                radius,
                visible_to_camera,
                ..
            } => {
                finite3(position, "position")?;
                dir(direction, look_at, position)?;
                nonneg(*power, "power")?;
                nonneg(*radius, "radius")?;
                seen_sphere(*visible_to_camera, *radius)?;
                if !(spot_size_deg.is_finite() && *spot_size_deg > 0.0 && *spot_size_deg <= 180.0) {
                    return Err(format!("spot_size_deg {spot_size_deg} must be in (0, 180]"));
                }
                if !(0.0..=1.0).contains(blend) {
                    return Err(format!("blend {blend} must be in [0, 1]"));
                }
                Ok(())
            }
            Light::Area {
                position,
                direction,
                look_at,
                size,
                size_y,
                power,
                ..
            } => {
                finite3(position, "position")?;
                dir(direction, look_at, position)?;
                nonneg(*power, "power")?;
                if !(size.is_finite() && *size > 0.0) {
                    return Err(format!("size {size} must be positive"));
                }
                if let Some(sy) = size_y {
                    if !(sy.is_finite() && *sy > 0.0) {
                        return Err(format!("size_y {sy} must be positive"));
                    }
                }
                Ok(())
            }
            Light::Sun {
                direction,
                strength,
                angle_deg,
                ..
            } => {
                dir(direction, &None, &[0.0; 3])?;
                nonneg(*strength, "strength")?;
                if !(angle_deg.is_finite() && (0.0..=180.0).contains(angle_deg)) {
                    return Err(format!("angle_deg {angle_deg} must be in [0, 180]"));
                }
                Ok(())
            }
        }
    }
}

/// The world (background / environment light): radiance `strength × color`, or
/// `strength × image texel` when `image` (an equirectangular linear HDR, `.exr`) is given.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct World {
    #[serde(default = "default_world_color")]
    pub color: Color,
    #[serde(default = "one")]
    pub strength: f32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image: Option<PathBuf>,
    /// Rotation of the image about the world up axis (+Y), degrees.
    #[serde(default)]
    pub rotation_deg: f32,
}

fn default_world_color() -> Color {
    Color::Rgb([0.05, 0.05, 0.05])
}
fn one() -> f32 {
    1.0
}

impl Default for World {
    fn default() -> Self {
        World {
            color: default_world_color(),
            strength: 1.0,
            image: None,
            rotation_deg: 0.0,
        }
    }
}

/// Serialisation format of a scene file, from its extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SceneFormat {
    Toml,
    Json,
}

impl SceneFormat {
    pub fn from_path(path: &Path) -> Result<Self> {
        match pixl_core::io::extension(path).as_str() {
            "toml" => Ok(SceneFormat::Toml),
            "json" => Ok(SceneFormat::Json),
            other => Err(RenderError::Invalid {
                path: path.to_owned(),
                message: format!("unknown scene file extension {other:?} (expected .toml or .json)"),
            }),
        }
    }
}

impl Scene {
    /// An empty scene around a camera.
    pub fn new(camera: Camera) -> Self {
        Scene {
            version: SCENE_VERSION,
            camera,
            world: None,
            objects: Vec::new(),
            lights: Vec::new(),
            base_dir: PathBuf::from("."),
            assets: Assets::default(),
        }
    }

    /// Reads a `.toml` or `.json` scene, validates it (values and that referenced files exist)
    /// and sets `base_dir` to the file's directory.
    pub fn load(path: &Path) -> Result<Self> {
        let format = SceneFormat::from_path(path)?;
        let text = std::fs::read_to_string(path).map_err(|e| pixl_core::CoreError::io(path, e))?;
        let mut scene = Self::parse(&text, format, path)?;
        scene.base_dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
            _ => PathBuf::from("."),
        };
        scene.validate_at(path)?;
        scene.validate_files_at(path)?;
        Ok(scene)
    }

    /// Parses and validates a TOML scene (values only; files are checked by
    /// [`Scene::validate_files`]); `base_dir` is `.`.
    pub fn from_toml_str(text: &str) -> Result<Self> {
        let path = Path::new("<toml>");
        let scene = Self::parse(text, SceneFormat::Toml, path)?;
        scene.validate_at(path)?;
        Ok(scene)
    }

    /// Parses and validates a JSON scene (values only); `base_dir` is `.`.
    pub fn from_json_str(text: &str) -> Result<Self> {
        let path = Path::new("<json>");
        let scene = Self::parse(text, SceneFormat::Json, path)?;
        scene.validate_at(path)?;
        Ok(scene)
    }

    fn parse(text: &str, format: SceneFormat, path: &Path) -> Result<Self> {
        let parsed: std::result::Result<Scene, String> = match format {
            SceneFormat::Toml => toml::from_str(text).map_err(|e| e.to_string()),
            SceneFormat::Json => serde_json::from_str(text).map_err(|e| e.to_string()),
        };
        let mut scene = parsed.map_err(|message| RenderError::Parse {
            path: path.to_owned(),
            message,
        })?;
        scene.base_dir = PathBuf::from(".");
        Ok(scene)
    }

    /// Serialises as TOML or JSON (by extension) and writes atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let text = self
            .to_string_as(SceneFormat::from_path(path)?)
            .map_err(|message| RenderError::Write {
                path: path.to_owned(),
                message,
            })?;
        pixl_core::io::atomic_write_bytes(path, text.as_bytes())?;
        Ok(())
    }

    /// The scene as TOML or JSON text.
    pub fn to_string_as(&self, format: SceneFormat) -> std::result::Result<String, String> {
        match format {
            SceneFormat::Toml => toml::to_string_pretty(self).map_err(|e| e.to_string()),
            SceneFormat::Json => serde_json::to_string_pretty(self).map_err(|e| e.to_string()),
        }
    }

    /// A path from the scene file, resolved against `base_dir` (absolute paths unchanged).
    pub fn resolve(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_owned()
        } else {
            self.base_dir.join(p)
        }
    }

    /// Checks every value (ranges, finiteness, camera completeness).
    pub fn validate(&self) -> Result<()> {
        self.validate_at(Path::new("<scene>"))
    }

    /// Checks that every referenced file (meshes, textures, world image) exists.
    pub fn validate_files(&self) -> Result<()> {
        self.validate_files_at(Path::new("<scene>"))
    }

    /// [`Scene::validate`], naming `path` (the scene's file) in its errors: use this one when
    /// the file is known, so a message never says `<scene>`.
    pub fn validate_at(&self, path: &Path) -> Result<()> {
        let bad = |message: String| RenderError::Invalid {
            path: path.to_owned(),
            message,
        };
        if self.version > SCENE_VERSION {
            return Err(bad(format!(
                "scene version {} is newer than supported ({SCENE_VERSION})",
                self.version
            )));
        }
        let c = &self.camera;
        if c.width == 0
            || c.height == 0
            || (c.width as usize).saturating_mul(c.height as usize) > pixl_core::io::MAX_PIXELS
        {
            return Err(bad(format!(
                "camera size {}x{} is empty or too large",
                c.width, c.height
            )));
        }
        match (c.fov_y_deg, c.focal_px) {
            (Some(_), Some(_)) => return Err(bad("camera: give fov_y_deg or focal_px, not both".into())),
            (None, None) => return Err(bad("camera: give fov_y_deg or focal_px".into())),
            (Some(f), None) if !(f.is_finite() && f > 0.0 && f < 180.0) => {
                return Err(bad(format!("camera: fov_y_deg {f} must be in (0, 180)")))
            }
            (None, Some(f)) if !(f.is_finite() && f > 0.0) => {
                return Err(bad(format!("camera: focal_px {f} must be positive")))
            }
            _ => {}
        }
        if let Some(d) = &c.dof {
            if !(d.focus_distance.is_finite() && d.focus_distance > 0.0) {
                return Err(bad(format!(
                    "camera: dof focus_distance {} must be positive",
                    d.focus_distance
                )));
            }
            if !(d.aperture_fstop.is_finite() && d.aperture_fstop > 0.0) {
                return Err(bad(format!(
                    "camera: dof aperture_fstop {} must be positive",
                    d.aperture_fstop
                )));
            }
        }
        if let Some(m) = c.matrix {
            if m.iter().flatten().any(|v| !v.is_finite()) {
                return Err(bad("camera: matrix has non-finite entries".into()));
            }
        } else {
            let t = c.look_at.unwrap_or(add(c.position, [0.0, 0.0, -1.0]));
            if length(sub(t, c.position)) < 1e-9 || c.position.iter().chain(t.iter()).any(|v| !v.is_finite()) {
                return Err(bad(
                    "camera: look_at must differ from position (and both be finite)".into()
                ));
            }
        }
        for (i, o) in self.objects.iter().enumerate() {
            let who = if o.name.is_empty() {
                format!("objects[{i}]")
            } else {
                format!("object {:?}", o.name)
            };
            let err = |m: String| bad(format!("{who}: {m}"));
            match &o.shape {
                Shape::Mesh { .. } => {}
                Shape::Sphere { radius } if !(radius.is_finite() && *radius > 0.0) => {
                    return Err(err(format!("sphere radius {radius} must be positive")))
                }
                Shape::Cuboid { size } if size.iter().any(|v| !(v.is_finite() && *v > 0.0)) => {
                    return Err(err(format!("cuboid size {size:?} must be positive")))
                }
                Shape::Quad { size } if size.iter().any(|v| !(v.is_finite() && *v > 0.0)) => {
                    return Err(err(format!("quad size {size:?} must be positive")))
                }
                Shape::Cylinder { radius, height }
                    if !(radius.is_finite() && *radius > 0.0 && height.is_finite() && *height > 0.0) =>
                {
                    return Err(err(format!(
                        "cylinder radius {radius} and height {height} must be positive"
                    )))
                }
                _ => {}
            }
            let t = &o.transform;
            if t.translate
                .iter()
                .chain(&t.rotate_deg)
                .chain(&t.scale)
                .any(|v| !v.is_finite())
                || t.matrix.is_some_and(|m| m.iter().flatten().any(|v| !v.is_finite()))
            {
                return Err(err("transform has non-finite values".into()));
            }
            let m = &o.material;
            m.base_color.check("base_color").map_err(err)?;
            m.emission_color.check("emission_color").map_err(err)?;
            for (v, what) in [
                (m.roughness, "roughness"),
                (m.metallic, "metallic"),
                (m.transmission, "transmission"),
                (m.specular_ior_level, "specular_ior_level"),
            ] {
                if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
                    return Err(err(format!("material {what} {v} must be in [0, 1]")));
                }
            }
            if !(m.ior.is_finite() && m.ior >= 1.0) {
                return Err(err(format!("material ior {} must be >= 1", m.ior)));
            }
            if !(m.emission_strength.is_finite() && m.emission_strength >= 0.0) {
                return Err(err(format!(
                    "material emission_strength {} must be non-negative",
                    m.emission_strength
                )));
            }
        }
        for (i, l) in self.lights.iter().enumerate() {
            let who = if l.name().is_empty() {
                format!("lights[{i}]")
            } else {
                format!("light {:?}", l.name())
            };
            l.check().map_err(|m| bad(format!("{who}: {m}")))?;
        }
        if let Some(w) = &self.world {
            w.color.check("world color").map_err(bad)?;
            if !(w.strength.is_finite() && w.strength >= 0.0) {
                return Err(bad(format!("world strength {} must be non-negative", w.strength)));
            }
            if !w.rotation_deg.is_finite() {
                return Err(bad("world rotation_deg is not finite".into()));
            }
        }
        Ok(())
    }

    /// [`Scene::validate_files`], naming `path` (the scene's file) in its errors.
    pub fn validate_files_at(&self, path: &Path) -> Result<()> {
        let check = |p: &Path, what: String| {
            let full = self.resolve(p);
            if full.is_file() || self.assets.meshes.contains_key(p) || self.assets.images.contains_key(p) {
                Ok(())
            } else {
                Err(RenderError::Invalid {
                    path: path.to_owned(),
                    message: format!("{what} file {} not found", full.display()),
                })
            }
        };
        for (i, o) in self.objects.iter().enumerate() {
            let who = if o.name.is_empty() {
                format!("objects[{i}]")
            } else {
                format!("object {:?}", o.name)
            };
            if let Shape::Mesh { path } = &o.shape {
                check(path, format!("{who}: mesh"))?;
            }
            let m = &o.material;
            for (t, what) in [
                (&m.base_color_texture, "base_color_texture"),
                (&m.roughness_texture, "roughness_texture"),
                (&m.metallic_texture, "metallic_texture"),
                (&m.normal_texture, "normal_texture"),
            ] {
                if let Some(t) = t {
                    check(t, format!("{who}: {what}"))?;
                }
            }
        }
        if let Some(img) = self.world.as_ref().and_then(|w| w.image.as_ref()) {
            check(img, "world image".into())?;
        }
        Ok(())
    }
}

// Small vector helpers used by the scene description (the renderer has its own `Vec3`).
fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
pub(crate) fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
pub(crate) fn length(a: [f32; 3]) -> f32 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}
pub(crate) fn normalize(a: [f32; 3]) -> [f32; 3] {
    let l = length(a);
    if l > 0.0 {
        [a[0] / l, a[1] / l, a[2] / l]
    } else {
        a
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXAMPLE: &str = r#"
[camera]
width = 64
height = 48
fov_y_deg = 50.0
position = [0.0, 1.0, 4.0]
look_at = [0.0, 0.5, 0.0]

[[objects]]
name = "floor"
shape = { type = "quad", size = [10.0, 10.0] }
transform = { rotate_deg = [-90.0, 0.0, 0.0] }
material = { base_color = [0.8, 0.8, 0.8], roughness = 0.9 }

[[objects]]
shape = { type = "sphere", radius = 0.5 }
material = { base_color = { kelvin = 3000 }, metallic = 1.0 }

[[lights]]
type = "point"
position = [1.0, 3.0, 1.0]
power = 100.0
color = { kelvin = 3200 }

[[lights]]
type = "area"
position = [0.0, 3.0, 0.0]
look_at = [0.0, 0.0, 0.0]
shape = "rectangle"
size = 2.0
size_y = 1.0
power = 50.0

[[lights]]
type = "sun"
direction = [0.0, -1.0, -1.0]
strength = 3.0

[world]
color = [0.05, 0.05, 0.08]
"#;

    #[test]
    fn parses_example_and_roundtrips() {
        let s = Scene::from_toml_str(EXAMPLE).unwrap();
        assert_eq!(s.objects.len(), 2);
        assert_eq!(s.lights.len(), 3);
        assert_eq!(s.objects[0].shape, Shape::Quad { size: [10.0, 10.0] });
        assert_eq!(s.lights[1].area_size(), Some((2.0, 1.0)));
        let toml_text = s.to_string_as(SceneFormat::Toml).unwrap();
        assert_eq!(Scene::from_toml_str(&toml_text).unwrap(), s);
        let json = s.to_string_as(SceneFormat::Json).unwrap();
        assert_eq!(Scene::from_json_str(&json).unwrap(), s);
    }

    #[test]
    fn file_roundtrip_resolves_base_dir() {
        let dir = tempfile::tempdir().unwrap();
        let s = Scene::from_toml_str(EXAMPLE).unwrap();
        let p = dir.path().join("scene.json");
        s.save(&p).unwrap();
        let back = Scene::load(&p).unwrap();
        assert_eq!(back.base_dir, dir.path());
        assert_eq!(back.lights, s.lights);
    }

    #[test]
    fn errors_name_the_problem_and_line() {
        let unknown = EXAMPLE.replace("type = \"sun\"", "type = \"laser\"");
        let e = Scene::from_toml_str(&unknown).unwrap_err().to_string();
        assert!(e.contains("laser") && e.contains("line"), "{e}");
        let neg = EXAMPLE.replace("power = 100.0", "power = -1.0");
        let e = Scene::from_toml_str(&neg).unwrap_err().to_string();
        assert!(e.contains("power") && e.contains("-1"), "{e}");
        let typo = EXAMPLE.replace("radius = 0.5", "radiu = 0.5");
        let e = Scene::from_toml_str(&typo).unwrap_err().to_string();
        assert!(e.contains("radiu") && e.contains("line"), "{e}");
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("s.toml");
        std::fs::write(
            &p,
            EXAMPLE.replace(
                "type = \"quad\", size = [10.0, 10.0]",
                "type = \"mesh\", path = \"nope.obj\"",
            ),
        )
        .unwrap();
        let e = Scene::load(&p).unwrap_err().to_string();
        assert!(
            e.contains("nope.obj") && e.contains("not found") && e.contains("s.toml"),
            "{e}"
        );
    }

    #[test]
    fn camera_frame_and_transform() {
        let c = Camera::new(100, 50, 90.0);
        let (o, r, u, b) = c.frame();
        assert_eq!(o, [0.0; 3]);
        assert!((r[0] - 1.0).abs() < 1e-6 && (u[1] - 1.0).abs() < 1e-6 && (b[2] - 1.0).abs() < 1e-6);
        // fov 90° → focal = h/2.
        assert!((c.focal_for_height(50) - 25.0).abs() < 1e-4);
        // Rotating +90° about X maps +Y to +Z (right-handed).
        let t = Transform {
            rotate_deg: [90.0, 0.0, 0.0],
            ..Default::default()
        };
        let m = t.to_matrix();
        let y = [m[0][1], m[1][1], m[2][1]];
        assert!(
            y[0].abs() < 1e-6 && y[1].abs() < 1e-6 && (y[2] - 1.0).abs() < 1e-6,
            "{y:?}"
        );
    }
}
