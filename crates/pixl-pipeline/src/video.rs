//! Video: a clip (or an image sequence) relit frame by frame, streamed from a decoder through the
//! network to an encoder without holding the clip in memory.
//!
//! **FFmpeg.** Frames are decoded and encoded by the system's `ffmpeg` and `ffprobe` programs
//! ([`Ffmpeg::find`]: `PIXL_FFMPEG_DIR`, else `PATH`), talking raw RGB 8-bit over pipes. Chosen
//! over a binding crate: no C libraries or headers at build time, every codec and container the
//! distribution's FFmpeg has, and no coupling to one FFmpeg ABI. Without them, a video request is
//! one clear error naming the package to install.
//!
//! **Colour.** Frames are taken as sRGB 8-bit (`-pix_fmt rgb24`: FFmpeg converts any other pixel
//! format and range to it, and higher bit depths are rounded to 8 bits); no colour-space metadata
//! is carried over. Output video is H.264 (VP9 for `.webm`) in yuv420p, odd sizes padded by one
//! pixel to even; the frame rate is the input's; audio is copied (re-encoded to Opus for
//! `.webm`). An image-sequence output (`out/%04d.png`) is written frame by frame as PNGs
//! numbered from 1, as FFmpeg numbers them.
//!
//! **Checks.** A file FFmpeg cannot read, a file without a video stream and a variable frame rate
//! (the stream's `r_frame_rate` and `avg_frame_rate` differ by more than 1 %) are refused before
//! any work; a decode that fails part-way (a truncated file) is an error. Output is written to a
//! temporary file registered for removal on interruption and renamed at the end; on any error it
//! is removed (written frames of a sequence too): nothing is left half-written.
//!
//! **Camera.** A static camera ([`CameraMotion::Static`], detected from the first frames by
//! [`is_static`] unless said): the scene is reconstructed once from the per-pixel median of the
//! first frames (moving things and noise removed), `C_T` rendered once, and the network runs per
//! frame — the relit clip flickers only as much as the network's response to the frames' own
//! changes. A moving camera: each frame's depth is estimated, aligned to the previous frame's by a
//! least-squares scale and shift ([`align_depth`]) so that its scale does not jump, the scene
//! reconstructed and `C_T` rendered per frame, under the lights placed in the **first frame's**
//! scene, kept in camera coordinates: lights travel with the camera, not with the world (no camera
//! poses are estimated), and the render's noise differs between frames.
use crate::depth::DepthEstimator;
use crate::error::{PipelineError, Result};
use crate::exif::photo_focal;
use crate::job::{DepthSource, LightSet};
use crate::observe::{Observer, Silent, Stage};
use crate::photo::Photo;
use crate::reconstruct::{reconstruct, Maps, MeshSettings};
use crate::relight::{check_budget, ct_at_working_size, relight, Network};
use crate::render::{render_intrinsics, RenderSettings};
use candle_core::Device;
use pixl_core::Image;
use pixl_render::depth::DepthMap;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

/// Video containers, by extension.
pub const VIDEO_EXTS: &[&str] = &["mp4", "mov", "mkv", "webm", "avi", "m4v"];
/// Frames looked at to decide whether the camera is static, and to median for its reference.
pub const REFERENCE_FRAMES: usize = 24;

/// Whether `path` names a video: a container extension, or an image-sequence pattern.
pub fn is_video(path: &Path) -> bool {
    VIDEO_EXTS.contains(&pixl_core::io::extension(path).as_str()) || is_sequence(path)
}

/// Whether `path`'s file name is a printf-style sequence pattern (`%d`, `%04d`).
pub fn is_sequence(path: &Path) -> bool {
    sequence_parts(path).is_some()
}

/// A pattern's file name split around its `%0Nd`: prefix, width, suffix.
fn sequence_parts(path: &Path) -> Option<(String, usize, String)> {
    let name = path.file_name()?.to_string_lossy().into_owned();
    let at = name.find('%')?;
    let rest = &name[at + 1..];
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    let after = rest.get(digits.len()..)?;
    let suffix = after.strip_prefix('d')?;
    Some((name[..at].to_string(), digits.parse().unwrap_or(0), suffix.to_string()))
}

