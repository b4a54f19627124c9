//! [`Linear`]: a candle `Linear` (PyTorch's `weight (out, in)`, `bias (out)`) whose forward pass
//! takes the fused f32 CPU path ([`crate::fused::linear`]) whenever no gradient is needed; after
//! [`Linear::pack_f32`] (CPUs with AVX-512F) the f32 weights are held only in the packed layout
//! of [`crate::packed`], whose kernel also applies the bias, the activation and a (layer-scaled)
//! residual add ([`Linear::forward_residual`]); after [`Linear::quantize_int8`] (CPUs with the
//! kernel) the 8-bit path ([`crate::int8`]) is taken instead. Training, other devices and other
//! dtypes are untouched (a packed layer rebuilds its dense weights for them).
use crate::fused::{self, Act, Vector};
use crate::int8::Int8Linear;
use crate::packed::{self, Epilogue, PackedLinear};
use candle_core::{Device, Module, Result, Tensor};
use candle_nn::VarBuilder;
use std::sync::Arc;

/// Smallest input width quantized: below it the 8-bit path does not pay for quantizing its
/// input (`examples/bench_int8`: 48 inputs ran at 0.9× the f32 speed, 384 and more at 2.4–4×).
pub const INT8_MIN_INPUTS: usize = 128;

#[derive(Clone, Debug)]
pub struct Linear {
    weights: Weights,
    int8: Option<Arc<Int8Linear>>,
}

/// Where the f32 weights live.
#[derive(Clone, Debug)]
enum Weights {
    /// candle's layer: any device and dtype, trainable.
    Dense(candle_nn::Linear),
    /// Packed for the AVX-512 kernel (frozen, f32, CPU); the only copy.
    Packed(Arc<PackedLinear>),
}

impl Linear {
    pub fn new(inner: candle_nn::Linear) -> Self {
        Self {
            weights: Weights::Dense(inner),
            int8: None,
        }
    }

