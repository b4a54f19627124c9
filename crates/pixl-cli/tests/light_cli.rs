//! `pixl light add`: camera visibility of area lights (Blender's Ray Visibility ▸ Camera).
mod common;
use common::{cmd, run, write_file};

const SCENE: &str = r#"
[camera]
width = 8
height = 6
fov_y_deg = 40.0
"#;

fn area_visibility(scene: &pixl_render::Scene) -> Vec<bool> {
    scene
        .lights
        .iter()
        .map(|l| match l {
            pixl_render::scene::Light::Area { visible_to_camera, .. } => *visible_to_camera,
            other => panic!("expected an area light, got {other:?}"),
        })
        .collect()
}

#[test]
fn area_lights_are_seen_by_the_camera_only_when_asked() {
    let dir = common::tempdir();
    let scene = write_file(&dir.path().join("scene.toml"), SCENE);
    // `pixl light add` of `flags` and `--visible-to-camera` if `visible`, into `name`.
    let add = |flags: &str, visible: bool, name: &str| {
        let out = dir.path().join(name);
        let mut c = cmd();
        c.args(["light", "add"]).arg(&scene).args(flags.split_whitespace());
        if visible {
            c.arg("--visible-to-camera");
        }
        (run(c.arg("-o").arg(&out)), out)
    };
    let area = "--type area --power 100 --position 0,3,0";
    // Default: off (Blender's default), and not written to the file.
    add(area, false, "plain.toml").0.ok();
    let text = std::fs::read_to_string(dir.path().join("plain.toml")).unwrap();
    assert!(!text.contains("visible_to_camera"), "{text}");
    let plain = pixl_render::Scene::load(&dir.path().join("plain.toml")).unwrap();
    assert_eq!(area_visibility(&plain), [false]);
    // Asked for: on, and it survives a save/load round trip.
    add(area, true, "seen.toml").0.ok();
    let seen = pixl_render::Scene::load(&dir.path().join("seen.toml")).unwrap();
    assert_eq!(area_visibility(&seen), [true]);
    // A point light's sphere can be seen too (it needs a radius); a sun never is: the flag is
    // refused, nothing written.
    let (o, out) = add(
        "--type point --power 10 --position 0,1,0 --radius 0.1",
        true,
        "point.toml",
    );
    o.ok();
    let seen = pixl_render::Scene::load(&out).unwrap();
    assert!(matches!(
        seen.lights.as_slice(),
        [pixl_render::scene::Light::Point {
            visible_to_camera: true,
            ..
        }]
    ));
    for (flags, name, why) in [
        ("--type point --power 10 --position 0,1,0", "bare.toml", "radius"),
        ("--type sun --strength 3", "sun.toml", "sun"),
    ] {
        let (o, out) = add(flags, true, name);
        assert!(!o.success());
        let err = &o.stderr;
        assert!(err.contains("--visible-to-camera") && err.contains(why), "{err}");
        assert!(!out.exists());
    }
}

/// A 4 m x 3 m wall 3 m in front of a camera at the origin looking down -Z (the frame of a scene
/// from `pixl reconstruct`), 40 x 30 pixels, 60° vertical field of view.
const WALL: &str = r#"
[camera]
width = 40
height = 30
fov_y_deg = 60.0

[[objects]]
name = "wall"
shape = { type = "quad", size = [4.0, 3.0] }
transform = { translate = [0.0, 0.0, -3.0] }
"#;

/// Runs `pixl light add` on the wall scene with `flags` (split at white space), returning (exit
/// code, stdout, stderr, the lights written).
fn add_to_wall(flags: &str) -> (Option<i32>, String, String, Vec<pixl_render::Light>) {
    let dir = common::tempdir();
    let scene = write_file(&dir.path().join("scene.toml"), WALL);
    let out = dir.path().join("lit.toml");
    let o = run(cmd()
        .args(["light", "add"])
        .arg(&scene)
        .args(flags.split_whitespace())
        .arg("-o")
        .arg(&out));
    let lights = if out.exists() {
        pixl_render::Scene::load(&out).unwrap().lights
    } else {
        Vec::new()
    };
    (o.code(), o.stdout, o.stderr, lights)
}

fn close(a: [f32; 3], b: [f32; 3], tol: f32) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
}

