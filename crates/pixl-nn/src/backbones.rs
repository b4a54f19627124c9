//! Pretrained-CNN feature extractors in **torchvision layout**, for the perceptual loss (training)
//! and LPIPS (evaluation, `pixl-eval`).
//!
//! Both take an `(N, 3, H, W)` tensor that the *caller* has already normalised, and return five
//! feature taps (post-ReLU), the ones LPIPS uses:
//!
//! | net | taps (torchvision `features` index of the ReLU) | channels | stride |
//! |---|---|---|---|
//! | [`AlexNet`] | relu1 (1), relu2 (4), relu3 (7), relu4 (9), relu5 (11) | 64, 192, 384, 256, 256 | 4, 8, 16, 16, 16 |
//! | [`Vgg16`] | relu1_2 (3), relu2_2 (8), relu3_3 (15), relu4_3 (22), relu5_3 (29) | 64, 128, 256, 512, 512 | 1, 2, 4, 8, 16 |
//!
//! Weights are looked up under the given `VarBuilder` as torchvision names them:
//! `features.{i}.weight` `(out, in, k, k)` and `features.{i}.bias` `(out)`, with
//! AlexNet convs at `i ∈ {0, 3, 6, 8, 10}` and VGG16 convs at
//! `i ∈ {0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28}` (the classifier is not used). A
//! torchvision `state_dict()` saved with `safetensors.torch.save_file` loads as is.
//!
//! Input normalisation: torchvision's ImageNet statistics ([`imagenet_normalize`]) for the
//! perceptual loss; LPIPS instead maps [0, 1] to [−1, 1] and applies its own scaling layer
//! (`pixl_eval::lpips`). Every op used (conv2d, ReLU, max-pool) has a candle backward, so
//! gradients flow to the input for a perceptual loss.
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};

/// ImageNet mean of torchvision's pretrained models (RGB, [0, 1] input).
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// ImageNet standard deviation of torchvision's pretrained models.
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// `(xs − mean) / std` per channel with [`IMAGENET_MEAN`] / [`IMAGENET_STD`]; `xs` is
/// `(N, 3, H, W)` RGB in [0, 1]. Differentiable.
pub fn imagenet_normalize(xs: &Tensor) -> Result<Tensor> {
    channel_affine(xs, &IMAGENET_MEAN, &IMAGENET_STD)
}

/// `(xs − shift[c]) / scale[c]` on the channel dim of an `(N, 3, H, W)` tensor.
pub fn channel_affine(xs: &Tensor, shift: &[f32; 3], scale: &[f32; 3]) -> Result<Tensor> {
    let (_, c, _, _) = xs.dims4()?;
    if c != 3 {
        candle_core::bail!("expected a 3-channel (N, 3, H, W) input, got {c} channels");
    }
    let dev = xs.device();
    let shift = Tensor::new(shift, dev)?.to_dtype(xs.dtype())?.reshape((1, 3, 1, 1))?;
    let scale = Tensor::new(scale, dev)?.to_dtype(xs.dtype())?.reshape((1, 3, 1, 1))?;
    xs.broadcast_sub(&shift)?.broadcast_div(&scale)
}

fn conv(c_in: usize, c_out: usize, k: usize, stride: usize, padding: usize, vb: VarBuilder) -> Result<Conv2d> {
    let cfg = Conv2dConfig {
        padding,
        stride,
        ..Default::default()
    };
    candle_nn::conv2d(c_in, c_out, k, cfg, vb)
}

/// One step of a torchvision `features` sequence.
#[derive(Clone, Debug)]
enum Layer {
    /// Convolution followed by ReLU (torchvision indices `i` and `i + 1`).
    ConvRelu(Conv2d),
    /// `MaxPool2d(kernel, stride)`, no padding, floor mode.
    MaxPool { kernel: usize, stride: usize },
    /// Marks that the output of the preceding ReLU is a tap.
    Tap,
}

fn run_layers(layers: &[Layer], xs: &Tensor) -> Result<Vec<Tensor>> {
    let mut taps = Vec::with_capacity(5);
    let mut xs = xs.clone();
    for layer in layers {
        match layer {
            Layer::ConvRelu(c) => xs = c.forward(&xs)?.relu()?,
            Layer::MaxPool { kernel, stride } => xs = xs.max_pool2d_with_stride(*kernel, *stride)?,
            Layer::Tap => taps.push(xs.clone()),
        }
    }
    Ok(taps)
}

fn check_input(xs: &Tensor, min_side: usize, net: &str) -> Result<()> {
    let (_, c, h, w) = xs.dims4()?;
    if c != 3 {
        candle_core::bail!("{net}: expected (N, 3, H, W) input, got {c} channels");
    }
    if h < min_side || w < min_side {
        candle_core::bail!("{net}: input {w}x{h} is too small; at least {min_side}x{min_side} is needed");
    }
    if xs.dtype() == DType::U8 || xs.dtype() == DType::U32 || xs.dtype() == DType::I64 {
        candle_core::bail!("{net}: expected a float input, got {:?}", xs.dtype());
    }
    Ok(())
}

