//! The methods `pixl eval` scores, behind one trait: the two reference baselines and the network.
//!
//! - [`Identity`]: the prediction is the source photograph itself (what "no relighting" scores).
//! - [`Compose`]: the prediction is the target intrinsics recomposed, `A ⊙ S + R` of C_T (paper
//!   eq. 1), tonemapped like the targets: targets are sRGB in [0, 1] (PNG/JPEG as stored, EXR clipped
//!   to [0, 1] and sRGB-encoded by `pixl_data::load_image`), so the linear recomposition is
//!   clipped to [0, 1] and sRGB-encoded ([`pixl_core::image::linear_to_srgb`]). This is what the
//!   conditioning alone explains, without the source.
//!   `compose-reinhard` ([`ComposeTonemap::Reinhard`]) shows the recomposition with Reinhard
//!   auto-exposure instead ([`pixl_core::image::tonemap_reinhard`], key 0.18) — how the paper
//!   displays path-traced renders and how `pixl synth` writes its images, so on synthetic sets it
//!   is the recomposition shown exactly like the targets.
//! - [`ModelMethod`]: a PIXLRelight checkpoint, `Î_T = f_θ(I_S, C_T)` (paper §3.2).
use crate::error::{EvalError, Result};
use crate::timing::{time_runs, Timing};
use candle_core::{DType, Device, Tensor};
use pixl_core::image::linear_to_srgb;
use pixl_core::Image;
use pixl_intrinsics::ct::Ct;
use pixl_model::PixlRelight;

/// A relighting method under evaluation.
pub trait Method {
    /// Row label in the tables ("Identity (source)", "Ours", …).
    fn name(&self) -> &str;
    /// The target-lighting cue it consumes (the "Lighting cue" column of Table 1).
    fn cue(&self) -> &str;
    /// Whether [`Method::predict`] reads C_T (if no method does, intrinsics are never loaded).
    fn needs_ct(&self) -> bool;
    /// The prediction for the target, 3-channel sRGB in [0, 1], the size of `source`.
    fn predict(&self, source: &Image, ct: Option<&Ct>) -> Result<Image>;
    /// The paper's timing protocol on one input: forward pass only (inputs prepared beforehand),
    /// `warmups` untimed then `runs` timed runs.
    fn time(&self, source: &Image, ct: Option<&Ct>, warmups: usize, runs: usize) -> Result<Timing> {
        time_runs(warmups, runs, || self.predict(source, ct).map(|_| ()))
    }
    /// "cpu f32", "cuda:0 bf16": where and how it runs, printed with its timing.
    fn device_desc(&self) -> String {
        "cpu f32".into()
    }
}

/// The source photograph as the prediction.
#[derive(Clone, Copy, Debug, Default)]
pub struct Identity;

impl Method for Identity {
    fn name(&self) -> &str {
        "Identity (source)"
    }
    fn cue(&self) -> &str {
        "none"
    }
    fn needs_ct(&self) -> bool {
        false
    }
    fn predict(&self, source: &Image, _ct: Option<&Ct>) -> Result<Image> {
        Ok(source.clone())
    }
}

/// `linear_to_srgb(clip(A ⊙ S + R, 0, 1))` of C_T (see the module docs).
pub fn compose_baseline(ct: &Ct) -> Image {
    ct.recompose().map(|v| linear_to_srgb(v.clamp(0.0, 1.0)))
}

/// How [`Compose`] turns the linear recomposition into a displayed image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ComposeTonemap {
    /// Clip to [0, 1], sRGB-encode ([`compose_baseline`]).
    #[default]
    Clip,
    /// Reinhard with auto-exposure ([`pixl_core::image::tonemap_reinhard`]).
    Reinhard,
    /// A camera's tone curve ([`pixl_core::image::tonemap_camera`]), as `pixl synth --style
    /// photo` shows its images.
    Camera,
}

/// The recomposed target intrinsics as the prediction ([`compose_baseline`], or Reinhard).
#[derive(Clone, Copy, Debug, Default)]
pub struct Compose {
    pub tonemap: ComposeTonemap,
}

impl Method for Compose {
    fn name(&self) -> &str {
        match self.tonemap {
            ComposeTonemap::Clip => "Compose (A⊙S+R of C_T)",
            ComposeTonemap::Reinhard => "Compose, Reinhard (A⊙S+R of C_T)",
            ComposeTonemap::Camera => "Compose, camera (A⊙S+R of C_T)",
        }
    }
    fn cue(&self) -> &str {
        "Full intrinsics"
    }
    fn needs_ct(&self) -> bool {
        true
    }
    fn predict(&self, _source: &Image, ct: Option<&Ct>) -> Result<Image> {
        let ct = ct.ok_or_else(|| EvalError::Method {
            method: self.name().into(),
            reason: "needs C_T".into(),
        })?;
        Ok(match self.tonemap {
            ComposeTonemap::Clip => compose_baseline(ct),
            ComposeTonemap::Reinhard => pixl_core::image::tonemap_reinhard(&ct.recompose()),
            ComposeTonemap::Camera => pixl_core::image::tonemap_camera(&ct.recompose()),
        })
    }
}

