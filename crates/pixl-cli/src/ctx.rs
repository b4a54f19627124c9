//! What every subcommand gets besides its own flags, and the conventions they share:
//!
//! - stdout carries results (one summary line, or with `--json` one JSON document and nothing
//!   else: [`Ctx::for_json`]); stderr carries logs, warnings, progress and errors.
//! - Colour and progress bars only on a terminal: [`color_enabled`] (stderr is a terminal and
//!   `NO_COLOR` is unset or empty) and [`Ctx::progress`] (hidden under `--quiet` or when stderr is
//!   not a terminal).
//! - Errors print each cause once ([`error_text`]).
//! - Outputs are checked before any work with `pixl_core::output::{check_output,
//!   check_output_dir}`; SIGINT / SIGTERM / SIGHUP remove the live temporary files and
//!   provisional folders and exit with 130 ([`install_signal_handler`]).
//! - Count flags that must be positive parse with [`at_least_one`] ("must be at least 1").
//! - Help texts shared by several subcommands: [`dataset_kinds_help!`], [`scene_axes_help!`].
use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;

#[derive(Clone, Debug)]
pub struct Ctx {
    /// `--quiet`: no progress bars, no summaries on stdout.
    pub quiet: bool,
    /// stdout holds a JSON document: [`Ctx::say`] stays silent.
    pub json: bool,
}

impl Ctx {
    pub fn new(quiet: bool) -> Self {
        Ctx { quiet, json: false }
    }

    /// The context of a command printing JSON: stdout is reserved for the document (human
    /// lines are dropped; progress bars and logs stay on stderr).
    pub fn for_json(&self, json: bool) -> Ctx {
        Ctx {
            quiet: self.quiet,
            json: self.json || json,
        }
    }

    /// A progress bar on stderr, hidden under `--quiet` and when stderr is not a terminal.
    pub fn progress(&self, len: u64, msg: &str) -> ProgressBar {
        if self.quiet || !std::io::stderr().is_terminal() {
            return ProgressBar::hidden();
        }
        let pb = ProgressBar::new(len);
        let style =
            ProgressStyle::with_template("{msg:>12} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta} {per_sec}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ");
        pb.set_style(style);
        pb.set_message(msg.to_string());
        pb
    }

    /// Prints a line on stdout unless `--quiet` or `--json`.
    pub fn say(&self, line: impl AsRef<str>) {
        if !self.quiet && !self.json {
            stdout_line(line.as_ref());
        }
    }

    /// Prints a JSON document on stdout (even under `--quiet`).
    pub fn print_json(&self, value: &serde_json::Value) -> anyhow::Result<()> {
        stdout_line(&serde_json::to_string_pretty(value)?);
        Ok(())
    }
}

/// One line on stdout. A reader that went away (`pixl … | head`) is not an error of ours: the
/// rest of the output is dropped quietly instead of panicking as `println!` does.
fn stdout_line(text: &str) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{text}").and_then(|()| out.flush());
}

/// Whether to colour stderr: it is a terminal and `NO_COLOR` is unset or empty
/// (<https://no-color.org>).
pub fn color_enabled() -> bool {
    let no_color = std::env::var_os("NO_COLOR").is_some_and(|v| !v.is_empty());
    !no_color && std::io::stderr().is_terminal()
}

/// The error and its causes, `: `-separated, each cause once: a cause whose text the message
/// already holds (a library error that prints its inner error and also returns it as its
/// `source`) is left out.
pub fn error_text(e: &anyhow::Error) -> String {
    let mut text = String::new();
    for cause in e.chain() {
        let part = cause.to_string();
        if part.is_empty() || text.contains(&part) {
            continue;
        }
        if !text.is_empty() {
            text.push_str(": ");
        }
        text.push_str(&part);
    }
    text
}

/// Removes live temporary files and provisional folders and exits with 130 on SIGINT, SIGTERM
/// or SIGHUP (see `pixl_core::output`). Installed once, first thing in `main`.
pub fn install_signal_handler() {
    if let Err(e) = ctrlc::set_handler(|| pixl_core::output::remove_live_paths_and_exit(130)) {
        tracing::debug!("no signal handler: {e}");
    }
}

/// Parses a whole number in `min..=max`, saying which bound a value misses ("must be at least 1").
pub fn parse_count(s: &str, min: u64, max: u64) -> Result<u64, String> {
    let v: u64 = s.trim().parse().map_err(|_| format!("{s:?} is not a whole number"))?;
    if v < min {
        return Err(format!("must be at least {min}"));
    }
    if v > max {
        return Err(format!("must be at most {max}"));
    }
    Ok(v)
}

