//! `pixl studio`: a local web page to place lights on a photo and watch it relight. A thin
//! wrapper over `pixl_studio`: it reads the flags, opens the photo or scene file, binds the
//! address (loopback unless `--host` says otherwise, with a warning), prints the URL and serves
//! until interrupted. "Light like this photo" uses Marigold-IID-Lighting when its weights are on
//! disk (never downloaded here), loaded on the first such request.
use crate::Ctx;
use anyhow::{bail, Context, Result};
use pixl_studio::{Studio, StudioConfig};
use std::path::PathBuf;

#[derive(clap::Args, Debug)]
#[command(
    after_help = "Examples:\n  pixl studio photo.jpg\n  pixl studio photo.jpg --depth depth.exr --open\n  \
pixl studio assets/demo/scene.toml --port 8080\n  pixl studio --weights W.safetensors --out my-lights/\n\n\
Opens http://127.0.0.1:PORT/ (printed). Click the photo to place a light, drag it, pick a preset; the\n\
quick preview follows at once, the path-traced render and the relit photo when you stop. Without a\n\
depth map the geometry is a labelled stand-in (a ground plane and a backdrop). \"Light like photo…\"\n\
relights the photo with the lighting of another photo of the same view; it needs Marigold-IID-Lighting's\n\
weights on disk (`pixl models fetch marigold-lighting`, licence OpenRAIL++-M; about 2.6 GB, loaded on\n\
first use). The JSON API behind the page is documented in crates/pixl-studio/README.md."
)]
pub struct Args {
    /// A photo (.png, .jpg), a video (.mp4, .mov, … or frames/%04d.png: lights are placed on its
    /// first frames, "Export video" relights every frame) or a scene file (.toml, .json) to open.
    pub input: Option<PathBuf>,
    /// A depth map of the photo (.exr, 16-bit .png, .npy).
    #[arg(long)]
    pub depth: Option<PathBuf>,
    /// What the depth map holds: metric (metres), relative, or disparity.
    #[arg(long, default_value = "metric")]
    pub depth_kind: String,
    /// Port (0: any free port).
    #[arg(long, default_value_t = 8765)]
    pub port: u16,
    /// Address to listen on. Default 127.0.0.1 (this machine only); anything else exposes the
    /// session, and the files it can write, to the network.
    #[arg(long, default_value = "127.0.0.1")]
    pub host: String,
    #[arg(long, value_name = "bundled|pixlrelight|FILE", help = crate::weights::NETWORK_WEIGHTS_HELP)]
    pub weights: Option<PathBuf>,
    /// 8-bit matrix products in the network's linear layers (CPU with AVX-512 VNNI; elsewhere
    /// a warning and f32): a faster relit preview, see `pixl relight --int8`.
    #[arg(long)]
    pub int8: bool,
    /// Where "save scene" and the exports write.
    #[arg(long, default_value = "studio-out")]
    pub out: PathBuf,
    /// Long side of the working size (render and network).
    #[arg(long, default_value_t = 512)]
    pub size: usize,
    /// Vertical field of view assumed for the photo, degrees.
    #[arg(long, default_value_t = 50.0)]
    pub fov: f32,
    /// Samples per pixel of the final render stage.
    #[arg(long, default_value_t = 16)]
    pub spp: u32,
    /// Open the page in the default browser.
    #[arg(long)]
    pub open: bool,
    /// Device of the depth and lighting estimators: cpu, or cuda[:N].
    #[arg(long, default_value = "cpu")]
    pub device: String,
    #[command(flatten)]
    pub models: crate::weights::WeightsArgs,
}

/// Depth Anything 3 for photos loaded without a depth map, as `pixl relight` estimates depth:
/// `da3-metric` when its weights are on disk, else `da3-mono` (relative depth, mapped to 1-10 m).
/// The studio never downloads (`pixl models fetch da3-metric` does); with neither on disk,
/// `None`: photos get the labelled fallback geometry, and a note says how to get the weights.
fn depth_estimator(args: &Args, ctx: &Ctx) -> Result<Option<std::sync::Arc<dyn pixl_studio::DepthEstimator>>> {
    use pixl_estimate::da3::Da3Variant;
    let hub = args.models.hub();
    for (name, variant) in [("da3-metric", Da3Variant::Metric), ("da3-mono", Da3Variant::Mono)] {
        let spec = pixl_estimate::hub::lookup(name)?;
        let Some(resolved) = hub.locate(spec)? else { continue };
        let device = crate::device::parse_device(&args.device)?;
        let net = pixl_pipeline::estimators::Da3Depth::load(&resolved.dir, variant, spec.name, &device)?;
        ctx.say(format!(
            "depth of photos without a depth map: {name} ({}, from {})",
            spec.licence, resolved.source
        ));
        return Ok(Some(std::sync::Arc::new(net)));
    }
    ctx.say(
        "no Depth Anything 3 weights on disk (`pixl models fetch da3-metric`, or --models DIR): photos \
         without a depth map get a labelled stand-in geometry",
    );
    Ok(None)
}

/// Marigold-IID-Lighting behind "light like this photo", loaded on its first use (its weights
/// take gigabytes of memory, and most sessions never ask).
struct LazyLighting {
    dir: PathBuf,
    label: &'static str,
    device: candle_core::Device,
    model: std::sync::OnceLock<std::result::Result<pixl_pipeline::estimators::MarigoldLighting, String>>,
}

impl pixl_studio::LightingEstimator for LazyLighting {
    fn name(&self) -> String {
        format!("Marigold-IID Lighting ({})", self.label)
    }

