//! The 3×3 convolution kernel ([`pixl_nn::conv3x3`]) on the DPT head's shapes: median wall time
//! and GFLOP/s per shape, by tile size (`conv3x3_tiled`), by Winograd block size
//! (`pixl_nn::winograd`, stride 1; more sizes in `WINOGRAD_BLOCKS=16,64,...`, and its rounding
//! against the im2col path), against candle's own conv2d.
//!
//! `cargo run --release -p pixl-nn --example bench_conv3x3 [TILE...]` (threads:
//! `RAYON_NUM_THREADS`; `scripts/bench/conv_torch.py` times the same shapes in PyTorch).
use candle_core::{Device, Module, Result, Tensor};
use pixl_nn::conv3x3::{conv3x3_tiled, tile_pixels, Epilogue, Im2colWeight};
use pixl_nn::fused::Act;
use pixl_nn::winograd::{block_tiles, conv3x3_winograd, WinogradWeight};
use std::time::Instant;

fn median_ms(mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    f()?;
    let mut t = Vec::new();
    for _ in 0..5 {
        let s = Instant::now();
        f()?;
        t.push(s.elapsed().as_secs_f64() * 1e3);
    }
    t.sort_by(f64::total_cmp);
    Ok(t[t.len() / 2])
}

fn main() -> Result<()> {
    let tiles: Vec<usize> = std::env::args().skip(1).filter_map(|s| s.parse().ok()).collect();
    let dev = Device::Cpu;
    // (name, cin, cout, side, stride): small's output convs and refinenet1, paper's refinenet1.
    let shapes = [
        ("small output_conv2", 64, 32, 512, 1),
        ("small output_conv1", 128, 64, 256, 1),
        ("small refinenet1 rcu", 128, 128, 256, 1),
        ("paper refinenet1 rcu", 256, 256, 256, 1),
        ("paper resize3 s2", 1024, 1024, 32, 2),
        ("128 at 64x64", 128, 128, 64, 1),
        ("256 at 32x32", 256, 256, 32, 1),
        ("256 at 16x16", 256, 256, 16, 1),
        ("9 -> 32 at 256x256", 9, 32, 256, 1),
    ];
    for (name, cin, cout, side, stride) in shapes {
        let xs = Tensor::randn(0f32, 1.0, (1, cin, side, side), &dev)?;
        let w = Tensor::randn(0f32, 0.05, (cout, cin, 3, 3), &dev)?;
        let im2col = Im2colWeight::new(&w)?;
        let bias = vec![0.1f32; cout];
        let epi = Epilogue {
            bias: Some(&bias),
            residual: None,
            act: Act::Relu,
        };
        let out_side = (side - 1) / stride + 1;
        let gflop = 2.0 * (cin * 9 * cout * out_side * out_side) as f64 / 1e9;
        let mut sizes = vec![tile_pixels(cin)];
        sizes.extend(&tiles);
        for tile in sizes {
            let ms = median_ms(|| conv3x3_tiled(&xs, &im2col, stride, false, &epi, tile).map(|_| ()))?;
            println!(
                "{name:<22} tile {tile:>5}: {ms:>8.1} ms  {:>6.1} GFLOP/s",
                gflop / ms * 1e3
            );
        }
        if stride == 1 {
            let t0 = Instant::now();
            let wino = WinogradWeight::new(&w)?;
            println!(
                "{name:<22} winograd weight transform: {:.2} ms",
                t0.elapsed().as_secs_f64() * 1e3
            );
            let mut blocks = vec![block_tiles(cin, cout)];
            blocks.extend(
                std::env::var("WINOGRAD_BLOCKS")
                    .unwrap_or_default()
                    .split(',')
                    .filter_map(|s| s.parse::<usize>().ok()),
            );
            // Rounding against the im2col path (one f32 GEMM over 9·C terms per output).
            let a = conv3x3_winograd(&xs, &wino, false, &epi, block_tiles(cin, cout))?;
            let b = conv3x3_tiled(&xs, &im2col, 1, false, &epi, tile_pixels(cin))?;
            let diff = (a - &b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            let scale = b.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            println!(
                "{name:<22} winograd vs im2col: max |diff| {diff:.2e}, {:.2e} of max |output|",
                diff / scale
            );
            for blk in blocks {
                let ms = median_ms(|| conv3x3_winograd(&xs, &wino, false, &epi, blk).map(|_| ()))?;
                println!(
                    "{name:<22} winograd {blk:>4}: {ms:>6.1} ms  {:>6.1} GFLOP/s (direct-equivalent)",
                    gflop / ms * 1e3
                );
            }
        }
        let cfg = candle_nn::Conv2dConfig {
            padding: 1,
            stride,
            ..Default::default()
        };
        let conv = candle_nn::Conv2d::new(w.clone(), None, cfg);
        let ms = median_ms(|| conv.forward(&xs).map(|_| ()))?;
        println!("{name:<22} candle    : {ms:>8.1} ms  {:>6.1} GFLOP/s", gflop / ms * 1e3);
    }
    Ok(())
}
