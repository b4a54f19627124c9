//! 3×3 convolution (padding 1, stride 1 or 2) for inference on the CPU (the relighting network's
//! DPT head, DA3's DPT head, Marigold's VAE), and [`Conv3x3`], the layer that uses it: the input is copied
//! once into a zero-padded channels-last buffer, each band of output rows is unrolled into an
//! im2col matrix by contiguous copies of `C` floats, multiplied by the weights with one large
//! (internally parallel) matrix product, and written back channels-first with the bias, a
//! skip connection and the activation applied on the way.
//!
//! Same operation as `candle_nn::Conv2d` (which the head uses on other devices): weight
//! `(O, C, 3, 3)`, `out[o, y, x] = b[o] + Σ_{c,ky,kx} w[o, c, ky, kx]·in[c, s·y + ky − 1,
//! s·x + kx − 1]` (zero outside), output `(B, O, ⌊(H − 1)/s⌋ + 1, ⌊(W − 1)/s⌋ + 1)`.
use crate::fused::{self, bias_act_channels, bias_residual_channels, Act, Vector};
use candle_core::{Layout, Module, Result, Storage, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use rayon::prelude::*;

/// Largest im2col band, in floats (about 32 MiB).
const BAND_FLOATS: usize = 8 << 20;

/// Weights in im2col order: `(O, 9·C)`, columns `(ky, kx, c)`.
#[derive(Clone, Debug)]
pub struct Im2colWeight {
    matrix: Tensor,
    cin: usize,
}

impl Im2colWeight {
    pub fn new(weight: &Tensor) -> Result<Self> {
        let (o, c, kh, kw) = weight.dims4()?;
        if (kh, kw) != (3, 3) {
            candle_core::bail!("3x3 convolution given a {kh}x{kw} kernel");
        }
        let matrix = weight.permute((0, 2, 3, 1))?.contiguous()?.reshape((o, 9 * c))?;
        Ok(Self { matrix, cin: c })
    }
}

/// What happens to each output value `v` of channel `o` at flat index `i` of its plane.
pub struct Epilogue<'a> {
    pub bias: Option<&'a [f32]>,
    /// Added after the bias, same shape as the output.
    pub residual: Option<&'a [f32]>,
    pub act: Act,
}

/// The f32 values of a contiguous CPU tensor's storage, borrowed.
fn cpu_f32_slice<'a>(storage: &'a Storage, layout: &Layout) -> Result<&'a [f32]> {
    let Storage::Cpu(cpu) = storage else {
        candle_core::bail!("3x3 convolution: expected a CPU tensor");
    };
    fused::slice(cpu, layout, "3x3 convolution")
}

/// `(B, C, H, W)` f32 CPU tensor → `(B, O, H', W')`, im2col bands of up to 8 Mi floats.
pub fn conv3x3(xs: &Tensor, w: &Im2colWeight, stride: usize, epi: &Epilogue) -> Result<Tensor> {
    conv3x3_banded(xs, w, stride, epi, BAND_FLOATS)
}

/// [`conv3x3`] with im2col bands of at most `band_floats` floats (whole output rows, at least
/// one): smaller bands hold less memory, larger ones give the matrix product more work per call.
pub fn conv3x3_banded(
    xs: &Tensor,
    w: &Im2colWeight,
    stride: usize,
    epi: &Epilogue,
    band_floats: usize,
) -> Result<Tensor> {
    let (b, c, h, wd) = xs.dims4()?;
    if c != w.cin {
        candle_core::bail!("3x3 convolution expects {} input channels, got {c}", w.cin);
    }
    let o = w.matrix.dim(0)?;
    let (ho, wo) = ((h - 1) / stride + 1, (wd - 1) / stride + 1);
    let xs = xs.contiguous()?;
    let (storage, layout) = xs.storage_and_layout();
    let src = cpu_f32_slice(&storage, layout)?;
    let mut out = vec![0f32; b * o * ho * wo];
    if let Some(r) = epi.residual {
        if r.len() != out.len() {
            candle_core::bail!("residual of {} values for an output of {}", r.len(), out.len());
        }
    }
    let (ph, pw) = (h + 2, wd + 2);
    let k = 9 * c;
    // Output rows per band: as many as fit `band_floats`, at least one.
    let band_rows = (band_floats / (k * wo).max(1)).clamp(1, ho.max(1));
    for bi in 0..b {
        // Zero-padded channels-last copy of this image: padded[(y, x, c)].
        let mut padded = vec![0f32; ph * pw * c];
        let plane = &src[bi * c * h * wd..(bi + 1) * c * h * wd];
        padded
            .par_chunks_mut(pw * c)
            .enumerate()
            .filter(|(y, _)| (1..=h).contains(y))
            .for_each(|(y, row)| {
                for ch in 0..c {
                    let s = &plane[ch * h * wd + (y - 1) * wd..ch * h * wd + y * wd];
                    for (x, &v) in s.iter().enumerate() {
                        row[(x + 1) * c + ch] = v;
                    }
                }
            });
        let dst = &mut out[bi * o * ho * wo..(bi + 1) * o * ho * wo];
        for y0 in (0..ho).step_by(band_rows) {
            let rows = band_rows.min(ho - y0);
            let t = rows * wo;
            let mut cols = vec![0f32; t * k];
            cols.par_chunks_mut(k).enumerate().for_each(|(p, col)| {
                let (oy, ox) = (y0 + p / wo, p % wo);
                for ky in 0..3 {
                    let row = (oy * stride + ky) * pw;
                    for kx in 0..3 {
                        let s = (row + ox * stride + kx) * c;
                        col[(ky * 3 + kx) * c..(ky * 3 + kx + 1) * c].copy_from_slice(&padded[s..s + c]);
                    }
                }
            });
            let cols = Tensor::from_vec(cols, (t, k), xs.device())?;
            let res = w.matrix.matmul(&cols.t()?)?.contiguous()?; // (O, t)
            drop(cols);
            let (res_storage, res_layout) = res.storage_and_layout();
            let res = cpu_f32_slice(&res_storage, res_layout)?;
            let start = y0 * wo;
            dst.par_chunks_mut(ho * wo).enumerate().for_each(|(oc, plane)| {
                let bias = epi.bias.map_or(0.0, |bv| bv[oc]);
                let seg = &mut plane[start..start + t];
                let r = &res[oc * t..(oc + 1) * t];
                let base = bi * o * ho * wo + oc * ho * wo + start;
                for (j, (d, &v)) in seg.iter_mut().zip(r).enumerate() {
                    let mut v = v + bias;
                    if let Some(skip) = epi.residual {
                        v += skip[base + j];
                    }
                    *d = epi.act.apply(v);
                }
            });
        }
    }
    Tensor::from_vec(out, (b, o, ho, wo), xs.device())
}

