//! One light as the user says it (`pixl light add`, `pixl relight --light '…'`): a [`LightSpec`]
//! checked without a scene ([`LightSpec::check`]) and placed in one ([`LightSpec::build`]).
//!
//! Where the light goes can be said three ways: `position` (scene coordinates); `at_pixel` (the
//! surface seen through that pixel of the scene's camera, pushed `offset` metres off it along
//! its normal; default `0.15 ×` the scene bounds' diagonal); or `from` a side / `azimuth` and
//! `elevation` around the centre of the scene's bounds at `distance` (default `1.5 ×` the
//! bounds' half-diagonal). Conventions are those of `pixl_render::placement`. Placed spot and
//! area lights aim at the picked point (at-pixel) or at the bounds' centre unless `direction` or
//! `look_at` says otherwise; a placed sun shines from that side toward the centre. Without a
//! power (a strength for a sun), a placed light gets the power that gives
//! [`PLACED_IRRADIANCE`] where it aims (the presets' flash irradiance), and says so.
//!
//! Checks: a setting that does not apply to the light's type is an error (a spot size on a point
//! light); powers must be finite and non-negative (warnings for 0 and for more than
//! [`MAX_PLAUSIBLE_POWER`] W or [`MAX_PLAUSIBLE_SUN`] W/m²). With the `clap` feature the spec is
//! a set of command-line flags, whose names the messages use.
use crate::error::{PipelineError, Result};
use pixl_render::math::V3;
use pixl_render::placement::{pick_pixel, power_for_irradiance, Emitter, SceneFrame, Side};
use pixl_render::scene::{AreaShape, Color, Light};
use pixl_render::Scene;

/// Above this power (W) a light is reported as implausible (a bright studio strobe is ~10 kW).
pub const MAX_PLAUSIBLE_POWER: f32 = 1.0e6;
/// Above this sun strength (W/m²) it is reported as implausible (the midday sun gives ~1000).
pub const MAX_PLAUSIBLE_SUN: f32 = 1.0e4;
/// Irradiance (W/m²) a placed light without `--power` gives where it aims.
pub const PLACED_IRRADIANCE: f32 = 4.0;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum LightType {
    Point,
    Spot,
    Area,
    Sun,
}

impl LightType {
    fn name(self) -> &'static str {
        match self {
            LightType::Point => "point",
            LightType::Spot => "spot",
            LightType::Area => "area",
            LightType::Sun => "sun",
        }
    }

    fn emitter(self) -> Emitter {
        match self {
            LightType::Point => Emitter::Point,
            LightType::Spot => Emitter::Spot,
            LightType::Area => Emitter::Area,
            LightType::Sun => Emitter::Sun,
        }
    }
}