#[test]
fn at_pixel_puts_the_light_off_the_surface_seen_through_the_pixel() {
    use pixl_render::Light;
    // The image centre sees the wall's centre (0, 0, -3), normal +Z; the default offset is 0.15 x
    // the bounds' diagonal (5 m) = 0.75 m; the default power gives 4 W/m² there: 4π·4·0.75².
    let (code, stdout, stderr, lights) = add_to_wall("--type point --at-pixel 20,15");
    assert_eq!(code, Some(0), "{stderr}");
    match &lights[..] {
        [Light::Point { position, power, .. }] => {
            assert!(close(*position, [0.0, 0.0, -2.25], 1e-4), "{position:?}");
            let want = 4.0 * std::f32::consts::PI * 4.0 * 0.75 * 0.75;
            assert!((power - want).abs() < 1e-3 * want, "{power} vs {want}");
        }
        other => panic!("{other:?}"),
    }
    assert!(
        stdout.contains("0.15 x the bounds' diagonal") && stdout.contains("W/m²"),
        "{stdout}"
    );
    // An off-centre pixel, an explicit offset; a spot there aims at the picked point.
    let f = 15.0 / 30f32.to_radians().tan();
    let hit = [3.0 * 10.5 / f, 3.0 * 9.5 / f, -3.0];
    let (code, _, stderr, lights) = add_to_wall("--type spot --at-pixel 30.5,5.5 --offset 0.5 --power 100");
    assert_eq!(code, Some(0), "{stderr}");
    match &lights[..] {
        [Light::Spot {
            position,
            look_at: Some(t),
            power,
            ..
        }] => {
            assert!(close(*t, hit, 1e-3), "{t:?} vs {hit:?}");
            assert!(close(*position, [hit[0], hit[1], -2.5], 1e-3), "{position:?}");
            assert_eq!(*power, 100.0);
        }
        other => panic!("{other:?}"),
    }
    // A pixel that sees only the background, and one outside the image.
    let (code, _, stderr, _) = add_to_wall("--type point --at-pixel 0.5,15");
    assert_eq!(code, Some(1));
    assert!(stderr.contains("no surface"), "{stderr}");
    let (code, _, stderr, _) = add_to_wall("--type point --at-pixel 45,3");
    assert_eq!(code, Some(1));
    assert!(stderr.contains("outside the 40x30 image"), "{stderr}");
}