/// The file of frame `index` of a sequence pattern.
pub fn sequence_frame(pattern: &Path, index: usize) -> Option<PathBuf> {
    let (prefix, width, suffix) = sequence_parts(pattern)?;
    Some(pattern.with_file_name(format!("{prefix}{index:0width$}{suffix}")))
}

/// Refuses an output that is not a video or a sequence pattern, whose folder is missing, or that
/// would overwrite `input`.
pub fn check_output(output: &Path, input: &Path) -> Result<()> {
    let name = output.display();
    if !is_video(output) {
        return Err(PipelineError::input(format!(
            "-o {name}: a clip is written as a video ({}) or an image sequence (frames/%04d.png)",
            VIDEO_EXTS.join(", ")
        )));
    }
    let dir = pixl_core::output::parent_dir(output);
    if !dir.is_dir() {
        return Err(PipelineError::input(format!(
            "-o {name}: the folder {} does not exist",
            dir.display()
        )));
    }
    if pixl_core::output::same_file(output, input) || output == input {
        return Err(PipelineError::input(format!(
            "-o {name}: the output would overwrite the clip"
        )));
    }
    Ok(())
}

/// The `ffmpeg` and `ffprobe` programs.
#[derive(Clone, Debug)]
pub struct Ffmpeg {
    pub ffmpeg: PathBuf,
    pub ffprobe: PathBuf,
}

impl Ffmpeg {
    /// Finds both programs in `PIXL_FFMPEG_DIR`, else on `PATH`.
    pub fn find() -> Result<Ffmpeg> {
        let dirs: Vec<PathBuf> = match std::env::var_os("PIXL_FFMPEG_DIR") {
            Some(d) => vec![PathBuf::from(d)],
            None => std::env::var_os("PATH")
                .map(|p| std::env::split_paths(&p).collect())
                .unwrap_or_default(),
        };
        let find = |name: &str| dirs.iter().map(|d| d.join(name)).find(|p| p.is_file());
        match (find("ffmpeg"), find("ffprobe")) {
            (Some(ffmpeg), Some(ffprobe)) => Ok(Ffmpeg { ffmpeg, ffprobe }),
            _ => Err(PipelineError::input(
                "video needs the programs ffmpeg and ffprobe, which were not found (on PATH, or in PIXL_FFMPEG_DIR): \
                 install the `ffmpeg` package (Debian/Ubuntu: apt-get install ffmpeg; Fedora: dnf install ffmpeg; \
                 macOS: brew install ffmpeg)",
            )),
        }
    }
}

/// What `ffprobe` says of a clip's video stream.
#[derive(Clone, Debug, PartialEq)]
pub struct VideoInfo {
    pub width: usize,
    pub height: usize,
    /// Frame rate as a fraction.
    pub fps: (u64, u64),
    /// Frame count where the container says it.
    pub frames: Option<u64>,
    pub audio: bool,
    pub codec: String,
    pub pix_fmt: String,
}

impl VideoInfo {
    pub fn fps(&self) -> f64 {
        self.fps.0 as f64 / self.fps.1.max(1) as f64
    }
}

fn rational(s: &str) -> Option<(u64, u64)> {
    let (n, d) = s.split_once('/').unwrap_or((s, "1"));
    let (n, d) = (n.trim().parse().ok()?, d.trim().parse().ok()?);
    (d > 0).then_some((n, d))
}

/// The first line of a program's error output.
fn first_line(bytes: &[u8]) -> String {
    let text = String::from_utf8_lossy(bytes);
    text.lines()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("")
        .trim()
        .to_string()
}