/// One light, as flags (`pixl light add`, and each `pixl relight --light '…'`).
#[derive(Debug, Clone, Default)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct LightSpec {
    /// Light type (default point when other light flags are given).
    #[cfg_attr(feature = "clap", arg(long = "type", value_enum))]
    pub light_type: Option<LightType>,
    /// Name of the light.
    #[cfg_attr(feature = "clap", arg(long))]
    pub name: Option<String>,
    /// Power in W (point, spot, area). Default for a placed light: 4 W/m² where it aims.
    #[cfg_attr(feature = "clap", arg(long, allow_negative_numbers = true))]
    pub power: Option<f32>,
    /// Sun irradiance in W/m² (sun). Default for a placed sun: 4.
    #[cfg_attr(feature = "clap", arg(long, allow_negative_numbers = true))]
    pub strength: Option<f32>,
    /// Position x,y,z in scene coordinates, metres (point, spot, area).
    #[cfg_attr(feature = "clap", arg(long, value_parser = parse_vec3, allow_hyphen_values = true,
          conflicts_with_all = ["at_pixel", "from", "azimuth", "elevation"]))]
    pub position: Option<[f32; 3]>,
    /// Direction the light travels x,y,z (spot, area, sun).
    #[cfg_attr(feature = "clap", arg(long, value_parser = parse_vec3, allow_hyphen_values = true, conflicts_with = "look_at"))]
    pub direction: Option<[f32; 3]>,
    /// Point to aim at x,y,z (spot, area).
    #[cfg_attr(feature = "clap", arg(long, value_parser = parse_vec3, allow_hyphen_values = true))]
    pub look_at: Option<[f32; 3]>,
    /// Linear RGB colour r,g,b.
    #[cfg_attr(feature = "clap", arg(long, value_parser = parse_rgb, conflicts_with = "temperature"))]
    pub color: Option<[f32; 3]>,
    /// Blackbody colour temperature in kelvin.
    #[cfg_attr(feature = "clap", arg(long))]
    pub temperature: Option<f32>,
    /// Radius in metres, for soft shadows (point, spot; default 0).
    #[cfg_attr(feature = "clap", arg(long))]
    pub radius: Option<f32>,
    /// Cone full angle in degrees (spot; default 45).
    #[cfg_attr(feature = "clap", arg(long))]
    pub spot_size: Option<f32>,
    /// Edge blend in [0, 1] (spot; default 0.15).
    #[cfg_attr(feature = "clap", arg(long))]
    pub blend: Option<f32>,
    /// Size (edge or diameter) in metres (area; default 1).
    #[cfg_attr(feature = "clap", arg(long))]
    pub size: Option<f32>,
    /// Second size for rectangle / ellipse (area).
    #[cfg_attr(feature = "clap", arg(long))]
    pub size_y: Option<f32>,
    /// Shape (area; default square).
    #[cfg_attr(feature = "clap", arg(long, value_parser = ["square", "rectangle", "disk", "ellipse"]))]
    pub shape: Option<String>,
    /// Angular diameter in degrees (sun; default 0.526).
    #[cfg_attr(feature = "clap", arg(long))]
    pub angle: Option<f32>,
    /// Camera rays see the emitter itself (area; point and spot with a --radius: their sphere;
    /// Blender's Ray Visibility ▸ Camera). Off by
    /// default, as in Blender: the light still lights the scene and shows in reflections.
    #[cfg_attr(feature = "clap", arg(long))]
    pub visible_to_camera: bool,
    /// Put the light off the surface seen through pixel X,Y of the camera image (point, spot, area).
    #[cfg_attr(feature = "clap", arg(long, value_name = "X,Y", value_parser = parse_pixel, conflicts_with_all = ["from", "azimuth", "elevation"]))]
    pub at_pixel: Option<[f32; 2]>,
    /// With --at-pixel: metres off the surface along its normal (default 0.15 x the scene bounds' diagonal).
    #[cfg_attr(feature = "clap", arg(long, allow_negative_numbers = true))]
    pub offset: Option<f32>,
    /// Light the scene from this side of the bounds' centre, as the camera sees it ("front" is
    /// the camera's side; "behind" is beyond the scene, a backlight: a reconstructed photo is one
    /// surface facing the camera, which a light behind it reaches only from the back).
    #[cfg_attr(feature = "clap", arg(long, value_parser = ["left", "right", "above", "below", "front", "behind"],
          conflicts_with = "azimuth"))]
    pub from: Option<String>,
    /// Degrees around the vertical from the camera's side: 0 front, 90 right, 180 behind, -90 left.
    #[cfg_attr(feature = "clap", arg(long, allow_negative_numbers = true))]
    pub azimuth: Option<f32>,
    /// Degrees above the level of the bounds' centre (90 straight above; default 0); with
    /// --from left|right|front|behind, raises that side's light.
    #[cfg_attr(feature = "clap", arg(long, allow_negative_numbers = true))]
    pub elevation: Option<f32>,
    /// With --from / --azimuth: metres from the bounds' centre (default 1.5 x its half-diagonal).
    #[cfg_attr(feature = "clap", arg(long))]
    pub distance: Option<f32>,
}

use LightType::{Area, Point, Spot, Sun};

