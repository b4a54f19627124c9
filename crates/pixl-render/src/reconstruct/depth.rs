//! Depth map + pinhole intrinsics → a textured triangle grid (paper §3.4).
//!
//! # Conventions
//! - **Camera space** is right-handed, metres: the camera sits at the origin looking down **−Z**,
//!   **+X** is image right and **+Y** image up (Blender's and glTF's camera convention, and the
//!   scene's camera in [`crate::scene`]).
//! - **Depth is z-depth**: the distance along −Z (the optical axis), not along the ray, as in
//!   Cycles' Depth pass. A pixel with depth `d` unprojects to `z = −d`.
//! - **Pixels**: the image spans `[0, W] × [0, H]` in pixel units with `y` growing downwards;
//!   pixel `(x, y)` is sampled at its centre `(x + ½, y + ½)`. The principal point is the image
//!   centre `(W/2, H/2)`, pixels are square, so `f_x = f_y = f` with `f = (H/2) / tan(fov_y/2)`:
//!   `X = (x + ½ − W/2) · d / f`, `Y = −(y + ½ − H/2) · d / f`, `Z = −d`.
//! - **UVs**: `u = (x + ½)/W`, `v = (y + ½)/H` with `v = 0` at the top row (see [`crate::scene::mesh`]),
//!   so the photo (or an albedo map of the same size) is the mesh's texture, pixel for pixel.
//! - **Triangles**: each quad of neighbouring samples gives two triangles, counter-clockwise seen
//!   from the camera (their geometric normal points towards +Z, at the camera). A triangle is
//!   **cut** when a vertex has no valid depth (non-finite, ≤ 0 or above [`MeshOptions::max_depth`])
//!   or when it straddles a depth discontinuity: `max(d)/min(d) − 1 > max_jump`.
//!
//! # Depth files ([`read_depth`])
//! - OpenEXR: the channel `Z` (or `*.Z`, e.g. Blender's `ViewLayer.Depth.Z`), else `Y`, else `R`,
//!   else the only channel; values in metres.
//! - 16-bit greyscale PNG: raw integer × `depth_scale` metres (default [`DEFAULT_DEPTH_SCALE`] =
//!   1 mm per unit, the Kinect/RealSense convention); 0 reads as depth 0, i.e. "no depth" (its
//!   triangles are cut). 8-bit PNGs are refused.
//! - NumPy `.npy` (v1–v3): little-endian `float32`, `float64` (metres) or `uint16` (× `depth_scale`),
//!   C order, shape `(H, W)` or `(H, W, 1)`.
use crate::scene::mesh::Mesh;
use pixl_core::Image;
use std::path::{Path, PathBuf};

/// Metres per unit of 16-bit PNG and `uint16` `.npy` depth, unless told otherwise (1 mm).
pub const DEFAULT_DEPTH_SCALE: f32 = 0.001;
/// Default relative depth jump above which a triangle is cut.
pub const DEFAULT_MAX_JUMP: f32 = 0.05;
/// Depths above this are treated as background (Cycles writes 1e10 where it sees only the world).
pub const DEFAULT_MAX_DEPTH: f32 = 1.0e9;

#[derive(Debug, thiserror::Error)]
pub enum DepthError {
    #[error(transparent)]
    Core(#[from] pixl_core::CoreError),
    /// A `.npy` file that is not a plain little-endian 2-D array of a supported dtype.
    #[error("{path}: not a supported .npy depth array: {reason}")]
    Npy { path: PathBuf, reason: String },
    /// A depth file of an unusable kind (wrong channel count, 8-bit PNG, ...).
    #[error("{path}: {reason}")]
    Format { path: PathBuf, reason: String },
    /// Bad intrinsics or options.
    #[error("{0}")]
    Invalid(String),
}

pub type Result<T, E = DepthError> = std::result::Result<T, E>;

/// A z-depth map in metres, row-major (`data[y * width + x]`).
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
}