    /// `candle_nn::linear(in_dim, out_dim, vb)`: weights `weight`, `bias` under `vb`.
    pub fn load(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self::new(candle_nn::linear(in_dim, out_dim, vb)?))
    }

    /// The f32 layer as candle's (rebuilt on the CPU from the packed weights after
    /// [`Linear::pack_f32`]).
    pub fn inner(&self) -> Result<candle_nn::Linear> {
        match &self.weights {
            Weights::Dense(layer) => Ok(layer.clone()),
            Weights::Packed(p) => {
                let (w, b) = p.to_dense();
                let w = Tensor::from_vec(w, (p.n(), p.k()), &Device::Cpu)?;
                let b = b.map(|b| Tensor::from_vec(b, p.n(), &Device::Cpu)).transpose()?;
                Ok(candle_nn::Linear::new(w, b))
            }
        }
    }

    /// Whether the 8-bit path is on.
    pub fn is_int8(&self) -> bool {
        self.int8.is_some()
    }

    /// Whether the f32 weights are packed ([`Linear::pack_f32`]).
    pub fn is_packed(&self) -> bool {
        matches!(self.weights, Weights::Packed(_))
    }

    /// Packs the f32 weights for the AVX-512 kernel of [`crate::packed`], dropping the dense
    /// copy, for inference on this CPU; returns whether it did (not where the CPU lacks
    /// AVX-512F or the weights are not f32 on the CPU). Trained weights (variables) are refused.
    pub fn pack_f32(&mut self) -> Result<bool> {
        let Weights::Dense(layer) = &self.weights else {
            return Ok(true);
        };
        let (w, b) = (layer.weight(), layer.bias());
        if w.track_op() || b.is_some_and(|b| b.track_op()) {
            candle_core::bail!("packed linear: a layer whose weights are being trained cannot be packed");
        }
        if !packed::available() || !fused::cpu_f32(w) || b.is_some_and(|b| !fused::cpu_f32(b)) {
            return Ok(false);
        }
        let (n, k) = w.dims2()?;
        let wv = w.flatten_all()?.to_vec1::<f32>()?;
        let bv = b.map(|b| b.to_vec1::<f32>()).transpose()?;
        let p = PackedLinear::from_weights(&wv, n, k, bv.as_deref()).map_err(candle_core::Error::msg)?;
        self.weights = Weights::Packed(Arc::new(p));
        Ok(true)
    }

    /// Quantizes the weights to 8 bits for inference on this CPU; returns whether it did (not
    /// where the CPU has no kernel, the weights are not f32 on the CPU, or the layer has fewer
    /// than [`INT8_MIN_INPUTS`] inputs). Trained weights (variables) are refused: the 8-bit copy
    /// would not follow their updates.
    pub fn quantize_int8(&mut self) -> Result<bool> {
        let inner = self.inner()?;
        let w = inner.weight();
        if w.track_op() || inner.bias().is_some_and(|b| b.track_op()) {
            candle_core::bail!("int8: a layer whose weights are being trained cannot be quantized");
        }
        if !fused::cpu_f32(w) || w.dim(1)? < INT8_MIN_INPUTS {
            return Ok(false);
        }
        self.int8 = Int8Linear::new(&inner)?.map(Arc::new);
        Ok(self.int8.is_some())
    }

    /// Bytes of the 8-bit copy ([`Int8Linear::bytes`]; 0 when not quantized).
    pub fn int8_bytes(&self) -> usize {
        self.int8.as_ref().map_or(0, |q| q.bytes())
    }

    /// `act(xs · Wᵀ + b)` over the last dim.
    pub fn forward_act(&self, xs: &Tensor, act: Act) -> Result<Tensor> {
        match (&self.int8, &self.weights) {
            (Some(q), _) if fused::cpu_f32(xs) && !crate::needs_grad(&[xs]) => q.forward(xs, act),
            (None, Weights::Packed(p)) if fused::cpu_f32(xs) && !crate::needs_grad(&[xs]) => {
                packed_forward(p, xs, act, None, None)
            }
            (_, Weights::Dense(layer)) => fused::linear(xs, layer, act),
            (_, Weights::Packed(_)) => fused::linear(xs, &self.inner()?, act),
        }
    }

    /// `residual + scale ⊙ (xs · Wᵀ + b)` (`scale` over the last dim, LayerScale) in the packed
    /// kernel's epilogue, when the weights are packed (and not in 8 bits) and no gradient is
    /// needed; `None` otherwise, and the caller adds the branch itself.
    pub fn forward_residual(&self, xs: &Tensor, residual: &Tensor, scale: Option<&Vector>) -> Result<Option<Tensor>> {
        let Weights::Packed(p) = &self.weights else {
            return Ok(None);
        };
        let plain = [xs, residual].into_iter().all(|t| fused::cpu_f32(t) && !t.track_op());
        if self.int8.is_some() || !plain {
            return Ok(None);
        }
        if residual.dims().last() != Some(&p.n())
            || residual.elem_count() / p.n().max(1) != xs.elem_count() / p.k().max(1)
        {
            candle_core::bail!(
                "linear: residual {:?} does not fit an output of width {} for input {:?}",
                residual.dims(),
                p.n(),
                xs.dims()
            );
        }
        if scale.is_some_and(|g| g.len() != p.n()) {
            candle_core::bail!(
                "linear: scale of {} values for {} outputs",
                scale.map_or(0, Vector::len),
                p.n()
            );
        }
        packed_forward(p, xs, Act::None, scale.map(Vector::values), Some(residual)).map(Some)
    }
}

/// The packed kernel on an f32 CPU tensor, any leading dims: `residual + scale ⊙ act(…)` as
/// [`Epilogue`] says (`residual` the same shape as the output).
fn packed_forward(
    p: &PackedLinear,
    xs: &Tensor,
    act: Act,
    scale: Option<&[f32]>,
    residual: Option<&Tensor>,
) -> Result<Tensor> {
    let _t = crate::profile::span("matmul (linear)");
    let dims = xs.dims();
    let Some((&k, lead)) = dims.split_last() else {
        candle_core::bail!("linear: a scalar input");
    };
    if k != p.k() {
        candle_core::bail!("linear: input width {k}, layer {}", p.k());
    }
    let rows: usize = lead.iter().product();
    let xs = xs.contiguous()?;
    let residual = residual.map(Tensor::contiguous).transpose()?;
    let out = {
        let (storage, layout) = xs.storage_and_layout();
        let x = fused::storage_slice(&storage, layout, "linear input")?;
        let res_guard = residual.as_ref().map(|r| r.storage_and_layout());
        let residual = match &res_guard {
            Some((storage, layout)) => Some(fused::storage_slice(storage, layout, "linear residual")?),
            None => None,
        };
        let epi = Epilogue { act, residual, scale };
        p.forward_vec(x, rows, &epi)
    };
    let mut out_dims = lead.to_vec();
    out_dims.push(p.n());
    Tensor::from_vec(out, out_dims, xs.device())
}

