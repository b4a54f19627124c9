//! What every subcommand gets besides its own flags.
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Clone, Debug)]
pub struct Ctx {
    /// `--quiet`: no progress bars, no summaries on stdout.
    pub quiet: bool,
}

impl Ctx {
    /// A progress bar on stderr (hidden under `--quiet`).
    pub fn progress(&self, len: u64, msg: &str) -> ProgressBar {
        if self.quiet {
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

    /// Prints a line on stdout unless `--quiet`.
    pub fn say(&self, line: impl AsRef<str>) {
        if !self.quiet {
            println!("{}", line.as_ref());
        }
    }
}
