//! `pixl relight`: `Î_T = f_θ(I_S, C_T)` for one photograph (paper §3.4, step 5).
//!
//! Reads the source (PNG/JPEG as stored values in [0, 1], EXR as stored; non-finite values are
//! refused), the C_T file (`albedo.R/G/B`, `shading.R/G/B`, `residual.R/G/B`) and the weights
//! (config from the file's metadata), checks the sizes agree, runs one forward pass and writes
//! the result atomically (`.png` 16-bit, `.exr` f32). With freshly initialised weights the output
//! equals the source exactly.
use crate::Ctx;
use anyhow::{bail, Context};
use candle_core::{Device, Tensor};
use pixl_core::Image;
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Example:\n  pixl relight --source photo.png --intrinsics ct.exr --weights model.safetensors --out relit.png\n\n\
The network pads to a multiple of its patch size internally; any size and aspect ratio works."
)]
pub struct Args {
    /// Source photograph I_S (.png, .jpg or .exr; RGB, values in [0, 1]).
    #[arg(long)]
    pub source: PathBuf,
    /// Target intrinsics C_T (.exr with albedo.*, shading.* and residual.* channels), same size.
    #[arg(long)]
    pub intrinsics: PathBuf,
    /// Network weights (.safetensors written by `pixl model init` or `pixl train`).
    #[arg(long)]
    pub weights: PathBuf,
    /// Output image (.png: 16-bit; .exr: 32-bit float).
    #[arg(long)]
    pub out: PathBuf,
    /// Compute dtype of the network.
    #[arg(long, value_enum, default_value_t = super::bench::DtypeArg::F32)]
    pub dtype: super::bench::DtypeArg,
    /// Device for the network: cpu, or cuda[:N] (needs a build with `--features cuda`).
    #[arg(long, default_value = "cpu")]
    pub device: String,
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ext = pixl_core::io::extension(&args.out);
    if !["png", "exr", "jpg", "jpeg"].contains(&ext.as_str()) {
        bail!("{}: output must be .png or .exr", args.out.display());
    }
    let src = pixl_core::io::read_rgb_finite(&args.source)?;
    let ct = pixl_intrinsics::ct::read_ct(&args.intrinsics)?;
    if (src.width, src.height) != (ct.width(), ct.height()) {
        bail!(
            "source {} is {}x{} but intrinsics {} are {}x{}; they must be the same size",
            args.source.display(),
            src.width,
            src.height,
            args.intrinsics.display(),
            ct.width(),
            ct.height()
        );
    }
    let device = super::eval::parse_device(&args.device)?;
    let (cfg, model) = pixl_model::load(&args.weights, &device, args.dtype.into())?;
    tracing::info!("loaded {} ({} parameters)", args.weights.display(), cfg.param_count());
    let src = clamp_to_unit(&src, &args.source);
    let relit = relight_image(&model, &src, &ct.to_chw(), &device)?;
    pixl_core::io::write_image(&args.out, &relit)?;
    ctx.say(format!(
        "wrote {} ({}x{})",
        args.out.display(),
        relit.width,
        relit.height
    ));
    Ok(())
}

/// The paper's source is in [0, 1]; EXR sources may exceed it. Clamped values are reported.
fn clamp_to_unit(img: &Image, path: &Path) -> Image {
    let outside = img.data.iter().filter(|v| !(0.0..=1.0).contains(*v)).count();
    if outside == 0 {
        return img.clone();
    }
    tracing::warn!(
        "{}: {outside} values outside [0, 1] clamped (the network expects I_S in [0, 1])",
        path.display()
    );
    img.map(|v| v.clamp(0.0, 1.0))
}

/// Runs the network on one image and its planar `9 × H × W` C_T.
pub fn relight_image(
    model: &pixl_model::PixlRelight,
    src: &Image,
    ct_chw: &[f32],
    device: &Device,
) -> anyhow::Result<Image> {
    let (w, h) = (src.width, src.height);
    let src_t = Tensor::from_vec(src.to_chw(), (1, 3, h, w), device)?;
    let ct_t = Tensor::from_vec(ct_chw.to_vec(), (1, 9, h, w), device)?;
    let out = model.forward(&src_t, &ct_t).context("network forward pass")?;
    let chw = out.flatten_all()?.to_vec1::<f32>()?;
    Ok(Image::from_chw(w, h, 3, &chw)?)
}