impl DepthMap {
    pub fn new(width: usize, height: usize, data: Vec<f32>) -> Result<Self> {
        if width == 0 || height == 0 || data.len() != width * height {
            return Err(DepthError::Invalid(format!(
                "depth buffer has {} values, expected {width}x{height} (non-empty)",
                data.len()
            )));
        }
        Ok(Self { width, height, data })
    }

    #[inline]
    pub fn get(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }

    /// Number of pixels whose depth is usable (finite, > 0, ≤ `max_depth`).
    pub fn count_valid(&self, max_depth: f32) -> usize {
        self.data.iter().filter(|d| is_valid(**d, max_depth)).count()
    }
}

#[inline]
fn is_valid(d: f32, max_depth: f32) -> bool {
    d.is_finite() && d > 0.0 && d <= max_depth
}

/// Pinhole intrinsics: square pixels, principal point at the image centre.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub width: usize,
    pub height: usize,
    /// Focal length in pixels (`f_x = f_y`).
    pub focal_px: f64,
}

impl Intrinsics {
    /// From the **vertical** field of view in degrees, in (0, 180).
    pub fn from_vfov_deg(width: usize, height: usize, vfov_deg: f64) -> Result<Self> {
        if !(vfov_deg.is_finite() && vfov_deg > 0.0 && vfov_deg < 180.0) {
            return Err(DepthError::Invalid(format!(
                "vertical field of view {vfov_deg}° is not in (0, 180)"
            )));
        }
        let focal_px = 0.5 * height as f64 / (0.5 * vfov_deg.to_radians()).tan();
        Self::from_focal_px(width, height, focal_px)
    }

    /// From the focal length in pixels (> 0).
    pub fn from_focal_px(width: usize, height: usize, focal_px: f64) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(DepthError::Invalid(format!("image size {width}x{height} is empty")));
        }
        if !(focal_px.is_finite() && focal_px > 0.0) {
            return Err(DepthError::Invalid(format!(
                "focal length {focal_px} px is not a positive number"
            )));
        }
        Ok(Self {
            width,
            height,
            focal_px,
        })
    }

    /// Vertical field of view in degrees.
    pub fn vfov_deg(&self) -> f64 {
        (2.0 * (0.5 * self.height as f64 / self.focal_px).atan()).to_degrees()
    }

    /// Camera-space point of pixel position `(px, py)` (continuous pixel units, `y` down, the
    /// centre of pixel `(x, y)` is `(x + ½, y + ½)`) at z-depth `depth`.
    pub fn unproject(&self, px: f64, py: f64, depth: f64) -> [f64; 3] {
        let cx = 0.5 * self.width as f64;
        let cy = 0.5 * self.height as f64;
        [
            (px - cx) * depth / self.focal_px,
            -(py - cy) * depth / self.focal_px,
            -depth,
        ]
    }
}

/// Options of [`depth_to_mesh`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshOptions {
    /// Cut a triangle when `max(d)/min(d) − 1` over its vertices exceeds this (default 0.05).
    pub max_jump: f32,
    /// Keep every `stride`-th pixel in x and y (the last row and column are always kept); 1 = all.
    pub stride: usize,
    /// Depths above this are background (default [`DEFAULT_MAX_DEPTH`]).
    pub max_depth: f32,
    /// Put the outermost vertices on the image's edges (pixel coordinates 0 and width / height)
    /// instead of the border pixels' centres, at those pixels' depths, so that the mesh covers
    /// the whole frame (default false: every vertex at a pixel centre).
    pub full_frame: bool,
}

impl Default for MeshOptions {
    fn default() -> Self {
        Self {
            max_jump: DEFAULT_MAX_JUMP,
            stride: 1,
            max_depth: DEFAULT_MAX_DEPTH,
            full_frame: false,
        }
    }
}

