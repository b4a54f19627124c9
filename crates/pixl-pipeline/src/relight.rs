//! The network's step (paper §3.2): `Î_T = f_θ(I_S, C_T)` for a photo of any size.
//!
//! The network runs at a working size (long side `max_side`; the paper trains at 512) and its
//! gain and bias are resized bilinearly to the photo and applied there
//! (`pixl_model::fullres`), so the output has the photo's size and detail. A C_T at the photo's
//! size is area-averaged to the working size; one at the working size is used as is.
//!
//! Before any work the network's peak memory is planned ([`Budget`]: the network's plan, its
//! 8-bit weight copies, the full-size buffers) and a request that does not fit the limit is
//! refused with the figure and a working size that fits ([`check_budget`]).
//!
//! Weights: a file — one of ours (our format, config in the metadata) or the paper's released
//! checkpoint (`model.safetensors` with its `config.yaml` beside it, loaded unchanged through
//! `pixl_model::official`; [`Network::licence`] then holds its non-commercial licence, which
//! callers show) — else the bundled demo weights compiled into the binary ([`BUNDLED_WEIGHTS`], a
//! `dim128-p8` demo model; `assets/demo-weights/README.md`). Both kinds take the photo as sRGB values in
//! `[0, 1]` and are edge-padded to their patch size, so everything after loading is shared.
use crate::error::{PipelineError, Result};
use crate::observe::{Observer, Stage};
use candle_core::{DType, Device};
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;
use pixl_model::fullres::{self, MemoryPlan};
use std::path::Path;

/// The bundled demo weights (the `dim128-p8` demo model, see `assets/demo-weights/README.md`).
pub const BUNDLED_WEIGHTS: &[u8] = include_bytes!("../../../assets/demo-weights/pixl-tiny-synth.safetensors");
/// How the bundled weights are named in messages.
pub const BUNDLED_NAME: &str = "bundled pixl-tiny-synth.safetensors";
/// Default long side of the working size.
pub const DEFAULT_MAX_SIDE: usize = 1024;

/// The network, its config, and where it came from.
pub struct Network {
    pub model: pixl_model::PixlRelight,
    pub cfg: pixl_model::Config,
    /// The weights file, or [`BUNDLED_NAME`].
    pub name: String,
    pub dtype: DType,
    /// Bytes of the 8-bit weight copies (`int8`; 0 otherwise), held beside the f32 weights.
    pub int8_bytes: u64,
    /// The weights' licence where it restricts use (the released checkpoint's
    /// [`pixl_model::official::LICENCE`]); `None` for ours.
    pub licence: Option<&'static str>,
}

/// How many networks this process has loaded ([`Network::loads`]).
static LOADS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

impl Network {
    /// How many networks this process has loaded so far (a batch loads one).
    pub fn loads() -> usize {
        LOADS.load(std::sync::atomic::Ordering::Relaxed)
    }

    /// Loads `weights` (or the bundled ones) on `device` in `dtype`; with `int8`, the linear
    /// layers are quantized where the CPU has AVX-512 VNNI (a warning and f32 elsewhere).
    pub fn load(weights: Option<&Path>, dtype: DType, device: &Device, int8: bool) -> Result<Network> {
        LOADS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut licence = None;
        let (cfg, mut model, name) = match weights {
            Some(w) if is_native(w)? => {
                let (cfg, model) = pixl_model::load(w, device, dtype)?;
                (cfg, model, w.display().to_string())
            }
            Some(w) => {
                let table = pixl_model::official::name_table(None)?;
                let off = pixl_model::official::load(w, None, &table, device, dtype)?;
                for note in &off.inspection.notes {
                    tracing::info!("{}: {note}", w.display());
                }
                licence = Some(pixl_model::official::LICENCE);
                (off.config, off.model, format!("PIXLRelight release {}", w.display()))
            }
            None => {
                let (cfg, model) = pixl_model::load_bytes(Path::new(BUNDLED_NAME), BUNDLED_WEIGHTS, device, dtype)?;
                (cfg, model, BUNDLED_NAME.to_string())
            }
        };
        if int8 {
            match model.quantize_int8()? {
                0 => tracing::warn!("--int8: this CPU has no AVX-512 VNNI; the network runs in f32"),
                n => tracing::info!("--int8: {n} linear layers quantized to 8 bits"),
            }
        }
        tracing::info!(
            "weights: {name} ({} parameters, patch {})",
            cfg.param_count(),
            cfg.patch
        );
        let int8_bytes = model.int8_bytes();
        Ok(Network {
            model,
            cfg,
            name,
            dtype,
            int8_bytes,
            licence,
        })
    }

    /// One line naming the weights, with their licence where it restricts use.
    pub fn describe(&self) -> String {
        let params = self.cfg.param_count() as f64 / 1e6;
        match self.licence {
            Some(l) => format!("weights: {} ({params:.1} M parameters) — licence {l}", self.name),
            None => format!("weights: {} ({params:.1} M parameters)", self.name),
        }
    }
}

