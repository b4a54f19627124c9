//! `pixl`: the one binary of pixlrelight. A thin layer over the library crates: it parses flags,
//! turns them into library calls, and reports errors with `anyhow` at this edge only.
//!
//! Exit codes: 0 success, 1 error (message on stderr), 2 bad command line (from clap), 130
//! interrupted (SIGINT / SIGTERM / SIGHUP; temporary files removed, see `ctx`).
use clap::{Parser, Subcommand};
use std::process::ExitCode;

mod args;
mod cmd;
mod ctx;
mod device;
mod estimators;
mod iid;
mod normals;
mod weights;

pub use ctx::Ctx;

#[derive(Parser, Debug)]
#[command(
    name = "pixl",
    version,
    about = "Relight a photograph under physically authored lights, in one feed-forward pass",
    long_about = "pixlrelight: relight a single photograph under physically authored lights.\n\n\
Pipeline: reconstruct (photo + depth -> scene) -> light (add lights / presets) -> render (passes) \
-> compose (passes -> C_T) -> relight (photo + C_T -> relit photo).\n\n\
Start with `pixl demo`, which runs the whole pipeline on the bundled example.\n\
Logs go to stderr; set RUST_LOG=debug for more.",
    after_help = "Example:\n  pixl demo --out demo-out"
)]
struct Cli {
    /// Print nothing but errors (no progress bars, no summaries).
    #[arg(long, short, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Run the whole pipeline on the bundled example scene and write an HTML report.
    Demo(cmd::demo::Args),
    /// Relight a photograph: from the photo and new lights in one command, or given its C_T.
    Relight(Box<cmd::relight::Args>),
    /// Create or inspect network weights.
    #[command(subcommand)]
    Model(cmd::model::Command),
    /// Split weights into parts of bounded size (e.g. 16 MiB, optionally as f16/bf16) and join them back.
    #[command(subcommand)]
    Weights(cmd::weights::Command),
    /// Benchmarks (paper timing protocol: warm-ups, then timed runs).
    #[command(subcommand)]
    Bench(cmd::bench::Command),
    /// Compose C_T = [albedo; shading; residual] from Cycles render passes (paper App. B).
    Compose(cmd::compose::Args),
    /// Inspect C_T files.
    #[command(subcommand)]
    Intrinsics(cmd::intrinsics::Command),
    /// Draw corrupted variants of a C_T (paper App. C) as a contact sheet.
    Augment(cmd::augment::Args),
    /// Build a scene (mesh, textures, scene.toml) from a photo and its depth map (estimated if not given).
    Reconstruct(cmd::reconstruct::Args),
    /// Path-trace a scene into Cycles-equivalent render passes.
    Render(cmd::render::Args),
    /// Add lights to a scene file.
    #[command(subcommand)]
    Light(cmd::light::Command),
    /// Inspect scene files (bounds, camera, axes, lights).
    #[command(subcommand)]
    Scene(cmd::scene::Command),
    /// Bridge to Blender (export a scene as a Blender Python script).
    #[command(subcommand)]
    Blender(cmd::blender::Command),
    /// Generate a synthetic multi-illumination dataset with exact intrinsics.
    Synth(cmd::synth::Args),
    /// Write the training targets (C_T) of a photo dataset with Marigold-IID Lighting.
    PrepareTargets(cmd::prepare_targets::Args),
    /// Train the network.
    Train(cmd::train::Args),
    /// Evaluate a model and baselines (PSNR / SSIM / LPIPS, timing).
    Eval(cmd::eval::Args),
    /// Pretrained estimators' weights: list them, fetch them once, show where they are.
    #[command(
        subcommand,
        after_help = "Examples:\n  pixl models list\n  pixl models fetch da3-metric\n  pixl models path da3-metric --json\n\n\
Lookup: --models DIR (or PIXL_MODELS_DIR), then the Hugging Face cache (HF_HUB_CACHE, HF_HOME/hub, \
~/.cache/huggingface/hub), then a download; --offline (PIXL_OFFLINE=1, HF_HUB_OFFLINE=1) never downloads."
    )]
    Models(cmd::models::Command),
    /// Estimate maps from a photo with pretrained estimators (depth: Depth Anything 3; materials and
    /// lighting: Marigold-IID; normals: Marigold Normals).
    #[command(
        subcommand,
        after_help = "Example:\n  pixl estimate depth photo.jpg -o depth.exr --preview depth.png"
    )]
    Estimate(cmd::estimate::Command),
    /// Place lights on a photo in the browser and watch it relight (a local web page).
    Studio(cmd::studio::Args),
    /// What this build and machine offer (features, CPU SIMD and threads, CUDA devices, where
    /// weights are looked for): paste its output into a bug report.
    Doctor(cmd::doctor::Args),
    /// Print a shell completion script (bash, zsh, fish, elvish, powershell) on stdout.
    #[command(
        after_help = "Examples:\n  pixl completions bash > ~/.local/share/bash-completion/completions/pixl\n  \
pixl completions zsh > ~/.zfunc/_pixl\n  pixl completions fish > ~/.config/fish/completions/pixl.fish"
    )]
    Completions {
        /// The shell.
        shell: clap_complete::Shell,
    },
}

fn main() -> ExitCode {
    pixl_nn::prefer_rayon_pool();
    pixl_nn::recycle_freed_buffers();
    let cli = Cli::parse();
    ctx::install_signal_handler();
    init_logging(cli.quiet);
    let ctx = Ctx::new(cli.quiet);
    match run(cli.command, &ctx) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", ctx::error_text(&e));
            ExitCode::FAILURE
        }
    }
}

fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::Demo(a) => cmd::demo::run(a, ctx),
        Command::Relight(a) => cmd::relight::run(*a, ctx),
        Command::Model(c) => cmd::model::run(c, ctx),
        Command::Weights(c) => cmd::weights::run(c, ctx),
        Command::Bench(c) => cmd::bench::run(c, ctx),
        Command::Compose(a) => cmd::compose::run(a, ctx),
        Command::Intrinsics(c) => cmd::intrinsics::run(c, ctx),
        Command::Augment(a) => cmd::augment::run(a, ctx),
        Command::Reconstruct(a) => cmd::reconstruct::run(a, ctx),
        Command::Render(a) => cmd::render::run(a, ctx),
        Command::Light(c) => cmd::light::run(c, ctx),
        Command::Scene(c) => cmd::scene::run(c, ctx),
        Command::Blender(c) => cmd::blender::run(c, ctx),
        Command::Synth(a) => cmd::synth::run(a, ctx),
        Command::PrepareTargets(a) => cmd::prepare_targets::run(a, ctx),
        Command::Train(a) => cmd::train::run(a, ctx),
        Command::Eval(a) => cmd::eval::run(a, ctx),
        Command::Models(c) => cmd::models::run(c, ctx),
        Command::Estimate(c) => cmd::estimate::run(c, ctx),
        Command::Studio(a) => cmd::studio::run(a, ctx),
        Command::Doctor(a) => cmd::doctor::run(a, ctx),
        Command::Completions { shell } => {
            use clap::CommandFactory;
            clap_complete::generate(shell, &mut Cli::command(), "pixl", &mut std::io::stdout());
            Ok(())
        }
    }
}

fn init_logging(quiet: bool) {
    use tracing_subscriber::EnvFilter;
    let default = if quiet { "error" } else { "info" };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(ctx::color_enabled())
        .with_target(false)
        .without_time()
        .try_init();
}
