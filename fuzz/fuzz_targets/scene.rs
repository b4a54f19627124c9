//! The scene parser (TOML and JSON) on arbitrary text: must return `Ok` or `Err`, never panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = pixl_render::scene::Scene::from_toml_str(text);
        let _ = pixl_render::scene::Scene::from_json_str(text);
    }
});
