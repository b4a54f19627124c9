//! The Blender bridge: the generated script is valid Python (checked with `python3 -m py_compile`
//! when python3 exists), enables exactly the passes, and its data folder holds meshes that read
//! back as the native renderer's tessellation.
use pixl_render::blender::{export_blender, PASS_TOGGLES};
use pixl_render::Scene;

const SCENE: &str = r#"
[camera]
width = 32
height = 24
fov_y_deg = 40.0
position = [0.0, 1.0, 4.0]
look_at = [0.0, 0.5, 0.0]
dof = { focus_distance = 3.5, aperture_fstop = 2.8 }

[[objects]]
name = "floor's quad"
shape = { type = "quad", size = [4.0, 4.0] }
transform = { rotate_deg = [-90.0, 0.0, 0.0] }
material = { base_color = { kelvin = 3000 }, roughness = 0.6 }

[[objects]]
shape = { type = "sphere", radius = 0.5 }
material = { metallic = 1.0, roughness = 0.2, emission_strength = 2.0 }

[[lights]]
type = "area"
position = [0.0, 3.0, 0.0]
shape = "rectangle"
size = 1.0
size_y = 0.5
power = 100.0
visible_to_camera = true

[[lights]]
type = "sun"
direction = [0.3, -1.0, 0.2]
strength = 2.0

[[lights]]
type = "spot"
position = [1.0, 2.0, 1.0]
look_at = [0.0, 0.0, 0.0]
power = 50.0

[[lights]]
type = "point"
position = [-1.0, 2.0, 1.0]
power = 30.0
radius = 0.2
visible_to_camera = true

[world]
color = [0.1, 0.1, 0.1]
"#;

#[test]
fn script_is_valid_python_with_exactly_the_passes() {
    let dir = tempfile::tempdir().unwrap();
    let scene = Scene::from_toml_str(SCENE).unwrap();
    let script = dir.path().join("scene.py");
    let e = export_blender(&scene, &script).unwrap();
    assert_eq!(e.meshes, 2);
    let text = std::fs::read_to_string(&script).unwrap();
    for p in PASS_TOGGLES {
        assert!(text.contains(&format!("\"{p}\"")), "pass {p} not enabled");
    }
    assert!(text.contains("use_pass_volume_direct = True") && text.contains("use_pass_volume_indirect = True"));
    assert!(text.contains("use_denoising = False") && text.contains("c.device = \"CPU\""));
    assert!(text.contains("OPEN_EXR_MULTILAYER"));
    // Exactly 14 + 2 toggles: no denoising data or other passes.
    assert_eq!(PASS_TOGGLES.len(), 14);
    assert!(text.contains("denoising_store_passes = False"));
    // The embedded scene parses as JSON and carries the lights' Blender types and units.
    let start = text.find("json.loads(r'''").unwrap() + "json.loads(r'''".len();
    let end = start + text[start..].find("''')").unwrap();
    let desc: serde_json::Value = serde_json::from_str(&text[start..end]).unwrap();
    let types: Vec<&str> = desc["lights"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["type"].as_str().unwrap())
        .collect();
    assert_eq!(types, ["AREA", "SUN", "SPOT", "POINT"]);
    assert_eq!(desc["lights"][0]["energy"], 100.0);
    // Camera visibility: the area and point lights asked for it; the script sets it on every
    // light object (off unless asked, Blender 4/5's default too).
    assert_eq!(desc["lights"][0]["visible_camera"], true);
    assert!(desc["lights"][1].get("visible_camera").is_none());
    assert_eq!(desc["lights"][2]["visible_camera"], false);
    assert_eq!(desc["lights"][3]["visible_camera"], true);
    assert_eq!(desc["lights"][3]["radius"], 0.2f32 as f64);
    assert!(text.contains("ob.visible_camera = bool(l.get(\"visible_camera\", False))"));
    assert_eq!(desc["objects"][0]["name"], "floor's quad");
    // Depth of field: Blender's own settings, switched on only when the scene has them.
    assert_eq!(desc["camera"]["dof"]["focus_distance"], 3.5);
    assert_eq!(desc["camera"]["dof"]["aperture_fstop"], 2.8f32 as f64);
    assert!(text.contains("data.dof.use_dof = dof is not None"));
    // Light frames: local −Z is the direction of travel (sun (0.3, −1, 0.2) normalised).
    let m = &desc["lights"][1]["matrix"];
    let d = [0.3f64, -1.0, 0.2];
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    for r in 0..3 {
        let z = m[r][2].as_f64().unwrap();
        assert!((z + d[r] / l).abs() < 1e-6, "row {r}: {z}");
    }
    // Meshes in the data folder equal the native tessellation.
    for (i, obj) in scene.objects.iter().enumerate() {
        let native = pixl_render::geometry::shape_mesh(&scene, &obj.shape).unwrap();
        let exported = pixl_render::export::load_mesh(&e.data_dir.join(format!("obj_{i}.ply"))).unwrap();
        assert_eq!(exported.positions, native.positions);
        assert_eq!(exported.indices, native.indices);
    }
    // Python syntax, when a python3 is available.
    match std::process::Command::new("python3")
        .arg("-m")
        .arg("py_compile")
        .arg(&script)
        .output()
    {
        Ok(o) => assert!(o.status.success(), "py_compile: {}", String::from_utf8_lossy(&o.stderr)),
        Err(_) => eprintln!("python3 not found; skipping the syntax check"),
    }
}
