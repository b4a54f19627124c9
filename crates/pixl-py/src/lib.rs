//! `import pixlrelight`: the relighting pipeline (`pixl_pipeline`) from Python, on numpy arrays.
//!
//! **Contract.**
//! - Images in: numpy arrays `H × W × 3`, `uint8` (divided by 255) or `float32`/`float64` with
//!   values in `[0, 1]` (sRGB-encoded, as a PNG or JPEG stores them), or PIL images (converted to
//!   RGB). Anything else — another dtype, another shape, values outside `[0, 1]` or not finite —
//!   raises `TypeError` or `ValueError` naming what is wrong. Images out: `float32 H × W × 3`.
//! - Depth in: `None` (estimated with Depth Anything 3, weights on disk), a path to a depth file
//!   (EXR, 16-bit PNG, `.npy`; as `pixl relight --depth`), or a float `H × W` array of metric
//!   z-depth (0 = missing).
//! - Weights: `Model.load(weights="bundled" | "pixlrelight" | path)` loads the network once; every
//!   call given `model=` reuses it (`Model.loads()` counts the loads of the process). The
//!   estimators' weights are looked up on disk only (`models_dir`, `PIXL_MODELS_DIR`, the Hugging
//!   Face cache) — `pixl models fetch NAME` downloads them — and a missing one raises
//!   `FileNotFoundError` saying so.
//! - The GIL is released while the pipeline works; `progress(stage, done, total)`, if given, is
//!   called from the worker threads with the GIL taken (exceptions in it are ignored).
//! - Errors of the pipeline raise `ValueError` (bad input, with the message `pixl` prints),
//!   `OSError` (files) or `RuntimeError` (anything else).
// The pipeline's error is returned once per call from the worker closures and turned into a
// Python exception at once; boxing it there would gain nothing.
#![allow(clippy::result_large_err)]
use candle_core::{DType, Device};
use numpy::ndarray::{Array2, Array3};
use numpy::{IntoPyArray, PyArray2, PyArray3, PyReadonlyArrayDyn};
use pixl_core::Image;
use pixl_estimate::hub::{self, Hub, HubOptions};
use pixl_pipeline::depth::DepthFile;
use pixl_pipeline::estimators::{Da3Depth, MarigoldLighting, MarigoldOptions};
use pixl_pipeline::job::{self, DepthSource, Job, LightSet, Lighting};
use pixl_pipeline::relight::Network;
use pixl_pipeline::{Observer, Photo, PipelineError, Stage};
use pixl_render::depth::DepthMap;
use pyo3::exceptions::{PyFileNotFoundError, PyOSError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A pipeline error as the Python exception a caller expects.
fn py_err(e: PipelineError) -> PyErr {
    let msg = e.to_string();
    let mut inner = &e;
    while let PipelineError::Stage { source, .. } = inner {
        inner = source;
    }
    match inner {
        PipelineError::Input(_) => PyValueError::new_err(msg),
        PipelineError::Io { .. } => PyOSError::new_err(msg),
        _ => PyRuntimeError::new_err(msg),
    }
}

fn parse_device(name: &str) -> PyResult<Device> {
    match name {
        "cpu" => Ok(Device::Cpu),
        s if s == "cuda" || s.starts_with("cuda:") => {
            let n = s.strip_prefix("cuda:").unwrap_or("0");
            let n: usize = n
                .parse()
                .map_err(|_| PyValueError::new_err(format!("device {s:?}: expected cpu, cuda or cuda:N")))?;
            Device::new_cuda(n).map_err(|e| PyRuntimeError::new_err(format!("device {s:?}: {e}")))
        }
        s => Err(PyValueError::new_err(format!(
            "device {s:?}: expected cpu, cuda or cuda:N"
        ))),
    }
}

/// An image argument as an RGB [`Image`] with values in `[0, 1]` (see the module docs).
fn image_arg(py: Python<'_>, what: &str, obj: &Bound<'_, PyAny>) -> PyResult<Image> {
    let mut obj = obj.clone();
    if obj.hasattr("convert")? && obj.hasattr("mode")? && !obj.hasattr("shape")? {
        obj = obj.call_method1("convert", ("RGB",))?;
    }
    let arr = py.import("numpy")?.call_method1("asarray", (obj,))?;
    let dtype: String = arr.getattr("dtype")?.getattr("name")?.extract()?;
    let shape: Vec<usize> = arr.getattr("shape")?.extract()?;
    if shape.len() != 3 || shape[2] != 3 || shape[0] == 0 || shape[1] == 0 {
        return Err(PyValueError::new_err(format!(
            "{what}: expected an H x W x 3 RGB image, got an array of shape {shape:?}"
        )));
    }
    let (h, w) = (shape[0], shape[1]);
    let data: Vec<f32> = match dtype.as_str() {
        "uint8" => {
            let a: PyReadonlyArrayDyn<'_, u8> = arr.extract()?;
            a.as_array().iter().map(|v| *v as f32 / 255.0).collect()
        }
        "float32" | "float64" => {
            let a = arr.call_method1("astype", ("float32",))?;
            let a: PyReadonlyArrayDyn<'_, f32> = a.extract()?;
            let v: Vec<f32> = a.as_array().iter().copied().collect();
            if let Some(bad) = v.iter().find(|x| !x.is_finite() || **x < 0.0 || **x > 1.0) {
                return Err(PyValueError::new_err(format!(
                    "{what}: float values must be finite and in [0, 1] (found {bad}); divide 8-bit values by 255"
                )));
            }
            v
        }
        other => {
            return Err(PyTypeError::new_err(format!(
                "{what}: dtype {other} is not supported; give uint8, or float32 in [0, 1]"
            )))
        }
    };
    Image::from_vec(w, h, 3, data).map_err(|e| PyValueError::new_err(format!("{what}: {e}")))
}

fn image_out<'py>(py: Python<'py>, img: &Image) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let c = img.channels;
    let data: Vec<f32> = (0..img.width * img.height)
        .flat_map(|i| (0..3).map(move |k| (i, k)))
        .map(|(i, k)| img.data[i * c + k.min(c - 1)])
        .collect();
    let a =
        Array3::from_shape_vec((img.height, img.width, 3), data).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py))
}