/// Whether `path` is one of our checkpoints (our `format` in its metadata) rather than a file
/// for the released model's loader. Reads the header only.
pub fn is_native(path: &Path) -> Result<bool> {
    let (_, meta) = pixl_model::official::read_header(path)?;
    Ok(meta.get("format").map(String::as_str) == Some(pixl_model::checkpoint::FORMAT))
}

/// Bytes of memory available now (Linux `MemAvailable`), if known.
pub fn available_memory() -> Option<u64> {
    meminfo().map(|m| m.1)
}

/// `(total, available)` bytes from `/proc/meminfo` (Linux), if readable.
pub fn meminfo() -> Option<(u64, u64)> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let field = |name: &str| -> Option<u64> {
        let line = text.lines().find(|l| l.starts_with(name))?;
        let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
        Some(kb * 1024)
    };
    Some((field("MemTotal:")?, field("MemAvailable:")?))
}

/// Gigabytes, two decimals.
pub fn gb(bytes: u64) -> String {
    format!("{:.2} GB", bytes as f64 / 1e9)
}

/// What relighting a `w × h` photo at `max_side` costs: the working size, the network's plan,
/// the 8-bit weight copies, and the full-size buffers (`full_bytes_per_px` per photo pixel).
#[derive(Clone, Debug)]
pub struct Budget {
    pub work: (usize, usize),
    pub plan: MemoryPlan,
    pub int8: u64,
    pub full: u64,
}

impl Budget {
    pub fn new(net: &Network, size: (usize, usize), max_side: usize, full_bytes_per_px: u64) -> Self {
        let work = fullres::working_size(size.0, size.1, max_side);
        Budget {
            work,
            plan: fullres::plan_memory(&net.cfg, net.dtype, work.0, work.1),
            int8: net.int8_bytes,
            full: full_bytes_per_px * (size.0 * size.1) as u64,
        }
    }

    /// The network's planned peak with its 8-bit weight copies.
    pub fn network(&self) -> u64 {
        self.plan.peak_bytes() + self.int8
    }

    pub fn total(&self) -> u64 {
        self.network() + self.full
    }
}

/// Plans the memory of relighting a `size` photo at `max_side` and refuses a request above
/// `max_memory` bytes (default: the memory available now), naming the figure and a `--max-side`
/// that fits.
pub fn check_budget(
    net: &Network,
    size: (usize, usize),
    max_side: usize,
    per_px: u64,
    max_memory: Option<u64>,
) -> Result<Budget> {
    let budget = Budget::new(net, size, max_side, per_px);
    let (limit, whence) = match max_memory {
        Some(b) => (b, "--max-memory"),
        None => match available_memory() {
            Some(b) => (b, "available now"),
            None => (u64::MAX, "unknown"),
        },
    };
    let (stage, _) = budget.plan.peak();
    tracing::info!(
        "working size {}x{} ({} tokens): planned peak {} ({stage}) + {} for the full-size image",
        budget.work.0,
        budget.work.1,
        budget.plan.tokens,
        gb(budget.network()),
        gb(budget.full)
    );
    if budget.total() > limit {
        // The largest --max-side (a multiple of 64, or 16 at the least) that fits.
        let mut fits = None;
        let mut side = max_side.min(size.0.max(size.1));
        while side > 16 {
            side = if side > 64 { (side - 1) / 64 * 64 } else { 16 };
            let b = Budget::new(net, size, side, per_px);
            if b.total() <= limit {
                fits = Some((side, b.total()));
                break;
            }
        }
        let hint = match fits {
            Some((s, bytes)) => format!("lower --max-side (e.g. --max-side {s} needs about {})", gb(bytes)),
            None => "even the smallest working size does not fit; free memory".to_string(),
        };
        return Err(PipelineError::input(format!(
            "relighting this {}x{} photo at a working size of {}x{} (--max-side {max_side}) needs about {} \
             (network peak {} in the {stage}, over {} tokens; full-size image {}), more than the {} {whence}; {hint}, \
             or raise --max-memory",
            size.0,
            size.1,
            budget.work.0,
            budget.work.1,
            gb(budget.total()),
            gb(budget.network()),
            budget.plan.tokens,
            gb(budget.full),
            gb(limit),
        )));
    }
    Ok(budget)
}

/// Planar `9 × wh × ww` C_T at the working size: area-averaged from another size, or as is.
pub fn ct_at_working_size(ct: &Ct, work: (usize, usize)) -> Result<Vec<f32>> {
    Ok(ct.to_chw_at(work.0, work.1)?)
}

/// Runs the network at the working size `work` on `photo` (RGB, values in [0, 1], any size)
/// under `ct_work` (planar, at `work`) and applies its result to the full-size photo; progress
/// over the network's blocks goes to `observer`.
pub fn relight(
    net: &Network,
    photo: Image,
    ct_work: &[f32],
    work: (usize, usize),
    device: &Device,
    observer: &dyn Observer,
) -> Result<Image> {
    observer.begin(Stage::Network, 0);
    let mut progress = |done: usize, total: usize, _stage: &str| {
        observer.progress(Stage::Network, done as u64, total as u64);
    };
    let relit = fullres::relight_full(&net.model, photo, ct_work, work, device, &mut progress)
        .map_err(|e| PipelineError::from(e).context("relighting"));
    observer.end(Stage::Network);
    relit
}
