//! The lights as the page edits them ([`StudioLight`]) and their translation to the scene
//! format's [`pixl_render::Light`] (and back, for presets and loaded scene files).
//!
//! A light is usually *anchored* to a point of the photo: `anchor = [u, v]` (fractions of the
//! image's width and height from the top-left corner). The surface seen there (a ray of the
//! coarse scene's camera) gives a point `p` and a normal `n` facing the camera; the light sits
//! at `p + distance · n`. Spot and area lights aim back at `p` (they light the spot that was
//! clicked), a sun travels along `−n`. Where the ray sees no surface, the surface point is taken
//! `2 × distance` along the camera ray, facing the camera. Without an anchor, `position` and
//! `direction` are used as given (presets, lights from scene files, scripts).
//!
//! Units are the scene format's (`pixl_render::scene`): `power` is watts for point, spot and
//! area lights, the irradiance in W/m² (Blender's strength) for a sun, and the radiance
//! multiplier of the world colour for an environment light. `size` is the sphere radius (m) of
//! point and spot lights, the edge (m) of a square area light, and the angular diameter (°) of a
//! sun. Environment lights have no position: every enabled one adds `power × colour` to the
//! world's radiance.
use crate::error::{Result, StudioError};
use pixl_render::scene::{AreaShape, Color, Light, World};
use serde::{Deserialize, Serialize};

/// The kinds of light the page offers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LightKind {
    Point,
    Spot,
    Area,
    Sun,
    Environment,
}

/// One light of the session.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StudioLight {
    /// Assigned by the session; unique within it.
    pub id: u64,
    pub name: String,
    pub kind: LightKind,
    pub enabled: bool,
    /// The photo point the light is attached to (`[u, v]` in `[0, 1]²`), if any.
    pub anchor: Option<[f32; 2]>,
    /// Metres from the anchored surface point along its normal.
    pub distance: f32,
    /// World position (derived from the anchor when there is one).
    pub position: [f32; 3],
    /// Unit direction the light travels (spot, area, sun).
    pub direction: [f32; 3],
    pub color: Color,
    pub power: f32,
    pub size: f32,
    /// Spot cone, full angle in degrees, and its edge softness in `[0, 1]`.
    pub spot_deg: f32,
    pub blend: f32,
}

/// A partial update: every field that is present replaces the light's.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightPatch {
    pub name: Option<String>,
    pub kind: Option<LightKind>,
    pub enabled: Option<bool>,
    /// `[u, v]` to anchor (or move) the light; `null` is not accepted (give `position` to detach).
    pub anchor: Option<[f32; 2]>,
    pub distance: Option<f32>,
    /// An explicit position; detaches the light from its anchor.
    pub position: Option<[f32; 3]>,
    pub direction: Option<[f32; 3]>,
    pub color: Option<Color>,
    pub power: Option<f32>,
    pub size: Option<f32>,
    pub spot_deg: Option<f32>,
    pub blend: Option<f32>,
    /// Merge this change into the previous undo step when that step changed the same light
    /// (what the page sends while dragging or moving a slider).
    #[serde(default)]
    pub coalesce: bool,
}

impl LightKind {
    /// Defaults for a new light of this kind at `distance` metres from what it lights, in a
    /// scene of bounding radius `radius`: point and spot lights give about 4 W/m² at that
    /// distance (the presets' flashes), area lights the same on their axis.
    pub fn defaults(self, distance: f32, radius: f32) -> StudioLight {
        use pixl_render::placement::{power_for_irradiance, Emitter};
        let (power, size, color) = match self {
            LightKind::Point => (
                power_for_irradiance(Emitter::Point, 4.0, distance),
                0.03 * radius,
                Color::Blackbody { kelvin: 4500.0 },
            ),
            LightKind::Spot => (
                power_for_irradiance(Emitter::Spot, 4.0, distance),
                0.02 * radius,
                Color::Blackbody { kelvin: 4000.0 },
            ),
            LightKind::Area => (
                power_for_irradiance(Emitter::Area, 4.0, distance),
                0.25 * radius,
                Color::Blackbody { kelvin: 5000.0 },
            ),
            LightKind::Sun => (3.0, 2.0, Color::Blackbody { kelvin: 5500.0 }),
            LightKind::Environment => (1.0, 0.0, Color::Rgb([0.15, 0.15, 0.18])),
        };
        StudioLight {
            id: 0,
            name: String::new(),
            kind: self,
            enabled: true,
            anchor: None,
            distance,
            position: [0.0, 0.0, 0.0],
            direction: [0.0, -1.0, 0.0],
            color,
            power,
            size,
            spot_deg: 45.0,
            blend: 0.15,
        }
    }
}

fn finite(v: &[f32], what: &str) -> Result<()> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(StudioError::BadRequest(format!(
            "{what} must be finite numbers, got {v:?}"
        )))
    }
}