/// Sample positions along one axis: `0, s, 2s, …` plus the last index.
fn samples(n: usize, stride: usize) -> Vec<usize> {
    let mut v: Vec<usize> = (0..n).step_by(stride).collect();
    if v.last() != Some(&(n - 1)) {
        v.push(n - 1);
    }
    v
}

/// Why a triangle of the grid was cut.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Cut {
    /// A corner has no valid depth.
    MissingDepth,
    /// Its depths differ by more than `max_jump`.
    DepthJump,
}

/// Calls `f` with every triangle of the sample grid (corners as grid coordinates) and why it is
/// cut, if it is.
fn for_each_triangle(
    depth: &DepthMap,
    xs: &[usize],
    ys: &[usize],
    opts: &MeshOptions,
    mut f: impl FnMut([(usize, usize); 3], Option<Cut>),
) {
    let depth_at = |(gx, gy): (usize, usize)| depth.get(xs[gx], ys[gy]);
    let cut = |ids: [(usize, usize); 3]| -> Option<Cut> {
        let d = ids.map(depth_at);
        if !d.iter().all(|&v| is_valid(v, opts.max_depth)) {
            return Some(Cut::MissingDepth);
        }
        let lo = d[0].min(d[1]).min(d[2]);
        let hi = d[0].max(d[1]).max(d[2]);
        (hi / lo - 1.0 > opts.max_jump).then_some(Cut::DepthJump)
    };
    for gy in 0..ys.len().saturating_sub(1) {
        for gx in 0..xs.len().saturating_sub(1) {
            // a b      (image rows grow downwards; camera +Y is up)
            // c d
            let (a, b, c, d) = ((gx, gy), (gx + 1, gy), (gx, gy + 1), (gx + 1, gy + 1));
            for t in [[a, c, d], [a, d, b]] {
                f(t, cut(t));
            }
        }
    }
}

/// How the triangles of [`depth_to_mesh`]'s grid fare under `opts`, for messages that name the
/// right cause when few or none are kept.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CutCounts {
    /// Vertices of the sample grid across and down (`stride` decides them).
    pub grid: (usize, usize),
    /// Triangles kept.
    pub kept: usize,
    /// Triangles cut because a corner has no valid depth.
    pub missing_depth: usize,
    /// Triangles cut at a depth jump over `max_jump`.
    pub depth_jump: usize,
}

/// Counts kept and cut triangles as [`depth_to_mesh`] would (options unchecked: a zero stride
/// counts as 1).
pub fn cut_counts(depth: &DepthMap, opts: &MeshOptions) -> CutCounts {
    if depth.width == 0 || depth.height == 0 || depth.data.len() != depth.width * depth.height {
        return CutCounts::default();
    }
    let xs = samples(depth.width, opts.stride.max(1));
    let ys = samples(depth.height, opts.stride.max(1));
    let mut c = CutCounts {
        grid: (xs.len(), ys.len()),
        ..Default::default()
    };
    for_each_triangle(depth, &xs, &ys, opts, |_, cut| match cut {
        None => c.kept += 1,
        Some(Cut::MissingDepth) => c.missing_depth += 1,
        Some(Cut::DepthJump) => c.depth_jump += 1,
    });
    c
}

