//! `pixl scene info`: what a scene file holds, in the terms light placement uses — the bounds
//! of its objects (meshes loaded), its camera (position, axes, field of view, image size), the
//! axes and units, and its lights — as text or `--json`.
use crate::Ctx;
use pixl_render::placement::SceneFrame;
use pixl_render::scene::Light;
use pixl_render::Scene;
use serde_json::json;
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Print a scene's bounds, camera, axes and lights.
    #[command(after_help = concat!(
        "Examples:\n  pixl scene info scene/scene.toml\n  pixl scene info scene/scene.toml --json\n\n",
        crate::scene_axes_help!()
    ))]
    Info(InfoArgs),
}

#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    /// Scene file (.toml or .json).
    pub scene: PathBuf,
    /// Print one JSON document on stdout.
    #[arg(long)]
    pub json: bool,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    let Command::Info(a) = command;
    let scene = Scene::load(&a.scene)?;
    let frame = SceneFrame::of(&scene)?;
    let cam = &scene.camera;
    let (origin, right, up, back) = cam.frame();
    let forward = back.map(|v| -v);
    let lights: Vec<serde_json::Value> = scene.lights.iter().map(light_json).collect();
    let objects: Vec<serde_json::Value> = scene
        .objects
        .iter()
        .map(|o| json!({"name": o.name, "shape": serde_json::to_value(&o.shape).unwrap_or_default()}))
        .collect();
    let size = [
        frame.hi[0] - frame.lo[0],
        frame.hi[1] - frame.lo[1],
        frame.hi[2] - frame.lo[2],
    ];
    let doc = json!({
        "scene": a.scene.display().to_string(),
        "units": "metres",
        "axes": {
            "world": "right-handed, +Y up",
            "camera": "+X right, +Y up, -Z forward (the viewing direction); image row 0 is the top",
        },
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "fov_y_deg": cam.fov_y(),
            "focal_px": cam.focal_for_height(cam.height),
            "position": origin,
            "right": right,
            "up": up,
            "forward": forward,
        },
        "bounds": if frame.empty { serde_json::Value::Null } else { json!({
            "min": frame.lo,
            "max": frame.hi,
            "centre": frame.centre,
            "size": size,
            "half_diagonal": frame.radius,
            "distance_from_camera": dist(frame.centre, origin),
        })},
        "placement": {
            "right": frame.right,
            "up": frame.up,
            "forward": frame.forward,
            "default_distance": frame.default_distance(),
            "default_offset": frame.default_offset(),
        },
        "objects": objects,
        "lights": lights,
    });
    if a.json {
        return ctx.print_json(&doc);
    }
    let f3 = pixl_pipeline::lights::fmt3;
    let mut lines = vec![
        format!("scene {}", a.scene.display()),
        "axes: right-handed, metres, +Y up; the camera looks down its -Z (+X right, +Y up in its image)".to_string(),
        format!(
            "camera: {}x{} px, vertical FOV {:.1}° (focal {:.1} px), at {}, right {}, up {}, forward {}",
            cam.width,
            cam.height,
            cam.fov_y(),
            cam.focal_for_height(cam.height),
            f3(origin),
            f3(right),
            f3(up),
            f3(forward)
        ),
    ];
    if frame.empty {
        lines.push("bounds: none (no objects)".to_string());
    } else {
        lines.push(format!(
            "bounds: min {} max {} (size {:.2} x {:.2} x {:.2} m), centre {} at {:.2} m from the camera",
            f3(frame.lo),
            f3(frame.hi),
            size[0],
            size[1],
            size[2],
            f3(frame.centre),
            dist(frame.centre, origin)
        ));
    }
    lines.push(format!(
        "placement: --from/--azimuth go around the centre at {:.2} m by default; --at-pixel lights sit {:.2} m off the surface",
        frame.default_distance(),
        frame.default_offset()
    ));
    lines.push(format!("objects: {}", scene.objects.len()));
    for o in &scene.objects {
        lines.push(format!("  {}", if o.name.is_empty() { "(unnamed)" } else { &o.name }));
    }
    lines.push(format!("lights: {}", scene.lights.len()));
    for l in &scene.lights {
        lines.push(format!("  {}", light_line(l)));
    }
    // Printed even under --quiet: it is what the command is for.
    println!("{}", lines.join("\n"));
    Ok(())
}

fn dist(a: [f32; 3], b: [f32; 3]) -> f32 {
    (pixl_render::math::V3::from_arr(a) - pixl_render::math::V3::from_arr(b)).length()
}

fn color_text(l: &Light) -> String {
    match l.color() {
        pixl_render::Color::Rgb(c) => format!("rgb {:.2},{:.2},{:.2}", c[0], c[1], c[2]),
        pixl_render::Color::Blackbody { kelvin } => format!("{kelvin} K"),
    }
}

fn light_line(l: &Light) -> String {
    let f3 = pixl_pipeline::lights::fmt3;
    let name = if l.name().is_empty() {
        String::new()
    } else {
        format!("{:?} ", l.name())
    };
    let dir = l
        .direction()
        .map(|d| format!(", shining along {}", f3(d)))
        .unwrap_or_default();
    match l {
        Light::Point { position, power, .. } => {
            format!("{name}point {power:.1} W at {}, {}", f3(*position), color_text(l))
        }
        Light::Spot {
            position,
            power,
            spot_size_deg,
            ..
        } => format!(
            "{name}spot {power:.1} W at {}{dir}, cone {spot_size_deg}°, {}",
            f3(*position),
            color_text(l)
        ),
        Light::Area { position, power, .. } => {
            let (sx, sy) = l.area_size().unwrap_or((0.0, 0.0));
            format!(
                "{name}area {power:.1} W at {}{dir}, {sx} x {sy} m, {}",
                f3(*position),
                color_text(l)
            )
        }
        Light::Sun { strength, .. } => format!("{name}sun {strength} W/m²{dir}, {}", color_text(l)),
    }
}

fn light_json(l: &Light) -> serde_json::Value {
    let mut v = serde_json::to_value(l).unwrap_or_default();
    if let (Some(obj), Some(d)) = (v.as_object_mut(), l.direction()) {
        obj.insert("resolved_direction".into(), json!(d));
    }
    v
}