fn normalize(d: [f32; 3]) -> Option<[f32; 3]> {
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    (l.is_finite() && l > 1e-9).then(|| d.map(|c| c / l))
}

impl StudioLight {
    /// Applies `patch` (values checked; the anchor is not resolved here, see
    /// [`StudioLight::resolve`]).
    pub fn apply(&mut self, patch: &LightPatch) -> Result<()> {
        let bad = |m: String| Err(StudioError::BadRequest(m));
        if let Some(n) = &patch.name {
            if n.len() > 200 {
                return bad("a light's name is at most 200 bytes".into());
            }
            self.name = n.clone();
        }
        if let Some(k) = patch.kind {
            self.kind = k;
        }
        if let Some(e) = patch.enabled {
            self.enabled = e;
        }
        if let Some(a) = patch.anchor {
            finite(&a, "anchor")?;
            if !a.iter().all(|c| (0.0..=1.0).contains(c)) {
                return bad(format!("anchor {a:?} is outside the image ([u, v] in [0, 1])"));
            }
            self.anchor = Some(a);
        }
        if let Some(d) = patch.distance {
            if !(d.is_finite() && (0.0..=1.0e4).contains(&d)) {
                return bad(format!("distance {d} must be in [0, 10000] m"));
            }
            self.distance = d;
        }
        if let Some(p) = patch.position {
            finite(&p, "position")?;
            self.position = p;
            self.anchor = None;
        }
        if let Some(d) = patch.direction {
            finite(&d, "direction")?;
            self.direction =
                normalize(d).ok_or_else(|| StudioError::BadRequest("direction is the zero vector".into()))?;
        }
        if let Some(c) = patch.color {
            self.color = c;
        }
        if let Some(p) = patch.power {
            if !(p.is_finite() && p >= 0.0) {
                return bad(format!("power {p} must be finite and non-negative"));
            }
            self.power = p;
        }
        if let Some(s) = patch.size {
            if !(s.is_finite() && s >= 0.0) {
                return bad(format!("size {s} must be finite and non-negative"));
            }
            self.size = s;
        }
        if let Some(s) = patch.spot_deg {
            if !(s.is_finite() && s > 0.0 && s <= 180.0) {
                return bad(format!("spot_deg {s} must be in (0, 180]"));
            }
            self.spot_deg = s;
        }
        if let Some(b) = patch.blend {
            if !(b.is_finite() && (0.0..=1.0).contains(&b)) {
                return bad(format!("blend {b} must be in [0, 1]"));
            }
            self.blend = b;
        }
        // The scene format's own checks (colour range, sizes), on the light as it now is.
        if let Some(l) = self.to_render() {
            let mut probe = pixl_render::Scene::new(pixl_render::Camera::new(1, 1, 50.0));
            probe.lights.push(l);
            probe.validate().map_err(|e| StudioError::BadRequest(e.to_string()))?;
        } else if let Color::Rgb(c) = self.color {
            finite(&c, "color")?;
            if c.iter().any(|v| *v < 0.0) {
                return bad(format!("color {c:?} must be non-negative"));
            }
        }
        Ok(())
    }

    /// Recomputes `position` (and `direction` for spot, area and sun) from the anchor through
    /// `pick` (surface point and camera-facing normal at `[u, v]`) or, where it sees nothing,
    /// `along_ray` (a point at a distance along the camera ray and the direction back to the
    /// camera). No-op without an anchor.
    pub fn resolve(
        &mut self,
        pick: impl Fn(f32, f32) -> Option<([f32; 3], [f32; 3])>,
        along_ray: impl Fn(f32, f32, f32) -> ([f32; 3], [f32; 3]),
    ) {
        let Some([u, v]) = self.anchor else { return };
        let (p, n) = pick(u, v).unwrap_or_else(|| along_ray(u, v, 2.0 * self.distance.max(1e-3)));
        self.position = [0, 1, 2].map(|i| p[i] + self.distance * n[i]);
        self.direction = n.map(|c| -c);
    }

    /// The light in the scene format, `None` for environment lights and disabled lights.
    pub fn to_render(&self) -> Option<Light> {
        if !self.enabled {
            return None;
        }
        let name = if self.name.is_empty() {
            format!("light{}", self.id)
        } else {
            self.name.clone()
        };
        Some(match self.kind {
            LightKind::Point => Light::Point {
                name,
                position: self.position,
                power: self.power,
                radius: self.size,
                color: self.color,
                visible_to_camera: false,
            },
            LightKind::Spot => Light::Spot {
                name,
                position: self.position,
                direction: Some(self.direction),
                look_at: None,
                power: self.power,
                spot_size_deg: self.spot_deg,
                blend: self.blend,
                radius: self.size,
                color: self.color,
                visible_to_camera: false,
            },
            LightKind::Area => Light::Area {
                name,
                position: self.position,
                direction: Some(self.direction),
                look_at: None,
                shape: AreaShape::Square,
                size: self.size.max(1e-4),
                size_y: None,
                power: self.power,
                color: self.color,
                visible_to_camera: false,
            },
            LightKind::Sun => Light::Sun {
                name,
                direction: Some(self.direction),
                strength: self.power,
                angle_deg: self.size.min(180.0),
                color: self.color,
            },
            LightKind::Environment => return None,
        })
    }