/// Unprojects every (strided) pixel and triangulates the grid (see the module docs).
///
/// `normals`, if given, is a 3-channel **camera-space** normal map of the depth map's size
/// (X right, Y up, Z towards the camera; unit length — renormalised here); otherwise per-vertex
/// normals are the area-weighted average of the kept triangles' normals. Vertices used by no
/// kept triangle are dropped.
pub fn depth_to_mesh(depth: &DepthMap, intr: &Intrinsics, normals: Option<&Image>, opts: &MeshOptions) -> Result<Mesh> {
    if (depth.width, depth.height) != (intr.width, intr.height) {
        return Err(DepthError::Invalid(format!(
            "depth map is {}x{} but the intrinsics are for {}x{}",
            depth.width, depth.height, intr.width, intr.height
        )));
    }
    if !(opts.max_jump.is_finite() && opts.max_jump >= 0.0) {
        return Err(DepthError::Invalid(format!(
            "max_jump {} must be a finite number ≥ 0",
            opts.max_jump
        )));
    }
    if opts.stride == 0 {
        return Err(DepthError::Invalid("stride must be ≥ 1".into()));
    }
    if let Some(n) = normals {
        if (n.width, n.height) != (depth.width, depth.height) || n.channels < 3 {
            return Err(DepthError::Invalid(format!(
                "normal map is {}x{}x{} but must be {}x{}x3 like the depth map",
                n.width, n.height, n.channels, depth.width, depth.height
            )));
        }
    }
    let (w, h) = (depth.width, depth.height);
    let xs = samples(w, opts.stride);
    let ys = samples(h, opts.stride);
    let (gw, gh) = (xs.len(), ys.len());

    // Triangles over the grid of samples, in grid-vertex ids `gy * gw + gx`.
    let mut tris: Vec<[usize; 3]> = Vec::with_capacity(2 * (gw - 1) * (gh - 1));
    for_each_triangle(depth, &xs, &ys, opts, |t, cut| {
        if cut.is_none() {
            tris.push(t.map(|(x, y)| y * gw + x));
        }
    });

    // Compact: only vertices that a kept triangle uses, in grid order.
    let mut remap = vec![u32::MAX; gw * gh];
    for t in &tris {
        for &v in t {
            remap[v] = 0;
        }
    }
    let mut mesh = Mesh::default();
    for (gy, &y) in ys.iter().enumerate() {
        for (gx, &x) in xs.iter().enumerate() {
            let g = gy * gw + gx;
            if remap[g] == u32::MAX {
                continue;
            }
            remap[g] = u32::try_from(mesh.positions.len())
                .map_err(|_| DepthError::Invalid("mesh has more than 2^32 vertices; use a larger stride".into()))?;
            // Pixel centre, or (full frame) the image edge for the outermost samples.
            let at = |g: usize, n: usize, v: usize, size: usize| match (opts.full_frame, g) {
                (true, 0) => 0.0,
                (true, g) if g + 1 == n => size as f64,
                _ => v as f64 + 0.5,
            };
            let (px, py) = (at(gx, gw, x, w), at(gy, gh, y, h));
            let p = intr.unproject(px, py, depth.get(x, y) as f64);
            mesh.positions.push(p.map(|c| c as f32));
            mesh.uvs.push([(px / w as f64) as f32, (py / h as f64) as f32]);
            if let Some(n) = normals {
                let v = [n.get(x, y, 0), n.get(x, y, 1), n.get(x, y, 2)];
                mesh.normals.push(normalize(v).unwrap_or([0.0, 0.0, 1.0]));
            }
        }
    }
    mesh.indices = tris.iter().map(|t| t.map(|v| remap[v])).collect();
    if normals.is_none() {
        mesh.normals = vertex_normals(&mesh);
    }
    Ok(mesh)
}

fn normalize(v: [f32; 3]) -> Option<[f32; 3]> {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (l.is_finite() && l > 0.0).then(|| v.map(|c| c / l))
}

/// Area-weighted average of adjacent face normals (`+Z` for a vertex with degenerate faces).
pub fn vertex_normals(mesh: &Mesh) -> Vec<[f32; 3]> {
    let mut acc = vec![[0.0f64; 3]; mesh.positions.len()];
    for t in &mesh.indices {
        let [a, b, c] = t.map(|i| mesh.positions[i as usize].map(f64::from));
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let n = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        for &i in t {
            for k in 0..3 {
                acc[i as usize][k] += n[k];
            }
        }
    }
    acc.into_iter()
        .map(|n| normalize(n.map(|c| c as f32)).unwrap_or([0.0, 0.0, 1.0]))
        .collect()
}