/// Parses a `--baselines` list (`identity,compose,compose-reinhard,compose-camera`; empty
/// entries ignored).
pub fn parse_baselines(list: &str) -> Result<Vec<Box<dyn Method>>> {
    let mut out: Vec<Box<dyn Method>> = Vec::new();
    for name in list.split(',').map(str::trim).filter(|s| !s.is_empty()) {
        match name {
            "identity" => out.push(Box::new(Identity)),
            "compose" => out.push(Box::new(Compose::default())),
            "compose-reinhard" => out.push(Box::new(Compose {
                tonemap: ComposeTonemap::Reinhard,
            })),
            "compose-camera" => out.push(Box::new(Compose {
                tonemap: ComposeTonemap::Camera,
            })),
            other => return Err(EvalError::UnknownBaseline(other.to_string())),
        }
    }
    Ok(out)
}

/// A PIXLRelight network as a method.
pub struct ModelMethod {
    pub label: String,
    pub model: PixlRelight,
    pub device: Device,
    /// Longest side the network works at, as `pixl relight --max-side`: a larger pair is
    /// area-averaged to [`pixl_model::fullres::working_size`] and the network's gain and bias
    /// are applied to the full-size source ([`pixl_model::fullres`]). `None`: always the
    /// image's own size.
    pub max_side: Option<usize>,
}

impl ModelMethod {
    /// The size the network runs at for a `width × height` pair.
    fn working_size(&self, width: usize, height: usize) -> (usize, usize) {
        match self.max_side {
            Some(m) => pixl_model::fullres::working_size(width, height, m),
            None => (width, height),
        }
    }

    /// Source `(1,3,h,w)` and C_T `(1,9,h,w)` at the working size.
    fn inputs(&self, source: &Image, ct: Option<&Ct>) -> Result<(Tensor, Tensor)> {
        let ct = ct.ok_or_else(|| self.err("needs C_T"))?;
        if source.channels != 3 || (ct.width(), ct.height()) != (source.width, source.height) {
            return Err(self.err(format!(
                "source is {}x{}x{} but C_T is {}x{}",
                source.width,
                source.height,
                source.channels,
                ct.width(),
                ct.height()
            )));
        }
        let (w, h) = self.working_size(source.width, source.height);
        let src = pixl_core::resample::area_resize_to_chw(source, w, h).map_err(|e| self.err(e))?;
        let ct = ct.to_chw_at(w, h).map_err(|e| self.err(e))?;
        let src = Tensor::from_vec(src, (1, 3, h, w), &self.device).map_err(|e| self.err(e))?;
        let ct = Tensor::from_vec(ct, (1, 9, h, w), &self.device).map_err(|e| self.err(e))?;
        Ok((src, ct))
    }

    fn err(&self, e: impl std::fmt::Display) -> EvalError {
        EvalError::Method {
            method: self.label.clone(),
            reason: e.to_string(),
        }
    }
}