    /// A light of the scene format as an unanchored studio light.
    pub fn from_render(l: &Light, distance: f32) -> StudioLight {
        let dir = l.direction().unwrap_or([0.0, -1.0, 0.0]);
        let mut s = match l {
            Light::Point {
                position,
                power,
                radius,
                ..
            } => StudioLight {
                position: *position,
                power: *power,
                size: *radius,
                ..LightKind::Point.defaults(distance, 1.0)
            },
            Light::Spot {
                position,
                power,
                spot_size_deg,
                blend,
                radius,
                ..
            } => StudioLight {
                position: *position,
                power: *power,
                size: *radius,
                spot_deg: *spot_size_deg,
                blend: *blend,
                ..LightKind::Spot.defaults(distance, 1.0)
            },
            Light::Area { position, power, .. } => StudioLight {
                position: *position,
                power: *power,
                // Non-square shapes keep their area.
                size: l.area_size().map(|(a, b)| (a * b).sqrt()).unwrap_or(1.0),
                ..LightKind::Area.defaults(distance, 1.0)
            },
            Light::Sun {
                strength, angle_deg, ..
            } => StudioLight {
                power: *strength,
                size: *angle_deg,
                ..LightKind::Sun.defaults(distance, 1.0)
            },
        };
        s.name = l.name().to_string();
        s.color = l.color();
        s.direction = dir;
        s
    }
}

/// The world that the enabled environment lights make (`None` when there are none: the coarse
/// scene's own world is kept). Colours are summed as linear RGB, `power` times `color`.
pub fn environment(lights: &[StudioLight]) -> Option<World> {
    let envs: Vec<&StudioLight> = lights
        .iter()
        .filter(|l| l.enabled && l.kind == LightKind::Environment)
        .collect();
    if envs.is_empty() {
        return None;
    }
    let mut c = [0.0f32; 3];
    for l in envs {
        let rgb = l.color.rgb();
        for i in 0..3 {
            c[i] += l.power * rgb[i];
        }
    }
    Some(World {
        color: Color::Rgb(c),
        strength: 1.0,
        image: None,
        rotation_deg: 0.0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn anchored_light_sits_along_the_normal_and_aims_back() {
        let mut l = LightKind::Spot.defaults(0.5, 1.0);
        l.anchor = Some([0.5, 0.5]);
        l.resolve(
            |_, _| Some(([1.0, 2.0, -3.0], [0.0, 0.0, 1.0])),
            |_, _, _| unreachable!(),
        );
        assert_eq!(l.position, [1.0, 2.0, -2.5]);
        assert_eq!(l.direction, [0.0, 0.0, -1.0]);
        match l.to_render() {
            Some(Light::Spot { direction, .. }) => assert_eq!(direction, Some([0.0, 0.0, -1.0])),
            other => panic!("{other:?}"),
        }
        // Nothing under the anchor: along the ray at twice the distance, then back by the distance.
        l.resolve(|_, _| None, |_, _, t| ([0.0, 0.0, -t], [0.0, 0.0, 1.0]));
        assert_eq!(l.position, [0.0, 0.0, -0.5]);
    }

    #[test]
    fn patches_are_checked() {
        let mut l = LightKind::Point.defaults(1.0, 1.0);
        for bad in [
            r#"{"power": -1}"#,
            r#"{"anchor": [1.5, 0.2]}"#,
            r#"{"color": {"kelvin": 100}}"#,
            r#"{"spot_deg": 0}"#,
            r#"{"direction": [0, 0, 0]}"#,
        ] {
            let p: LightPatch = serde_json::from_str(bad).unwrap();
            assert!(l.clone().apply(&p).is_err(), "{bad}");
        }
        assert!(serde_json::from_str::<LightPatch>(r#"{"powr": 1}"#).is_err());
        let p: LightPatch = serde_json::from_str(r#"{"power": 7, "color": [1, 0.5, 0.25]}"#).unwrap();
        l.apply(&p).unwrap();
        assert_eq!((l.power, l.color), (7.0, Color::Rgb([1.0, 0.5, 0.25])));
    }

    #[test]
    fn environment_sums_enabled_colours() {
        let mut a = LightKind::Environment.defaults(1.0, 1.0);
        a.color = Color::Rgb([0.1, 0.2, 0.3]);
        a.power = 2.0;
        let mut b = a.clone();
        b.enabled = false;
        assert_eq!(
            environment(&[a.clone(), b]).map(|w| w.color),
            Some(Color::Rgb([0.2, 0.4, 0.6]))
        );
        assert!(environment(&[]).is_none());
    }
}