/// Reads a depth map (EXR, 16-bit PNG or `.npy`, see the module docs), in metres.
/// `depth_scale` (metres per unit) applies to 16-bit PNG and `uint16` `.npy` only.
pub fn read_depth(path: &Path, depth_scale: f32) -> Result<DepthMap> {
    if !(depth_scale.is_finite() && depth_scale > 0.0) {
        return Err(DepthError::Invalid(format!(
            "depth scale {depth_scale} must be a positive number"
        )));
    }
    if !path.exists() {
        return Err(pixl_core::CoreError::NotFound { path: path.to_owned() }.into());
    }
    match pixl_core::io::extension(path).as_str() {
        "exr" => read_depth_exr(path),
        "png" => read_depth_png(path, depth_scale),
        "npy" => {
            let bytes = std::fs::read(path).map_err(|e| pixl_core::CoreError::io(path, e))?;
            let arr = parse_npy(&bytes).map_err(|reason| DepthError::Npy {
                path: path.to_owned(),
                reason,
            })?;
            arr.into_depth(path, depth_scale)
        }
        _ => Err(pixl_core::CoreError::UnknownExtension {
            path: path.to_owned(),
            expected: "exr, png, npy",
        }
        .into()),
    }
}

/// The depth channel of an EXR with these channel names: `Z`, else the `Z` of a `Depth` layer
/// (Cycles' `ViewLayer.Depth.Z`); in a file whose channels are all of one layer, also that
/// layer's `Z`, `Y` or `R` channel, or its only channel. A multilayer file without a `Depth`
/// layer has none: another layer's `Z` or `Y` (a normal pass) is not depth.
fn pick_depth_channel<'a>(names: &[&'a str]) -> Option<&'a str> {
    let layer = |n: &str| n.rsplit_once('.').map(|(l, _)| l.to_owned()).unwrap_or_default();
    let exact = |want: &str| names.iter().copied().find(|n| *n == want);
    if let Some(n) = exact("Z").or_else(|| {
        names
            .iter()
            .copied()
            .find(|n| *n == "Depth.Z" || n.ends_with(".Depth.Z"))
    }) {
        return Some(n);
    }
    let first = layer(names.first()?);
    if names.iter().any(|n| layer(n) != first) {
        return None;
    }
    let in_layer = |c: &str| {
        names
            .iter()
            .copied()
            .find(|n| n.rsplit_once('.').map_or(*n == c, |(_, ch)| ch == c))
    };
    in_layer("Z")
        .or_else(|| in_layer("Y"))
        .or_else(|| in_layer("R"))
        .or_else(|| (names.len() == 1).then(|| names[0]))
}

fn read_depth_exr(path: &Path) -> Result<DepthMap> {
    let chans = pixl_core::exrio::read_exr_channels(path)?;
    let names: Vec<&str> = chans.names().collect();
    let pick = pick_depth_channel(&names);
    let Some(name) = pick else {
        return Err(DepthError::Format {
            path: path.to_owned(),
            reason: format!(
                "no depth channel (looked for Z or a Depth layer's Z, else in a file of one layer its Z, Y, R or only channel); found {}",
                names.join(", ")
            ),
        });
    };
    let data = chans.get(name).map(<[f32]>::to_vec).unwrap_or_default();
    DepthMap::new(chans.width, chans.height, data)
}