impl Method for ModelMethod {
    fn name(&self) -> &str {
        &self.label
    }
    fn cue(&self) -> &str {
        "Full intrinsics"
    }
    fn needs_ct(&self) -> bool {
        true
    }
    fn predict(&self, source: &Image, ct: Option<&Ct>) -> Result<Image> {
        let (src, ct) = self.inputs(source, ct)?;
        let work = self.working_size(source.width, source.height);
        if work != (source.width, source.height) {
            let flat = |t: Tensor| t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>();
            let (g, b) = self.model.gain_bias(&src, &ct).map_err(|e| self.err(e))?;
            let (g, b) = (flat(g).map_err(|e| self.err(e))?, flat(b).map_err(|e| self.err(e))?);
            let mut out = source.clone();
            pixl_model::fullres::apply_gain_bias(&mut out, &g, &b, work.0, work.1).map_err(|e| self.err(e))?;
            return Ok(out);
        }
        let out = self.model.forward(&src, &ct).map_err(|e| self.err(e))?;
        let chw = out
            .squeeze(0)
            .and_then(|t| t.to_dtype(DType::F32))
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1::<f32>())
            .map_err(|e| self.err(e))?;
        Ok(Image::from_chw(source.width, source.height, 3, &chw)?)
    }
    /// Times `model.forward` only: the input tensors are built once, outside the timed region,
    /// and the device is synchronised at the end of every run.
    fn time(&self, source: &Image, ct: Option<&Ct>, warmups: usize, runs: usize) -> Result<Timing> {
        let (src, ct) = self.inputs(source, ct)?;
        time_runs(warmups, runs, || {
            let out = self.model.forward(&src, &ct)?;
            self.device.synchronize()?;
            drop(out);
            Ok::<(), candle_core::Error>(())
        })
        .map_err(|e| self.err(e))
    }
    fn device_desc(&self) -> String {
        let dev = match &self.device {
            Device::Cpu => "cpu".to_string(),
            other => format!("{:?}", other.location()),
        };
        format!("{dev} {:?}", self.model.dtype()).to_lowercase()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compose_is_clipped_srgb_of_recomposition() {
        let a = Image::from_fn(2, 2, 3, |x, _, c| [0.5, 0.8, 1.0][c] * (x as f32 + 1.0) / 2.0);
        let s = Image::from_fn(2, 2, 3, |_, y, _| 0.5 + y as f32);
        let r = Image::from_fn(2, 2, 3, |_, _, c| 0.05 * c as f32);
        let ct = Ct::new(a.clone(), s.clone(), r.clone()).unwrap();
        let out = compose_baseline(&ct);
        for y in 0..2 {
            for x in 0..2 {
                for c in 0..3 {
                    let lin = (a.get(x, y, c) * s.get(x, y, c) + r.get(x, y, c)) as f64;
                    let lin = lin.clamp(0.0, 1.0);
                    // sRGB OETF written out here independently.
                    let want = if lin <= 0.0031308 {
                        12.92 * lin
                    } else {
                        1.055 * lin.powf(1.0 / 2.4) - 0.055
                    };
                    assert!((out.get(x, y, c) as f64 - want).abs() < 1e-5, "({x},{y},{c})");
                }
            }
        }
        // Values above 1 in linear are white, not overflow.
        assert!((out.get(1, 1, 2) - 1.0).abs() < 1e-6);
    }

    /// Reinhard compose: per channel `v·k / (1 + v·k)`, sRGB-encoded, with the exposure `k =
    /// 0.18 / exp(mean ln(1e-4 + luminance))` — recomputed here in f64; and being scale-free, it
    /// shows a C_T and the same C_T with twice the shading (and residual) alike.
    /// compose-camera shows the recomposition with the camera tone curve, so the light's
    /// overall scale (shading and residual ×4) cancels, and it differs from Reinhard.
    #[test]
    fn compose_camera_is_the_camera_curve_of_the_recomposition_and_scale_free() {
        let a = Image::from_fn(8, 6, 3, |x, _, c| [0.5, 0.8, 0.3][c] * (x as f32 + 1.0) / 8.0);
        let s = Image::from_fn(8, 6, 3, |_, y, c| 0.2 + 0.3 * y as f32 + 0.1 * c as f32);
        let r = Image::from_fn(8, 6, 3, |x, _, c| 0.01 * (c + x) as f32);
        let m = Compose {
            tonemap: ComposeTonemap::Camera,
        };
        let ct = Ct::new(a.clone(), s.clone(), r.clone()).unwrap();
        let out = m.predict(&a, Some(&ct)).unwrap();
        assert_eq!(out.data, pixl_core::image::tonemap_camera(&ct.recompose()).data);
        let brighter = Ct::new(a.clone(), s.map(|v| 4.0 * v), r.map(|v| 4.0 * v)).unwrap();
        let out4 = m.predict(&a, Some(&brighter)).unwrap();
        let worst = out
            .data
            .iter()
            .zip(&out4.data)
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-3, "{worst}");
        let reinhard = Compose {
            tonemap: ComposeTonemap::Reinhard,
        }
        .predict(&a, Some(&ct))
        .unwrap();
        assert!(reinhard.data.iter().zip(&out.data).any(|(p, q)| (p - q).abs() > 0.02));
    }

    #[test]
    fn compose_reinhard_is_auto_exposed_reinhard_of_recomposition() {
        let a = Image::from_fn(3, 2, 3, |x, _, c| [0.5, 0.8, 0.3][c] * (x as f32 + 1.0) / 3.0);
        let s = Image::from_fn(3, 2, 3, |_, y, c| 0.5 + y as f32 + 0.1 * c as f32);
        let r = Image::from_fn(3, 2, 3, |x, _, c| 0.02 * (c + x) as f32);
        let ct = Ct::new(a.clone(), s.clone(), r.clone()).unwrap();
        let m = Compose {
            tonemap: ComposeTonemap::Reinhard,
        };
        let out = m.predict(&a, Some(&ct)).unwrap();
        let lin = |x: usize, y: usize, c: usize| (a.get(x, y, c) * s.get(x, y, c) + r.get(x, y, c)) as f64;
        let mut log_sum = 0.0;
        for y in 0..2 {
            for x in 0..3 {
                let l = 0.2126 * lin(x, y, 0) + 0.7152 * lin(x, y, 1) + 0.0722 * lin(x, y, 2);
                log_sum += (1e-4 + l).ln();
            }
        }
        let k = 0.18 / (log_sum / 6.0).exp();
        for y in 0..2 {
            for x in 0..3 {
                for c in 0..3 {
                    let v = lin(x, y, c) * k;
                    let t = v / (1.0 + v);
                    let want = if t <= 0.0031308 {
                        12.92 * t
                    } else {
                        1.055 * t.powf(1.0 / 2.4) - 0.055
                    };
                    assert!((out.get(x, y, c) as f64 - want).abs() < 1e-5, "({x},{y},{c})");
                }
            }
        }
        let twice = Ct::new(a.clone(), s.map(|v| 2.0 * v), r.map(|v| 2.0 * v)).unwrap();
        let out2 = m.predict(&a, Some(&twice)).unwrap();
        let max_diff = out
            .data
            .iter()
            .zip(&out2.data)
            .map(|(p, q)| (p - q).abs())
            .fold(0f32, f32::max);
        assert!(max_diff < 1e-3, "{max_diff}");
    }

    #[test]
    fn baseline_list_parses_and_rejects() {
        let m = parse_baselines("identity, compose,compose-reinhard,compose-camera").unwrap();
        assert_eq!(
            m.iter().map(|m| m.needs_ct()).collect::<Vec<_>>(),
            vec![false, true, true, true]
        );
        assert_eq!(m[2].name(), "Compose, Reinhard (A⊙S+R of C_T)");
        assert_eq!(m[3].name(), "Compose, camera (A⊙S+R of C_T)");
        assert!(matches!(parse_baselines("identity,magic"), Err(EvalError::UnknownBaseline(n)) if n == "magic"));
        assert!(parse_baselines("").unwrap().is_empty());
    }

    #[test]
    fn identity_returns_source() {
        let img = Image::from_fn(3, 2, 3, |x, y, c| (x + y + c) as f32 / 10.0);
        assert_eq!(Identity.predict(&img, None).unwrap(), img);
        assert!(Compose::default().predict(&img, None).is_err());
    }

    /// With `max_side` below the pair's size the network runs at the working size and its gain
    /// and bias are applied at full size — what `pixl_model::fullres::relight_full` (the code of
    /// `pixl relight`, a separate path through the network) gives; at or above it, the plain
    /// full-size forward.
    #[test]
    fn model_method_works_at_max_side_as_relight_does() {
        let weights = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../assets/demo-weights/pixl-tiny-synth.safetensors");
        let model = |max_side| ModelMethod {
            label: "ours".into(),
            model: pixl_model::checkpoint::load(&weights, &Device::Cpu, DType::F32)
                .unwrap()
                .1,
            device: Device::Cpu,
            max_side,
        };
        let (w, h) = (40, 24);
        let src = Image::from_fn(w, h, 3, |x, y, c| ((x * 7 + y * 13 + c * 5) % 17) as f32 / 17.0);
        let group = |k: f32| Image::from_fn(w, h, 3, |x, y, c| k * (0.2 + ((x + 2 * y + c) % 9) as f32 / 10.0));
        let ct = Ct::new(group(0.8), group(1.5), group(0.1)).unwrap();
        let full = model(None).predict(&src, Some(&ct)).unwrap();
        assert_eq!(model(Some(40)).predict(&src, Some(&ct)).unwrap().data, full.data);
        let small = model(Some(16)).predict(&src, Some(&ct)).unwrap();
        let work = pixl_model::fullres::working_size(w, h, 16);
        assert_eq!(work, (16, 10));
        let want = pixl_model::fullres::relight_full(
            &model(None).model,
            src.clone(),
            &ct.to_chw_at(work.0, work.1).unwrap(),
            work,
            &Device::Cpu,
            &mut |_, _, _| {},
        )
        .unwrap();
        assert_eq!((small.width, small.height), (w, h));
        assert_eq!(small.data, want.data);
        assert_ne!(
            small.data, full.data,
            "the working size changed nothing: the test proves nothing"
        );
    }
}
