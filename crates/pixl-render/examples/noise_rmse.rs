//! Noise of a render against a reference, pass by pass (the noise benchmark,
//! `scripts/bench-noise-vs-cycles.sh`).
//!
//! ```text
//! noise_rmse render SCENE.toml SPP OUT.exr [SEED [REPEAT]]  # prints "RENDER_S <median seconds>"
//! noise_rmse rmse REF.exr TEST.exr                  # "RMSE <pass> <rmse> <test mean> <ref mean> <under half>"
//! ```
//!
//! `render` times the path tracing alone (after the mesh load and BVH build, as Cycles'
//! `path_trace` phase in `run_cycles.py`). `rmse` reads two multilayer EXRs of Cycles pass names
//! (ours or Cycles'), and for every RGB pass present in both (not Normal) prints the
//! root-mean-square difference over pixels and channels, both image means, and the share of the
//! pixels lit in the reference (sum of R, G, B) that get less than half of it in the test.
use pixl_core::exrio::read_exr_channels;
use pixl_core::passes;
use std::path::Path;

fn render(scene: &str, spp: &str, out: &str, rest: &[String]) -> Result<(), Box<dyn std::error::Error>> {
    let scene = pixl_render::Scene::load(Path::new(scene))?;
    let opts = pixl_render::RenderOptions {
        spp: spp.parse()?,
        seed: rest.first().map(|s| s.parse()).transpose()?.unwrap_or(0),
        ..Default::default()
    };
    let repeat: usize = rest.get(1).map(|s| s.parse()).transpose()?.unwrap_or(1).max(1);
    let r = pixl_render::integrator::Renderer::new(&scene, &opts)?;
    // The same image each time (deterministic per seed); the median time is printed.
    let mut times = Vec::new();
    let mut film = None;
    for _ in 0..repeat {
        let t = std::time::Instant::now();
        film = Some(r.render(&|_, _| {}));
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    film.ok_or("no render")?.write_exr(Path::new(out))?;
    println!("RENDER_S {:.4}", times[times.len() / 2]);
    Ok(())
}

fn rmse(reference: &str, test: &str) -> Result<(), Box<dyn std::error::Error>> {
    let a = read_exr_channels(Path::new(reference))?;
    let b = read_exr_channels(Path::new(test))?;
    if (a.width, a.height) != (b.width, b.height) {
        return Err(format!("sizes differ: {}x{} vs {}x{}", a.width, a.height, b.width, b.height).into());
    }
    for pass in passes::ALL {
        if pass.channels.len() < 3 || *pass == passes::NORMAL {
            continue;
        }
        let (mut sr, mut st, mut se, mut n) = (0f64, 0f64, 0f64, 0usize);
        // Per pixel, the sum over R, G, B of reference and test.
        let (mut pr, mut pt) = (vec![0f64; a.width * a.height], vec![0f64; a.width * a.height]);
        for ch in ["R", "G", "B"] {
            let (Some(x), Some(y)) = (a.pass_channel(pass, ch), b.pass_channel(pass, ch)) else {
                continue;
            };
            for (i, (r, t)) in x.iter().zip(y).enumerate() {
                let (r, t) = (*r as f64, *t as f64);
                sr += r;
                st += t;
                se += (t - r) * (t - r);
                n += 1;
                pr[i] += r;
                pt[i] += t;
            }
        }
        if n == 0 {
            continue;
        }
        let n = n as f64;
        // Share of the pixels lit in the reference that get less than half of it.
        let lit = pr.iter().filter(|r| **r > 1e-6).count();
        let dark = pr
            .iter()
            .zip(&pt)
            .filter(|(r, t)| **r > 1e-6 && **t < 0.5 * **r)
            .count();
        let half = if lit > 0 { dark as f64 / lit as f64 } else { 0.0 };
        println!(
            "RMSE {} {:.6e} {:.6} {:.6} {:.5}",
            pass.short,
            (se / n).sqrt(),
            st / n,
            sr / n,
            half
        );
    }
    Ok(())
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.as_slice() {
        [cmd, scene, spp, out, rest @ ..] if cmd == "render" && rest.len() <= 2 => render(scene, spp, out, rest),
        [cmd, reference, test] if cmd == "rmse" => rmse(reference, test),
        _ => Err(
            "usage: noise_rmse render SCENE.toml SPP OUT.exr [SEED [REPEAT]] | noise_rmse rmse REF.exr TEST.exr".into(),
        ),
    }
}
