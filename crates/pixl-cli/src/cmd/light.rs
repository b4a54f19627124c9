//! `pixl light add`: add a preset's lights or one light spelled out on the command line to a
//! scene file (rewritten atomically, in place unless `-o` is given).
use crate::Ctx;
use anyhow::bail;
use pixl_render::presets::{apply_preset, PRESETS};
use pixl_render::scene::{AreaShape, Color, Light};
use pixl_render::Scene;
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Add lights to a scene: a preset of the paper or one light given by flags.
    #[command(after_help = "Examples:\n  \
pixl light add scene.toml --preset cool-side-flash\n  \
pixl light add scene.toml --preset dim-overhead-spot --replace -o lit.toml\n  \
pixl light add scene.toml --type point --power 100 --position 1,3,1 --temperature 3200\n  \
pixl light add scene.toml --type spot --power 500 --position 0,3,2 --look-at 0,0,0 --spot-size 40\n  \
pixl light add scene.toml --type area --power 200 --position 0,3,0 --look-at 0,0,0 --size 1.5\n  \
pixl light add scene.toml --type sun --strength 3 --direction -0.3,-1,-0.2 --color 1,0.95,0.9\n\n\
Units as in Blender: power in W (point intensity = P/4π W/sr; area radiance = P/(πA)), sun strength in W/m².")]
    Add(AddArgs),
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightType {
    Point,
    Spot,
    Area,
    Sun,
}

#[derive(clap::Args, Debug)]
pub struct AddArgs {
    /// Scene file (.toml or .json).
    pub scene: PathBuf,
    /// Write here instead of rewriting the scene in place.
    #[arg(short, long)]
    pub out: Option<PathBuf>,
    /// A preset of the paper (§4.2).
    #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(PRESETS), conflicts_with = "light_type")]
    pub preset: Option<String>,
    /// Remove the scene's existing lights first.
    #[arg(long)]
    pub replace: bool,
    /// Light type.
    #[arg(long = "type", value_enum)]
    pub light_type: Option<LightType>,
    /// Name of the light.
    #[arg(long, default_value = "")]
    pub name: String,
    /// Power in W (point, spot, area).
    #[arg(long)]
    pub power: Option<f32>,
    /// Sun irradiance in W/m².
    #[arg(long)]
    pub strength: Option<f32>,
    /// Position x,y,z (point, spot, area).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub position: Option<[f32; 3]>,
    /// Direction the light travels x,y,z (spot, area, sun).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub direction: Option<[f32; 3]>,
    /// Point to aim at x,y,z (spot, area).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub look_at: Option<[f32; 3]>,
    /// Linear RGB colour r,g,b.
    #[arg(long, value_parser = parse_vec3, conflicts_with = "temperature")]
    pub color: Option<[f32; 3]>,
    /// Blackbody colour temperature in kelvin.
    #[arg(long)]
    pub temperature: Option<f32>,
    /// Point/spot radius (soft shadows), metres.
    #[arg(long, default_value_t = 0.0)]
    pub radius: f32,
    /// Spot cone full angle, degrees.
    #[arg(long, default_value_t = 45.0)]
    pub spot_size: f32,
    /// Spot edge blend in [0, 1].
    #[arg(long, default_value_t = 0.15)]
    pub blend: f32,
    /// Area light size (edge or diameter), metres.
    #[arg(long, default_value_t = 1.0)]
    pub size: f32,
    /// Area light second size (rectangle / ellipse).
    #[arg(long)]
    pub size_y: Option<f32>,
    /// Area light shape.
    #[arg(long, value_parser = ["square", "rectangle", "disk", "ellipse"], default_value = "square")]
    pub shape: String,
    /// Sun angular diameter, degrees.
    #[arg(long, default_value_t = 0.526)]
    pub angle: f32,
    /// Area light: camera rays see the emitter itself (Blender's Ray Visibility ▸ Camera). Off by
    /// default, as in Blender: the light still lights the scene and shows in reflections.
    #[arg(long)]
    pub visible_to_camera: bool,
}