/// Progress from the pipeline to an optional Python callable.
struct Progress(Option<Py<PyAny>>);

impl Progress {
    fn call(&self, stage: Stage, done: u64, total: u64) {
        if let Some(cb) = &self.0 {
            Python::with_gil(|py| {
                let _ = cb.call1(py, (stage.name(), done, total));
            });
        }
    }
}

impl Observer for Progress {
    fn begin(&self, stage: Stage, total: u64) {
        self.call(stage, 0, total);
    }
    fn progress(&self, stage: Stage, done: u64, total: u64) {
        self.call(stage, done, total);
    }
}

/// Where the estimators' weights are looked for.
fn hub(models_dir: Option<PathBuf>) -> Hub {
    Hub::new(HubOptions::from_env(models_dir, true))
}

/// The folder holding `name`'s weights on disk, or `FileNotFoundError`.
fn weights_dir(models_dir: Option<PathBuf>, name: &str) -> PyResult<PathBuf> {
    let spec = hub::lookup(name).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    match hub(models_dir).locate(spec) {
        Ok(Some(r)) => Ok(r.dir),
        Ok(None) => Err(PyFileNotFoundError::new_err(format!(
            "the weights of `{name}` ({}, licence {}) are not on disk: run `pixl models fetch {name}`, or pass \
             models_dir= a folder holding them",
            spec.repo, spec.licence
        ))),
        Err(e) => Err(PyFileNotFoundError::new_err(e.to_string())),
    }
}

/// The relighting network, loaded once and kept across calls.
#[pyclass(frozen, name = "Model", module = "pixlrelight")]
struct Model {
    net: Arc<Network>,
    device: Device,
}

#[pymethods]
impl Model {
    /// Loads the network: `weights` is `"bundled"` (the demo weights inside the module),
    /// `"pixlrelight"` (the paper's released checkpoint, on disk after `pixl models fetch
    /// pixlrelight`; CC BY-NC 4.0) or the path of a `.safetensors` file.
    #[staticmethod]
    #[pyo3(signature = (weights = "bundled", device = "cpu", models_dir = None))]
    fn load(py: Python<'_>, weights: &str, device: &str, models_dir: Option<PathBuf>) -> PyResult<Model> {
        let device = parse_device(device)?;
        let path = match weights {
            "bundled" => None,
            "pixlrelight" => Some(weights_dir(models_dir, "pixlrelight")?.join("model.safetensors")),
            p if Path::new(p).is_file() => Some(PathBuf::from(p)),
            p => {
                return Err(PyFileNotFoundError::new_err(format!(
                    "weights {p:?}: no such file (or give \"bundled\" or \"pixlrelight\")"
                )))
            }
        };
        let d = device.clone();
        let net = py
            .allow_threads(move || Network::load(path.as_deref(), DType::F32, &d, false))
            .map_err(py_err)?;
        if let Some(l) = net.licence {
            eprintln!("pixlrelight: {}: licence {l}", net.name);
        }
        Ok(Model {
            net: Arc::new(net),
            device,
        })
    }