    fn decompose(
        &self,
        photo: &pixl_core::Image,
        observer: &dyn pixl_pipeline::Observer,
    ) -> pixl_pipeline::Result<pixl_pipeline::like::Decomposition> {
        let model = self.model.get_or_init(|| {
            let opts = pixl_pipeline::estimators::MarigoldOptions {
                steps: Some(pixl_pipeline::like::LIKE_STEPS),
                ..Default::default()
            };
            pixl_pipeline::estimators::MarigoldLighting::load(&self.dir, opts, self.label, &self.device)
                .map_err(|e| e.to_string())
        });
        match model {
            Ok(m) => m.decompose(photo, observer),
            Err(e) => Err(pixl_pipeline::PipelineError::input(e.clone())),
        }
    }
}

/// Marigold-IID-Lighting for "light like this photo" when its weights are on disk (the studio
/// never downloads them); `None` otherwise, with a note saying how to get them.
fn lighting_estimator(args: &Args, ctx: &Ctx) -> Result<Option<std::sync::Arc<dyn pixl_studio::LightingEstimator>>> {
    let spec = pixl_estimate::hub::lookup("marigold-lighting")?;
    let Some(resolved) = args.models.hub().locate(spec)? else {
        ctx.say(
            "no Marigold-IID-Lighting weights on disk (`pixl models fetch marigold-lighting`, or --models DIR): \
             \"light like this photo\" is off",
        );
        return Ok(None);
    };
    ctx.say(format!(
        "light like a photo: {} ({}, from {}; loaded on first use)",
        spec.name, spec.licence, resolved.source
    ));
    Ok(Some(std::sync::Arc::new(LazyLighting {
        dir: resolved.dir,
        label: spec.name,
        device: crate::device::parse_device(&args.device)?,
        model: std::sync::OnceLock::new(),
    })))
}

pub fn run(args: Args, ctx: &Ctx) -> Result<()> {
    let depth_kind = pixl_studio::DepthKind::parse(&args.depth_kind)
        .with_context(|| format!("--depth-kind {:?}: give metric, relative or disparity", args.depth_kind))?;
    if args.depth.is_some() && args.input.is_none() {
        bail!("--depth needs a photo");
    }
    if !(args.fov.is_finite() && args.fov > 1.0 && args.fov < 179.0) {
        bail!("--fov {} must be between 1 and 179 degrees", args.fov);
    }
    if args.size < 16 || args.size > 4096 {
        bail!("--size {} must be between 16 and 4096", args.size);
    }
    let estimator = match (&args.input, &args.depth) {
        (Some(i), None) if !matches!(pixl_core::io::extension(i).as_str(), "toml" | "json") => {
            depth_estimator(&args, ctx)?
        }
        (None, _) => depth_estimator(&args, ctx)?,
        _ => None,
    };
    let lighting = lighting_estimator(&args, ctx)?;
    let choice = args.weights.as_deref().map(|p| p.to_string_lossy().into_owned());
    let weights = crate::weights::network_weights(choice.as_deref(), &args.models, ctx)?;
    if weights
        .as_deref()
        .is_some_and(|w| !pixl_pipeline::relight::is_native(w).unwrap_or(true))
    {
        eprintln!(
            "weights: PIXLRelight release {} — licence {}",
            weights.as_deref().map(|w| w.display().to_string()).unwrap_or_default(),
            pixl_model::official::LICENCE
        );
    }
    let config = StudioConfig {
        estimator,
        lighting,
        work_side: args.size,
        stages: vec![
            pixl_studio::Stage {
                side: (args.size / 2).max(16),
                spp: 4.min(args.spp.max(1)),
            },
            pixl_studio::Stage {
                side: args.size,
                spp: args.spp.max(1),
            },
        ],
        fov_y_deg: args.fov,
        weights,
        int8: args.int8,
        out_dir: args.out.clone(),
        ..StudioConfig::default()
    };
    let studio = Studio::new(config).context("starting the studio")?;
    if let Some(input) = &args.input {
        let ext = pixl_core::io::extension(input);
        if ext == "toml" || ext == "json" {
            studio
                .open_scene_file(input)
                .with_context(|| format!("opening {}", input.display()))?;
        } else {
            let video = pixl_pipeline::video::is_video(input);
            if video {
                studio.load_video_file(input)
            } else {
                studio.load_photo_file(input)
            }
            .with_context(|| format!("opening {}", input.display()))?;
            if let Some(d) = &args.depth {
                let bytes = std::fs::read(d).with_context(|| format!("reading {}", d.display()))?;
                let name = d
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default();
                studio
                    .load_depth_bytes(&bytes, &name, depth_kind)
                    .with_context(|| format!("using the depth map {}", d.display()))?;
            }
        }
    }
    let loopback = matches!(args.host.as_str(), "127.0.0.1" | "localhost" | "::1");
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .worker_threads(2)
        .build()
        .context("starting the async runtime")?;
    rt.block_on(async {
        let addr = (args.host.as_str(), args.port);
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .with_context(|| format!("cannot listen on {}:{}", args.host, args.port))?;
        let local = listener.local_addr()?;
        if !loopback {
            eprintln!(
                "warning: listening on {local}: anyone who can reach this address can use the session and make it \
                 write files to {}",
                args.out.display()
            );
        }
        let host = if local.ip().is_unspecified() {
            "127.0.0.1".to_string()
        } else {
            local.ip().to_string()
        };
        let host = if host.contains(':') { format!("[{host}]") } else { host };
        let url = format!("http://{host}:{}/", local.port());
        // The URL is the command's output: printed even with --quiet.
        println!("{url}");
        ctx.say("pixl studio is running; press Ctrl+C to stop");
        if args.open {
            if let Err(e) = std::process::Command::new("xdg-open").arg(&url).spawn() {
                tracing::warn!("could not open a browser ({e}); open {url} yourself");
            }
        }
        pixl_studio::serve(studio, listener).await.context("serving")
    })
}