impl LightSpec {
    /// The flags given, each with the light types it applies to.
    fn given(&self) -> Vec<(&'static str, &'static [LightType])> {
        let all: &'static [LightType] = &[Point, Spot, Area, Sun];
        let positioned: &'static [LightType] = &[Point, Spot, Area];
        let flags: [(&'static str, bool, &'static [LightType]); 22] = [
            ("--name", self.name.is_some(), all),
            ("--power", self.power.is_some(), positioned),
            ("--strength", self.strength.is_some(), &[Sun]),
            ("--position", self.position.is_some(), positioned),
            ("--direction", self.direction.is_some(), &[Spot, Area, Sun]),
            ("--look-at", self.look_at.is_some(), &[Spot, Area]),
            ("--color", self.color.is_some(), all),
            ("--temperature", self.temperature.is_some(), all),
            ("--radius", self.radius.is_some(), &[Point, Spot]),
            ("--spot-size", self.spot_size.is_some(), &[Spot]),
            ("--blend", self.blend.is_some(), &[Spot]),
            ("--size", self.size.is_some(), &[Area]),
            ("--size-y", self.size_y.is_some(), &[Area]),
            ("--shape", self.shape.is_some(), &[Area]),
            ("--angle", self.angle.is_some(), &[Sun]),
            ("--visible-to-camera", self.visible_to_camera, &[Point, Spot, Area]),
            ("--at-pixel", self.at_pixel.is_some(), positioned),
            ("--offset", self.offset.is_some(), positioned),
            ("--from", self.from.is_some(), all),
            ("--azimuth", self.azimuth.is_some(), all),
            ("--elevation", self.elevation.is_some(), all),
            ("--distance", self.distance.is_some(), positioned),
        ];
        flags.into_iter().filter(|f| f.1).map(|f| (f.0, f.2)).collect()
    }

    /// Whether any light flag was given (including `--type`).
    pub fn is_given(&self) -> bool {
        self.light_type.is_some() || !self.given().is_empty()
    }

    /// The light's type: `--type`, else point.
    pub fn kind(&self) -> LightType {
        self.light_type.unwrap_or(Point)
    }

    /// The checks that need no scene: flags that do not apply to the type, values out of range.
    pub fn check(&self) -> Result<()> {
        let t = self.kind();
        let typed = if self.light_type.is_some() {
            format!("--type {}", t.name())
        } else {
            "point, the default; give --type".to_string()
        };
        for (flag, applies) in self.given() {
            if !applies.contains(&t) {
                let kinds: Vec<&str> = applies.iter().map(|k| k.name()).collect();
                let kinds = match kinds.as_slice() {
                    [init @ .., last] if !init.is_empty() => format!("{} and {last}", init.join(", ")),
                    _ => kinds.join(""),
                };
                let why = if flag == "--visible-to-camera" {
                    " (a sun is never seen by the camera, as in Blender)"
                } else if flag == "--at-pixel" || flag == "--distance" || flag == "--offset" {
                    " (a sun has no position: use --from, --azimuth/--elevation or --direction)"
                } else {
                    ""
                };
                return Err(PipelineError::input(format!(
                    "{flag} is for {kinds} lights, and this is a {} light ({typed}){why}",
                    t.name()
                )));
            }
        }
        if self.offset.is_some() && self.at_pixel.is_none() {
            return Err(PipelineError::input(
                "--offset is the distance from the surface at --at-pixel X,Y; give --at-pixel too",
            ));
        }
        if self.distance.is_some() && self.from.is_none() && self.azimuth.is_none() && self.elevation.is_none() {
            return Err(PipelineError::input(
                "--distance is measured from the scene's centre for --from or --azimuth/--elevation; give one of them",
            ));
        }
        if let Some(p) = self.power {
            check_power("--power", p, "W", MAX_PLAUSIBLE_POWER)?;
        }
        if let Some(s) = self.strength {
            check_power("--strength", s, "W/m²", MAX_PLAUSIBLE_SUN)?;
        }
        if let Some(c) = self.color {
            if c.iter().any(|v| !v.is_finite() || *v < 0.0) {
                return Err(PipelineError::input(format!(
                    "--color {c:?}: values must be finite and non-negative"
                )));
            }
        }
        for (flag, v) in [
            ("--radius", self.radius),
            ("--distance", self.distance),
            ("--offset", self.offset),
            ("--azimuth", self.azimuth),
            ("--elevation", self.elevation),
        ] {
            if let Some(v) = v {
                if !v.is_finite() {
                    return Err(PipelineError::input(format!("{flag} {v}: must be a finite number")));
                }
            }
        }
        if let Some(r) = self.radius {
            if r < 0.0 {
                return Err(PipelineError::input(format!("--radius {r}: must be non-negative")));
            }
        }
        if self.visible_to_camera && t != LightType::Area && !self.radius.is_some_and(|r| r > 0.0) {
            return Err(PipelineError::input(format!(
                "--visible-to-camera on a {} light needs --radius R > 0 (the camera sees its sphere; a light without one has none)",
                t.name()
            )));
        }
        if let Some(d) = self.distance {
            if d <= 0.0 {
                return Err(PipelineError::input(format!("--distance {d}: must be positive")));
            }
        }
        if let Some(e) = self.elevation {
            if !(-90.0..=90.0).contains(&e) {
                return Err(PipelineError::input(format!(
                    "--elevation {e}: must be in [-90, 90] degrees"
                )));
            }
        }
        if t == Sun && self.direction.is_none() && !self.placed() {
            tracing::info!("a sun without --direction, --from or --azimuth shines straight down");
        }
        Ok(())
    }

