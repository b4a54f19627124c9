//! [`Linear`]: a candle `Linear` (PyTorch's `weight (out, in)`, `bias (out)`) whose forward pass
//! takes the fused f32 CPU path ([`crate::fused::linear`]) and, once [`Linear::quantize_int8`]
//! has been called on a CPU with the kernel, the 8-bit one ([`crate::int8`]) whenever no
//! gradient is needed. Training, other devices and other dtypes are untouched.
use crate::fused::{self, Act};
use crate::int8::Int8Linear;
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;
use std::sync::Arc;

/// Smallest input width quantized: below it the 8-bit path does not pay for quantizing its
/// input (`examples/bench_int8`: 48 inputs ran at 0.9× the f32 speed, 384 and more at 2.4–4×).
pub const INT8_MIN_INPUTS: usize = 128;

#[derive(Clone, Debug)]
pub struct Linear {
    inner: candle_nn::Linear,
    int8: Option<Arc<Int8Linear>>,
}

impl Linear {
    pub fn new(inner: candle_nn::Linear) -> Self {
        Self { inner, int8: None }
    }

    /// `candle_nn::linear(in_dim, out_dim, vb)`: weights `weight`, `bias` under `vb`.
    pub fn load(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self::new(candle_nn::linear(in_dim, out_dim, vb)?))
    }

    /// The f32 layer.
    pub fn inner(&self) -> &candle_nn::Linear {
        &self.inner
    }

    /// Whether the 8-bit path is on.
    pub fn is_int8(&self) -> bool {
        self.int8.is_some()
    }

    /// Quantizes the weights to 8 bits for inference on this CPU; returns whether it did (not
    /// where the CPU has no kernel, the weights are not f32 on the CPU, or the layer has fewer
    /// than [`INT8_MIN_INPUTS`] inputs). Trained weights (variables) are refused: the 8-bit copy
    /// would not follow their updates.
    pub fn quantize_int8(&mut self) -> Result<bool> {
        let w = self.inner.weight();
        if w.track_op() || self.inner.bias().is_some_and(|b| b.track_op()) {
            candle_core::bail!("int8: a layer whose weights are being trained cannot be quantized");
        }
        if !fused::cpu_f32(w) || w.dim(1)? < INT8_MIN_INPUTS {
            return Ok(false);
        }
        self.int8 = Int8Linear::new(&self.inner)?.map(Arc::new);
        Ok(self.int8.is_some())
    }

    /// Bytes of the 8-bit copy ([`Int8Linear::bytes`]; 0 when not quantized).
    pub fn int8_bytes(&self) -> usize {
        self.int8.as_ref().map_or(0, |q| q.bytes())
    }

    /// `act(xs · Wᵀ + b)` over the last dim.
    pub fn forward_act(&self, xs: &Tensor, act: Act) -> Result<Tensor> {
        match &self.int8 {
            Some(q) if fused::cpu_f32(xs) && !crate::needs_grad(&[xs]) => q.forward(xs, act),
            _ => fused::linear(xs, &self.inner, act),
        }
    }
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