    /// How many networks this process has loaded.
    #[staticmethod]
    fn loads() -> usize {
        Network::loads()
    }

    /// The weights' name (a file, or the bundled weights).
    #[getter]
    fn name(&self) -> String {
        self.net.name.clone()
    }

    /// The weights' licence where it restricts use, else `None`.
    #[getter]
    fn licence(&self) -> Option<&'static str> {
        self.net.licence
    }

    fn __repr__(&self) -> String {
        format!("Model({:?})", self.net.name)
    }
}

/// The photo's focal length (`focal` pixels, else the vertical `fov` degrees, else 50°).
fn photo(img: Image, focal: Option<f64>, fov: Option<f64>) -> PyResult<Photo> {
    let f = pixl_pipeline::exif::photo_focal(Path::new(""), img.width, img.height, focal, fov).map_err(py_err)?;
    Ok(Photo::from_image(img, f))
}

/// The lights of `preset` and `lights` (each the flags of `pixl light add` in one string).
fn light_set(preset: Option<String>, lights: Option<Vec<String>>) -> PyResult<LightSet> {
    if let Some(p) = preset.as_deref().filter(|p| !pixl_render::presets::PRESETS.contains(p)) {
        return Err(PyValueError::new_err(format!(
            "preset {p:?}: not one of {}",
            pixl_render::presets::PRESETS.join(", ")
        )));
    }
    let placed = lights
        .unwrap_or_default()
        .into_iter()
        .map(|w| pixl_pipeline::lights::parse_light_words(&w).map(|s| (w, s)))
        .collect::<Result<Vec<_>, _>>()
        .map_err(py_err)?;
    Ok(LightSet {
        preset,
        placed,
        fixed: Vec::new(),
    })
}

