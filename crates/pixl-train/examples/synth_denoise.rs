//! How close the photo style's images come to a high-spp reference, with and without the guided
//! median (`pixl_render::denoise`), in the shown (tone-mapped sRGB) space the network sees.
//!
//! `cargo run --release -p pixl-train --example synth_denoise -- [SCENES] [SIZE] [SPP] [REF_SPP]`
//! (defaults 6 128 64 1024): per scene and lighting 0..3, PSNR of the shown render at SPP
//! (radius 0 = unfiltered, 1, 2) against the unfiltered render at REF_SPP; prints the means.
use pixl_core::Image;
use pixl_render::{render, RenderOptions};
use pixl_train::synth::{photo, SynthOptions};

fn psnr(a: &Image, b: &Image) -> f64 {
    let mse = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| ((x - y) as f64).powi(2))
        .sum::<f64>()
        / a.data.len() as f64;
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let arg = |i: usize, d: u32| std::env::args().nth(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let (scenes, size, spp, ref_spp) = (arg(1, 6), arg(2, 128), arg(3, 64), arg(4, 1024));
    let opts = SynthOptions::default();
    let dir = tempfile::tempdir()?;
    let mut made = pixl_core::output::Provisional::new();
    std::fs::create_dir_all(dir.path().join("textures"))?;
    let radii = [0usize, 1, 2];
    let mut sums = [0.0f64; 3];
    let mut n = 0;
    for i in 0..scenes as usize {
        let (base, layout) = photo::build(opts.seed, 0x9407_05CE, i, size, dir.path(), &mut made)?;
        for k in 0..3 {
            let (lights, world, _) = photo::draw_lighting(opts.seed, 0x9407_0116, i, k, &layout);
            let mut scene = base.clone();
            scene.lights = lights;
            scene.world = Some(world);
            let ro = |spp: u32, seed: u64| RenderOptions {
                spp,
                width: Some(size),
                height: Some(size),
                seed,
                max_bounces: opts.max_bounces,
            };
            let reference = render(&scene, &ro(ref_spp, 7), &|_, _| {})?;
            let shown_ref =
                pixl_core::image::tonemap_camera(&pixl_render::denoise::guided_median(&reference, 0).ok_or("passes")?);
            let noisy = render(&scene, &ro(spp, 1), &|_, _| {})?;
            let mut line = format!("scene {i} light {k}:");
            for (r, sum) in radii.iter().zip(&mut sums) {
                let shown =
                    pixl_core::image::tonemap_camera(&pixl_render::denoise::guided_median(&noisy, *r).ok_or("passes")?);
                let p = psnr(&shown, &shown_ref);
                *sum += p;
                line += &format!(" r{r} {p:.2} dB");
            }
            println!("{line}");
            n += 1;
        }
    }
    for (r, sum) in radii.iter().zip(&sums) {
        println!("mean PSNR vs {ref_spp} spp, radius {r}: {:.2} dB", sum / n as f64);
    }
    made.keep();
    Ok(())
}