/// Probes `path` and refuses what cannot be relit (see the module docs).
pub fn probe(ff: &Ffmpeg, path: &Path) -> Result<VideoInfo> {
    let name = path.display();
    if !is_sequence(path) && !path.is_file() {
        return Err(PipelineError::input(format!("{name}: no such file")));
    }
    let out = Command::new(&ff.ffprobe)
        .args(["-v", "error", "-print_format", "json", "-show_streams", "-show_format"])
        .arg(path)
        .output()
        .map_err(|e| PipelineError::io(&ff.ffprobe, e))?;
    if !out.status.success() {
        return Err(PipelineError::input(format!(
            "{name}: not a video FFmpeg can read ({})",
            first_line(&out.stderr)
        )));
    }
    let v: serde_json::Value = serde_json::from_slice(&out.stdout)
        .map_err(|e| PipelineError::input(format!("{name}: ffprobe's answer is not JSON: {e}")))?;
    let streams = v["streams"].as_array().cloned().unwrap_or_default();
    let video = streams
        .iter()
        .find(|s| s["codec_type"] == "video")
        .ok_or_else(|| PipelineError::input(format!("{name}: has no video stream")))?;
    let dim = |k: &str| video[k].as_u64().unwrap_or(0) as usize;
    let (width, height) = (dim("width"), dim("height"));
    if width == 0 || height == 0 {
        return Err(PipelineError::input(format!(
            "{name}: the video stream has no frame size"
        )));
    }
    let r = video["r_frame_rate"].as_str().and_then(rational).filter(|r| r.0 > 0);
    let avg = video["avg_frame_rate"].as_str().and_then(rational).filter(|r| r.0 > 0);
    let fps = r
        .or(avg)
        .ok_or_else(|| PipelineError::input(format!("{name}: no frame rate")))?;
    if let (Some(r), Some(a)) = (r, avg) {
        let (rf, af) = (r.0 as f64 / r.1 as f64, a.0 as f64 / a.1 as f64);
        if (rf - af).abs() > 0.01 * rf {
            return Err(PipelineError::input(format!(
                "{name}: variable frame rate (stream rate {rf:.3} fps, average {af:.3} fps); pixl relights clips with a \
                 constant frame rate: convert it first, e.g. `ffmpeg -i {name} -fps_mode cfr -r {:.0} constant.mp4`",
                af.round().max(1.0)
            )));
        }
    }
    Ok(VideoInfo {
        width,
        height,
        fps,
        frames: video["nb_frames"].as_str().and_then(|s| s.parse().ok()),
        audio: streams.iter().any(|s| s["codec_type"] == "audio"),
        codec: video["codec_name"].as_str().unwrap_or("").to_string(),
        pix_fmt: video["pix_fmt"].as_str().unwrap_or("").to_string(),
    })
}

/// Frames of a clip as RGB images in `[0, 1]`, decoded by `ffmpeg` as they are read.
pub struct Decoder {
    child: Child,
    out: ChildStdout,
    size: (usize, usize),
    name: String,
    frames: u64,
}

impl Decoder {
    pub fn open(ff: &Ffmpeg, path: &Path, info: &VideoInfo) -> Result<Decoder> {
        let mut child = Command::new(&ff.ffmpeg)
            .args(["-v", "error", "-nostdin", "-i"])
            .arg(path)
            .args([
                "-map",
                "0:v:0",
                "-f",
                "rawvideo",
                "-pix_fmt",
                "rgb24",
                "-fps_mode",
                "passthrough",
                "pipe:1",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| PipelineError::io(&ff.ffmpeg, e))?;
        let out = child
            .stdout
            .take()
            .ok_or_else(|| PipelineError::input("ffmpeg gave no output pipe"))?;
        Ok(Decoder {
            child,
            out,
            size: (info.width, info.height),
            name: path.display().to_string(),
            frames: 0,
        })
    }

    /// The next frame, `None` at the end; a decode that fails part-way is an error.
    pub fn next_frame(&mut self) -> Result<Option<Image>> {
        let (w, h) = self.size;
        let mut buf = vec![0u8; w * h * 3];
        let mut filled = 0;
        while filled < buf.len() {
            match self.out.read(&mut buf[filled..]) {
                Ok(0) => break,
                Ok(n) => filled += n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(PipelineError::io(&self.name, e)),
            }
        }
        if filled == buf.len() {
            self.frames += 1;
            return Ok(Some(Image::from_fn(w, h, 3, |x, y, c| {
                buf[(y * w + x) * 3 + c] as f32 / 255.0
            })));
        }
        let mut err = Vec::new();
        if let Some(mut e) = self.child.stderr.take() {
            let _ = e.read_to_end(&mut err);
        }
        let status = self.child.wait().map_err(|e| PipelineError::io(&self.name, e))?;
        let reason = first_line(&err);
        if filled > 0 || !status.success() || (self.frames == 0) || !reason.is_empty() {
            return Err(PipelineError::input(format!(
                "{}: decoding failed after {} frames ({}); the file may be truncated or damaged",
                self.name,
                self.frames,
                if reason.is_empty() {
                    "no frame data"
                } else {
                    reason.as_str()
                }
            )));
        }
        Ok(None)
    }
}

impl Drop for Decoder {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Where relit frames go: an encoded file, or a numbered image sequence.
pub enum Sink {
    Video(Encoder),
    Frames(FrameSink),
}

impl Sink {
    /// A sink for `dest` (a video file or a sequence pattern); `audio_from` is the clip whose
    /// audio is copied.
    pub fn create(ff: &Ffmpeg, dest: &Path, info: &VideoInfo, audio_from: Option<&Path>) -> Result<Sink> {
        if is_sequence(dest) {
            return Ok(Sink::Frames(FrameSink {
                pattern: dest.to_owned(),
                written: Vec::new(),
                finished: false,
            }));
        }
        Encoder::create(ff, dest, info, audio_from).map(Sink::Video)
    }

