//! Native renderer vs Blender Cycles on one scene: renders `SCENE` natively at `SPP`, writes
//! `NATIVE.exr`, and compares it pass by pass with `CYCLES.exr` (rendered by the script of
//! `pixl blender export`): per pass, the image means (over pixels and R, G, B), their relative
//! error `|native − cycles| / |cycles|`, and the mean absolute per-pixel difference.
//!
//! ```text
//! pixl blender export crates/pixl-render/examples/compare_scene.toml -o /tmp/cmp/scene.py
//! python /tmp/cmp/scene.py --out /tmp/cmp/cycles.exr --spp 64
//! cargo run --release -p pixl-render --example compare_cycles -- \
//!     crates/pixl-render/examples/compare_scene.toml 64 /tmp/cmp/native.exr /tmp/cmp/cycles.exr
//! ```
//!
//! An optional fifth argument sets the native `max_bounces` (default 8, as the exported script's
//! `--max-bounces`).
use pixl_core::exrio::read_exr_channels;
use pixl_core::passes;
use std::path::Path;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (scene, spp, native, cycles, bounces) = match args.as_slice() {
        [a, b, c, d] => (a, b, c, d, None),
        [a, b, c, d, e] => (a, b, c, d, Some(e.parse::<u32>()?)),
        _ => return Err("usage: compare_cycles SCENE.toml SPP NATIVE.exr CYCLES.exr [MAX_BOUNCES]".into()),
    };
    let scene = pixl_render::Scene::load(Path::new(scene))?;
    let mut opts = pixl_render::integrator::RenderOptions {
        spp: spp.parse()?,
        ..Default::default()
    };
    if let Some(b) = bounces {
        opts.max_bounces = b;
    }
    let t = std::time::Instant::now();
    let film = pixl_render::integrator::render(&scene, &opts, &|_, _| {})?;
    let secs = t.elapsed().as_secs_f64();
    film.write_exr(Path::new(native))?;
    println!("native render: {secs:.2} s ({} threads)", rayon::current_num_threads());
    let a = read_exr_channels(Path::new(native))?;
    let b = read_exr_channels(Path::new(cycles))?;
    if (a.width, a.height) != (b.width, b.height) {
        return Err(format!("sizes differ: {}x{} vs {}x{}", a.width, a.height, b.width, b.height).into());
    }
    println!("| pass | native mean | Cycles mean | rel. error of means | mean abs. diff |");
    println!("|---|---|---|---|---|");
    for pass in passes::ALL {
        if pass.channels.len() < 3 || *pass == passes::NORMAL {
            continue;
        }
        let (mut sa, mut sb, mut sd, mut n) = (0f64, 0f64, 0f64, 0usize);
        for ch in ["R", "G", "B"] {
            let (Some(x), Some(y)) = (a.pass_channel(pass, ch), b.pass_channel(pass, ch)) else {
                continue;
            };
            for (p, q) in x.iter().zip(y) {
                sa += *p as f64;
                sb += *q as f64;
                sd += (*p as f64 - *q as f64).abs();
                n += 1;
            }
        }
        if n == 0 {
            println!("| {} | – | – | missing | – |", pass.short);
            continue;
        }
        let (ma, mb, mad) = (sa / n as f64, sb / n as f64, sd / n as f64);
        let rel = if mb.abs() > 1e-6 {
            format!("{:.1} %", 100.0 * (ma - mb).abs() / mb.abs())
        } else {
            "(both ≈ 0)".into()
        };
        println!("| {} | {ma:.5} | {mb:.5} | {rel} | {mad:.5} |", pass.short);
    }
    Ok(())
}