impl Module for Linear {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        self.forward_act(xs, Act::None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// Packed (where the CPU has AVX-512F): the same outputs as the dense layer, the residual
    /// epilogue the same as the separate add, the dense weights given back unchanged, and the
    /// gradient path still open through the rebuilt layer.
    #[test]
    fn packed_follows_the_dense_layer() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 13, 70), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.1, (45, 70), &dev).unwrap();
        let b = Tensor::randn(0f32, 0.1, 45, &dev).unwrap();
        let res = Tensor::randn(0f32, 1.0, (2, 13, 45), &dev).unwrap();
        let gamma = Vector::new(Tensor::randn(0f32, 1.0, 45, &dev).unwrap()).unwrap();
        let dense = Linear::new(candle_nn::Linear::new(w.clone(), Some(b.clone())));
        let mut layer = dense.clone();
        assert!(dense.forward_residual(&x, &res, None).unwrap().is_none());
        let packed = layer.pack_f32().unwrap();
        assert_eq!(packed, packed::available());
        assert_eq!(layer.is_packed(), packed);
        let diff = |a: &Tensor, b: &Tensor| crate::testing::max_abs_diff(a, b).unwrap();
        for act in [Act::None, Act::Gelu, Act::Relu] {
            let want = dense.forward_act(&x, act).unwrap();
            assert!(diff(&layer.forward_act(&x, act).unwrap(), &want) < 1e-5, "{act:?}");
        }
        let y = dense.forward(&x).unwrap();
        if packed {
            let got = layer.forward_residual(&x, &res, Some(&gamma)).unwrap().unwrap();
            let want = fused::add_scaled_rows(&res, &y, &gamma).unwrap();
            assert!(diff(&got, &want) < 1e-5);
            let got = layer.forward_residual(&x, &res, None).unwrap().unwrap();
            assert!(diff(&got, &(&res + &y).unwrap()) < 1e-5);
            assert!(
                layer.forward_residual(&x, &x, None).is_err(),
                "a residual of the wrong width"
            );
        }
        let inner = layer.inner().unwrap();
        assert_eq!(diff(inner.weight(), &w), 0.0);
        assert_eq!(diff(inner.bias().unwrap(), &b), 0.0);
        let xv = Var::from_tensor(&x).unwrap();
        let grads = layer
            .forward(xv.as_tensor())
            .unwrap()
            .sum_all()
            .unwrap()
            .backward()
            .unwrap();
        assert!(grads.get(xv.as_tensor()).is_some());
        let var = Var::from_tensor(&w).unwrap();
        let mut trained = Linear::new(candle_nn::Linear::new(var.as_tensor().clone(), None));
        assert!(trained.pack_f32().is_err());
    }

    #[test]
    fn int8_follows_the_f32_layer_and_only_where_asked() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (2, 9, 256), &dev).unwrap();
        let w = Tensor::randn(0f32, 0.05, (40, 256), &dev).unwrap();
        let b = Tensor::randn(0f32, 0.05, 40, &dev).unwrap();
        let mut layer = Linear::new(candle_nn::Linear::new(w.clone(), Some(b.clone())));
        let f32_out = layer.forward_act(&x, Act::Gelu).unwrap();
        assert_eq!(layer.int8_bytes(), 0);
        let quantized = layer.quantize_int8().unwrap();
        assert_eq!(quantized, crate::int8::available());
        if quantized {
            // One byte per weight (channels padded to whole panels of 32), and per channel a
            // scale, a weight sum and a bias in f32: 40 channels pad to 64.
            assert_eq!(layer.int8_bytes(), 64 * 256 + 3 * 64 * 4);
        }
        let out = layer.forward_act(&x, Act::Gelu).unwrap();
        let err = crate::testing::max_abs_diff(&out, &f32_out).unwrap();
        let scale = f32_out.abs().unwrap().max_all().unwrap().to_scalar::<f32>().unwrap() as f64;
        if quantized {
            // 8 bits: a visible but small difference.
            assert!(err > 0.0 && err < 0.03 * scale, "{err} vs {scale}");
        } else {
            assert_eq!(err, 0.0);
        }
        // Narrow layers stay f32.
        let mut narrow = Linear::new(candle_nn::Linear::new(
            Tensor::ones((4, 48), candle_core::DType::F32, &dev).unwrap(),
            None,
        ));
        assert!(!narrow.quantize_int8().unwrap());
        // Variables (training) are refused.
        let var = Var::from_tensor(&w).unwrap();
        let mut trained = Linear::new(candle_nn::Linear::new(var.as_tensor().clone(), None));
        assert!(trained.quantize_int8().is_err());
    }
}