    /// Whether the position (or a sun's direction) comes from --at-pixel, --from or --azimuth/--elevation.
    fn placed(&self) -> bool {
        self.at_pixel.is_some() || self.from.is_some() || self.azimuth.is_some() || self.elevation.is_some()
    }

    /// The light for `scene` (placement needs the scene's geometry and camera), and one line per
    /// decision made for the user (where a placed light went, a default power).
    pub fn build(&self, scene: &Scene) -> Result<(Light, Vec<String>)> {
        self.check()?;
        let t = self.kind();
        let mut notes = Vec::new();
        let color = match (self.color, self.temperature) {
            (_, Some(k)) => Color::Blackbody { kelvin: k },
            (Some(c), None) => Color::Rgb(c),
            (None, None) => Color::default(),
        };
        // Where the light is, and the point it aims at (for a default aim and power).
        let mut target: Option<[f32; 3]> = None;
        let mut sun_dir: Option<[f32; 3]> = None;
        let position: Option<[f32; 3]> = if let Some([x, y]) = self.at_pixel {
            let frame = SceneFrame::of(scene)?;
            let hit = pick_pixel(scene, x, y)?.ok_or_else(|| {
                PipelineError::input(format!(
                    "--at-pixel {x},{y}: the camera sees no surface there (only the background); pick a pixel on the scene"
                ))
            })?;
            let (offset, how) = match self.offset {
                Some(o) => (o, "--offset".to_string()),
                None => (
                    frame.default_offset(),
                    format!("default: 0.15 x the bounds' diagonal of {:.2} m", 2.0 * frame.radius),
                ),
            };
            let p = (V3::from_arr(hit.point) + V3::from_arr(hit.normal) * offset).to_arr();
            notes.push(format!(
                "{} light at pixel ({x}, {y}): the surface there is {:.2} m from the camera at {}; light {offset:.2} m off it along its normal ({how}), at {}",
                t.name(),
                hit.distance,
                fmt3(hit.point),
                fmt3(p)
            ));
            target = Some(hit.point);
            Some(p)
        } else if self.from.is_some() || self.azimuth.is_some() || self.elevation.is_some() {
            let frame = SceneFrame::of(scene)?;
            let (az, el, said) = match &self.from {
                Some(side) => {
                    let s = Side::parse(side)
                        .ok_or_else(|| PipelineError::input(format!("--from {side}: unknown side")))?;
                    let (az, el) = s.azimuth_elevation();
                    match self.elevation {
                        // A side seen from the camera, raised or lowered by --elevation.
                        Some(e) if el == 0.0 => (az, e, format!("from {side}, elevation {e}°")),
                        Some(_) => return Err(PipelineError::input(format!("--elevation: --from {side} already sets the elevation; use --from left|right|front|behind with --elevation, or --azimuth/--elevation"))),
                        None => (az, el, format!("from {side}")),
                    }
                }
                None => {
                    let (az, el) = (self.azimuth.unwrap_or(0.0), self.elevation.unwrap_or(0.0));
                    (az, el, format!("azimuth {az}°, elevation {el}°"))
                }
            };
            if frame.empty {
                notes.push("the scene has no objects: placing around a 1 m sphere 3 m in front of the camera".into());
            }
            target = Some(frame.centre);
            if t == Sun {
                sun_dir = Some((V3::from_arr(frame.toward(az, el)) * -1.0).to_arr());
                notes.push(format!(
                    "sun {said}: shining along {}",
                    fmt3(sun_dir.unwrap_or_default())
                ));
                None
            } else {
                let (d, how) = match self.distance {
                    Some(d) => (d, "--distance"),
                    None => (frame.default_distance(), "default: 1.5 x the bounds' half-diagonal"),
                };
                let p = frame.around(az, el, d);
                notes.push(format!(
                    "{} light {said}, {d:.2} m from the centre of the scene's bounds {} ({how}): at {}",
                    t.name(),
                    fmt3(frame.centre),
                    fmt3(p)
                ));
                Some(p)
            }
        } else {
            self.position
        };
        // Spot and area lights aim at the target unless told otherwise.
        let (direction, look_at) = match (self.direction, self.look_at, target) {
            (None, None, Some(tgt)) if matches!(t, Spot | Area) => (None, Some(tgt)),
            (d, l, _) => (d, l),
        };
        let distance = match (position, look_at.or(target)) {
            (Some(p), Some(q)) => Some((V3::from_arr(p) - V3::from_arr(q)).length()),
            _ => None,
        };
        let power = || -> Result<f32> {
            match (self.power, distance) {
                (Some(p), _) => Ok(p),
                (None, Some(d)) if self.placed() => {
                    let p = power_for_irradiance(t.emitter(), PLACED_IRRADIANCE, d);
                    Ok(p)
                }
                _ => Err(PipelineError::input(format!(
                    "--type {} needs --power WATTS (or a placement: --at-pixel, --from, --azimuth)",
                    t.name()
                ))),
            }
        };
        let need_pos = || {
            position.ok_or_else(|| {
                PipelineError::input(format!(
                    "--type {} needs --position x,y,z, --at-pixel X,Y, --from SIDE or --azimuth DEG",
                    t.name()
                ))
            })
        };
        let name = self.name.clone().unwrap_or_default();
        let light = match t {
            Point => Light::Point {
                name,
                position: need_pos()?,
                power: power()?,
                radius: self.radius.unwrap_or(0.0),
                color,
                visible_to_camera: self.visible_to_camera,
            },
            Spot => Light::Spot {
                name,
                position: need_pos()?,
                direction,
                look_at,
                power: power()?,
                spot_size_deg: self.spot_size.unwrap_or(45.0),
                blend: self.blend.unwrap_or(0.15),
                radius: self.radius.unwrap_or(0.0),
                color,
                visible_to_camera: self.visible_to_camera,
            },
            Area => Light::Area {
                name,
                position: need_pos()?,
                direction,
                look_at,
                shape: match self.shape.as_deref() {
                    Some("rectangle") => AreaShape::Rectangle,
                    Some("disk") => AreaShape::Disk,
                    Some("ellipse") => AreaShape::Ellipse,
                    _ => AreaShape::Square,
                },
                size: self.size.unwrap_or(1.0),
                size_y: self.size_y,
                power: power()?,
                color,
                visible_to_camera: self.visible_to_camera,
            },
            Sun => Light::Sun {
                name,
                direction: sun_dir.or(self.direction),
                strength: match self.strength {
                    Some(s) => s,
                    None if self.placed() => PLACED_IRRADIANCE,
                    None => return Err(PipelineError::input("--type sun needs --strength W/m2")),
                },
                angle_deg: self.angle.unwrap_or(0.526),
                color,
            },
        };
        if self.power.is_none() && self.strength.is_none() {
            match &light {
                Light::Sun { strength, .. } => notes.push(format!(
                    "strength {strength} W/m² (default for a placed sun; --strength to change)"
                )),
                Light::Point { power, .. } | Light::Spot { power, .. } | Light::Area { power, .. } => {
                    notes.push(format!(
                    "power {power:.1} W: {PLACED_IRRADIANCE} W/m² at the point it {} ({:.2} m away; --power to change)",
                    if matches!(t, Point) { "faces" } else { "aims at" },
                    distance.unwrap_or(0.0)
                ))
                }
            }
        }
        Ok((light, notes))
    }
}

