//! LPIPS v0.1 (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a
//! Perceptual Metric"), paper §4.1. AlexNet backbone by default, VGG16 optional.
//!
//! Definition, for images `x0, x1` in [0, 1] (`(N, 3, H, W)`):
//! 1. `x ← 2x − 1` (to [−1, 1]), then the v0.1 scaling layer `x ← (x − shift) / scale` with
//!    `shift = (−0.030, −0.088, −0.188)`, `scale = (0.458, 0.448, 0.450)`;
//! 2. five backbone taps `f_l` ([`pixl_nn::backbones`]: AlexNet relu1..5 or VGG16 relu1_2..relu5_3);
//! 3. unit-normalise along channels: `f̂ = f / (‖f‖₂ + 1e-10)` per pixel;
//! 4. `d_l = mean_{h,w} Σ_c w_{l,c} (f̂0 − f̂1)²` with the learned 1×1 head `w_l` (no bias);
//! 5. `LPIPS = Σ_l d_l`.
//!
//! ## Weight file (`--lpips W.safetensors`)
//! One safetensors file holding backbone and heads. Canonical names:
//! - backbone, torchvision names: `features.{i}.weight`, `features.{i}.bias`
//!   (AlexNet `i ∈ {0,3,6,8,10}`; VGG16 `i ∈ {0,2,5,7,10,12,14,17,19,21,24,26,28}`);
//! - heads, the reference `lpips` package's names: `lin{l}.model.1.weight`, shape `(1, C_l, 1, 1)`,
//!   `l = 0..4`.
//!
//! Accepted renamings (all in [`canonical_lpips_name`]): a leading `net.` is dropped
//! (`net.features.0.weight`); the reference package's sliced backbone names
//! `net.slice{k}.{i}.{weight,bias}` become `features.{i}.*`; `lins.{l}.model.1.weight` (its
//! `ModuleList` alias) becomes `lin{l}.model.1.weight`. Everything else (`classifier.*`,
//! `scaling_layer.*` buffers) is ignored. So a full `lpips.LPIPS(net='alex').state_dict()`, or a
//! torchvision `alexnet` state dict merged with the package's `weights/v0.1/alex.pth`, loads as is.
//! The backbone kind is detected from the file: `features.28.weight` present → VGG16, else AlexNet.
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use pixl_core::Image;
use pixl_nn::backbones::{channel_affine, AlexNet, Vgg16};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The v0.1 scaling layer's shift (applied to [−1, 1] input).
pub const LPIPS_SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
/// The v0.1 scaling layer's scale.
pub const LPIPS_SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Added to the feature norm before dividing, as the reference implementation does.
pub const LPIPS_EPS: f64 = 1e-10;

/// Which backbone an [`Lpips`] runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LpipsNet {
    Alex,
    Vgg,
}

impl LpipsNet {
    /// Channels of the five taps (= input channels of the five heads).
    pub fn channels(self) -> [usize; 5] {
        match self {
            LpipsNet::Alex => AlexNet::CHANNELS,
            LpipsNet::Vgg => Vgg16::CHANNELS,
        }
    }
    /// Smallest image side the backbone accepts.
    pub fn min_side(self) -> usize {
        match self {
            LpipsNet::Alex => AlexNet::MIN_SIDE,
            LpipsNet::Vgg => Vgg16::MIN_SIDE,
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            LpipsNet::Alex => "alex",
            LpipsNet::Vgg => "vgg",
        }
    }
}

/// Why LPIPS could not be loaded or computed.
#[derive(Debug, thiserror::Error)]
pub enum LpipsError {
    #[error("{path}: cannot read LPIPS weights: {source}")]
    Read {
        path: PathBuf,
        source: Box<candle_core::Error>,
    },
    #[error("{path}: not usable as LPIPS-{net} weights (expected torchvision `features.*` and `lin0..4.model.1.weight`): {source}")]
    Weights {
        path: PathBuf,
        net: &'static str,
        source: Box<candle_core::Error>,
    },
    #[error("LPIPS needs two 3-channel images of equal size, got {a} and {b}")]
    Shape { a: String, b: String },
    #[error("LPIPS-{net} needs images of at least {min}x{min} pixels, got {width}x{height}")]
    TooSmall {
        net: &'static str,
        min: usize,
        width: usize,
        height: usize,
    },
    #[error("LPIPS computation failed: {0}")]
    Candle(Box<candle_core::Error>),
}

impl From<candle_core::Error> for LpipsError {
    fn from(e: candle_core::Error) -> Self {
        LpipsError::Candle(Box::new(e))
    }
}