#[test]
fn from_and_azimuth_place_lights_around_the_scene_bounds() {
    use pixl_render::Light;
    // Bounds centre (0, 0, -3), half-diagonal 2.5 m: default distance 3.75 m.
    let (code, stdout, stderr, lights) = add_to_wall("--type spot --from left --power 100");
    assert_eq!(code, Some(0), "{stderr}");
    match &lights[..] {
        [Light::Spot {
            position,
            look_at: Some(t),
            ..
        }] => {
            assert!(close(*position, [-3.75, 0.0, -3.0], 1e-4), "{position:?}");
            assert!(close(*t, [0.0, 0.0, -3.0], 1e-5));
        }
        other => panic!("{other:?}"),
    }
    assert!(stdout.contains("from left"), "{stdout}");
    // Azimuth 90 (right), elevation 30, 2 m: by hand.
    let (code, _, stderr, lights) = add_to_wall("--type point --azimuth 90 --elevation 30 --distance 2 --power 10");
    assert_eq!(code, Some(0), "{stderr}");
    let e = 30f32.to_radians();
    match &lights[..] {
        [Light::Point { position, .. }] => {
            assert!(
                close(*position, [2.0 * e.cos(), 2.0 * e.sin(), -3.0], 1e-4),
                "{position:?}"
            )
        }
        other => panic!("{other:?}"),
    }
    // --from left raised by --elevation 30, 2 m: by hand, mirrored from the case above.
    let (code, stdout, stderr, lights) = add_to_wall("--type point --from left --elevation 30 --distance 2 --power 10");
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stdout.contains("from left, elevation 30"), "{stdout}");
    assert!(
        matches!(&lights[..], [Light::Point { position, .. }] if close(*position, [-2.0 * e.cos(), 2.0 * e.sin(), -3.0], 1e-4)),
        "{lights:?}"
    );
    // Above already is an elevation.
    let (code, _, stderr, lights) = add_to_wall("--type point --from above --elevation 30 --power 10");
    assert_eq!(code, Some(1));
    assert!(stderr.contains("--from above already sets the elevation"), "{stderr}");
    assert!(lights.is_empty());
    // "front" is the camera's side; "behind" the far side of the scene.
    let (_, _, _, lights) = add_to_wall("--type point --from front --distance 1 --power 10");
    assert!(matches!(&lights[..], [Light::Point { position, .. }] if close(*position, [0.0, 0.0, -2.0], 1e-5)));
    let (_, _, _, lights) = add_to_wall("--type point --from behind --distance 1 --power 10");
    assert!(matches!(&lights[..], [Light::Point { position, .. }] if close(*position, [0.0, 0.0, -4.0], 1e-5)));
    // A sun from above shines straight down, at the default 4 W/m².
    let (code, _, stderr, lights) = add_to_wall("--type sun --from above");
    assert_eq!(code, Some(0), "{stderr}");
    match &lights[..] {
        [Light::Sun {
            direction: Some(d),
            strength,
            ..
        }] => {
            assert!(close(*d, [0.0, -1.0, 0.0], 1e-5), "{d:?}");
            assert_eq!(*strength, 4.0);
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn flags_that_do_not_fit_the_light_are_refused_and_nothing_is_written() {
    for (flags, want) in [
        (
            "--type point --power 10 --position 0,1,0 --spot-size 30",
            "--spot-size is for spot lights",
        ),
        (
            "--type point --power 10 --position 0,1,0 --size 2",
            "--size is for area lights",
        ),
        ("--type sun --strength 3 --angle 1 --power 5", "--power is for point"),
        ("--type sun --at-pixel 20,15", "a sun has no position"),
        (
            "--type spot --power 10 --position 0,1,0 --angle 2",
            "--angle is for sun lights",
        ),
        ("--spot-size 30 --position 0,1,0 --power 1", "the default; give --type"),
        ("--type point --power nan --position 0,1,0", "finite, non-negative"),
        ("--type point --power -3 --position 0,1,0", "finite, non-negative"),
        ("--type point --position 0,1,0", "needs --power"),
        (
            "--type point --power 1 --position 0,1,0 --color 1,0",
            "expected 3 values r,g,b",
        ),
        ("--type point --power 1 --position 0,1", "expected 3 values x,y,z"),
        ("--type point --power 1 --elevation 120", "[-90, 90]"),
        ("--preset cool-side-flash --power 5", "either --preset"),
        (
            "--type point --power 1 --position 0,1,0 --offset 1",
            "give --at-pixel too",
        ),
        (
            "--type point --power 1 --position 0,1,0 --distance 1",
            "give one of them",
        ),
    ] {
        let (code, _, stderr, lights) = add_to_wall(flags);
        assert_ne!(code, Some(0), "{flags:?} should fail");
        assert!(stderr.contains(want), "{flags:?}: {stderr}");
        assert!(lights.is_empty(), "{flags:?} wrote a scene");
    }
    // Placements exclude each other (clap: exit 2).
    for flags in [
        "--type point --power 1 --position 0,1,0 --from left",
        "--type point --power 1 --at-pixel 3,3 --azimuth 10",
        "--type point --power 1 --from left --azimuth 10",
    ] {
        let (code, _, _, lights) = add_to_wall(flags);
        assert_eq!(code, Some(2), "{flags:?}");
        assert!(lights.is_empty());
    }
    // Implausible power: a warning, not an error.
    let (code, _, stderr, lights) = add_to_wall("--type point --power 2e6 --position 0,1,0");
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stderr.contains("implausibly bright"), "{stderr}");
    assert_eq!(lights.len(), 1);
}

#[test]
fn scene_info_reports_bounds_camera_axes_and_lights() {
    let dir = common::tempdir();
    let scene = write_file(&dir.path().join("scene.toml"), WALL);
    run(cmd()
        .args(["light", "add"])
        .arg(&scene)
        .args(["--type", "spot", "--from", "above", "--power", "40", "--name", "top"]))
    .ok();
    let v = run(cmd().args(["scene", "info"]).arg(&scene).arg("--json")).ok().json();
    let arr =
        |x: &serde_json::Value| -> Vec<f64> { x.as_array().unwrap().iter().map(|n| n.as_f64().unwrap()).collect() };
    assert_eq!(arr(&v["bounds"]["min"]), [-2.0, -1.5, -3.0]);
    assert_eq!(arr(&v["bounds"]["max"]), [2.0, 1.5, -3.0]);
    assert_eq!(arr(&v["bounds"]["centre"]), [0.0, 0.0, -3.0]);
    assert!((v["bounds"]["half_diagonal"].as_f64().unwrap() - 2.5).abs() < 1e-6);
    assert_eq!(v["camera"]["width"], 40);
    assert!((v["camera"]["fov_y_deg"].as_f64().unwrap() - 60.0).abs() < 1e-3);
    assert_eq!(arr(&v["camera"]["forward"]), [0.0, 0.0, -1.0]);
    assert_eq!(arr(&v["camera"]["right"]), [1.0, 0.0, 0.0]);
    assert_eq!(v["units"], "metres");
    assert!(v["axes"]["camera"].as_str().unwrap().contains("-Z forward"));
    let lights = v["lights"].as_array().unwrap();
    assert_eq!(lights.len(), 1);
    assert_eq!(lights[0]["type"], "spot");
    assert_eq!(lights[0]["name"], "top");
    assert!((lights[0]["position"][1].as_f64().unwrap() - 3.75).abs() < 1e-4);
    // Text form: the same facts, in words.
    let text = run(cmd().args(["scene", "info"]).arg(&scene)).stdout;
    assert!(
        text.contains("+Y up") && text.contains("bounds: min (-2.00, -1.50, -3.00)") && text.contains("spot 40.0 W"),
        "{text}"
    );
}