fn read_depth_png(path: &Path, depth_scale: f32) -> Result<DepthMap> {
    let decode = |e: image::ImageError| pixl_core::CoreError::Decode {
        path: path.to_owned(),
        format: "PNG",
        reason: e.to_string(),
    };
    let reader = image::ImageReader::open(path).map_err(|e| pixl_core::CoreError::io(path, e))?;
    let (w, h) = reader.into_dimensions().map_err(decode)?;
    pixl_core::io::check_size(path, w as usize, h as usize)?;
    let img = image::ImageReader::open(path)
        .map_err(|e| pixl_core::CoreError::io(path, e))?
        .decode()
        .map_err(decode)?;
    let raw = match img {
        image::DynamicImage::ImageLuma16(g) => g.into_raw(),
        other => {
            return Err(DepthError::Format {
                path: path.to_owned(),
                reason: format!(
                    "a PNG depth map must be 16-bit greyscale (found {:?}); 8-bit depth is too coarse",
                    other.color()
                ),
            })
        }
    };
    let data = raw.into_iter().map(|v| v as f32 * depth_scale).collect();
    DepthMap::new(w as usize, h as usize, data)
}

/// Element type of a parsed `.npy` array.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NpyDtype {
    F32,
    F64,
    U16,
}

/// A parsed 2-D `.npy` array, values widened to `f64` (exact for all three dtypes).
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    pub dtype: NpyDtype,
    /// `(rows, cols)`; a trailing axis of length 1 is dropped.
    pub shape: (usize, usize),
    pub data: Vec<f64>,
}

impl NpyArray {
    fn into_depth(self, path: &Path, depth_scale: f32) -> Result<DepthMap> {
        let (h, w) = self.shape;
        pixl_core::io::check_size(path, w, h)?;
        let scale = if self.dtype == NpyDtype::U16 {
            depth_scale as f64
        } else {
            1.0
        };
        let data = self.data.into_iter().map(|v| (v * scale) as f32).collect();
        DepthMap::new(w, h, data)
    }
}

/// Parses `.npy` bytes (format v1, v2 or v3): a C-order, little-endian `<f4`, `<f8` or `<u2`
/// array of shape `(H, W)` or `(H, W, 1)`. Errors are plain sentences (the caller adds the path).
pub fn parse_npy(bytes: &[u8]) -> std::result::Result<NpyArray, String> {
    const MAGIC: &[u8] = b"\x93NUMPY";
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err("missing the \\x93NUMPY magic bytes".into());
    }
    let major = bytes[6];
    let (header_len, header_start): (usize, usize) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err("truncated header".into());
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(format!("unsupported .npy format version {v}")),
    };
    let header_end = header_start
        .checked_add(header_len)
        .filter(|e| *e <= bytes.len())
        .ok_or_else(|| {
            format!(
                "header announces {header_len} bytes but the file has {} after the preamble",
                bytes.len() - header_start
            )
        })?;
    let header = std::str::from_utf8(&bytes[header_start..header_end]).map_err(|_| "header is not text".to_string())?;
    let dict = parse_header_dict(header)?;
    let descr = dict.descr.ok_or("header has no 'descr'")?;
    let fortran = dict.fortran_order.ok_or("header has no 'fortran_order'")?;
    let shape = dict.shape.ok_or("header has no 'shape'")?;
    let dtype = match descr.as_str() {
        "<f4" => NpyDtype::F32,
        "<f8" => NpyDtype::F64,
        "<u2" => NpyDtype::U16,
        d if d.starts_with('>') => return Err(format!("dtype {d:?} is big-endian; save it little-endian")),
        d => {
            return Err(format!(
                "dtype {d:?} is not supported (float32 '<f4', float64 '<f8' or uint16 '<u2')"
            ))
        }
    };
    if fortran {
        return Err("array is in Fortran order; save a C-order array (np.ascontiguousarray)".into());
    }
    let (h, w) = match shape.as_slice() {
        [h, w] | [h, w, 1] => (*h, *w),
        s => return Err(format!("shape {s:?} is not 2-D (H, W) or (H, W, 1)")),
    };
    let n = h.checked_mul(w).ok_or("shape overflows")?;
    let size = match dtype {
        NpyDtype::F32 => 4,
        NpyDtype::F64 => 8,
        NpyDtype::U16 => 2,
    };
    let body = &bytes[header_end..];
    let need = n.checked_mul(size).ok_or("shape overflows")?;
    if body.len() != need {
        return Err(format!(
            "shape ({h}, {w}) of {descr} needs {need} data bytes, file has {}",
            body.len()
        ));
    }
    let data: Vec<f64> = match dtype {
        NpyDtype::F32 => body
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
            .collect(),
        NpyDtype::F64 => body
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect(),
        NpyDtype::U16 => body
            .chunks_exact(2)
            .map(|c| u16::from_le_bytes([c[0], c[1]]) as f64)
            .collect(),
    };
    Ok(NpyArray {
        dtype,
        shape: (h, w),
        data,
    })
}