/// A depth argument for a photo of `size` (see the module docs); `None` when it is to be estimated.
fn depth_arg(obj: Option<&Bound<'_, PyAny>>, size: (usize, usize)) -> PyResult<Option<DepthSource<'static>>> {
    let Some(obj) = obj else { return Ok(None) };
    if let Ok(path) = obj.extract::<PathBuf>() {
        return Ok(Some(DepthSource::File {
            path,
            how: DepthFile::default(),
        }));
    }
    let py = obj.py();
    let arr = py.import("numpy")?.call_method1("asarray", (obj,))?;
    let shape: Vec<usize> = arr.getattr("shape")?.extract()?;
    if shape != [size.1, size.0] {
        return Err(PyValueError::new_err(format!(
            "depth: expected an H x W = {} x {} array of metres (the photo's size), got shape {shape:?}",
            size.1, size.0
        )));
    }
    let a: PyReadonlyArrayDyn<'_, f32> = arr.call_method1("astype", ("float32",))?.extract()?;
    let map = DepthMap::new(size.0, size.1, a.as_array().iter().copied().collect())
        .map_err(|e| PyValueError::new_err(format!("depth: {e}")))?;
    Ok(Some(DepthSource::Given(map)))
}

fn da3(models_dir: Option<PathBuf>, device: &Device) -> PyResult<Da3Depth> {
    let dir = weights_dir(models_dir, "da3-metric")?;
    Da3Depth::load(&dir, pixl_estimate::da3::Da3Variant::Metric, "da3-metric", device).map_err(py_err)
}

fn marigold(
    models_dir: Option<PathBuf>,
    steps: usize,
    resolution: Option<usize>,
    seed: u64,
    device: &Device,
) -> PyResult<MarigoldLighting> {
    let dir = weights_dir(models_dir, "marigold-lighting")?;
    let opts = MarigoldOptions {
        steps: Some(steps),
        resolution,
        seed,
        ..Default::default()
    };
    MarigoldLighting::load(&dir, opts, "marigold-lighting", device).map_err(py_err)
}

/// Relights `image` under new lights (`preset` and/or `lights`, placed in its reconstructed
/// scene, with `depth`) or like a reference photo of the same view (`like`); returns the relit
/// image at the photo's size. `model` (from `Model.load`) is reused; without it the `weights`
/// are loaded for this call.
#[pyfunction]
#[pyo3(signature = (
    image, preset = None, lights = None, like = None, depth = None, *, fov = None, focal = None,
    model = None, weights = "bundled", device = "cpu", max_side = 1024, spp = 64, bounces = 8,
    seed = 0, like_steps = 1, models_dir = None, progress = None
))]
#[allow(clippy::too_many_arguments)]
fn relight<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    preset: Option<String>,
    lights: Option<Vec<String>>,
    like: Option<&Bound<'py, PyAny>>,
    depth: Option<&Bound<'py, PyAny>>,
    fov: Option<f64>,
    focal: Option<f64>,
    model: Option<PyRef<'py, Model>>,
    weights: &str,
    device: &str,
    max_side: usize,
    spp: u32,
    bounces: u32,
    seed: u64,
    like_steps: usize,
    models_dir: Option<PathBuf>,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let photo = photo(image_arg(py, "image", image)?, focal, fov)?;
    let size = photo.size();
    let lights = light_set(preset, lights)?;
    let target = like.map(|t| image_arg(py, "like", t)).transpose()?;
    if lights.is_empty() == target.is_none() {
        return Err(PyValueError::new_err(
            "give the new lighting: preset=, lights=[...] (flags of `pixl light add`), or like=a reference photo",
        ));
    }
    let model = match model {
        Some(m) => (m.net.clone(), m.device.clone()),
        None => {
            let m = Model::load(py, weights, device, models_dir.clone())?;
            (m.net, m.device)
        }
    };
    let (net, dev) = model;
    let depth = depth_arg(depth, size)?;
    let est_depth = match (&target, &depth) {
        (None, None) => Some(da3(models_dir.clone(), &dev)?),
        _ => None,
    };
    let est_light = match &target {
        Some(_) => Some(marigold(models_dir, like_steps, None, seed, &dev)?),
        None => None,
    };
    let observer = Progress(progress);
    let relit = py
        .allow_threads(|| {
            let lighting = match (&target, &est_light) {
                (Some(t), Some(m)) => Lighting::Like {
                    target: t,
                    estimator: m,
                },
                _ => Lighting::Lights {
                    lights: &lights,
                    depth: match (depth, &est_depth) {
                        (Some(d), _) => d,
                        (None, Some(e)) => DepthSource::Estimate(e),
                        (None, None) => return Err(PipelineError::input("no depth")),
                    },
                },
            };
            let job = Job {
                photo,
                lighting,
                max_side,
                render: pixl_pipeline::render::RenderSettings { spp, bounces, seed },
                max_memory: None,
                keep: None,
            };
            job::run(&net, job, &dev, &observer)
        })
        .map_err(py_err)?;
    image_out(py, &relit.image)
}

/// Metric z-depth of `image` in metres (`H × W` float32; 0 where Depth Anything 3 sees sky),
/// with Depth Anything 3 (metric) from disk.
#[pyfunction]
#[pyo3(signature = (image, *, fov = None, focal = None, device = "cpu", models_dir = None))]
fn estimate_depth<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    fov: Option<f64>,
    focal: Option<f64>,
    device: &str,
    models_dir: Option<PathBuf>,
) -> PyResult<Bound<'py, PyArray2<f32>>> {
    let photo = photo(image_arg(py, "image", image)?, focal, fov)?;
    let dev = parse_device(device)?;
    let est = da3(models_dir, &dev)?;
    let map = py
        .allow_threads(|| {
            use pixl_pipeline::depth::DepthEstimator;
            est.estimate(&photo.srgb(), photo.focal.px)?.to_metric(photo.size())
        })
        .map_err(py_err)?;
    let a = Array2::from_shape_vec((map.height, map.width), map.data)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py))
}

fn ct_dict<'py>(py: Python<'py>, ct: &pixl_intrinsics::ct::Ct) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("albedo", image_out(py, &ct.albedo)?)?;
    d.set_item("shading", image_out(py, &ct.shading)?)?;
    d.set_item("residual", image_out(py, &ct.residual)?)?;
    Ok(d)
}

