//! `pixl doctor`: what this build and machine offer, in a form to paste into a bug report —
//! the build (version, profile, target, features), the CPU (model, SIMD level, matrix-kernel
//! threads, memory), CUDA (driver, devices, or why there is none) and where model weights
//! are looked for. `--json` prints the same as one JSON document (field names are a stable
//! interface; tests read them).
use crate::device::{self, CudaReport};
use crate::Ctx;
use pixl_estimate::hub::{self, Hub, HubOptions};
use serde_json::json;

#[derive(clap::Args, Debug)]
#[command(after_help = "Examples:\n  pixl doctor\n  pixl doctor --json > doctor.json")]
pub struct Args {
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub weights: crate::weights::WeightsArgs,
}

/// The CPU's SIMD extensions that matter for the matrix kernels, detected at run time.
fn simd_features() -> Vec<&'static str> {
    #[allow(unused_mut)]
    let mut v: Vec<&'static str> = Vec::new();
    #[cfg(target_arch = "x86_64")]
    {
        macro_rules! probe {
            ($($f:tt),*) => { $( if std::arch::is_x86_feature_detected!($f) { v.push($f); } )* };
        }
        probe!(
            "sse4.2",
            "avx",
            "avx2",
            "fma",
            "f16c",
            "avx512f",
            "avx512bw",
            "avx512vl",
            "avx512bf16",
            "avx512vnni"
        );
    }
    #[cfg(target_arch = "aarch64")]
    {
        macro_rules! probe {
            ($($f:tt),*) => { $( if std::arch::is_aarch64_feature_detected!($f) { v.push($f); } )* };
        }
        probe!("neon", "fp16", "bf16", "i8mm", "sve");
    }
    v
}

/// One word for the widest vector unit the kernels can use.
fn simd_level(features: &[&str]) -> &'static str {
    let has = |f: &str| features.contains(&f);
    if has("avx512f") {
        "avx512"
    } else if has("avx2") && has("fma") {
        "avx2+fma"
    } else if has("avx") {
        "avx"
    } else if has("sse4.2") {
        "sse4.2"
    } else if has("neon") {
        "neon"
    } else {
        "none detected"
    }
}

/// `/proc/cpuinfo`'s first "model name" (Linux), if any.
fn cpu_model() -> Option<String> {
    let text = std::fs::read_to_string("/proc/cpuinfo").ok()?;
    text.lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split_once(':'))
        .map(|(_, v)| v.trim().to_string())
}

fn gib(b: u64) -> String {
    format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64)
}

pub fn run(args: Args, ctx: &Ctx) -> anyhow::Result<()> {
    let ctx = &ctx.for_json(args.json);
    let features: Vec<&str> = [cfg!(feature = "cuda").then_some("cuda")]
        .into_iter()
        .flatten()
        .collect();
    let profile = if cfg!(debug_assertions) { "debug" } else { "release" };
    let target = format!("{}-{}", std::env::consts::ARCH, std::env::consts::OS);
    let simd = simd_features();
    let level = simd_level(&simd);
    let logical = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let threads = candle_core::utils::get_num_threads();
    let mem = pixl_pipeline::relight::meminfo();
    let cuda: CudaReport = device::cuda_report();
    let opts = HubOptions::from_env(args.weights.models.clone(), args.weights.offline);
    let hub = Hub::new(opts.clone());
    let estimators: Vec<serde_json::Value> = hub::REGISTRY
        .iter()
        .map(|spec| {
            let dir = match hub.locate(spec) {
                Ok(Some(r)) => Some(r.dir.display().to_string()),
                _ => None,
            };
            json!({ "name": spec.name, "present": dir.is_some(), "dir": dir })
        })
        .collect();
    let path_text = |p: &Option<std::path::PathBuf>| p.as_ref().map(|p| p.display().to_string());

    if args.json {
        return ctx.print_json(&json!({
            "version": env!("CARGO_PKG_VERSION"),
            "build": { "profile": profile, "target": target, "features": features },
            "cpu": {
                "model": cpu_model(),
                "logical_cores": logical,
                "threads": threads,
                "simd": level,
                "simd_features": simd,
                "memory_total_bytes": mem.map(|m| m.0),
                "memory_available_bytes": mem.map(|m| m.1),
            },
            "cuda": cuda,
            "weights": {
                "network": "built-in pixl-tiny-synth (used when --weights is not given)",
                "models_dir": path_text(&opts.models_dir),
                "hf_cache": path_text(&opts.hf_cache),
                "offline": opts.offline,
                "estimators": estimators,
            },
        }));
    }

    let features_text = if features.is_empty() {
        "none (CPU only)".to_string()
    } else {
        features.join(", ")
    };
    ctx.say(format!(
        "pixl {} ({profile} build, {target}; features: {features_text})",
        env!("CARGO_PKG_VERSION")
    ));
    ctx.say(format!(
        "CPU      {} — {logical} logical cores, matrix-kernel threads {threads}{}",
        cpu_model().unwrap_or_else(|| "unknown model".into()),
        if std::env::var_os("RAYON_NUM_THREADS").is_some() {
            " (RAYON_NUM_THREADS)"
        } else {
            ""
        }
    ));
    ctx.say(format!("SIMD     {level} ({})", simd.join(" ")));
    if let Some((total, avail)) = mem {
        ctx.say(format!("memory   {} total, {} available", gib(total), gib(avail)));
    }
    let built = cuda
        .built_for
        .as_deref()
        .map(|v| format!(", built for CUDA {v}"))
        .unwrap_or_default();
    let driver = cuda
        .driver_version
        .as_deref()
        .map(|v| format!(", driver CUDA {v}"))
        .unwrap_or_default();
    match &cuda.unavailable {
        Some(why) if cuda.devices.is_empty() => ctx.say(format!("CUDA     no device{built}{driver}: {why}")),
        Some(why) => ctx.say(format!("CUDA     devices found but unusable{built}{driver}: {why}")),
        None => ctx.say(format!("CUDA     available{built}{driver}")),
    }
    for d in &cuda.devices {
        ctx.say(format!(
            "  cuda:{}  {} (compute {}), {} total, {} free",
            d.ordinal,
            d.name,
            d.compute_capability,
            gib(d.memory_total_bytes),
            gib(d.memory_free_bytes)
        ));
    }
    ctx.say("weights  network: built-in pixl-tiny-synth unless --weights is given");
    ctx.say(format!(
        "         estimators: models folder {} then Hugging Face cache {}{}",
        path_text(&opts.models_dir).unwrap_or_else(|| "(none: --models / PIXL_MODELS_DIR)".into()),
        path_text(&opts.hf_cache).unwrap_or_else(|| "(none)".into()),
        if opts.offline { "; offline" } else { "" }
    ));
    for e in &estimators {
        let name = e["name"].as_str().unwrap_or_default();
        match e["dir"].as_str() {
            Some(dir) => ctx.say(format!("           {name:<20} {dir}")),
            None => ctx.say(format!("           {name:<20} not on disk")),
        }
    }
    Ok(())
}