/// A `u32` count that must be positive (`--spp 0` → "must be at least 1").
pub fn at_least_one(s: &str) -> Result<u32, String> {
    parse_count(s, 1, u32::MAX as u64).map(|v| v as u32)
}

/// A `usize` count that must be positive.
pub fn at_least_one_usize(s: &str) -> Result<usize, String> {
    parse_count(s, 1, u32::MAX as u64).map(|v| v as usize)
}

/// The dataset kinds `--dataset` / `[data] dataset` accept, for `--help` texts.
#[macro_export]
macro_rules! dataset_kinds_help {
    () => {
        "Datasets are given as KIND:ROOT:\n  \
miiw:ROOT        MIT Multi-Illumination: ROOT/<scene>/dir_<0..24>_mip2.(jpg|exr); miiw@N:ROOT for mip level N.\n                   \
Test split: the scenes whose names start with `everett`.\n  \
bigtime:ROOT     BigTime time-lapses: ROOT/<scene>/data/<frame>.(png|jpg), or frames directly in ROOT/<scene>/.\n  \
vidit:ROOT       VIDIT: ROOT/Image<NNN>_<temperature>_<direction>.png, one scene per <NNN>.\n  \
folder:ROOT      Any photos: ROOT/<scene>/*.(png|jpg|jpeg|exr), one folder per scene, each lit several ways.\n  \
synth:ROOT       A set made by `pixl synth` (ROOT/scenes.json; exact intrinsics beside every image).\n\
Without an official split (bigtime, vidit, folder), ROOT/test.txt lists the test scenes, one per line;\n\
if it is missing, every tenth scene in name order is a test scene. The target intrinsics of an image\n\
are the C_T file <stem>.intrinsics.exr beside it (synth sets have them; for photos, write them with\n\
`pixl prepare-targets --dataset KIND:ROOT` (Marigold-IID Lighting), or compose them from render passes\n\
with `pixl compose`)."
    };
}

/// The scene's axes and units, for `--help` texts.
#[macro_export]
macro_rules! scene_axes_help {
    () => {
        "Scene axes and units: right-handed, +Y up, in metres. A camera without look_at or matrix sits\n\
at its position looking down -Z: +X is right, +Y up, -Z forward in its image (image row 0 is the top);\n\
a scene from `pixl reconstruct` has that camera at the origin. Light units are Blender's: point, spot\n\
and area power in W, sun strength in W/m^2, colours linear RGB or a temperature in kelvin."
    };
}

/// The CLI's view of the pipeline's long stages ([`pixl_pipeline::Observer`]): a progress bar
/// per stage (hidden under `--quiet` or without a terminal, redrawing its elapsed time) and its
/// notes printed as summary lines ([`Ctx::say`]).
pub struct Bars<'a> {
    ctx: &'a Ctx,
    bars: std::sync::Mutex<Vec<(pixl_pipeline::Stage, ProgressBar)>>,
}

impl<'a> Bars<'a> {
    pub fn new(ctx: &'a Ctx) -> Self {
        Bars {
            ctx,
            bars: std::sync::Mutex::new(Vec::new()),
        }
    }

    fn with_bar(&self, stage: pixl_pipeline::Stage, f: impl FnOnce(&ProgressBar)) {
        if let Ok(bars) = self.bars.lock() {
            if let Some((_, b)) = bars.iter().find(|(s, _)| *s == stage) {
                f(b);
            }
        }
    }
}

impl pixl_pipeline::Observer for Bars<'_> {
    fn begin(&self, stage: pixl_pipeline::Stage, total: u64) {
        let bar = self.ctx.progress(total.max(1), stage.name());
        if !bar.is_hidden() {
            bar.enable_steady_tick(std::time::Duration::from_millis(250));
        }
        if let Ok(mut bars) = self.bars.lock() {
            bars.push((stage, bar));
        }
    }

    fn progress(&self, stage: pixl_pipeline::Stage, done: u64, total: u64) {
        self.with_bar(stage, |b| {
            b.set_length(total.max(1));
            b.set_position(done);
        });
    }

    fn end(&self, stage: pixl_pipeline::Stage) {
        if let Ok(mut bars) = self.bars.lock() {
            if let Some(i) = bars.iter().position(|(s, _)| *s == stage) {
                bars.remove(i).1.finish_and_clear();
            }
        }
    }

    fn note(&self, line: &str) {
        self.ctx.say(line);
    }
}