    pub fn write(&mut self, frame: &Image) -> Result<()> {
        match self {
            Sink::Video(e) => e.write(frame),
            Sink::Frames(f) => f.write(frame),
        }
    }

    /// Completes the output (the encoder's file renamed into place).
    pub fn finish(self) -> Result<()> {
        match self {
            Sink::Video(e) => e.finish(),
            Sink::Frames(mut f) => {
                f.finished = true;
                // Unregistered, kept.
                f.written.clear();
                Ok(())
            }
        }
    }
}

/// Frames written as numbered PNG/JPEG/EXR files; removed again unless finished (each is
/// registered for removal on interruption until then).
pub struct FrameSink {
    pattern: PathBuf,
    written: Vec<(PathBuf, pixl_core::output::LivePath)>,
    finished: bool,
}

impl FrameSink {
    fn write(&mut self, frame: &Image) -> Result<()> {
        let index = self.written.len() + 1;
        let path = sequence_frame(&self.pattern, index)
            .ok_or_else(|| PipelineError::input(format!("{}: not a sequence pattern", self.pattern.display())))?;
        let live = pixl_core::output::register(&path, false);
        pixl_core::io::write_image(&path, frame)?;
        self.written.push((path, live));
        Ok(())
    }
}

impl Drop for FrameSink {
    fn drop(&mut self) {
        if !self.finished {
            for (p, _) in &self.written {
                let _ = std::fs::remove_file(p);
            }
        }
    }
}

/// `ffmpeg` encoding raw frames into a temporary file beside the destination.
pub struct Encoder {
    child: Child,
    stdin: Option<ChildStdin>,
    tmp: PathBuf,
    dest: PathBuf,
    live: Option<pixl_core::output::LivePath>,
    size: (usize, usize),
}

impl Encoder {
    pub fn create(ff: &Ffmpeg, dest: &Path, info: &VideoInfo, audio_from: Option<&Path>) -> Result<Encoder> {
        let ext = pixl_core::io::extension(dest);
        let dir = pixl_core::output::parent_dir(dest);
        let stem = dest
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let tmp = dir.join(format!(".{stem}.tmp-{}.{ext}", std::process::id()));
        let live = pixl_core::output::register(&tmp, false);
        let mut cmd = Command::new(&ff.ffmpeg);
        cmd.args([
            "-v", "error", "-nostdin", "-y", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s",
        ])
        .arg(format!("{}x{}", info.width, info.height))
        .arg("-framerate")
        .arg(format!("{}/{}", info.fps.0, info.fps.1))
        .args(["-i", "pipe:0"]);
        if let Some(src) = audio_from.filter(|_| info.audio) {
            cmd.arg("-i")
                .arg(src)
                .args(["-map", "0:v:0", "-map", "1:a?", "-shortest"]);
            cmd.args(if ext == "webm" {
                ["-c:a", "libopus"]
            } else {
                ["-c:a", "copy"]
            });
        }
        cmd.args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-pix_fmt", "yuv420p"]);
        if ext == "webm" {
            cmd.args(["-c:v", "libvpx-vp9", "-crf", "30", "-b:v", "0"]);
        } else {
            cmd.args(["-c:v", "libx264", "-crf", "18", "-preset", "medium"]);
        }
        if ext == "mp4" || ext == "mov" || ext == "m4v" {
            cmd.args(["-movflags", "+faststart"]);
        }
        let mut child = cmd
            .arg(&tmp)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .map_err(|e| PipelineError::io(&ff.ffmpeg, e))?;
        let stdin = child.stdin.take();
        Ok(Encoder {
            child,
            stdin,
            tmp,
            dest: dest.to_owned(),
            live: Some(live),
            size: (info.width, info.height),
        })
    }