/// Refuses non-finite and negative values; warns for 0 (an unlit light) and above `max`.
fn check_power(flag: &str, v: f32, unit: &str, max: f32) -> Result<()> {
    if !v.is_finite() || v < 0.0 {
        return Err(PipelineError::input(format!(
            "{flag} {v}: must be a finite, non-negative number of {unit}"
        )));
    }
    if v == 0.0 {
        tracing::warn!("{flag} 0: this light gives no light");
    } else if v > max {
        tracing::warn!(
            "{flag} {v} {unit} is implausibly bright (more than {max:e} {unit}); the render will be blown out unless the scene is huge"
        );
    }
    Ok(())
}

/// `(x, y, z)` with two decimals.
pub fn fmt3(v: [f32; 3]) -> String {
    format!("({:.2}, {:.2}, {:.2})", v[0], v[1], v[2])
}

/// Parses `n` comma-separated numbers, naming what they are (`x,y,z`, `r,g,b`, `X,Y`).
fn parse_n<const N: usize>(s: &str, names: &str, example: &str) -> Result<[f32; N], String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|t| {
            t.trim()
                .parse::<f32>()
                .map_err(|_| format!("{s:?} is not {names} (e.g. {example})"))
        })
        .collect::<Result<_, _>>()?;
    <[f32; N]>::try_from(v.as_slice()).map_err(|_| {
        format!(
            "{s:?} has {} value(s), expected {N} values {names} (e.g. {example})",
            v.len()
        )
    })
}

