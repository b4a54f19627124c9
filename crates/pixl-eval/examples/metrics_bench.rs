//! Times the metrics at MIIW mip-2 resolution (1500×1000) with the paper's protocol
//! (2 warm-ups, 5 runs). LPIPS-Alex uses random weights (speed does not depend on the values).
//! `cargo run --release -p pixl-eval --example metrics_bench`
use candle_core::{DType, Device};
use candle_nn::{VarBuilder, VarMap};
use pixl_core::{Image, Rng};
use pixl_eval::{psnr, scale_correct, ssim, time_runs, Lpips, LpipsNet, DEFAULT_RUNS, DEFAULT_WARMUPS};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let (w, h) = (1500, 1000);
    let mut rng = Rng::new(0);
    let a = Image::from_vec(w, h, 3, (0..w * h * 3).map(|_| rng.f32()).collect())?;
    let b = a.map(|v| (0.9 * v + 0.05).min(1.0));
    let t = time_runs(DEFAULT_WARMUPS, DEFAULT_RUNS, || scale_correct(&b, &a).map(|_| ()))?;
    println!("scale_correct {w}x{h}: {}", t.describe());
    let t = time_runs(DEFAULT_WARMUPS, DEFAULT_RUNS, || psnr(&b, &a).map(|_| ()))?;
    println!("psnr {w}x{h}: {}", t.describe());
    let t = time_runs(DEFAULT_WARMUPS, DEFAULT_RUNS, || ssim(&b, &a).map(|_| ()))?;
    println!("ssim {w}x{h}: {}", t.describe());
    // VGG16 at this size needs several GiB of activations; pass `vgg` to time it too.
    let mut nets = vec![LpipsNet::Alex];
    if std::env::args().any(|a| a == "vgg") {
        nets.push(LpipsNet::Vgg);
    }
    for net in nets {
        let map = VarMap::new();
        let lpips = Lpips::new(net, VarBuilder::from_varmap(&map, DType::F32, &Device::Cpu))?;
        let t = time_runs(DEFAULT_WARMUPS, DEFAULT_RUNS, || lpips.distance(&b, &a).map(|_| ()))?;
        println!("lpips-{} {w}x{h}: {}", net.name(), t.describe());
    }
    Ok(())
}