/// torchvision `alexnet().features` (conv1 11×11/4 pad 2 → pool 3/2 → conv2 5×5 pad 2 → pool 3/2
/// → conv3..5 3×3 pad 1), up to relu5 (the last max-pool is not applied).
#[derive(Clone, Debug)]
pub struct AlexNet {
    layers: Vec<Layer>,
}

impl AlexNet {
    /// Output channels of the five taps.
    pub const CHANNELS: [usize; 5] = [64, 192, 384, 256, 256];
    /// Smallest input side for which every tap is non-empty.
    pub const MIN_SIDE: usize = 31;

    /// Loads `features.{0,3,6,8,10}.{weight,bias}` under `vb`.
    pub fn new(vb: VarBuilder) -> Result<Self> {
        let f = vb.pp("features");
        let layers = vec![
            Layer::ConvRelu(conv(3, 64, 11, 4, 2, f.pp("0"))?),
            Layer::Tap,
            Layer::MaxPool { kernel: 3, stride: 2 },
            Layer::ConvRelu(conv(64, 192, 5, 1, 2, f.pp("3"))?),
            Layer::Tap,
            Layer::MaxPool { kernel: 3, stride: 2 },
            Layer::ConvRelu(conv(192, 384, 3, 1, 1, f.pp("6"))?),
            Layer::Tap,
            Layer::ConvRelu(conv(384, 256, 3, 1, 1, f.pp("8"))?),
            Layer::Tap,
            Layer::ConvRelu(conv(256, 256, 3, 1, 1, f.pp("10"))?),
            Layer::Tap,
        ];
        Ok(Self { layers })
    }

    /// The five taps relu1..relu5 for a normalised `(N, 3, H, W)` input (`H, W ≥ 31`).
    pub fn features(&self, xs: &Tensor) -> Result<Vec<Tensor>> {
        check_input(xs, Self::MIN_SIDE, "AlexNet")?;
        run_layers(&self.layers, xs)
    }
}

/// torchvision `vgg16().features` (13 convs 3×3 pad 1, 2×2 max-pools), up to relu5_3.
#[derive(Clone, Debug)]
pub struct Vgg16 {
    layers: Vec<Layer>,
}

impl Vgg16 {
    /// Output channels of the five taps.
    pub const CHANNELS: [usize; 5] = [64, 128, 256, 512, 512];
    /// Smallest input side for which every tap is non-empty.
    pub const MIN_SIDE: usize = 16;
    /// torchvision indices of the convolutions, with their output channels; a `None` is a
    /// max-pool (at indices 4, 9, 16, 23).
    const PLAN: [Option<(usize, usize)>; 17] = [
        Some((0, 64)),
        Some((2, 64)),
        None,
        Some((5, 128)),
        Some((7, 128)),
        None,
        Some((10, 256)),
        Some((12, 256)),
        Some((14, 256)),
        None,
        Some((17, 512)),
        Some((19, 512)),
        Some((21, 512)),
        None,
        Some((24, 512)),
        Some((26, 512)),
        Some((28, 512)),
    ];

    /// Loads `features.{0,2,5,7,10,12,14,17,19,21,24,26,28}.{weight,bias}` under `vb`.
    pub fn new(vb: VarBuilder) -> Result<Self> {
        let f = vb.pp("features");
        let mut layers = Vec::with_capacity(22);
        let mut c_in = 3;
        for step in Self::PLAN {
            match step {
                Some((i, c_out)) => {
                    layers.push(Layer::ConvRelu(conv(c_in, c_out, 3, 1, 1, f.pp(i.to_string()))?));
                    c_in = c_out;
                }
                None => {
                    // A pool follows each block: the ReLU before it is a tap.
                    layers.push(Layer::Tap);
                    layers.push(Layer::MaxPool { kernel: 2, stride: 2 });
                }
            }
        }
        layers.push(Layer::Tap);
        Ok(Self { layers })
    }