/// Parses `x,y,z`.
pub fn parse_vec3(s: &str) -> Result<[f32; 3], String> {
    parse_n::<3>(s, "x,y,z", "1,3,-0.5")
}

/// Parses `r,g,b`.
pub fn parse_rgb(s: &str) -> Result<[f32; 3], String> {
    parse_n::<3>(s, "r,g,b", "1,0.9,0.8")
}

/// Parses a pixel `X,Y` (non-negative).
pub fn parse_pixel(s: &str) -> Result<[f32; 2], String> {
    let p = parse_n::<2>(s, "X,Y", "320,140")?;
    if p.iter().any(|v| !v.is_finite() || *v < 0.0) {
        return Err(format!("{s:?}: pixel coordinates must be non-negative"));
    }
    Ok(p)
}

/// Parses one light given as the flags of `pixl light add` in one string (`--type spot --from
/// left --power 300`; what `pixl relight --light '…'` and a batch manifest hold), checked.
#[cfg(feature = "clap")]
pub fn parse_light_words(words: &str) -> Result<LightSpec> {
    #[derive(clap::Parser, Debug)]
    #[command(name = "--light", no_binary_name = true, disable_help_flag = true)]
    struct Words {
        #[command(flatten)]
        spec: LightSpec,
    }
    let parsed = <Words as clap::Parser>::try_parse_from(words.split_whitespace()).map_err(|e| {
        let text = e.render().to_string();
        let first = text.lines().next().unwrap_or("").trim_start_matches("error: ");
        PipelineError::input(format!("--light '{words}': {first}"))
    })?;
    if !parsed.spec.is_given() {
        return Err(PipelineError::input(format!(
            "--light '{words}': give the light's flags, e.g. '--type spot --from left'"
        )));
    }
    parsed
        .spec
        .check()
        .map_err(|e| e.context(format!("--light '{words}'")))?;
    Ok(parsed.spec)
}

/// The `[[lights]]` of a `.toml` or `.json` scene-like file (everything else in it ignored),
/// validated; positions in the reconstructed scene's frame.
pub fn read_lights_file(path: &std::path::Path) -> Result<Vec<Light>> {
    #[derive(serde::Deserialize)]
    struct LightsFile {
        #[serde(default)]
        lights: Vec<Light>,
    }
    let name = path.display();
    let text = std::fs::read_to_string(path).map_err(|e| PipelineError::io(path, e))?;
    let file: LightsFile = match pixl_core::io::extension(path).as_str() {
        "toml" => toml::from_str(&text).map_err(|e| PipelineError::input(format!("{name}: {e}")))?,
        "json" => serde_json::from_str(&text).map_err(|e| PipelineError::input(format!("{name}: {e}")))?,
        other => {
            return Err(PipelineError::input(format!(
                "{name}: a lights file must be .toml or .json, not {other:?}"
            )))
        }
    };
    if file.lights.is_empty() {
        return Err(PipelineError::input(format!("{name}: no [[lights]] in it")));
    }
    let mut probe = Scene::new(pixl_render::Camera::new(1, 1, 50.0));
    probe.lights = file.lights.clone();
    probe
        .validate()
        .map_err(|e| PipelineError::input(format!("{name}: {}", e.to_string().trim_start_matches("<scene>: "))))?;
    Ok(file.lights)
}
