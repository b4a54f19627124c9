//! Depthwise `k×k` convolution, stride 1, "same" padding `k/2`: weight `(C, 1, k, k)`, bias `(C)`
//! (PyTorch `nn.Conv2d(C, C, k, padding=k//2, groups=C)` layout and names).
use candle_core::{Module, Result, Tensor};
use candle_nn::VarBuilder;

#[derive(Clone, Debug)]
pub struct DepthwiseConv2d {
    pub weight: Tensor,
    pub bias: Tensor,
    pub kernel: usize,
}

impl DepthwiseConv2d {
    pub fn new(channels: usize, kernel: usize, vb: VarBuilder) -> Result<Self> {
        let bound = 1.0 / ((kernel * kernel) as f64).sqrt();
        let init = candle_nn::Init::Uniform { lo: -bound, up: bound };
        let weight = vb.get_with_hints((channels, 1, kernel, kernel), "weight", init)?;
        let bias = vb.get_with_hints(channels, "bias", init)?;
        Ok(Self { weight, bias, kernel })
    }
}

impl Module for DepthwiseConv2d {
    fn forward(&self, xs: &Tensor) -> Result<Tensor> {
        let c = self.weight.dim(0)?;
        let ys = xs.conv2d(&self.weight, self.kernel / 2, 1, 1, c)?;
        ys.broadcast_add(&self.bias.reshape((1, c, 1, 1))?)
    }
}
