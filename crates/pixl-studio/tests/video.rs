//! A clip in the studio (needs the system's FFmpeg): its reference frame becomes the photo, the
//! state names the clip, and "export video" (`POST /api/export?what=video`) relights every frame
//! under the current lights, with the clip's frame count, size and rate; without a clip the
//! export is refused, and a new photo closes the clip.
mod common;

use common::*;
use pixl_studio::Studio;
use std::process::Command;

#[test]
fn a_clip_is_lit_on_its_reference_frame_and_exported_frame_by_frame() {
    let dir = tempfile::tempdir().unwrap();
    let clip = dir.path().join("clip.mp4");
    let o = Command::new("ffmpeg")
        .args([
            "-v",
            "error",
            "-y",
            "-f",
            "lavfi",
            "-i",
            "testsrc=size=48x32:rate=8",
            "-t",
            "1",
        ])
        .args(["-c:v", "libx264", "-pix_fmt", "yuv420p"])
        .arg(&clip)
        .output()
        .expect("this test needs ffmpeg");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.path().join("out");
    let studio = Studio::new(small_config(&out)).unwrap();
    let addr = spawn_server(studio.clone());

    // No clip yet: refused.
    studio.load_photo_bytes(&photo_png(48, 32), "photo.png").unwrap();
    let (code, body) = http_json(addr, "POST", "/api/export?what=video", "");
    assert_eq!(code, 404, "{body}");

    studio.load_video_file(&clip).unwrap();
    let (_, state) = http_json(addr, "GET", "/api/state", "");
    assert!(state["video"].as_str().unwrap().ends_with("clip.mp4"), "{state}");
    assert_eq!(state["photo"]["name"], "clip.mp4");
    let (code, body) = http_json(addr, "POST", "/api/preset", r#"{"name": "cool-side-flash"}"#);
    assert_eq!(code, 200, "{body}");
    let (code, body) = http_json(addr, "POST", "/api/export?what=video&timeout_ms=60000", "");
    assert_eq!(code, 200, "{body}");
    let path = body["paths"][0].as_str().unwrap().to_string();
    assert!(path.ends_with("clip-relit.mp4"), "{path}");
    let probe = Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
        .args([
            "-show_entries",
            "stream=width,height,r_frame_rate,nb_read_frames",
            "-of",
            "csv=p=0",
        ])
        .arg(&path)
        .output()
        .unwrap();
    assert_eq!(String::from_utf8_lossy(&probe.stdout).trim(), "48,32,8/1,8");
    // A new photo closes the clip.
    studio.load_photo_bytes(&photo_png(48, 32), "photo.png").unwrap();
    let (_, state) = http_json(addr, "GET", "/api/state", "");
    assert!(state["video"].is_null(), "{state}");
}