    /// The five taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 for an `(N, 3, H, W)` input
    /// (`H, W ≥ 16`) normalised by the caller — ImageNet statistics ([`imagenet_normalize`]) for a
    /// perceptual loss, LPIPS's scaling layer for LPIPS.
    pub fn features(&self, xs: &Tensor) -> Result<Vec<Tensor>> {
        check_input(xs, Self::MIN_SIDE, "VGG16")?;
        run_layers(&self.layers, xs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use candle_nn::VarMap;

    fn random_vb(map: &VarMap) -> VarBuilder<'_> {
        VarBuilder::from_varmap(map, DType::F32, &Device::Cpu)
    }

    #[test]
    fn alexnet_tap_shapes_match_torchvision() {
        let map = VarMap::new();
        let net = AlexNet::new(random_vb(&map)).unwrap();
        // torchvision at 224: 55, 27, 13, 13, 13; at 67: 16 → pool 7 → pool 3.
        for (side, sp) in [(224usize, [55usize, 27, 13, 13, 13]), (67, [16, 7, 3, 3, 3])] {
            let xs = Tensor::randn(0f32, 1.0, (1, 3, side, side), &Device::Cpu).unwrap();
            let taps = net.features(&xs).unwrap();
            let dims: Vec<_> = taps.iter().map(|t| t.dims4().unwrap()).collect();
            let want: Vec<_> = (0..5).map(|i| (1, AlexNet::CHANNELS[i], sp[i], sp[i])).collect();
            assert_eq!(dims, want, "side {side}");
        }
        // Tensor names as torchvision's.
        let mut names: Vec<_> = map.data().lock().unwrap().keys().cloned().collect();
        names.sort();
        let mut want: Vec<String> = [0, 3, 6, 8, 10]
            .iter()
            .flat_map(|i| [format!("features.{i}.bias"), format!("features.{i}.weight")])
            .collect();
        want.sort();
        assert_eq!(names, want);
    }

    #[test]
    fn vgg16_tap_shapes_and_names() {
        let map = VarMap::new();
        let net = Vgg16::new(random_vb(&map)).unwrap();
        let xs = Tensor::randn(0f32, 1.0, (2, 3, 32, 48), &Device::Cpu).unwrap();
        let taps = net.features(&xs).unwrap();
        let dims: Vec<_> = taps.iter().map(|t| t.dims4().unwrap()).collect();
        let want: Vec<_> = (0..5).map(|i| (2, Vgg16::CHANNELS[i], 32 >> i, 48 >> i)).collect();
        assert_eq!(dims, want);
        let data = map.data().lock().unwrap();
        for i in [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28] {
            assert!(
                data.contains_key(&format!("features.{i}.weight")),
                "missing features.{i}.weight"
            );
        }
        assert_eq!(data.len(), 26);
        let w = data["features.10.weight"].as_tensor().dims().to_vec();
        assert_eq!(w, vec![256, 128, 3, 3]);
    }

    /// relu1 of AlexNet against a direct f64 convolution with stride 4, zero padding 2.
    #[test]
    #[allow(clippy::needless_range_loop)] // index loops are the point of a naive reference
    fn alexnet_first_tap_matches_naive_conv() {
        let map = VarMap::new();
        let net = AlexNet::new(random_vb(&map)).unwrap();
        let side = 35;
        let xs = Tensor::randn(0f32, 1.0, (1, 3, side, side), &Device::Cpu).unwrap();
        let taps = net.features(&xs).unwrap();
        let got = taps[0].squeeze(0).unwrap().to_vec3::<f32>().unwrap();
        let data = map.data().lock().unwrap();
        let w: Vec<Vec<Vec<Vec<f32>>>> = (0..64)
            .map(|o| {
                data["features.0.weight"]
                    .as_tensor()
                    .get(o)
                    .unwrap()
                    .to_vec3::<f32>()
                    .unwrap()
            })
            .collect();
        let b = data["features.0.bias"].as_tensor().to_vec1::<f32>().unwrap();
        let x = xs.squeeze(0).unwrap().to_vec3::<f32>().unwrap();
        let out = (side + 4 - 11) / 4 + 1;
        assert_eq!(got[0].len(), out);
        for o in [0usize, 17, 63] {
            for oy in 0..out {
                for ox in 0..out {
                    let mut acc = b[o] as f64;
                    for (c, xc) in x.iter().enumerate() {
                        for ky in 0..11 {
                            for kx in 0..11 {
                                let iy = (oy * 4 + ky) as isize - 2;
                                let ix = (ox * 4 + kx) as isize - 2;
                                if iy < 0 || ix < 0 || iy >= side as isize || ix >= side as isize {
                                    continue;
                                }
                                acc += w[o][c][ky][kx] as f64 * xc[iy as usize][ix as usize] as f64;
                            }
                        }
                    }
                    let want = acc.max(0.0);
                    let g = got[o][oy][ox] as f64;
                    assert!((g - want).abs() < 1e-4, "o {o} ({oy},{ox}): {g} vs {want}");
                }
            }
        }
    }

    #[test]
    fn imagenet_normalize_values_and_errors() {
        let xs = Tensor::ones((1, 3, 2, 2), DType::F32, &Device::Cpu).unwrap();
        let n = imagenet_normalize(&xs)
            .unwrap()
            .squeeze(0)
            .unwrap()
            .to_vec3::<f32>()
            .unwrap();
        for c in 0..3 {
            let want = (1.0 - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
            assert!((n[c][1][1] - want).abs() < 1e-6);
        }
        let small = Tensor::zeros((1, 3, 8, 8), DType::F32, &Device::Cpu).unwrap();
        let map = VarMap::new();
        assert!(Vgg16::new(random_vb(&map)).unwrap().features(&small).is_err());
        let four = Tensor::zeros((1, 4, 32, 32), DType::F32, &Device::Cpu).unwrap();
        assert!(imagenet_normalize(&four).is_err());
    }
}
