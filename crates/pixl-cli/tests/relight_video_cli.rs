//! `pixl relight` on video, through the real binary and the system's FFmpeg: a synthetic 48-frame
//! clip (the demo scene rendered by `pixl render`, with a slowly changing exposure and per-frame
//! noise) relit as an image sequence flickers no more than 1.1 × its source's own frame-to-frame
//! noise (`pixl_eval::temporal`); an MP4 with audio keeps its size, frame count, rate and audio;
//! bad input (not a video, truncated, variable frame rate, no FFmpeg) is one clear error each,
//! with nothing written.
mod common;
use common::{cmd, pixl_q, s, write_depth, write_file, write_image};
use pixl_core::Image;
use std::path::Path;
use std::process::Command;

fn ffmpeg(args: &[&str]) {
    let o = Command::new("ffmpeg")
        .args(["-v", "error", "-y"])
        .args(args)
        .output()
        .expect("these tests need ffmpeg (Debian: apt-get install ffmpeg; .ci/run installs it)");
    assert!(
        o.status.success(),
        "ffmpeg {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

fn probe(path: &Path) -> serde_json::Value {
    let o = Command::new("ffprobe")
        .args(["-v", "error", "-print_format", "json", "-show_streams", "-count_frames"])
        .arg(path)
        .output()
        .unwrap();
    serde_json::from_slice(&o.stdout).unwrap()
}

/// Files in `dir` (names), sorted.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

#[test]
fn a_static_clip_relit_as_a_sequence_flickers_no_more_than_its_source() {
    let dir = common::tempdir();
    let d = dir.path();
    // The scene, rendered once (its Depth pass is the clip's depth), then 48 frames with an
    // exposure drifting by ±15 % and independent noise of 2/255 per pixel.
    pixl_q(&[
        "render",
        s(&common::repo_path("assets/demo/scene.toml")),
        "--spp",
        "16",
        "--size",
        "64x48",
        "-o",
        s(&d.join("scene.exr")),
        "--preview",
        s(&d.join("scene.png")),
    ])
    .ok();
    let base = pixl_core::io::read_image(&d.join("scene.png")).unwrap();
    std::fs::create_dir_all(d.join("in")).unwrap();
    std::fs::create_dir_all(d.join("out")).unwrap();
    let mut state = 12345u64;
    let mut noise = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 33) as f32 / (1u64 << 31) as f32 - 0.5) * 4.0 / 255.0
    };
    let mut source = Vec::new();
    for t in 0..48 {
        let gain = 1.0 + 0.15 * (t as f32 / 48.0 * std::f32::consts::TAU).sin();
        let jitter: Vec<f32> = (0..64 * 48 * 3).map(|_| noise()).collect();
        let frame = Image::from_fn(64, 48, 3, |x, y, c| {
            (base.get(x, y, c) * gain + jitter[(y * 64 + x) * 3 + c]).clamp(0.0, 1.0)
        });
        let path = write_image(&d.join(format!("in/{:03}.png", t + 1)), &frame);
        source.push(pixl_core::io::read_image(&path).unwrap());
    }
    let out = pixl_q(&[
        "relight",
        s(&d.join("in/%03d.png")),
        "--depth",
        s(&d.join("scene.exr")),
        "--preset",
        "warm-overhead-flash",
        "--spp",
        "8",
        "-o",
        s(&d.join("out/%03d.png")),
        "--json",
    ])
    .ok()
    .json();
    assert_eq!(out["frames"].as_u64(), Some(48), "{out}");
    assert_eq!(out["static_camera"].as_bool(), Some(true), "{out}");
    let relit: Vec<Image> = (1..=48)
        .map(|t| pixl_core::io::read_image(&d.join(format!("out/{t:03}.png"))).unwrap())
        .collect();
    assert_eq!(names(&d.join("out")).len(), 48);
    let noise = pixl_eval::temporal::temporal_noise(&source).unwrap();
    let added = pixl_eval::temporal::added_flicker(&relit, &source).unwrap();
    eprintln!("flicker: relit vs source {added:.5}, source's own {noise:.5}");
    assert!(added <= 1.1 * noise, "relit flicker {added} vs source noise {noise}");
    // The relit clip is not the source (the light changed it).
    let diff: f32 = relit[0]
        .data
        .iter()
        .zip(&source[0].data)
        .map(|(a, b)| (a - b).abs())
        .sum::<f32>()
        / relit[0].data.len() as f32;
    assert!(diff > 0.005, "relit equals the source (mean difference {diff})");
}

