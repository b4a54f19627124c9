//! How far the 8-bit linear layers ([`pixl_model::PixlRelight::quantize_int8`]) move the
//! network's output from f32: the same weights and inputs, forward in f32, then quantized.
//!
//! `cargo run --release -p pixl-model --example int8_error -- WEIGHTS.safetensors [SIDE] [PERTURB]`
//!
//! `PERTURB` (default 0) adds seeded Gaussian noise to every tensor, `PERTURB` times its own
//! std (or 1/√fan-in for constant weights, 0.1 for constant vectors), as
//! `scripts/bench/pixl_torch.py perturb` does, so that fresh weights (`pixl model init`, whose
//! zero-initialised modulation returns the source unchanged) give an output that depends on
//! every layer. Inputs: uniform random source and C_T, `SIDE²` (default 512).
//!
//! Prints the layers quantized, the PSNR of the 8-bit output against the f32 one, the largest
//! difference, and the change the f32 network makes to the source (RMS), for scale.
use candle_core::{DType, Device, Result, Tensor};
use candle_nn::VarBuilder;
use pixl_core::Rng;
use std::collections::HashMap;

fn perturbed(tensors: HashMap<String, Tensor>, scale: f32) -> Result<HashMap<String, Tensor>> {
    if scale == 0.0 {
        return Ok(tensors);
    }
    let mut names: Vec<String> = tensors.keys().cloned().collect();
    names.sort();
    let mut rng = Rng::new(0);
    let mut out = HashMap::new();
    for name in names {
        let t = tensors[&name].to_dtype(DType::F32)?;
        let v = t.flatten_all()?.to_vec1::<f32>()?;
        let n = v.len() as f64;
        let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
        let std = if v.len() > 1 {
            (v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
        } else {
            0.0
        };
        let reference = if std > 0.0 {
            std as f32
        } else if t.rank() >= 2 {
            1.0 / ((v.len() / t.dim(0)?) as f32).sqrt()
        } else {
            0.1
        };
        let noisy: Vec<f32> = v.iter().map(|&x| x + scale * reference * rng.normal()).collect();
        out.insert(name, Tensor::from_vec(noisy, t.shape(), t.device())?);
    }
    Ok(out)
}

fn main() -> std::result::Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(path) = args.first() else {
        return Err("usage: int8_error WEIGHTS.safetensors [SIDE] [PERTURB]".into());
    };
    let side: usize = args.get(1).map_or(Ok(512), |s| s.parse())?;
    let scale: f32 = args.get(2).map_or(Ok(0.0), |s| s.parse())?;
    let dev = Device::Cpu;
    let (cfg, _) = pixl_model::load(std::path::Path::new(path), &dev, DType::F32)?;
    let tensors = perturbed(candle_core::safetensors::load(path, &dev)?, scale)?;
    let mut model = pixl_model::PixlRelight::new(&cfg, VarBuilder::from_tensors(tensors, DType::F32, &dev))?;
    let mut rng = Rng::new(1);
    let mut rand = |c: usize| -> Result<Tensor> {
        let v: Vec<f32> = (0..c * side * side).map(|_| rng.f32()).collect();
        Tensor::from_vec(v, (1, c, side, side), &dev)
    };
    let (src, ct) = (rand(3)?, rand(9)?);
    let f32_out = model.forward(&src, &ct)?;
    let layers = model.quantize_int8()?;
    if layers == 0 {
        println!(
            "no layer quantized (this CPU has no AVX-512 VNNI, or every layer is narrower than {})",
            pixl_nn::linear::INT8_MIN_INPUTS
        );
        return Ok(());
    }
    let int8_out = model.forward(&src, &ct)?;
    let mse = (&int8_out - &f32_out)?.sqr()?.mean_all()?.to_scalar::<f32>()? as f64;
    let max = (&int8_out - &f32_out)?.abs()?.max_all()?.to_scalar::<f32>()?;
    let change = (&f32_out - &src)?.sqr()?.mean_all()?.sqrt()?.to_scalar::<f32>()?;
    println!(
        "{path} ({side}², perturbed {scale}): {layers} linear layers in 8 bits; PSNR against f32 {:.1} dB, max |diff| {max:.4}; RMS change f32 output − source {change:.4}",
        10.0 * (1.0 / mse.max(1e-20)).log10()
    );
    Ok(())
}