/// The one place that maps foreign tensor names to the canonical ones (see the module docs);
/// `None` for tensors LPIPS does not use.
pub fn canonical_lpips_name(name: &str) -> Option<String> {
    let name = name.strip_prefix("net.").unwrap_or(name);
    if name.starts_with("features.") {
        return Some(name.to_string());
    }
    if let Some(rest) = name.strip_prefix("slice") {
        // slice{k}.{i}.{param}
        let mut parts = rest.splitn(3, '.');
        let (_k, i, param) = (parts.next()?, parts.next()?, parts.next()?);
        return Some(format!("features.{i}.{param}"));
    }
    if let Some(rest) = name.strip_prefix("lins.") {
        let (l, tail) = rest.split_once('.')?;
        return (tail == "model.1.weight").then(|| format!("lin{l}.model.1.weight"));
    }
    if name.starts_with("lin") && name.ends_with(".model.1.weight") {
        return Some(name.to_string());
    }
    None
}

#[derive(Clone, Debug)]
enum Backbone {
    Alex(AlexNet),
    Vgg(Vgg16),
}

/// A loaded LPIPS v0.1 model: backbone plus five linear heads.
#[derive(Clone, Debug)]
pub struct Lpips {
    net: LpipsNet,
    backbone: Backbone,
    /// Head weights reshaped to `(1, C_l, 1, 1)`.
    heads: Vec<Tensor>,
    device: Device,
}

impl Lpips {
    /// Builds from a `VarBuilder` holding canonical names (`features.*`, `lin{l}.model.1.weight`).
    pub fn new(net: LpipsNet, vb: VarBuilder) -> candle_core::Result<Self> {
        let backbone = match net {
            LpipsNet::Alex => Backbone::Alex(AlexNet::new(vb.clone())?),
            LpipsNet::Vgg => Backbone::Vgg(Vgg16::new(vb.clone())?),
        };
        let heads = net
            .channels()
            .iter()
            .enumerate()
            .map(|(l, &c)| vb.get((1, c, 1, 1), &format!("lin{l}.model.1.weight")))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self {
            net,
            backbone,
            heads,
            device: vb.device().clone(),
        })
    }

    /// Loads one safetensors file (names and renamings in the module docs), computing in f32.
    pub fn load(path: &Path, device: &Device) -> Result<Self, LpipsError> {
        let raw = candle_core::safetensors::load(path, device).map_err(|source| LpipsError::Read {
            path: path.to_path_buf(),
            source: Box::new(source),
        })?;
        let mut tensors = HashMap::new();
        for (name, t) in raw {
            if let Some(canon) = canonical_lpips_name(&name) {
                tensors.insert(canon, t);
            }
        }
        let net = if tensors.contains_key("features.28.weight") {
            LpipsNet::Vgg
        } else {
            LpipsNet::Alex
        };
        let vb = VarBuilder::from_tensors(tensors, DType::F32, device);
        Self::new(net, vb).map_err(|source| LpipsError::Weights {
            path: path.to_path_buf(),
            net: net.name(),
            source: Box::new(source),
        })
    }

    pub fn net(&self) -> LpipsNet {
        self.net
    }

    /// LPIPS per batch item, `(N,)`, for `(N, 3, H, W)` inputs in [0, 1] (differentiable).
    pub fn forward(&self, x0: &Tensor, x1: &Tensor) -> candle_core::Result<Tensor> {
        let f0 = self.taps(x0)?;
        let f1 = self.taps(x1)?;
        let mut total: Option<Tensor> = None;
        for ((a, b), w) in f0.iter().zip(&f1).zip(&self.heads) {
            let d = unit_normalize(a)?.sub(&unit_normalize(b)?)?.sqr()?;
            let d = d.broadcast_mul(&w.to_dtype(d.dtype())?)?.sum(1)?; // (N, h, w)
            let d = d.mean(2)?.mean(1)?; // (N,)
            total = Some(match total {
                None => d,
                Some(t) => t.add(&d)?,
            });
        }
        total.ok_or_else(|| candle_core::Error::Msg("LPIPS has no layers".into()))
    }

    fn taps(&self, xs: &Tensor) -> candle_core::Result<Vec<Tensor>> {
        let xs = channel_affine(&xs.affine(2.0, -1.0)?, &LPIPS_SHIFT, &LPIPS_SCALE)?;
        match &self.backbone {
            Backbone::Alex(n) => n.features(&xs),
            Backbone::Vgg(n) => n.features(&xs),
        }
    }

    /// LPIPS between two 3-channel images in [0, 1] (HWC [`Image`]s of the same size).
    pub fn distance(&self, pred: &Image, gt: &Image) -> Result<f64, LpipsError> {
        let shape = |i: &Image| format!("{}x{}x{}", i.width, i.height, i.channels);
        if (pred.width, pred.height, pred.channels) != (gt.width, gt.height, gt.channels) || pred.channels != 3 {
            return Err(LpipsError::Shape {
                a: shape(pred),
                b: shape(gt),
            });
        }
        let min = self.net.min_side();
        if pred.width < min || pred.height < min {
            return Err(LpipsError::TooSmall {
                net: self.net.name(),
                min,
                width: pred.width,
                height: pred.height,
            });
        }
        let to_tensor = |i: &Image| Tensor::from_vec(i.to_chw(), (1, 3, i.height, i.width), &self.device);
        let d = self.forward(&to_tensor(pred)?, &to_tensor(gt)?)?;
        Ok(d.to_dtype(DType::F64)?.to_vec1::<f64>()?[0])
    }
}