/// `Conv2d(cin, cout, 3, stride, padding=1)` with the bias, an optional skip connection and an
/// activation applied in the same pass ([`conv3x3`] on the CPU, candle's `Conv2d`
/// followed by the fused ops elsewhere).
#[derive(Clone, Debug)]
pub struct Conv3x3 {
    conv: Conv2d,
    im2col: Im2colWeight,
    stride: usize,
    bias: Option<Vector>,
}

impl Conv3x3 {
    pub fn new(cin: usize, cout: usize, stride: usize, bias: bool, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get((cout, cin, 3, 3), "weight")?;
        let bias = if bias {
            Some(Vector::new(vb.get(cout, "bias")?)?)
        } else {
            None
        };
        Self::from_parts(weight, bias, stride)
    }

    pub fn from_parts(weight: Tensor, bias: Option<Vector>, stride: usize) -> Result<Self> {
        let cfg = Conv2dConfig {
            padding: 1,
            stride,
            ..Default::default()
        };
        Ok(Self {
            im2col: Im2colWeight::new(&weight)?,
            conv: Conv2d::new(weight, None, cfg),
            stride,
            bias,
        })
    }

    /// `act((conv(xs) + b) + residual)`.
    pub fn apply(&self, xs: &Tensor, residual: Option<&Tensor>, act: Act) -> Result<Tensor> {
        if fused::cpu_f32(xs) && residual.is_none_or(fused::cpu_f32) {
            let skip = match residual {
                Some(r) => Some(r.contiguous()?.flatten_all()?.to_vec1::<f32>()?),
                None => None,
            };
            let epi = Epilogue {
                bias: self.bias.as_ref().map(Vector::values),
                residual: skip.as_deref(),
                act,
            };
            return conv3x3(xs, &self.im2col, self.stride, &epi);
        }
        let ys = self.conv.forward(xs)?;
        match (&self.bias, residual) {
            (Some(b), Some(r)) => bias_residual_channels(&ys, b, r, act),
            (Some(b), None) => bias_act_channels(&ys, b, act),
            (None, Some(r)) => fused::add_act(&ys, r, act),
            (None, None) if act == Act::Relu => fused::relu(&ys),
            (None, None) => Ok(ys),
        }
    }

    pub fn forward(&self, xs: &Tensor, act: Act) -> Result<Tensor> {
        self.apply(xs, None, act)
    }

    /// `(conv(xs) + b) + residual`.
    pub fn forward_residual(&self, xs: &Tensor, residual: &Tensor) -> Result<Tensor> {
        self.apply(xs, Some(residual), Act::None)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Module};

    /// Against candle's conv2d, with bias, residual and ReLU, both strides, odd sizes.
    #[test]
    fn matches_candle_conv2d() {
        let dev = Device::Cpu;
        for (stride, (h, w)) in [(1, (9, 13)), (2, (9, 13)), (2, (8, 6)), (1, (1, 1))] {
            let xs = Tensor::randn(0f32, 1.0, (2, 5, h, w), &dev).unwrap();
            let wt = Tensor::randn(0f32, 1.0, (7, 5, 3, 3), &dev).unwrap();
            let bias = Tensor::randn(0f32, 1.0, 7, &dev).unwrap();
            let cfg = candle_nn::Conv2dConfig {
                padding: 1,
                stride,
                ..Default::default()
            };
            let want = candle_nn::Conv2d::new(wt.clone(), Some(bias.clone()), cfg)
                .forward(&xs)
                .unwrap();
            let skip = Tensor::randn(0f32, 1.0, want.dims(), &dev).unwrap();
            let want = (want + &skip).unwrap().relu().unwrap();
            let bv = bias.to_vec1::<f32>().unwrap();
            let sv = skip.flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let epi = Epilogue {
                bias: Some(&bv),
                residual: Some(&sv),
                act: Act::Relu,
            };
            let im2col = Im2colWeight::new(&wt).unwrap();
            let got = conv3x3(&xs, &im2col, stride, &epi).unwrap();
            assert_eq!(got.dims(), want.dims());
            let max_abs = |a: &Tensor, b: &Tensor| -> f32 {
                (a - b)
                    .unwrap()
                    .abs()
                    .unwrap()
                    .flatten_all()
                    .unwrap()
                    .max(0)
                    .unwrap()
                    .to_scalar::<f32>()
                    .unwrap()
            };
            assert!(max_abs(&got, &want) < 1e-4, "stride {stride} {h}x{w}");
            // One output row per band gives the same values.
            let banded = conv3x3_banded(&xs, &im2col, stride, &epi, 1).unwrap();
            assert!(max_abs(&got, &banded) < 1e-5, "banded, stride {stride} {h}x{w}");
        }
    }
}
