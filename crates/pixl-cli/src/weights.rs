//! Where the estimators' weights come from, shared by every command that loads one: the
//! `--models DIR` / `--offline` flags ([`WeightsArgs`]) and the console side of finding or
//! downloading them ([`resolve`]: the licence and size shown first, a progress bar per file).
//! Lookup order and environment variables: `pixl_estimate::hub`.
use crate::Ctx;
use indicatif::{ProgressBar, ProgressStyle};
use pixl_estimate::hub::{self, FetchObserver, Hub, HubOptions, ModelFile, ModelSpec, Resolved};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};

/// Where estimator weights come from (shared by every command that loads one).
#[derive(clap::Args, Debug, Clone, Default)]
pub struct WeightsArgs {
    /// Folder of model weights, searched first: DIR/<name>/<files> (e.g. DIR/da3-metric/config.json
    /// and model.safetensors) or a Hugging Face cache layout; downloads go there too.
    /// Default: $PIXL_MODELS_DIR.
    #[arg(long = "models", value_name = "DIR")]
    pub models: Option<PathBuf>,
    /// Never use the network: fail at once if the weights are not on disk
    /// (also PIXL_OFFLINE=1 or HF_HUB_OFFLINE=1).
    #[arg(long)]
    pub offline: bool,
}

impl WeightsArgs {
    pub fn hub(&self) -> Hub {
        Hub::new(HubOptions::from_env(self.models.clone(), self.offline))
    }
}

/// Finds or downloads a model, with the licence/size notice and a progress bar on stderr.
pub fn resolve(hub: &Hub, spec: &'static ModelSpec, ctx: &Ctx) -> anyhow::Result<Resolved> {
    let mut obs = Console { ctx, bar: None };
    Ok(hub.resolve(spec, &mut obs)?)
}

/// Console output of a download: notice on stderr, one progress bar per file.
struct Console<'a> {
    ctx: &'a Ctx,
    bar: Option<ProgressBar>,
}

impl FetchObserver for Console<'_> {
    fn before_download(&mut self, spec: &ModelSpec, missing: &[ModelFile], into: &Path) {
        let bytes: u64 = missing.iter().map(|f| f.approx_bytes).sum();
        // Always shown (even under --quiet): the user must know what is being downloaded and
        // under which licence.
        eprintln!(
            "downloading `{}` from https://huggingface.co/{} (about {}, {} file(s)) into {}\n  licence: {} ({})\n  use: {}",
            spec.name,
            spec.repo,
            hub::human_bytes(bytes),
            missing.len(),
            into.display(),
            spec.licence,
            spec.licence_url,
            spec.purpose
        );
    }
    fn file_started(&mut self, file: &str, bytes: u64) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
        if self.ctx.quiet || !std::io::stderr().is_terminal() {
            return;
        }
        let b = ProgressBar::new(bytes);
        let style =
            ProgressStyle::with_template("{msg:>18} [{bar:30}] {bytes}/{total_bytes} {bytes_per_sec} eta {eta}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> ");
        b.set_style(style);
        b.set_message(file.to_string());
        self.bar = Some(b);
    }
    fn file_progress(&mut self, bytes: u64) {
        if let Some(b) = &self.bar {
            b.inc(bytes);
        }
    }
    fn file_finished(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish();
        }
    }
}
