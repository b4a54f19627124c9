//! Where pretrained weights come from, shared by every command that loads them: the
//! `--models DIR` / `--offline` flags ([`WeightsArgs`]) and the console side of finding or
//! downloading them ([`resolve`]: the licence and size shown first, a progress bar per file, a
//! line while a pinned SHA-256 is checked) and of re-checking files on disk ([`verify`]).
//! Everything goes to stderr. Lookup order, environment variables and digest checks:
//! `pixl_estimate::hub`.
use crate::Ctx;
use indicatif::{ProgressBar, ProgressStyle};
use pixl_estimate::hub::{self, FetchObserver, FileCheck, Hub, HubOptions, ModelFile, ModelSpec, Resolved};
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

/// The network's weights as `--weights` names them (shared by `relight`, `studio`, `demo`).
pub const NETWORK_WEIGHTS_HELP: &str = "Network weights: `bundled` (the demo model compiled into pixl, \
1.7 M parameters, permissive licence), `pixlrelight` (the paper's released model, 641 M parameters, \
CC BY-NC 4.0 — non-commercial use only; fetched once, about 2.6 GB, unless --offline), or a \
.safetensors file (ours, or the release's model.safetensors with its config.yaml beside it). \
Default: the released model when it is on disk (`pixl models fetch pixlrelight`), else bundled";

/// Which network weights to load: `None` = the bundled ones. `choice` is `--weights`
/// (`bundled`, `pixlrelight` or a path); without it, the released checkpoint when it is already
/// on disk (never downloaded unasked), else the bundled weights with a one-line hint on stderr.
pub fn network_weights(choice: Option<&str>, models: &WeightsArgs, ctx: &Ctx) -> anyhow::Result<Option<PathBuf>> {
    let spec = hub::lookup("pixlrelight")?;
    let model_file = |r: &Resolved| r.file("model.safetensors");
    match choice {
        Some("bundled") => Ok(None),
        Some("pixlrelight") => Ok(Some(model_file(&resolve(&models.hub(), spec, ctx)?))),
        Some(path) => {
            let p = PathBuf::from(path);
            if !p.is_file() {
                anyhow::bail!("--weights {path}: no such file (or use `bundled` or `pixlrelight`)");
            }
            Ok(Some(p))
        }
        None => match models.hub().locate(spec) {
            Ok(Some(r)) => Ok(Some(model_file(&r))),
            _ => {
                ctx.say(
                    "using the bundled demo weights (1.7 M parameters); for the paper's model: \
                     `pixl models fetch pixlrelight` (CC BY-NC 4.0 — non-commercial use only), then run again",
                );
                Ok(None)
            }
        },
    }
}

/// Finds or downloads a model, with the licence/size notice and a progress bar on stderr.
pub fn resolve(hub: &Hub, spec: &'static ModelSpec, ctx: &Ctx) -> anyhow::Result<Resolved> {
    let mut obs = Console { ctx, bar: None };
    Ok(hub.resolve(spec, &mut obs)?)
}

/// Checks the files of `r` that have a pinned SHA-256 (a line on stderr per file being read,
/// unless `--quiet`); fails naming the first file that differs.
pub fn verify(r: &Resolved, ctx: &Ctx) -> anyhow::Result<Vec<FileCheck>> {
    let mut obs = Console { ctx, bar: None };
    Ok(r.verify(&mut obs)?)
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
        if missing.iter().any(|f| f.sha256.is_some()) {
            eprintln!("  checked against the SHA-256 pinned for revision {}", spec.revision);
        }
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
    fn file_checking(&mut self, file: &str, bytes: u64) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
        if !self.ctx.quiet {
            eprintln!("checking the sha256 of {file} ({})", hub::human_bytes(bytes));
        }
    }
}