#[derive(Default)]
struct NpyHeader {
    descr: Option<String>,
    fortran_order: Option<bool>,
    shape: Option<Vec<usize>>,
}

/// Parses the Python dict literal of a `.npy` header:
/// `{'descr': '<f4', 'fortran_order': False, 'shape': (3, 4), }`.
fn parse_header_dict(text: &str) -> std::result::Result<NpyHeader, String> {
    let mut p = Lexer {
        s: text.trim_end_matches(['\n', ' ', '\0']).as_bytes(),
        i: 0,
    };
    let mut out = NpyHeader::default();
    p.expect(b'{')?;
    loop {
        p.skip_ws();
        if p.eat(b'}') {
            break;
        }
        let key = p.string()?;
        p.expect(b':')?;
        p.skip_ws();
        match key.as_str() {
            "descr" => out.descr = Some(p.string()?),
            "fortran_order" => out.fortran_order = Some(p.boolean()?),
            "shape" => out.shape = Some(p.tuple()?),
            k => return Err(format!("unexpected header key {k:?}")),
        }
        p.skip_ws();
        if !p.eat(b',') {
            p.expect(b'}')?;
            break;
        }
    }
    p.skip_ws();
    if p.i != p.s.len() {
        return Err("trailing characters after the header dict".into());
    }
    Ok(out)
}

struct Lexer<'a> {
    s: &'a [u8],
    i: usize,
}

impl Lexer<'_> {
    fn skip_ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }
    fn eat(&mut self, c: u8) -> bool {
        self.skip_ws();
        if self.s.get(self.i) == Some(&c) {
            self.i += 1;
            true
        } else {
            false
        }
    }
    fn expect(&mut self, c: u8) -> std::result::Result<(), String> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("malformed header: expected '{}' at byte {}", c as char, self.i))
        }
    }
    fn string(&mut self) -> std::result::Result<String, String> {
        self.skip_ws();
        let q = match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => q,
            _ => return Err(format!("malformed header: expected a quoted string at byte {}", self.i)),
        };
        let start = self.i + 1;
        let len = self.s[start..]
            .iter()
            .position(|&c| c == q)
            .ok_or("malformed header: unterminated string")?;
        self.i = start + len + 1;
        Ok(String::from_utf8_lossy(&self.s[start..start + len]).into_owned())
    }
    fn boolean(&mut self) -> std::result::Result<bool, String> {
        for (word, v) in [(&b"True"[..], true), (&b"False"[..], false)] {
            if self.s[self.i..].starts_with(word) {
                self.i += word.len();
                return Ok(v);
            }
        }
        Err(format!("malformed header: expected True or False at byte {}", self.i))
    }
    fn tuple(&mut self) -> std::result::Result<Vec<usize>, String> {
        self.expect(b'(')?;
        let mut v = Vec::new();
        loop {
            self.skip_ws();
            if self.eat(b')') {
                return Ok(v);
            }
            let start = self.i;
            while self.i < self.s.len() && self.s[self.i].is_ascii_digit() {
                self.i += 1;
            }
            if start == self.i {
                return Err(format!("malformed header: expected a dimension at byte {}", self.i));
            }
            let digits = std::str::from_utf8(&self.s[start..self.i]).map_err(|_| "malformed header")?;
            v.push(
                digits
                    .parse::<usize>()
                    .map_err(|e| format!("malformed header: dimension {digits}: {e}"))?,
            );
            // Python 2 headers may write `3L`.
            if self.s.get(self.i) == Some(&b'L') {
                self.i += 1;
            }
            if !self.eat(b',') {
                self.expect(b')')?;
                return Ok(v);
            }
        }
    }
}

