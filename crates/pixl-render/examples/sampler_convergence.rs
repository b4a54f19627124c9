//! How fast the render error falls with spp, per sampler: renders `SCENE` (default the bundled
//! demo scene) at 4, 8, …, 256 spp with the Sobol and the independent sampler and prints, for
//! the Diffuse Direct and Combined passes, the RMSE against a high-spp reference of this
//! renderer and the fitted exponent `k` of `RMSE ∝ spp^k` (independent sampling: −0.5).
//!
//! ```text
//! cargo run --release -p pixl-render --example sampler_convergence -- [SCENE.toml [WIDTH [REF_SPP [SEEDS]]]]
//! ```
//!
//! The reference is the mean of two Sobol renders at `REF_SPP` (default 1024) with their own
//! seeds; its own noise is removed from each squared error (the two references differ by
//! `2σ²` per value, their mean carries `σ²/2`). Each spp is rendered with `SEEDS` (default 2)
//! seeds and the squared errors averaged. Also printed: the image means of the reference and
//! of an independent-sampler render at `REF_SPP` (unbiasedness), and the render times.
use pixl_render::integrator::{RenderOptions, Renderer};
use pixl_render::sampler::Sampler;
use std::path::Path;
use std::time::Instant;

const PASSES: [(&str, usize); 2] = [("DiffDir", 3), ("Combined", 3)];

/// The R, G, B values of `pass` (Combined's alpha left out).
fn values(film: &pixl_render::Film, pass: &str, used: usize) -> Vec<f64> {
    let img = film.pass(pass).expect("pass");
    img.data
        .chunks(img.channels)
        .flat_map(|px| px[..used].iter().map(|v| *v as f64))
        .collect()
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let scene_path = args.first().map(String::as_str).unwrap_or("assets/demo/scene.toml");
    let width: Option<u32> = args.get(1).map(|s| s.parse()).transpose()?;
    let ref_spp: u32 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(1024);
    let seeds: u64 = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(2);
    let scene = pixl_render::Scene::load(Path::new(scene_path))?;
    let render =
        |sampler: Sampler, spp: u32, seed: u64| -> Result<(pixl_render::Film, f64), Box<dyn std::error::Error>> {
            let opts = RenderOptions {
                spp,
                width,
                seed,
                ..Default::default()
            };
            let mut r = Renderer::new(&scene, &opts)?;
            r.sampler = sampler;
            let t = Instant::now();
            let film = r.render(&|_, _| {});
            Ok((film, t.elapsed().as_secs_f64()))
        };
    let (ref_a, ta) = render(Sampler::Sobol, ref_spp, 1_000_001)?;
    let (ref_b, tb) = render(Sampler::Sobol, ref_spp, 1_000_002)?;
    let (ind_ref, ti) = render(Sampler::Independent, ref_spp, 1_000_003)?;
    println!(
        "{scene_path}: {}x{}, reference 2 x {ref_spp} spp Sobol ({ta:.1} s, {tb:.1} s), independent {ref_spp} spp ({ti:.1} s), {} threads",
        ref_a.width,
        ref_a.height,
        rayon::current_num_threads()
    );
    // Per pass: reference values and the variance of the reference's own noise.
    let mut refs = Vec::new();
    for (pass, used) in PASSES {
        let (a, b) = (values(&ref_a, pass, used), values(&ref_b, pass, used));
        let r: Vec<f64> = a.iter().zip(&b).map(|(x, y)| 0.5 * (x + y)).collect();
        let ref_var = a.iter().zip(&b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len() as f64 / 4.0;
        let ind = values(&ind_ref, pass, used);
        let ind_mse = ind.iter().zip(&r).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / r.len() as f64;
        // σ of an image mean ≈ RMSE / √values (independent pixels).
        let sigma = (ind_mse / r.len() as f64).sqrt();
        println!(
            "  {pass}: reference mean {:.6}, independent {ref_spp} spp mean {:.6} (diff {:+.6}, σ ≈ {:.6}), reference RMSE ≈ {:.2e}",
            mean(&r),
            mean(&ind),
            mean(&ind) - mean(&r),
            sigma,
            ref_var.sqrt()
        );
        refs.push((r, ref_var));
    }
    let spps = [4u32, 8, 16, 32, 64, 128, 256];
    for sampler in [Sampler::Sobol, Sampler::Independent] {
        let mut rmse = vec![Vec::new(); PASSES.len()];
        let mut means = vec![Vec::new(); PASSES.len()];
        let mut times = Vec::new();
        for &spp in &spps {
            let mut se = vec![0.0; PASSES.len()];
            let mut m = vec![0.0; PASSES.len()];
            let mut t = 0.0;
            for seed in 0..seeds {
                let (film, secs) = render(sampler, spp, seed)?;
                t += secs;
                for (k, (pass, used)) in PASSES.iter().enumerate() {
                    let v = values(&film, pass, *used);
                    let (r, ref_var) = &refs[k];
                    se[k] += v.iter().zip(r).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / v.len() as f64 - ref_var;
                    m[k] += mean(&v) / seeds as f64;
                }
            }
            for k in 0..PASSES.len() {
                rmse[k].push((se[k] / seeds as f64).max(0.0).sqrt());
                means[k].push(m[k]);
            }
            times.push(t / seeds as f64);
        }
        println!("{sampler:?} sampler:");
        for (k, (pass, _)) in PASSES.iter().enumerate() {
            println!(
                "  {pass}: fitted exponent {:.3}; RMSE by spp {}",
                slope(&spps, &rmse[k]),
                spps.iter()
                    .zip(&rmse[k])
                    .map(|(n, e)| format!("{n}: {e:.3e}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            println!(
                "  {pass}: image mean by spp {}",
                means[k].iter().map(|m| format!("{m:.5}")).collect::<Vec<_>>().join(" ")
            );
        }
        println!(
            "  render s by spp {}",
            times.iter().map(|t| format!("{t:.3}")).collect::<Vec<_>>().join(" ")
        );
    }
    Ok(())
}

/// Least-squares slope of ln(err) against ln(spp).
fn slope(ns: &[u32], errs: &[f64]) -> f64 {
    let xs: Vec<f64> = ns.iter().map(|n| (*n as f64).ln()).collect();
    let ys: Vec<f64> = errs.iter().map(|e| e.ln()).collect();
    let (mx, my) = (mean(&xs), mean(&ys));
    let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    sxy / sxx
}
