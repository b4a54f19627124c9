//! `pixl light add`: camera visibility of area lights (Blender's Ray Visibility ▸ Camera).
use std::process::Command;

fn pixl() -> Command {
    Command::new(env!("CARGO_BIN_EXE_pixl"))
}

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
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene.toml");
    std::fs::write(&scene, SCENE).unwrap();
    let add = |extra: &[&str], out: &str| {
        pixl()
            .args(["light", "add"])
            .arg(&scene)
            .args(["--type", "area", "--power", "100", "--position", "0,3,0"])
            .args(extra)
            .arg("-o")
            .arg(dir.path().join(out))
            .output()
            .unwrap()
    };
    // Default: off (Blender's default), and not written to the file.
    let o = add(&[], "plain.toml");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = std::fs::read_to_string(dir.path().join("plain.toml")).unwrap();
    assert!(!text.contains("visible_to_camera"), "{text}");
    let plain = pixl_render::Scene::load(&dir.path().join("plain.toml")).unwrap();
    assert_eq!(area_visibility(&plain), [false]);
    // Asked for: on, and it survives a save/load round trip.
    let o = add(&["--visible-to-camera"], "seen.toml");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let seen = pixl_render::Scene::load(&dir.path().join("seen.toml")).unwrap();
    assert_eq!(area_visibility(&seen), [true]);
    // Other light types are never seen by the camera: the flag is refused, nothing written.
    let out = dir.path().join("point.toml");
    let o = pixl()
        .args(["light", "add"])
        .arg(&scene)
        .args([
            "--type",
            "point",
            "--power",
            "10",
            "--position",
            "0,1,0",
            "--visible-to-camera",
            "-o",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--visible-to-camera") && err.contains("area"), "{err}");
    assert!(!out.exists());
}