#[cfg(test)]
mod depth_input_tests {
    use super::*;

    /// A render's passes hold `Normal.X/Y/Z` beside `Depth.Z`: the depth is `Depth.Z`, never the
    /// normal's `Y`; without a Depth layer a multilayer file has no depth; a one-layer file's
    /// `Y` or only channel is its depth.
    #[test]
    fn depth_channel_of_multilayer_and_single_layer_files() {
        let render = [
            "ViewLayer.Combined.R",
            "ViewLayer.Depth.Z",
            "ViewLayer.Normal.X",
            "ViewLayer.Normal.Y",
            "ViewLayer.Normal.Z",
        ];
        assert_eq!(pick_depth_channel(&render), Some("ViewLayer.Depth.Z"));
        let no_depth = [
            "ViewLayer.Normal.X",
            "ViewLayer.Normal.Y",
            "ViewLayer.Normal.Z",
            "ViewLayer.Combined.R",
        ];
        assert_eq!(pick_depth_channel(&no_depth), None);
        assert_eq!(pick_depth_channel(&["B", "G", "R"]), Some("R"));
        assert_eq!(pick_depth_channel(&["Y"]), Some("Y"));
        assert_eq!(pick_depth_channel(&["depth"]), Some("depth"));
        assert_eq!(pick_depth_channel(&["Z", "Normal.Y"]), Some("Z"));
    }

    /// A 5×4 map: a floor whose depth grows 10 % per row, and one pixel without depth. Counted
    /// by hand: at stride 1, 4×3 quads = 24 triangles; the 6 around (2, 1) lack depth; rows
    /// differ by 10 % (> 5 %), so every other triangle spans a jump and none is kept; with
    /// max_jump 0.2 all 18 with depth are kept. At stride 4 the grid is 2×2 (x 0, 4; y 0, 3),
    /// 2 triangles, the rows 33 % apart.
    #[test]
    fn counts_by_cause() {
        let (w, h) = (5, 4);
        let mut data: Vec<f32> = (0..w * h).map(|i| 1.1f32.powi((i / w) as i32)).collect();
        data[w + 2] = 0.0;
        let map = DepthMap {
            width: w,
            height: h,
            data,
        };
        let at = |stride: usize, max_jump: f32| {
            cut_counts(
                &map,
                &MeshOptions {
                    stride,
                    max_jump,
                    ..Default::default()
                },
            )
        };
        let c = at(1, 0.05);
        assert_eq!((c.grid, c.kept, c.missing_depth, c.depth_jump), ((5, 4), 0, 6, 18));
        let c = at(1, 0.2);
        assert_eq!((c.kept, c.missing_depth, c.depth_jump), (18, 6, 0));
        let c = at(4, 0.2);
        assert_eq!((c.grid, c.kept, c.depth_jump), ((2, 2), 0, 2));
        // depth_to_mesh keeps what cut_counts calls kept.
        let k = Intrinsics::from_vfov_deg(w, h, 50.0).unwrap();
        for (stride, jump) in [(1, 0.05), (1, 0.2), (4, 0.2), (2, 0.2)] {
            let opts = MeshOptions {
                stride,
                max_jump: jump,
                ..Default::default()
            };
            let mesh = depth_to_mesh(&map, &k, None, &opts).unwrap();
            assert_eq!(
                mesh.num_triangles(),
                at(stride, jump).kept,
                "stride {stride}, jump {jump}"
            );
        }
    }
}