/// The photo's own `C_T` — albedo, diffuse shading, non-diffuse residual (App. B's joint p98
/// rescale) — by Marigold-IID-Lighting from disk; a dict of three `H × W × 3` arrays and `tau`.
#[pyfunction]
#[pyo3(signature = (image, *, steps = 1, resolution = None, seed = 0, device = "cpu", models_dir = None))]
fn estimate_lighting<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    steps: usize,
    resolution: Option<usize>,
    seed: u64,
    device: &str,
    models_dir: Option<PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    let img = image_arg(py, "image", image)?;
    let dev = parse_device(device)?;
    let m = marigold(models_dir, steps, resolution, seed, &dev)?;
    let size = (img.width, img.height);
    let like = py
        .allow_threads(|| pixl_pipeline::like::target_ct(&m, &img, size, &pixl_pipeline::Silent))
        .map_err(py_err)?;
    let d = ct_dict(py, &like.ct)?;
    d.set_item("tau", like.tau)?;
    Ok(d)
}

/// The target `C_T` the network is conditioned on under new lights: the photo reconstructed with
/// `depth` (a path or an `H × W` array of metres), lit by `preset`/`lights`, path-traced at the
/// working size (long side `max_side`) and composed (App. B); a dict of three arrays at that size.
#[pyfunction]
#[pyo3(signature = (image, depth, preset = None, lights = None, *, fov = None, focal = None, max_side = 512, spp = 64, bounces = 8, seed = 0, progress = None))]
#[allow(clippy::too_many_arguments)]
fn intrinsics<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    depth: &Bound<'py, PyAny>,
    preset: Option<String>,
    lights: Option<Vec<String>>,
    fov: Option<f64>,
    focal: Option<f64>,
    max_side: usize,
    spp: u32,
    bounces: u32,
    seed: u64,
    progress: Option<Py<PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    let photo = photo(image_arg(py, "image", image)?, focal, fov)?;
    let size = photo.size();
    let lights = light_set(preset, lights)?;
    if lights.is_empty() {
        return Err(PyValueError::new_err("give the lights: preset= or lights=[...]"));
    }
    let depth = depth_arg(Some(depth), size)?.ok_or_else(|| PyValueError::new_err("depth: required"))?;
    let observer = Progress(progress);
    let ct = py
        .allow_threads(|| {
            let map = match depth {
                DepthSource::File { path, how } => pixl_pipeline::depth::read_depth_file(&path, &how, size)?,
                DepthSource::Given(m) => m,
                DepthSource::Estimate(_) => return Err(PipelineError::input("no depth")),
            };
            let work = pixl_model::fullres::working_size(size.0, size.1, max_side);
            let settings = pixl_pipeline::reconstruct::MeshSettings {
                stride: Some(size.0.max(size.1).div_ceil(work.0.max(work.1)).max(1)),
                ..Default::default()
            };
            let g = pixl_pipeline::reconstruct::reconstruct(
                &photo,
                &map,
                "depth",
                &Default::default(),
                &settings,
                &observer,
            )?;
            let mut scene = g.scene.clone();
            lights.apply(&mut scene, &observer)?;
            let rs = pixl_pipeline::render::RenderSettings { spp, bounces, seed };
            Ok(pixl_pipeline::render::render_intrinsics(&scene, work, &rs, &observer)?
                .1
                .ct)
        })
        .map_err(py_err)?;
    ct_dict(py, &ct)
}

/// Reads an image file (PNG, JPEG, EXR) as `float32 H × W × 3` with its values as stored (8-bit
/// values divided by 255), as `pixl` reads photos.
#[pyfunction]
fn read_image<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyArray3<f32>>> {
    let img = pixl_core::io::read_rgb(&path).map_err(|e| match &e {
        pixl_core::CoreError::NotFound { .. } => PyFileNotFoundError::new_err(e.to_string()),
        pixl_core::CoreError::Io { .. } => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    })?;
    image_out(py, &img)
}

/// The paper's lighting presets (§4.2).
#[pyfunction]
fn presets() -> Vec<&'static str> {
    pixl_render::presets::PRESETS.to_vec()
}

#[pymodule]
fn pixlrelight(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add_class::<Model>()?;
    m.add_function(wrap_pyfunction!(relight, m)?)?;
    m.add_function(wrap_pyfunction!(estimate_depth, m)?)?;
    m.add_function(wrap_pyfunction!(estimate_lighting, m)?)?;
    m.add_function(wrap_pyfunction!(intrinsics, m)?)?;
    m.add_function(wrap_pyfunction!(presets, m)?)?;
    m.add_function(wrap_pyfunction!(read_image, m)?)?;
    Ok(())
}
