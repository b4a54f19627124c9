//! `pixl intrinsics`: inspect C_T files.
//!
//! `preview` draws `A | S | R | A⊙S+R` side by side as an 8-bit sRGB PNG. Display mapping
//! (`pixl_intrinsics::preview`): A clipped to [0, 1]; S, R and A⊙S+R divided by one shared
//! white point (1 for a rescaled C_T, compose's τ for an HDR one), clipped, sRGB-encoded.
use crate::Ctx;
use pixl_core::io::{write_png, PngDepth};
use pixl_intrinsics::ct::read_ct;
use pixl_intrinsics::preview::{preview_sheet, white_point};
use std::path::PathBuf;

#[derive(clap::Subcommand, Debug)]
pub enum Command {
    /// Draw albedo, shading, residual and their recomposition A⊙S+R side by side (PNG).
    #[command(after_help = "Example:\n  pixl intrinsics preview ct.exr -o sheet.png")]
    Preview(PreviewArgs),
}

#[derive(clap::Args, Debug)]
pub struct PreviewArgs {
    /// C_T file (EXR with albedo.R/G/B, shading.R/G/B, residual.R/G/B).
    pub ct: PathBuf,
    /// Output PNG.
    #[arg(short = 'o', long = "out", visible_alias = "output")]
    pub output: PathBuf,
}

pub fn run(command: Command, ctx: &Ctx) -> anyhow::Result<()> {
    match command {
        Command::Preview(a) => preview(a, ctx),
    }
}

fn preview(args: PreviewArgs, ctx: &Ctx) -> anyhow::Result<()> {
    pixl_core::output::check_output(&args.output, &["png"], &[&args.ct])?;
    let ct = read_ct(&args.ct)?;
    let sheet = preview_sheet(&ct)?;
    write_png(&args.output, &sheet, PngDepth::Eight)?;
    ctx.say(format!(
        "wrote {} (A | S | R | A⊙S+R, {}x{} each, white point {:.4})",
        args.output.display(),
        ct.width(),
        ct.height(),
        white_point(&ct)
    ));
    Ok(())
}