    fn failure(&mut self, what: &str) -> PipelineError {
        self.stdin = None;
        let mut err = Vec::new();
        if let Some(mut e) = self.child.stderr.take() {
            let _ = e.read_to_end(&mut err);
        }
        let _ = self.child.wait();
        PipelineError::input(format!("{}: {what} ({})", self.dest.display(), first_line(&err)))
    }

    fn write(&mut self, frame: &Image) -> Result<()> {
        if (frame.width, frame.height) != self.size {
            return Err(PipelineError::input(format!(
                "{}: a {}x{} frame for a {}x{} video",
                self.dest.display(),
                frame.width,
                frame.height,
                self.size.0,
                self.size.1
            )));
        }
        let bytes: Vec<u8> = (0..frame.width * frame.height)
            .flat_map(|i| (0..3).map(move |c| (i, c)))
            .map(|(i, c)| (frame.data[i * frame.channels + c].clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        let ok = match self.stdin.as_mut() {
            Some(s) => s.write_all(&bytes).is_ok(),
            None => false,
        };
        if ok {
            Ok(())
        } else {
            Err(self.failure("encoding failed"))
        }
    }

    fn finish(mut self) -> Result<()> {
        self.stdin = None;
        let status = self.child.wait().map_err(|e| PipelineError::io(&self.dest, e))?;
        if !status.success() {
            return Err(self.failure("encoding failed"));
        }
        let live = self
            .live
            .take()
            .ok_or_else(|| PipelineError::input("the encoder finished twice"))?;
        pixl_core::output::commit_rename(live, &self.tmp, &self.dest).map_err(|e| PipelineError::io(&self.dest, e))
    }
}

impl Drop for Encoder {
    fn drop(&mut self) {
        if self.live.is_some() {
            self.stdin = None;
            let _ = self.child.kill();
            let _ = self.child.wait();
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Luminance at most `side` pixels on its long side, for comparing frames.
fn thumb(img: &Image, side: usize) -> Result<Vec<f32>> {
    let (w, h) = pixl_model::fullres::working_size(img.width, img.height, side);
    let t = pixl_core::resample::area_resize(img, w, h)?;
    Ok((0..w * h)
        .map(|i| {
            let p = &t.data[i * t.channels..];
            0.2126 * p[0] + 0.7152 * p[1] + 0.0722 * p[2]
        })
        .collect())
}

/// Whether `frames` look like a static camera: on 64-pixel thumbnails, fewer than a third of the
/// pixels differ from the first frame's by more than 0.08 in any later frame (a pan or a zoom
/// moves nearly every textured pixel; a person walking through a fixed view moves few).
pub fn is_static(frames: &[Image]) -> Result<bool> {
    let Some(first) = frames.first() else { return Ok(true) };
    let reference = thumb(first, 64)?;
    for f in &frames[1..] {
        let t = thumb(f, 64)?;
        let moved = t.iter().zip(&reference).filter(|(a, b)| (*a - *b).abs() > 0.08).count();
        if moved * 3 > reference.len() {
            return Ok(false);
        }
    }
    Ok(true)
}

/// The per-pixel, per-channel median of `frames` (all of one size).
pub fn median_frame(frames: &[Image]) -> Result<Image> {
    let first = frames.first().ok_or_else(|| PipelineError::input("no frames"))?;
    if frames
        .iter()
        .any(|f| (f.width, f.height, f.channels) != (first.width, first.height, first.channels))
    {
        return Err(PipelineError::input("frames of different sizes"));
    }
    let mut column = vec![0.0f32; frames.len()];
    let data = (0..first.data.len())
        .map(|i| {
            for (v, f) in column.iter_mut().zip(frames) {
                *v = f.data[i];
            }
            column.sort_by(f32::total_cmp);
            column[column.len() / 2]
        })
        .collect();
    Ok(Image { data, ..first.clone() })
}

/// `depth` scaled and shifted (`a·d + b`, least squares over pixels valid in both) to agree with
/// `reference`; returns it with `(a, b)`. Unchanged where too few pixels are valid or the fit
/// is degenerate (then `(1, 0)`).
pub fn align_depth(depth: &DepthMap, reference: &DepthMap) -> (DepthMap, (f64, f64)) {
    let valid = |v: f32| v.is_finite() && v > 0.0;
    let (mut n, mut sx, mut sy, mut sxx, mut sxy) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
    if (depth.width, depth.height) == (reference.width, reference.height) {
        for (&x, &y) in depth.data.iter().zip(&reference.data) {
            if valid(x) && valid(y) {
                let (x, y) = (x as f64, y as f64);
                n += 1.0;
                sx += x;
                sy += y;
                sxx += x * x;
                sxy += x * y;
            }
        }
    }
    let var = n * sxx - sx * sx;
    if n < 16.0 || var <= 1e-12 * n * n {
        return (depth.clone(), (1.0, 0.0));
    }
    let a = (n * sxy - sx * sy) / var;
    let b = (sy - a * sx) / n;
    if a <= 0.0 {
        return (depth.clone(), (1.0, 0.0));
    }
    let mut out = depth.clone();
    for v in out.data.iter_mut() {
        if valid(*v) {
            *v = ((a * *v as f64 + b) as f32).max(1e-3);
        }
    }
    (out, (a, b))
}

/// A clip's reference frame — the per-pixel median of its first [`REFERENCE_FRAMES`] frames, what
/// a static camera's scene is reconstructed from — and its probe.
pub fn reference_frame(ff: &Ffmpeg, path: &Path) -> Result<(Image, VideoInfo)> {
    let info = probe(ff, path)?;
    let mut decoder = Decoder::open(ff, path, &info)?;
    let mut held = Vec::new();
    while held.len() < REFERENCE_FRAMES {
        match decoder.next_frame()? {
            Some(f) => held.push(f),
            None => break,
        }
    }
    Ok((median_frame(&held)?, info))
}

/// Whether the camera moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraMotion {
    /// Decided from the first frames ([`is_static`]).
    Auto,
    Static,
    Moving,
}

/// A clip to relight.
pub struct VideoJob<'a> {
    pub input: PathBuf,
    /// A video file or a sequence pattern; its folder must exist.
    pub output: PathBuf,
    pub lights: &'a LightSet,
    /// The reference frame's depth (a static camera): a file or an estimator. A moving camera
    /// needs an estimator.
    pub depth: DepthSource<'a>,
    pub camera: CameraMotion,
    pub max_side: usize,
    pub render: RenderSettings,
    pub max_memory: Option<u64>,
    pub focal_px: Option<f64>,
    pub fov_deg: Option<f64>,
}

/// How a clip went.
#[derive(Clone, Debug)]
pub struct VideoOutcome {
    pub info: VideoInfo,
    pub frames: u64,
    pub static_camera: bool,
    pub work: (usize, usize),
}

/// Relights `job.input` into `job.output` (see the module docs).
pub fn relight_video(
    ff: &Ffmpeg,
    net: &Network,
    job: VideoJob,
    device: &Device,
    observer: &dyn Observer,
) -> Result<VideoOutcome> {
    let info = probe(ff, &job.input)?;
    let size = (info.width, info.height);
    // The frame being relit, the decoded frames held for the reference, and the output frame.
    let budget = check_budget(
        net,
        size,
        job.max_side,
        12 * (REFERENCE_FRAMES as u64 + 2),
        job.max_memory,
    )?;
    let work = budget.work;
    let focal = photo_focal(&job.input, size.0, size.1, job.focal_px, job.fov_deg)?;
    let mut decoder = Decoder::open(ff, &job.input, &info)?;
    let mut held = Vec::new();
    while held.len() < REFERENCE_FRAMES {
        match decoder.next_frame()? {
            Some(f) => held.push(f),
            None => break,
        }
    }
    let static_camera = match job.camera {
        CameraMotion::Static => true,
        CameraMotion::Moving => false,
        CameraMotion::Auto => is_static(&held)?,
    };
    observer.note(&format!(
        "{}: {}x{}, {:.3} fps, {} frames{}; camera {}",
        job.input.display(),
        size.0,
        size.1,
        info.fps(),
        info.frames.map(|n| n.to_string()).unwrap_or_else(|| "?".into()),
        if info.audio { ", with audio (copied)" } else { "" },
        match (static_camera, job.camera) {
            (true, CameraMotion::Auto) =>
                "static (detected): the scene reconstructed once from the median of the first frames",
            (true, _) => "static: the scene reconstructed once from the median of the first frames",
            (false, _) => "moving: depth and C_T per frame, lights fixed to the first frame's camera",
        }
    ));
    let mesh = MeshSettings {
        stride: Some(size.0.max(size.1).div_ceil(work.0.max(work.1)).max(1)),
        ..Default::default()
    };
    // The C_T of one frame's photo and depth.
    let lit = |photo: &Photo,
               depth: &DepthMap,
               lights: Option<&[pixl_render::Light]>|
     -> Result<(Vec<f32>, Vec<pixl_render::Light>)> {
        let geometry = reconstruct(photo, depth, "the frame's depth", &Maps::default(), &mesh, &Silent)?;
        let mut scene = geometry.scene.clone();
        match lights {
            Some(l) => scene.lights = l.to_vec(),
            None => job.lights.apply(&mut scene, observer)?,
        }
        let (_, composed) = render_intrinsics(&scene, work, &job.render, &Silent)?;
        Ok((ct_at_working_size(&composed.ct, work)?, scene.lights))
    };
    let frame_photo = |img: Image| Photo {
        path: None,
        image: img,
        linear: false,
        focal,
    };
    let estimate = |photo: &Photo, est: &dyn DepthEstimator| -> Result<DepthMap> {
        est.estimate(&photo.srgb(), photo.focal.px)?.to_metric(photo.size())
    };

    let frames = if static_camera {
        let reference = frame_photo(median_frame(&held)?);
        let depth = match &job.depth {
            DepthSource::File { path, how } => crate::depth::read_depth_file(path, how, size)?,
            DepthSource::Estimate(est) => estimate(&reference, *est)?,
            DepthSource::Given(map) => map.clone(),
        };
        let (ct_work, _) = lit(&reference, &depth, None).map_err(|e| e.context("the reference frame"))?;
        stream(
            ff,
            &info,
            &job.input,
            &job.output,
            held,
            &mut decoder,
            observer,
            |frame, _| relight(net, frame, &ct_work, work, device, &Silent),
        )?
    } else {
        let DepthSource::Estimate(est) = &job.depth else {
            return Err(PipelineError::input(
                "a moving camera needs the depth of every frame: use the depth estimator (no --depth), or --static",
            ));
        };
        let (mut lights, mut previous) = (None::<Vec<pixl_render::Light>>, None::<DepthMap>);
        stream(
            ff,
            &info,
            &job.input,
            &job.output,
            held,
            &mut decoder,
            observer,
            |frame, i| {
                let photo = frame_photo(frame);
                let mut depth = estimate(&photo, *est)?;
                if let Some(prev) = &previous {
                    depth = align_depth(&depth, prev).0;
                }
                let (ct_work, placed) =
                    lit(&photo, &depth, lights.as_deref()).map_err(|e| e.context(format!("frame {}", i + 1)))?;
                lights.get_or_insert(placed);
                previous = Some(depth);
                relight(net, photo.image, &ct_work, work, device, &Silent)
            },
        )?
    };
    Ok(VideoOutcome {
        info,
        frames,
        static_camera,
        work,
    })
}

/// Streams `held` and then the rest of `decoder` through `relight` (a frame and its index → the
/// relit frame) into `output`, with progress; the output is complete only if every frame was.
#[allow(clippy::too_many_arguments)]
fn stream(
    ff: &Ffmpeg,
    info: &VideoInfo,
    input: &Path,
    output: &Path,
    held: Vec<Image>,
    decoder: &mut Decoder,
    observer: &dyn Observer,
    mut relight: impl FnMut(Image, u64) -> Result<Image>,
) -> Result<u64> {
    let audio = (!is_sequence(input)).then_some(input);
    let mut sink = Sink::create(ff, output, info, audio)?;
    let total = info.frames.unwrap_or(0);
    observer.begin(Stage::Frames, total);
    let mut frames = 0u64;
    let mut held = held.into_iter();
    let result = (|| -> Result<()> {
        loop {
            let frame = match held.next() {
                Some(f) => f,
                None => match decoder.next_frame()? {
                    Some(f) => f,
                    None => return Ok(()),
                },
            };
            let relit = relight(frame, frames)?;
            sink.write(&relit)?;
            frames += 1;
            observer.progress(Stage::Frames, frames, total);
        }
    })();
    observer.end(Stage::Frames);
    result?;
    if frames == 0 {
        return Err(PipelineError::input(format!("{}: no frames", input.display())));
    }
    sink.finish()?;
    Ok(frames)
}

/// Relights every frame of `input` with `model` under one `C_T` (planar, at the working size
/// `work`) into `output` — a static camera's clip relit under a `C_T` made elsewhere (the
/// studio's). Returns the frame count and the clip's probe.
#[allow(clippy::too_many_arguments)]
pub fn relight_frames(
    ff: &Ffmpeg,
    model: &pixl_model::PixlRelight,
    input: &Path,
    output: &Path,
    ct_work: &[f32],
    work: (usize, usize),
    device: &Device,
    observer: &dyn Observer,
) -> Result<(u64, VideoInfo)> {
    let info = probe(ff, input)?;
    let mut decoder = Decoder::open(ff, input, &info)?;
    let frames = stream(
        ff,
        &info,
        input,
        output,
        Vec::new(),
        &mut decoder,
        observer,
        |frame, _| {
            Ok(pixl_model::fullres::relight_full(
                model,
                frame,
                ct_work,
                work,
                device,
                &mut |_, _, _| {},
            )?)
        },
    )?;
    Ok((frames, info))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sequence_patterns_name_their_frames() {
        assert!(is_sequence(Path::new("out/%04d.png")) && is_sequence(Path::new("f_%d.exr")));
        assert!(!is_sequence(Path::new("100%.png")) && !is_sequence(Path::new("a.png")));
        assert_eq!(
            sequence_frame(Path::new("out/f%04d.png"), 7),
            Some(PathBuf::from("out/f0007.png"))
        );
        assert_eq!(sequence_frame(Path::new("%d.jpg"), 12), Some(PathBuf::from("12.jpg")));
        assert!(is_video(Path::new("clip.MOV")) && !is_video(Path::new("photo.jpg")));
    }

    #[test]
    fn depth_is_aligned_by_its_least_squares_scale_and_shift() {
        let reference = DepthMap::new(8, 4, (0..32).map(|i| 1.0 + i as f32 * 0.1).collect()).unwrap();
        // The same depth at another scale and offset, one pixel missing.
        let mut data: Vec<f32> = reference.data.iter().map(|d| (d - 0.2) / 2.5).collect();
        data[5] = 0.0;
        let (aligned, (a, b)) = align_depth(&DepthMap::new(8, 4, data).unwrap(), &reference);
        assert!((a - 2.5).abs() < 1e-4 && (b - 0.2).abs() < 1e-4, "{a} {b}");
        for (i, (x, y)) in aligned.data.iter().zip(&reference.data).enumerate() {
            if i == 5 {
                assert_eq!(*x, 0.0, "a missing pixel stays missing");
            } else {
                assert!((x - y).abs() < 1e-4);
            }
        }
        // Too little overlap: unchanged.
        let tiny = DepthMap::new(2, 2, vec![1.0; 4]).unwrap();
        assert_eq!(
            align_depth(&tiny, &DepthMap::new(2, 2, vec![2.0; 4]).unwrap()).1,
            (1.0, 0.0)
        );
    }

    #[test]
    fn the_median_removes_a_passing_object_and_a_pan_is_not_static() {
        let scene = |shift: usize| Image::from_fn(64, 32, 3, move |x, y, _| (((x + shift) / 4 + y / 4) % 2) as f32);
        let mut frames: Vec<Image> = (0..5).map(|_| scene(0)).collect();
        // A bright square crossing the view in frame 2.
        frames[2] = Image::from_fn(
            64,
            32,
            3,
            |x, y, c| if x < 8 && y < 8 { 0.5 } else { scene(0).get(x, y, c) },
        );
        assert!(is_static(&frames).unwrap());
        assert_eq!(median_frame(&frames).unwrap().data, scene(0).data);
        let pan: Vec<Image> = (0..5).map(|i| scene(i * 3)).collect();
        assert!(!is_static(&pan).unwrap());
    }
}