/// Parses `x,y,z`.
pub fn parse_vec3(s: &str) -> Result<[f32; 3], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f32>()
                .map_err(|_| format!("{s:?} is not x,y,z (e.g. 1,3,-0.5)"))
        })
        .collect::<Result<_, _>>()?;
    match v.as_slice() {
        [x, y, z] => Ok([*x, *y, *z]),
        _ => Err(format!("{s:?} has {} values, expected 3 (x,y,z)", v.len())),
    }
}

fn light_from_args(a: &AddArgs, t: LightType) -> anyhow::Result<Light> {
    let color = match (a.color, a.temperature) {
        (_, Some(k)) => Color::Blackbody { kelvin: k },
        (Some(c), None) => Color::Rgb(c),
        (None, None) => Color::default(),
    };
    if a.visible_to_camera && !matches!(t, LightType::Area) {
        anyhow::bail!("--visible-to-camera is for area lights (point, spot and sun lights are never seen by the camera, as in Blender)");
    }
    let need_pos = || {
        a.position
            .ok_or_else(|| anyhow::anyhow!("--type {t:?} needs --position x,y,z"))
    };
    let need_power = || {
        a.power
            .ok_or_else(|| anyhow::anyhow!("--type {t:?} needs --power WATTS"))
    };
    let name = a.name.clone();
    Ok(match t {
        LightType::Point => Light::Point {
            name,
            position: need_pos()?,
            power: need_power()?,
            radius: a.radius,
            color,
        },
        LightType::Spot => Light::Spot {
            name,
            position: need_pos()?,
            direction: a.direction,
            look_at: a.look_at,
            power: need_power()?,
            spot_size_deg: a.spot_size,
            blend: a.blend,
            radius: a.radius,
            color,
        },
        LightType::Area => Light::Area {
            name,
            position: need_pos()?,
            direction: a.direction,
            look_at: a.look_at,
            shape: match a.shape.as_str() {
                "rectangle" => AreaShape::Rectangle,
                "disk" => AreaShape::Disk,
                "ellipse" => AreaShape::Ellipse,
                _ => AreaShape::Square,
            },
            size: a.size,
            size_y: a.size_y,
            power: need_power()?,
            color,
            visible_to_camera: a.visible_to_camera,
        },
        LightType::Sun => Light::Sun {
            name,
            direction: a.direction,
            strength: a
                .strength
                .ok_or_else(|| anyhow::anyhow!("--type sun needs --strength W/m2"))?,
            angle_deg: a.angle,
            color,
        },
    })
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    let Command::Add(a) = command;
    let mut scene = Scene::load(&a.scene)?;
    let before = scene.lights.len();
    match (&a.preset, a.light_type) {
        (Some(p), _) => apply_preset(&mut scene, p, a.replace)?,
        (None, Some(t)) => {
            let light = light_from_args(&a, t)?;
            if a.replace {
                scene.lights.clear();
            }
            scene.lights.push(light);
            scene.validate()?;
        }
        (None, None) => bail!("give --preset NAME or --type point|spot|area|sun (see --help)"),
    }
    let out = a.out.clone().unwrap_or_else(|| a.scene.clone());
    // Relative paths in the scene stay valid only if the output sits beside the input.
    if let (Some(src), Some(dst)) = (a.scene.parent(), out.parent()) {
        if std::fs::canonicalize(if src.as_os_str().is_empty() {
            std::path::Path::new(".")
        } else {
            src
        })
        .ok()
            != std::fs::canonicalize(if dst.as_os_str().is_empty() {
                std::path::Path::new(".")
            } else {
                dst
            })
            .ok()
            && scene
                .objects
                .iter()
                .any(|o| matches!(&o.shape, pixl_render::Shape::Mesh { path } if path.is_relative()))
        {
            ctx.say(format!(
                "note: {} refers to mesh files relative to {}; keep it beside them",
                out.display(),
                src.display()
            ));
        }
    }
    scene.save(&out)?;
    let added = scene.lights.len() as isize - if a.replace { 0 } else { before as isize };
    ctx.say(format!(
        "{} light(s) added; {} now has {} light(s)",
        added,
        out.display(),
        scene.lights.len()
    ));
    Ok(())
}