#[test]
fn an_mp4_keeps_its_size_frames_rate_and_audio() {
    let dir = common::tempdir();
    let d = dir.path();
    let clip = d.join("clip.mp4");
    ffmpeg(&[
        "-f",
        "lavfi",
        "-i",
        "testsrc=size=62x46:rate=12",
        "-f",
        "lavfi",
        "-i",
        "sine=frequency=440:sample_rate=22050",
        "-t",
        "1",
        "-c:v",
        "libx264",
        "-pix_fmt",
        "yuv420p",
        "-c:a",
        "aac",
        "-shortest",
        s(&clip),
    ]);
    let depth = write_depth(&d.join("depth.exr"), 62, 46, |x, _| 2.0 + x as f32 / 62.0);
    let out = d.join("relit.mp4");
    let j = pixl_q(&[
        "relight",
        s(&clip),
        "--static",
        "--depth",
        s(&depth),
        "--preset",
        "cool-side-flash",
        "--spp",
        "4",
        "-o",
        s(&out),
        "--json",
    ])
    .ok()
    .json();
    assert_eq!(j["frames"].as_u64(), Some(12), "{j}");
    let p = probe(&out);
    let streams = p["streams"].as_array().unwrap();
    let v = streams.iter().find(|s| s["codec_type"] == "video").unwrap();
    // Odd sizes are padded to even for yuv420p.
    assert_eq!((v["width"].as_u64(), v["height"].as_u64()), (Some(62), Some(46)));
    assert_eq!(v["r_frame_rate"], "12/1");
    assert_eq!(v["nb_read_frames"], "12");
    assert!(streams.iter().any(|s| s["codec_type"] == "audio"), "{p}");
    assert_eq!(
        names(d),
        ["clip.mp4", "depth.exr", "relit.mp4"],
        "no temporary files left"
    );
}

#[test]
fn bad_clips_are_one_clear_error_each_and_nothing_is_written() {
    let dir = common::tempdir();
    let d = dir.path();
    let depth = write_depth(&d.join("depth.exr"), 32, 24, |_, _| 2.0);
    let relight = |clip: &Path| {
        let out = d.join("out.mp4");
        let o = pixl_q(&[
            "relight",
            s(clip),
            "--static",
            "--depth",
            s(&depth),
            "--preset",
            "cool-side-flash",
            "--spp",
            "2",
            "-o",
            s(&out),
        ]);
        assert!(!out.exists(), "{} left an output", clip.display());
        o
    };
    // Not a video.
    let text = write_file(&d.join("notes.mp4"), "not a video at all");
    relight(&text).fails(&["notes.mp4", "not a video FFmpeg can read"]);
    // Truncated: the first 40 % of a real clip.
    let good = d.join("good.mp4");
    ffmpeg(&[
        "-f",
        "lavfi",
        "-i",
        "testsrc=size=32x24:rate=24",
        "-t",
        "2",
        "-c:v",
        "libx264",
        "-pix_fmt",
        "yuv420p",
        "-movflags",
        "+faststart",
        s(&good),
    ]);
    let bytes = std::fs::read(&good).unwrap();
    let cut = write_file(&d.join("cut.mp4"), &bytes[..bytes.len() * 2 / 5]);
    relight(&cut).fails(&["cut.mp4"]);
    // Variable frame rate: the first half at 10 fps, the rest at 30.
    let vfr = d.join("vfr.mp4");
    ffmpeg(&[
        "-f",
        "lavfi",
        "-i",
        "testsrc=size=32x24:rate=30",
        "-t",
        "2",
        "-vf",
        "setpts='if(lt(N,30),N*3,N+60)/30/TB'",
        "-fps_mode",
        "vfr",
        "-c:v",
        "libx264",
        "-pix_fmt",
        "yuv420p",
        s(&vfr),
    ]);
    relight(&vfr).fails(&["variable frame rate", "-fps_mode cfr"]);
    // No FFmpeg.
    let empty = d.join("no-tools");
    std::fs::create_dir_all(&empty).unwrap();
    let o = common::run(
        cmd()
            .args([
                "relight",
                s(&good),
                "--static",
                "--depth",
                s(&depth),
                "--preset",
                "cool-side-flash",
                "-o",
                s(&d.join("out.mp4")),
                "--quiet",
            ])
            .env("PIXL_FFMPEG_DIR", &empty),
    );
    o.fails(&["ffmpeg", "apt-get install ffmpeg"]);
    // Only the inputs remain.
    assert_eq!(
        names(d),
        ["cut.mp4", "depth.exr", "good.mp4", "no-tools", "notes.mp4", "vfr.mp4"]
    );
}
