//! Compute devices: `--device cpu|cuda[:N]` for every command that runs a network, and what
//! `pixl doctor` reports about CUDA.
//!
//! Contract: asking for CUDA never panics and never silently falls back to the CPU. A build
//! without the `cuda` feature says so; a CUDA build (made by `scripts/cuda-setup.sh`, whose
//! candle-core loads the CUDA libraries at run time) checks that the driver and the libraries
//! candle opens for every device (cuBLAS, cuBLASLt, cuRAND) can be loaded and that a device
//! exists before it creates one, and otherwise fails with "no CUDA device: <why>".
use anyhow::Context as _;
use candle_core::Device;

/// `--int8` (8-bit linear layers, `PixlRelight::quantize_int8`) runs only on the CPU in f32:
/// an error naming the flags to change otherwise.
pub fn check_int8(device: &Device, dtype: candle_core::DType) -> anyhow::Result<()> {
    if !device.is_cpu() || dtype != candle_core::DType::F32 {
        anyhow::bail!("--int8 is a CPU f32 option: drop --device or --dtype bf16, or drop --int8");
    }
    Ok(())
}

/// One CUDA device as the driver describes it.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CudaDeviceInfo {
    pub ordinal: usize,
    pub name: String,
    /// "major.minor", e.g. "9.0" for Hopper.
    pub compute_capability: String,
    pub memory_total_bytes: u64,
    pub memory_free_bytes: u64,
}

/// What this build and machine offer for CUDA.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CudaReport {
    /// The binary was built with the `cuda` feature.
    pub compiled: bool,
    /// The CUDA version the kernels and bindings were built for ("13.0"), when compiled.
    pub built_for: Option<String>,
    /// The driver's CUDA version ("13.0"), when a driver was found.
    pub driver_version: Option<String>,
    pub devices: Vec<CudaDeviceInfo>,
    /// Why no device can be used (`None` when at least one can).
    pub unavailable: Option<String>,
}

/// `cpu` or `cuda[:N]` (N defaults to 0).
pub fn parse_device(s: &str) -> anyhow::Result<Device> {
    match s {
        "cpu" => Ok(Device::Cpu),
        _ if s.starts_with("cuda") => {
            let ord = match s.strip_prefix("cuda").unwrap_or_default() {
                "" => "0",
                rest => rest
                    .strip_prefix(':')
                    .with_context(|| format!("--device {s:?}: expected cpu or cuda[:N]"))?,
            };
            let ord: usize = ord.parse().with_context(|| format!("--device {s}: bad CUDA ordinal"))?;
            cuda_device(ord).with_context(|| format!("--device {s}"))
        }
        _ => anyhow::bail!("--device {s:?}: expected cpu or cuda[:N]"),
    }
}

#[cfg(not(feature = "cuda"))]
fn cuda_device(_ordinal: usize) -> anyhow::Result<Device> {
    anyhow::bail!(
        "CUDA is not available in this build: it was built without the `cuda` feature \
         (build one with scripts/cuda-setup.sh)"
    )
}

#[cfg(feature = "cuda")]
fn cuda_device(ordinal: usize) -> anyhow::Result<Device> {
    let report = cuda_report();
    if let Some(why) = report.unavailable {
        anyhow::bail!("no CUDA device: {why}");
    }
    if ordinal >= report.devices.len() {
        anyhow::bail!(
            "no CUDA device {ordinal}: this machine has {} (cuda:0 to cuda:{})",
            report.devices.len(),
            report.devices.len() - 1
        );
    }
    Device::new_cuda(ordinal).with_context(|| format!("could not start CUDA device {ordinal}"))
}

/// Probes the CUDA driver and devices without creating a candle device.
#[cfg(not(feature = "cuda"))]
pub fn cuda_report() -> CudaReport {
    CudaReport {
        compiled: false,
        built_for: None,
        driver_version: None,
        devices: Vec::new(),
        unavailable: Some("this build has no `cuda` feature (build one with scripts/cuda-setup.sh)".into()),
    }
}

/// Probes the CUDA driver and devices without creating a candle device.
#[cfg(feature = "cuda")]
pub fn cuda_report() -> CudaReport {
    use candle_core::cuda::cudarc::{cublas, cublaslt, curand, driver};
    let mut report = CudaReport {
        compiled: true,
        built_for: option_env!("CUDARC_CUDA_VERSION")
            .and_then(|v| v.parse::<i32>().ok())
            .map(cuda_version_text),
        driver_version: None,
        devices: Vec::new(),
        unavailable: None,
    };
    // SAFETY: these only try to open the shared libraries (dlopen) and close them again.
    if !unsafe { driver::sys::is_culib_present() } {
        report.unavailable = Some("the CUDA driver library (libcuda.so.1) was not found".into());
        return report;
    }
    let mut version = 0i32;
    // SAFETY: the library is present; cuDriverGetVersion writes one int and needs no cuInit.
    if unsafe { driver::sys::cuDriverGetVersion(&mut version) } == driver::sys::CUresult::CUDA_SUCCESS {
        report.driver_version = Some(cuda_version_text(version));
    }
    let count = match driver::CudaContext::device_count() {
        Ok(n) => n.max(0) as usize,
        Err(e) => {
            report.unavailable = Some(format!("the CUDA driver did not start: {e}"));
            return report;
        }
    };
    for ordinal in 0..count {
        let Ok(ctx) = driver::CudaContext::new(ordinal) else {
            continue;
        };
        let (free, total) = ctx.mem_get_info().unwrap_or((0, 0));
        report.devices.push(CudaDeviceInfo {
            ordinal,
            name: ctx.name().unwrap_or_else(|_| "unknown".into()),
            compute_capability: ctx
                .compute_capability()
                .map(|(a, b)| format!("{a}.{b}"))
                .unwrap_or_else(|_| "unknown".into()),
            memory_total_bytes: total as u64,
            memory_free_bytes: free as u64,
        });
    }
    let missing: Vec<&str> = [
        // SAFETY: as above, dlopen probes only.
        (unsafe { cublas::sys::is_culib_present() }, "cuBLAS (libcublas.so.13)"),
        (
            unsafe { cublaslt::sys::is_culib_present() },
            "cuBLASLt (libcublasLt.so.13)",
        ),
        (unsafe { curand::sys::is_culib_present() }, "cuRAND (libcurand.so.10)"),
    ]
    .into_iter()
    .filter(|(present, _)| !present)
    .map(|(_, name)| name)
    .collect();
    if report.devices.is_empty() {
        report.unavailable = Some("the driver reports no usable GPU".into());
    } else if !missing.is_empty() {
        report.unavailable = Some(format!(
            "{} not found; put the CUDA 13 libraries' folder on LD_LIBRARY_PATH",
            missing.join(", ")
        ));
    }
    report
}

/// 13000 -> "13.0".
#[cfg(feature = "cuda")]
fn cuda_version_text(v: i32) -> String {
    format!("{}.{}", v / 1000, (v % 1000) / 10)
}