/// `f / (‖f‖₂ + eps)` along the channel dim of `(N, C, H, W)`.
fn unit_normalize(f: &Tensor) -> candle_core::Result<Tensor> {
    let norm = f.sqr()?.sum_keepdim(1)?.sqrt()?;
    f.broadcast_div(&(norm + LPIPS_EPS)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use pixl_core::Rng;

    fn random_image(w: usize, h: usize, seed: u64) -> Image {
        let mut rng = Rng::new(seed);
        Image::from_vec(w, h, 3, (0..w * h * 3).map(|_| rng.f32()).collect()).unwrap()
    }

    fn rand_tensor(shape: &[usize], rng: &mut Rng, nonneg: bool) -> Tensor {
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n)
            .map(|_| if nonneg { rng.f32() } else { 0.1 * rng.normal() })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    /// Random AlexNet-LPIPS weights under the reference package's *full* state-dict names
    /// (`net.slice{k}.{i}.*`, `lins.{l}.*`, plus an ignored scaling-layer buffer), so loading
    /// exercises the renaming. `head_scale[l]` multiplies head `l` (0 switches a layer off).
    fn write_reference_style_alex(path: &Path, seed: u64, head_scale: [f32; 5]) {
        let mut rng = Rng::new(seed);
        let convs = [
            (1, 0, 64, 3, 11),
            (2, 3, 192, 64, 5),
            (3, 6, 384, 192, 3),
            (4, 8, 256, 384, 3),
            (5, 10, 256, 256, 3),
        ];
        let mut map = HashMap::new();
        for (slice, i, o, c, k) in convs {
            let fan_in = (c * k * k) as f32;
            let w = (rand_tensor(&[o, c, k, k], &mut rng, false) * (10.0 / fan_in.sqrt()) as f64).unwrap();
            map.insert(format!("net.slice{slice}.{i}.weight"), w);
            map.insert(format!("net.slice{slice}.{i}.bias"), rand_tensor(&[o], &mut rng, false));
        }
        for (l, c) in AlexNet::CHANNELS.iter().enumerate() {
            let w = (rand_tensor(&[1, *c, 1, 1], &mut rng, true) * head_scale[l] as f64).unwrap();
            map.insert(format!("lins.{l}.model.1.weight"), w);
        }
        map.insert(
            "scaling_layer.shift".into(),
            Tensor::new(&LPIPS_SHIFT, &Device::Cpu).unwrap(),
        );
        candle_core::safetensors::save(&map, path).unwrap();
    }

    #[test]
    fn renaming_rules() {
        assert_eq!(
            canonical_lpips_name("net.slice2.3.weight").as_deref(),
            Some("features.3.weight")
        );
        assert_eq!(
            canonical_lpips_name("features.10.bias").as_deref(),
            Some("features.10.bias")
        );
        assert_eq!(
            canonical_lpips_name("net.features.0.weight").as_deref(),
            Some("features.0.weight")
        );
        assert_eq!(
            canonical_lpips_name("lins.4.model.1.weight").as_deref(),
            Some("lin4.model.1.weight")
        );
        assert_eq!(
            canonical_lpips_name("lin0.model.1.weight").as_deref(),
            Some("lin0.model.1.weight")
        );
        assert_eq!(canonical_lpips_name("scaling_layer.shift"), None);
        assert_eq!(canonical_lpips_name("classifier.1.weight"), None);
    }

    #[test]
    fn random_weights_symmetric_nonnegative_zero_on_identical() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("lpips.safetensors");
        write_reference_style_alex(&path, 7, [1.0; 5]);
        let lpips = Lpips::load(&path, &Device::Cpu).unwrap();
        assert_eq!(lpips.net(), LpipsNet::Alex);
        let a = random_image(48, 40, 1);
        let b = random_image(48, 40, 2);
        let ab = lpips.distance(&a, &b).unwrap();
        let ba = lpips.distance(&b, &a).unwrap();
        assert!(ab.is_finite() && ab > 0.0, "lpips {ab}");
        assert!((ab - ba).abs() <= 1e-6 * ab, "not symmetric: {ab} vs {ba}");
        assert_eq!(lpips.distance(&a, &a).unwrap(), 0.0);
        // A small perturbation is closer than an unrelated image.
        let a2 = a.map(|v| (v + 0.02).min(1.0));
        let near = lpips.distance(&a, &a2).unwrap();
        assert!(near >= 0.0 && near < ab, "near {near} vs far {ab}");
    }

    /// With only head `l` switched on, LPIPS equals the definition evaluated by hand (f64 loops)
    /// on the backbone's tap `l`: this checks the [−1, 1] + scaling-layer input, the channel
    /// normalisation, the head weighting and the spatial mean independently of `forward`.
    #[test]
    fn single_layer_matches_hand_computation() {
        let dir = tempfile::tempdir().unwrap();
        let a = random_image(40, 36, 3);
        let b = random_image(40, 36, 4);
        for l in [0usize, 3] {
            let mut scale = [0.0f32; 5];
            scale[l] = 1.0;
            let path = dir.path().join(format!("l{l}.safetensors"));
            write_reference_style_alex(&path, 11, scale);
            let lpips = Lpips::load(&path, &Device::Cpu).unwrap();
            let got = lpips.distance(&a, &b).unwrap();

            // Hand computation: backbone on hand-normalised input.
            let raw = candle_core::safetensors::load(&path, &Device::Cpu).unwrap();
            let tensors: HashMap<_, _> = raw
                .into_iter()
                .filter_map(|(k, v)| canonical_lpips_name(&k).map(|k| (k, v)))
                .collect();
            let head = tensors[&format!("lin{l}.model.1.weight")]
                .flatten_all()
                .unwrap()
                .to_vec1::<f32>()
                .unwrap();
            let alex = AlexNet::new(VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu)).unwrap();
            let prep = |img: &Image| {
                let mut chw = img.to_chw();
                let hw = img.width * img.height;
                for (i, v) in chw.iter_mut().enumerate() {
                    let c = i / hw;
                    *v = ((2.0 * *v as f64 - 1.0 - LPIPS_SHIFT[c] as f64) / LPIPS_SCALE[c] as f64) as f32;
                }
                let t = Tensor::from_vec(chw, (1, 3, img.height, img.width), &Device::Cpu).unwrap();
                alex.features(&t).unwrap()[l]
                    .squeeze(0)
                    .unwrap()
                    .to_vec3::<f32>()
                    .unwrap()
            };
            let (fa, fb) = (prep(&a), prep(&b));
            let (c, h, w) = (fa.len(), fa[0].len(), fa[0][0].len());
            let mut sum = 0f64;
            for y in 0..h {
                for x in 0..w {
                    let na = (0..c).map(|k| (fa[k][y][x] as f64).powi(2)).sum::<f64>().sqrt() + LPIPS_EPS;
                    let nb = (0..c).map(|k| (fb[k][y][x] as f64).powi(2)).sum::<f64>().sqrt() + LPIPS_EPS;
                    for k in 0..c {
                        let d = fa[k][y][x] as f64 / na - fb[k][y][x] as f64 / nb;
                        sum += head[k] as f64 * d * d;
                    }
                }
            }
            let want = sum / (h * w) as f64;
            assert!(want > 0.0);
            assert!(
                (got - want).abs() < 1e-4 * want.max(1e-3),
                "layer {l}: {got} vs hand {want}"
            );
        }
    }

    #[test]
    fn errors_name_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("nope.safetensors");
        let e = Lpips::load(&missing, &Device::Cpu).unwrap_err().to_string();
        assert!(e.contains("nope.safetensors"), "{e}");
        // A file without heads.
        let partial = dir.path().join("partial.safetensors");
        let mut map = HashMap::new();
        map.insert(
            "features.0.weight".to_string(),
            Tensor::zeros((64, 3, 11, 11), DType::F32, &Device::Cpu).unwrap(),
        );
        candle_core::safetensors::save(&map, &partial).unwrap();
        let e = Lpips::load(&partial, &Device::Cpu).unwrap_err();
        assert!(matches!(e, LpipsError::Weights { .. }), "{e}");
        // Too-small images.
        let path = dir.path().join("ok.safetensors");
        write_reference_style_alex(&path, 1, [1.0; 5]);
        let lpips = Lpips::load(&path, &Device::Cpu).unwrap();
        let tiny = random_image(20, 20, 1);
        assert!(matches!(lpips.distance(&tiny, &tiny), Err(LpipsError::TooSmall { .. })));
    }
}
