//! The Blender bridge: a [`Scene`] → a Blender Python script that rebuilds it
//! and renders Cycles' passes into a multilayer EXR.
//!
//! [`export_blender`] writes `scene.py` and, beside it, a data folder `scene_data/` holding
//! every object's triangles as binary PLY (exactly the tessellation the native renderer uses, from
//! [`crate::trace::geometry::shape_mesh`]) and copies of every texture, so the script + folder can move
//! together. The script needs nothing but `bpy` (and the numpy it ships with):
//!
//! ```text
//! blender -b -P scene.py -- --out passes.exr --spp 64
//! python scene.py --out passes.exr --spp 64          # with PyPI's `bpy` module
//! ```
//!
//! # Mapping
//! - Axes: our +Y-up world maps to Blender's +Z-up by `C: (x, y, z) ↦ (x, −z, y)`; every
//!   object-to-world matrix `M` becomes `C·M` (vertices are kept in our object space).
//! - Camera: same frame (looks down local −Z, +Y up), `sensor_fit = VERTICAL`, lens from the
//!   vertical FOV (24 mm sensor height), principal point offsets as `shift_x/shift_y`, pixel
//!   filter box of width 1 (our renderer's uniform in-pixel jitter); depth of field as
//!   `dof.use_dof`, `focus_distance`, `aperture_fstop` (round aperture), off without `dof`.
//! - Materials: Principled BSDF with the same inputs; colour textures sRGB, roughness/metallic
//!   textures Non-Color; a normal map through a tangent-space Normal Map node (strength 1). UVs flip to Blender's `v = 0` at the bottom.
//! - Lights: Blender's own units, one to one (point/spot `energy` = power W and
//!   `shadow_soft_size` = radius; spot `spot_size`, `spot_blend`; area `shape`, `size`, `size_y`,
//!   power W, oriented with the native renderer's area axes; sun `energy` = strength W/m²,
//!   `angle`). Blackbody colours are converted to RGB here ([`Color::rgb`]). Every light
//!   object's `visible_camera` is set explicitly: on only for area, point and spot lights with
//!   `visible_to_camera` (the native renderer's rule; Blender 4/5 default it to off too).
//! - World: Background colour × strength, or an equirectangular Environment Texture rotated about
//!   the up axis by `rotation_deg`.
//! - Cycles: CPU, `--spp` samples, no adaptive sampling, no denoising, seed 0, all bounce limits
//!   = `--max-bounces` (default 8, the native default), no clamping, no glossy filter; passes
//!   enabled: Combined, Z, Normal, Emission, Environment, Diffuse/Glossy/Transmission
//!   Direct/Indirect/Color, Volume Direct/Indirect — and nothing else.
use crate::scene::{cross, length, normalize, AreaShape, Light, Scene, Shape};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum BlenderError {
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    #[error(transparent)]
    Render(#[from] crate::RenderError),
    #[error(transparent)]
    Mesh(#[from] crate::io::export::MeshIoError),
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
}

/// What [`export_blender`] wrote.
#[derive(Clone, Debug)]
pub struct BlenderExport {
    pub script: PathBuf,
    pub data_dir: PathBuf,
    pub meshes: usize,
    pub textures: usize,
}

/// The Cycles pass toggles the script sets (`view_layer.use_pass_<name>`), then the two
/// `view_layer.cycles.use_pass_volume_*` ones.
pub const PASS_TOGGLES: [&str; 14] = [
    "combined",
    "z",
    "normal",
    "emit",
    "environment",
    "diffuse_direct",
    "diffuse_indirect",
    "diffuse_color",
    "glossy_direct",
    "glossy_indirect",
    "glossy_color",
    "transmission_direct",
    "transmission_indirect",
    "transmission_color",
];

/// The axes of an area light emitting along `d` (unit): `(x, y)` with `x × y = −d`; the same
/// construction as the native renderer's.
fn light_axes(d: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let x = cross(d, [0.0, 1.0, 0.0]);
    let x = if length(x) < 1e-6 {
        [1.0, 0.0, 0.0]
    } else {
        normalize(x)
    };
    let y = normalize(cross(d.map(|c| -c), x));
    (x, y)
}

/// Row-major 4×4 from basis columns and an origin.
fn frame_matrix(x: [f32; 3], y: [f32; 3], z: [f32; 3], o: [f32; 3]) -> [[f32; 4]; 4] {
    [
        [x[0], y[0], z[0], o[0]],
        [x[1], y[1], z[1], o[1]],
        [x[2], y[2], z[2], o[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// Copies a texture into the data folder under a fresh name; returns the new file name.
fn copy_texture(scene: &Scene, p: &Path, data: &Path, n: &mut usize) -> Result<String, BlenderError> {
    let src = scene.resolve(p);
    if !src.is_file() {
        return Err(pixl_core::CoreError::NotFound { path: src }.into());
    }
    let ext = pixl_core::io::extension(&src);
    let name = format!("tex_{}.{}", *n, if ext.is_empty() { "png" } else { &ext });
    *n += 1;
    std::fs::copy(&src, data.join(&name)).map_err(|e| pixl_core::CoreError::io(&src, e))?;
    Ok(name)
}

/// Resolves the scene into the plain description the script reads (see the module docs):
/// meshes are written to `data` as PLY, textures copied there.
fn describe(scene: &Scene, data: &Path) -> Result<(Value, usize, usize), BlenderError> {
    let cam = &scene.camera;
    let (o, right, up, back) = cam.frame();
    let (w, h) = (cam.width as f32, cam.height as f32);
    let [cx, cy] = cam.principal_px.unwrap_or([0.5 * w, 0.5 * h]);
    let maxdim = w.max(h);
    let camera = json!({
        "width": cam.width, "height": cam.height, "fov_y_deg": cam.fov_y(),
        "shift_x": (0.5 * w - cx) / maxdim, "shift_y": (cy - 0.5 * h) / maxdim,
        "matrix": frame_matrix(right, up, back, o),
        "dof": match &cam.dof {
            Some(d) => json!({ "focus_distance": d.focus_distance, "aperture_fstop": d.aperture_fstop }),
            None => Value::Null,
        },
    });
    let mut textures = 0;
    let mut objects = Vec::new();
    for (i, obj) in scene.objects.iter().enumerate() {
        let mesh = crate::trace::geometry::shape_mesh(scene, &obj.shape)?;
        let file = format!("obj_{i}.ply");
        crate::io::export::ply::write_ply(&data.join(&file), &mesh)?;
        let m = &obj.material;
        let mut tex = |p: &Option<PathBuf>| -> Result<Value, BlenderError> {
            Ok(match p {
                Some(p) => json!(copy_texture(scene, p, data, &mut textures)?),
                None => Value::Null,
            })
        };
        let material = json!({
            "base_color": m.base_color.rgb(), "base_color_texture": tex(&m.base_color_texture)?,
            "roughness": m.roughness, "roughness_texture": tex(&m.roughness_texture)?,
            "metallic": m.metallic, "metallic_texture": tex(&m.metallic_texture)?,
            "normal_texture": tex(&m.normal_texture)?,
            "transmission": m.transmission,
            "specular_ior_level": m.specular_ior_level, "ior": m.ior,
            "emission_color": m.emission_color.rgb(), "emission_strength": m.emission_strength,
        });
        let name = if obj.name.is_empty() {
            format!("object_{i}")
        } else {
            obj.name.clone()
        };
        let smooth = !matches!(obj.shape, Shape::Cuboid { .. } | Shape::Quad { .. }) && !mesh.normals.is_empty();
        objects.push(json!({
            "name": name, "mesh": file, "matrix": obj.transform.to_matrix(), "smooth": smooth, "material": material,
        }));
    }
    let mut lights = Vec::new();
    for (i, l) in scene.lights.iter().enumerate() {
        let name = if l.name().is_empty() {
            format!("light_{i}")
        } else {
            l.name().to_string()
        };
        let d = l.direction().unwrap_or([0.0, -1.0, 0.0]);
        let (x, y) = light_axes(d);
        let z = d.map(|c| -c);
        let at = |p: [f32; 3]| frame_matrix(x, y, z, p);
        let color = l.color().rgb();
        lights.push(match l {
            Light::Point {
                position,
                power,
                radius,
                visible_to_camera,
                ..
            } => json!({
                "type": "POINT", "name": name, "matrix": at(*position), "color": color, "energy": power,
                "radius": radius, "visible_camera": visible_to_camera,
            }),
            Light::Spot {
                position,
                power,
                spot_size_deg,
                blend,
                radius,
                visible_to_camera,
                ..
            } => json!({
                "type": "SPOT", "name": name, "matrix": at(*position), "color": color, "energy": power,
                "radius": radius, "spot_size_deg": spot_size_deg, "blend": blend,
                "visible_camera": visible_to_camera,
            }),
            Light::Area {
                position,
                shape,
                power,
                visible_to_camera,
                ..
            } => {
                let (sx, sy) = l.area_size().unwrap_or((1.0, 1.0));
                let shape = match shape {
                    AreaShape::Square => "SQUARE",
                    AreaShape::Rectangle => "RECTANGLE",
                    AreaShape::Disk => "DISK",
                    AreaShape::Ellipse => "ELLIPSE",
                };
                json!({
                    "type": "AREA", "name": name, "matrix": at(*position), "color": color, "energy": power,
                    "shape": shape, "size": sx, "size_y": sy, "visible_camera": visible_to_camera,
                })
            }
            Light::Sun {
                strength, angle_deg, ..
            } => json!({
                "type": "SUN", "name": name, "matrix": at([0.0; 3]), "color": color, "energy": strength,
                "angle_deg": angle_deg,
            }),
        });
    }
    let world = match &scene.world {
        Some(wd) => json!({
            "color": wd.color.rgb(), "strength": wd.strength, "rotation_deg": wd.rotation_deg,
            "image": match &wd.image { Some(p) => json!(copy_texture(scene, p, data, &mut textures)?), None => Value::Null },
        }),
        None => Value::Null,
    };
    let desc = json!({ "camera": camera, "objects": objects, "lights": lights, "world": world });
    Ok((desc, scene.objects.len(), textures))
}

/// Writes `script` (a `.py` file) and its data folder `<stem>_data/` beside it.
pub fn export_blender(scene: &Scene, script: &Path) -> Result<BlenderExport, BlenderError> {
    let stem = script.file_stem().and_then(|s| s.to_str()).unwrap_or("scene");
    let dir = match script.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
        _ => PathBuf::from("."),
    };
    let data_name = format!("{stem}_data");
    let data_dir = dir.join(&data_name);
    std::fs::create_dir_all(&data_dir).map_err(|e| pixl_core::CoreError::io(&data_dir, e))?;
    let (desc, meshes, textures) = describe(scene, &data_dir)?;
    let text = script_text(&desc, &data_name);
    pixl_core::io::atomic_write_bytes(script, text.as_bytes())?;
    Ok(BlenderExport {
        script: script.to_owned(),
        data_dir,
        meshes,
        textures,
    })
}

/// The Python source for a resolved scene description (see [`describe`]).
pub fn script_text(desc: &Value, data_dir_name: &str) -> String {
    let json_text = serde_json::to_string_pretty(desc).unwrap_or_else(|_| "{}".into());
    let passes = PASS_TOGGLES
        .iter()
        .map(|p| format!("\"{p}\""))
        .collect::<Vec<_>>()
        .join(", ");
    SCRIPT
        .replace("@DATA_DIR@", &format!("{data_dir_name:?}"))
        .replace("@PASSES@", &passes)
        .replace("@SCENE_JSON@", &json_text.replace('\'', "\\u0027"))
}

const SCRIPT: &str = r#####""""Rebuild a pixlrelight scene in Blender and render Cycles passes into a multilayer EXR.

Generated by `pixl blender export`. Run:
    blender -b -P scene.py -- --out passes.exr --spp 64
    python scene.py --out passes.exr --spp 64      (with the PyPI `bpy` module)
Meshes (binary PLY) and textures live in the data folder beside this script.
"""
import argparse
import json
import math
import os
import struct
import sys
import time

import bpy
from mathutils import Matrix

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, @DATA_DIR@)
# Our world is +Y up; Blender's is +Z up: (x, y, z) -> (x, -z, y).
Y_UP_TO_Z_UP = Matrix(((1, 0, 0, 0), (0, 0, -1, 0), (0, 1, 0, 0), (0, 0, 0, 1)))
PASSES = [@PASSES@]
SCENE = json.loads(r'''@SCENE_JSON@''')


def parse_args():
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
    p = argparse.ArgumentParser(description="Render this scene's Cycles passes to a multilayer EXR.")
    p.add_argument("--out", required=True, help="output .exr")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel")
    p.add_argument("--max-bounces", type=int, default=8)
    p.add_argument("--threads", type=int, default=0, help="0 = all cores")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


def read_ply(path):
    """Binary little-endian PLY as written by pixlrelight: float vertex properties, uchar/uint faces."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    props, nv, nf = [], 0, 0
    element = None
    for line in header:
        w = line.split()
        if w[:1] == ["element"]:
            element = w[1]
            if element == "vertex":
                nv = int(w[2])
            elif element == "face":
                nf = int(w[2])
        elif w[:1] == ["property"] and element == "vertex":
            if w[1] != "float":
                raise ValueError(f"{path}: unexpected vertex property type {w[1]}")
            props.append(w[2])
    k = len(props)
    vals = struct.unpack_from(f"<{nv * k}f", data, end)
    rows = [vals[i * k:(i + 1) * k] for i in range(nv)]
    col = {name: i for i, name in enumerate(props)}
    verts = [(r[col["x"]], r[col["y"]], r[col["z"]]) for r in rows]
    normals = [(r[col["nx"]], r[col["ny"]], r[col["nz"]]) for r in rows] if "nx" in col else None
    uvs = [(r[col["s"]], r[col["t"]]) for r in rows] if "s" in col else None
    off = end + nv * k * 4
    faces = []
    for _ in range(nf):
        n = data[off]
        faces.append(struct.unpack_from(f"<{n}I", data, off + 1))
        off += 1 + 4 * n
    return verts, normals, uvs, faces


def matrix(rows):
    return Matrix([list(r) for r in rows])


def image_node(nt, name, non_color):
    node = nt.nodes.new("ShaderNodeTexImage")
    node.image = bpy.data.images.load(os.path.join(DATA, name))
    if non_color:
        node.image.colorspace_settings.name = "Non-Color"
    node.interpolation = "Linear"
    return node


def make_material(name, m):
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    if bsdf is None:
        nt.nodes.clear()
        bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    bsdf.inputs["Base Color"].default_value = (*m["base_color"], 1.0)
    bsdf.inputs["Roughness"].default_value = m["roughness"]
    bsdf.inputs["Metallic"].default_value = m["metallic"]
    bsdf.inputs["Transmission Weight"].default_value = m["transmission"]
    bsdf.inputs["IOR"].default_value = m["ior"]
    bsdf.inputs["Specular IOR Level"].default_value = m.get("specular_ior_level", 0.5)
    bsdf.inputs["Emission Color"].default_value = (*m["emission_color"], 1.0)
    bsdf.inputs["Emission Strength"].default_value = m["emission_strength"]
    for key, socket, non_color in (("base_color_texture", "Base Color", False),
                                   ("roughness_texture", "Roughness", True),
                                   ("metallic_texture", "Metallic", True)):
        if m.get(key):
            node = image_node(nt, m[key], non_color)
            nt.links.new(node.outputs["Color"], bsdf.inputs[socket])
    if m.get("normal_texture"):
        node = image_node(nt, m["normal_texture"], True)
        nmap = nt.nodes.new("ShaderNodeNormalMap")
        nmap.space = "TANGENT"
        nmap.inputs["Strength"].default_value = 1.0
        nt.links.new(node.outputs["Color"], nmap.inputs["Color"])
        nt.links.new(nmap.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def add_object(scene, o):
    verts, normals, uvs, faces = read_ply(os.path.join(DATA, o["mesh"]))
    mesh = bpy.data.meshes.new(o["name"])
    mesh.from_pydata(verts, [], faces)
    if uvs is not None:
        layer = mesh.uv_layers.new(name="UVMap")
        # PLY's t already has v = 0 at the bottom, Blender's convention.
        flat = [c for loop in mesh.loops for c in uvs[loop.vertex_index]]
        layer.data.foreach_set("uv", flat)
    mesh.polygons.foreach_set("use_smooth", [bool(o["smooth"])] * len(mesh.polygons))
    if normals is not None and o["smooth"]:
        mesh.normals_split_custom_set_from_vertices(normals)
    mesh.update()
    mesh.materials.append(make_material(o["name"] + "_material", o["material"]))
    ob = bpy.data.objects.new(o["name"], mesh)
    scene.collection.objects.link(ob)
    ob.matrix_world = Y_UP_TO_Z_UP @ matrix(o["matrix"])


def add_light(scene, l):
    data = bpy.data.lights.new(l["name"], type=l["type"])
    data.energy = l["energy"]
    data.color = l["color"]
    if l["type"] in ("POINT", "SPOT"):
        data.shadow_soft_size = l["radius"]
    if l["type"] == "SPOT":
        data.spot_size = math.radians(l["spot_size_deg"])
        data.spot_blend = l["blend"]
    if l["type"] == "AREA":
        data.shape = l["shape"]
        data.size = l["size"]
        data.size_y = l["size_y"]
    if l["type"] == "SUN":
        data.angle = math.radians(l["angle_deg"])
    ob = bpy.data.objects.new(l["name"], data)
    # Camera rays see a light only where the scene asks (area, point, spot); set explicitly rather
    # than relying on Blender's default (off in 4/5).
    ob.visible_camera = bool(l.get("visible_camera", False))
    scene.collection.objects.link(ob)
    ob.matrix_world = Y_UP_TO_Z_UP @ matrix(l["matrix"])


def add_camera(scene, c):
    data = bpy.data.cameras.new("Camera")
    data.type = "PERSP"
    data.sensor_fit = "VERTICAL"
    data.sensor_height = 24.0
    data.lens = 0.5 * data.sensor_height / math.tan(0.5 * math.radians(c["fov_y_deg"]))
    data.shift_x = c["shift_x"]
    data.shift_y = c["shift_y"]
    data.clip_start = 1e-3
    data.clip_end = 1e5
    dof = c.get("dof")
    data.dof.use_dof = dof is not None
    if dof is not None:
        data.dof.focus_distance = dof["focus_distance"]
        data.dof.aperture_fstop = dof["aperture_fstop"]
        data.dof.aperture_blades = 0
        data.dof.aperture_ratio = 1.0
    ob = bpy.data.objects.new("Camera", data)
    scene.collection.objects.link(ob)
    ob.matrix_world = Y_UP_TO_Z_UP @ matrix(c["matrix"])
    scene.camera = ob
    scene.render.resolution_x = c["width"]
    scene.render.resolution_y = c["height"]
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = 1.0
    scene.render.pixel_aspect_y = 1.0


def add_world(scene, w):
    world = bpy.data.worlds.new("World")
    scene.world = world
    if bpy.app.version < (5, 0, 0):
        world.use_nodes = True
    nt = world.node_tree
    bg = nt.nodes.get("Background")
    if bg is None:
        bg = nt.nodes.new("ShaderNodeBackground")
        out = nt.nodes.get("World Output") or nt.nodes.new("ShaderNodeOutputWorld")
        nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    if w is None:
        bg.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
        bg.inputs["Strength"].default_value = 0.0
        return
    bg.inputs["Color"].default_value = (*w["color"], 1.0)
    bg.inputs["Strength"].default_value = w["strength"]
    if w.get("image"):
        env = nt.nodes.new("ShaderNodeTexEnvironment")
        env.image = bpy.data.images.load(os.path.join(DATA, w["image"]))
        coords = nt.nodes.new("ShaderNodeTexCoord")
        mapping = nt.nodes.new("ShaderNodeMapping")
        # The native renderer looks the image up at R_up(-rotation) * direction.
        mapping.inputs["Rotation"].default_value = (0.0, 0.0, -math.radians(w["rotation_deg"]))
        nt.links.new(coords.outputs["Generated"], mapping.inputs["Vector"])
        nt.links.new(mapping.outputs["Vector"], env.inputs["Vector"])
        nt.links.new(env.outputs["Color"], bg.inputs["Color"])


def configure(scene, args):
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = args.spp
    c.use_adaptive_sampling = False
    c.use_denoising = False
    c.seed = args.seed
    c.max_bounces = args.max_bounces
    c.diffuse_bounces = args.max_bounces
    c.glossy_bounces = args.max_bounces
    c.transmission_bounces = args.max_bounces
    c.volume_bounces = args.max_bounces
    c.transparent_max_bounces = args.max_bounces
    c.sample_clamp_direct = 0.0
    c.sample_clamp_indirect = 0.0
    c.blur_glossy = 0.0
    c.pixel_filter_type = "BOX"
    c.filter_width = 1.0
    if args.threads:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = args.threads
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    vl = scene.view_layers[0]
    for name in PASSES:
        setattr(vl, "use_pass_" + name, True)
    vl.cycles.use_pass_volume_direct = True
    vl.cycles.use_pass_volume_indirect = True
    vl.cycles.denoising_store_passes = False
    im = scene.render.image_settings
    if hasattr(im, "media_type"):  # Blender >= 5.0
        im.media_type = "MULTI_LAYER_IMAGE"
    im.file_format = "OPEN_EXR_MULTILAYER"
    im.color_depth = "32"
    im.exr_codec = "ZIP"
    scene.render.filepath = os.path.abspath(args.out)
    scene.render.use_file_extension = False


def main():
    args = parse_args()
    t0 = time.time()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    add_camera(scene, SCENE["camera"])
    for o in SCENE["objects"]:
        add_object(scene, o)
    for l in SCENE["lights"]:
        add_light(scene, l)
    add_world(scene, SCENE["world"])
    configure(scene, args)
    t1 = time.time()
    bpy.ops.render.render(write_still=True)
    t2 = time.time()
    print(f"blender {bpy.app.version_string}: build {t1 - t0:.2f}s, render+write {t2 - t1:.2f}s, "
          f"{scene.render.resolution_x}x{scene.render.resolution_y} @ {args.spp} spp -> {args.out}")


if __name__ == "__main__":
    main()
"#####;
