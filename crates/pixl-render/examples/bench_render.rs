//! Speed benchmark of the native path tracer: a 512×512 render, 16 spp, of a
//! ~500 k-triangle depth-like mesh (a bumpy height field unprojected in front of the camera,
//! as `pixl reconstruct` makes) lit by one area light and a constant environment.
//!
//! `cargo run --release -p pixl-render --example bench_render [-- GRID SPP [render-only [REPEAT]]]`
//! (GRID = vertices per side, default 500 → 498 002 triangles; REPEAT renders the image that
//! many times and also prints the minimum and median wall time — the VM's host adds ±10 % from
//! run to run; `PIXL_BENCH_WIDTH=N` renders N×N pixels instead; `render-only` skips the ray
//! timings, e.g. for profiling; `PIXL_BENCH_SAVE=DIR` also writes the scene to `DIR/scene.toml`
//! with its mesh, for timing `pixl render` end to end; `PIXL_BENCH_SAMPLER=independent` renders
//! with the independent sampler instead of the default Sobol one).
//!
//! After the render it also times ray casting alone on the main thread (a load-independent
//! figure: rays per second per thread) for three ray kinds made from the camera view: primary
//! (closest hit), diffuse bounce from the primary hits (cosine about the normal, closest hit) and
//! shadow rays from the primary hits to a light sample (any hit).
use pixl_core::Rng;
use pixl_render::bvh::Ray;
use pixl_render::integrator::Renderer;
use pixl_render::light::ShadingPoint;
use pixl_render::math::Frame;
use pixl_render::sampler::Sampler;
use pixl_render::sampling::cosine_hemisphere;
use pixl_render::scene::{AreaShape, Camera, Color, Light, Material, Object, Scene, Shape, Transform, World};
use pixl_render::{Mesh, RenderOptions};
use std::time::Instant;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(500);
    let spp: u32 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(16);
    // A depth map z(u, v) = 4 + bumps, unprojected through a 50° pinhole at the origin.
    let tan = (25f32).to_radians().tan();
    let mut mesh = Mesh::default();
    for j in 0..n {
        for i in 0..n {
            let (u, v) = (i as f32 / (n - 1) as f32, j as f32 / (n - 1) as f32);
            let depth = 4.0 + 0.3 * (9.0 * u).sin() * (7.0 * v).cos() + 0.05 * (40.0 * u + 23.0 * v).sin() + 1.5 * v;
            let (x, y) = ((2.0 * u - 1.0) * tan * depth, (1.0 - 2.0 * v) * tan * depth);
            mesh.positions.push([x, y, -depth]);
            mesh.uvs.push([u, v]);
        }
    }
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = (j * n + i) as u32;
            let (b, c, d) = (a + 1, a + n as u32, a + n as u32 + 1);
            mesh.indices.push([a, c, b]);
            mesh.indices.push([b, c, d]);
        }
    }
    // `PIXL_BENCH_SAVE=DIR` keeps the mesh and writes the scene as `DIR/scene.toml` (to time
    // `pixl render DIR/scene.toml --spp 16` end to end); otherwise both live in a temp folder.
    let tmp = tempfile::tempdir()?;
    let save = std::env::var_os("PIXL_BENCH_SAVE").map(std::path::PathBuf::from);
    let dir = match &save {
        Some(d) => {
            std::fs::create_dir_all(d)?;
            d.clone()
        }
        None => tmp.path().to_owned(),
    };
    let mesh_path = dir.join("depth_mesh.ply");
    pixl_render::export::ply::write_ply(&mesh_path, &mesh)?;
    let mut scene = Scene::new(Camera::new(512, 512, 50.0));
    scene.base_dir = dir.clone();
    scene.objects.push(Object {
        name: "depth".into(),
        shape: Shape::Mesh {
            path: "depth_mesh.ply".into(),
        },
        transform: Transform::default(),
        material: Material {
            base_color: Color::Rgb([0.6, 0.55, 0.5]),
            roughness: 0.6,
            ..Default::default()
        },
    });
    scene.lights.push(Light::Area {
        name: "key".into(),
        position: [1.5, 2.5, -1.0],
        direction: None,
        look_at: Some([0.0, 0.0, -5.0]),
        shape: AreaShape::Square,
        size: 1.0,
        size_y: None,
        power: 400.0,
        color: Color::Blackbody { kelvin: 4500.0 },
        visible_to_camera: false,
    });
    scene.world = Some(World {
        color: Color::Rgb([0.1, 0.12, 0.15]),
        strength: 1.0,
        image: None,
        rotation_deg: 0.0,
    });
    if let Some(d) = &save {
        scene.save(&d.join("scene.toml"))?;
    }
    // `PIXL_BENCH_WIDTH=N` renders N×N instead (same scene and camera), e.g. for a quick
    // instruction count under callgrind.
    let width = std::env::var("PIXL_BENCH_WIDTH").ok().and_then(|v| v.parse().ok());
    let opts = RenderOptions {
        spp,
        width,
        height: width,
        ..Default::default()
    };
    let (t0, c0) = (Instant::now(), process_cpu_s());
    let mut r = Renderer::new(&scene, &opts)?;
    let (t_build, c_build) = (t0.elapsed().as_secs_f64(), process_cpu_s() - c0);
    r.sampler = match std::env::var("PIXL_BENCH_SAMPLER").as_deref() {
        Ok("independent") => Sampler::Independent,
        Ok("sobol") | Err(_) => Sampler::Sobol,
        Ok(other) => return Err(format!("PIXL_BENCH_SAMPLER={other}: sobol or independent").into()),
    };
    let repeat: usize = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(1).max(1);
    let mut walls = Vec::new();
    let (mut film, mut t_render, mut c_render) = (None, 0.0, 0.0);
    for _ in 0..repeat {
        let (t1, c1) = (Instant::now(), process_cpu_s());
        film = Some(r.render(&|_, _| {}));
        (t_render, c_render) = (t1.elapsed().as_secs_f64(), process_cpu_s() - c1);
        walls.push(t_render);
    }
    let film = film.ok_or("no render")?;
    let comb = film.pass("Combined").ok_or("no Combined")?;
    let mean: f64 = comb.data.iter().map(|v| *v as f64).sum::<f64>() / comb.data.len() as f64;
    // FNV-1a over the bits of every Combined value: equal checksums mean a bit-identical image.
    let bits = comb.data.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, v| {
        (h ^ v.to_bits() as u64).wrapping_mul(0x100_0000_01b3)
    });
    println!(
        "{} triangles, {} BVH nodes, {} leaf packets, {}x{} @ {} spp, {:?} sampler, {} threads: load+BVH {:.2} s (CPU {:.2} s), render {:.2} s (CPU {:.2} s) (mean Combined {:.4}, bits {:016x})",
        r.geom.tris.len(),
        r.geom.bvh.num_nodes(),
        r.geom.bvh.num_packets(),
        film.width,
        film.height,
        spp,
        r.sampler,
        rayon::current_num_threads(),
        t_build,
        c_build,
        t_render,
        c_render,
        mean,
        bits
    );
    if repeat > 1 {
        walls.sort_by(f64::total_cmp);
        println!(
            "  {} renders: wall min {:.2} s, median {:.2} s, max {:.2} s (sorted: {})",
            repeat,
            walls[0],
            walls[repeat / 2],
            walls[repeat - 1],
            walls.iter().map(|w| format!("{w:.2}")).collect::<Vec<_>>().join(" ")
        );
    }
    if args.get(3).map(String::as_str) != Some("render-only") {
        ray_throughput(&r);
    }
    Ok(())
}

/// Times closest-hit and any-hit queries alone on this thread and prints Mrays/s (wall clock
/// and per CPU-second of this thread, the figure that does not depend on other load).
fn ray_throughput(r: &Renderer) {
    let g = &r.geom;
    let mut rng = Rng::new(7);
    let mut primary = Vec::new();
    for y in 0..r.height {
        for x in 0..r.width {
            primary.push((r.camera.ray(x as f32 + rng.f32(), y as f32 + rng.f32()), f32::INFINITY));
        }
    }
    let time = |name: &str, rays: &[(Ray, f32)], f: &dyn Fn(&Ray, f32) -> bool| {
        // Best of three passes (the machine may be shared).
        let (mut wall, mut cpu, mut hits) = (f64::INFINITY, f64::INFINITY, 0);
        for _ in 0..3 {
            let (t, c) = (Instant::now(), thread_cpu_s());
            hits = rays.iter().filter(|(ray, tmax)| f(ray, *tmax)).count();
            wall = wall.min(t.elapsed().as_secs_f64());
            cpu = cpu.min(thread_cpu_s() - c);
        }
        println!(
            "  {name:<7} {:>7} rays, {:5.1}% hit: {:.2} Mrays/s wall, {:.2} Mrays per CPU-second (best of 3)",
            rays.len(),
            100.0 * hits as f64 / rays.len().max(1) as f64,
            rays.len() as f64 / wall / 1e6,
            rays.len() as f64 / cpu / 1e6
        );
    };
    let closest = |ray: &Ray, tmax: f32| g.intersect(ray, 0.0, tmax).is_some();
    time("primary", &primary, &closest);
    // The render's camera rays: 16 jittered samples per pixel, in pixel order (64 rows), one
    // by one and as one packet per pixel.
    let mut pixel_rays = Vec::new();
    for y in 0..64.min(r.height) {
        for x in 0..r.width {
            for _ in 0..16 {
                pixel_rays.push(r.camera.ray(x as f32 + rng.f32(), y as f32 + rng.f32()));
            }
        }
    }
    let pix: Vec<(Ray, f32)> = pixel_rays.iter().map(|r| (*r, f32::INFINITY)).collect();
    // From each camera hit, a cosine bounce and a light-sample shadow ray (16 per pixel).
    let (mut pix_bounce, mut pix_shadow) = (Vec::new(), Vec::new());
    for (ray, _) in &pix {
        let h = g.intersect(ray, 0.0, f32::INFINITY);
        let Some(h) = h else { continue };
        let n = if h.ng.dot(ray.d) < 0.0 { h.ng } else { -h.ng };
        let o = h.p + n * 1e-4 * (1.0 + h.p.x.abs().max(h.p.y.abs()).max(h.p.z.abs()));
        let f = Frame::new(n);
        pix_bounce.push((
            Ray::new(o, f.to_world(cosine_hemisphere(rng.f32(), rng.f32()))),
            f32::INFINITY,
        ));
        let pick = r.lights.pick_at(ShadingPoint {
            p: h.p,
            n,
            two_sided: false,
            solid_angle: false,
        });
        let ls = r.lights.sample(g, &pick, rng.f32(), rng.f32(), rng.f32());
        let (d, tmax) = match ls {
            Some(ls) if ls.dist.is_finite() => (ls.wi, ls.dist * (1.0 - 1e-3)),
            Some(ls) => (ls.wi, f32::INFINITY),
            None => (n, f32::INFINITY),
        };
        pix_shadow.push((Ray::new(o, d), tmax));
    }
    let packets = |name: &str, rays: &[(Ray, f32)], any: bool| {
        let (mut wall, mut cpu, mut hits) = (f64::INFINITY, f64::INFINITY, 0);
        let r16: Vec<Ray> = rays.iter().map(|p| p.0).collect();
        let t16: Vec<f32> = rays.iter().map(|p| p.1).collect();
        for _ in 0..3 {
            let (t, c) = (Instant::now(), thread_cpu_s());
            let mut out = [None; 16];
            let mut occ = [false; 16];
            hits = 0;
            for (rays, tmax) in r16.chunks(16).zip(t16.chunks(16)) {
                if any {
                    g.bvh.occluded_packet(rays, 0.0, tmax, &mut occ);
                    hits += occ.iter().filter(|h| **h).count();
                } else {
                    g.intersect_packet(rays, 0.0, tmax, &mut out);
                    hits += out.iter().filter(|h| h.is_some()).count();
                }
            }
            wall = wall.min(t.elapsed().as_secs_f64());
            cpu = cpu.min(thread_cpu_s() - c);
        }
        println!(
            "  {name:<7} {:>7} rays, {:5.1}% hit: {:.2} Mrays/s wall, {:.2} Mrays per CPU-second (best of 3; packets of 16)",
            rays.len(),
            100.0 * hits as f64 / rays.len().max(1) as f64,
            rays.len() as f64 / wall / 1e6,
            rays.len() as f64 / cpu / 1e6
        );
    };
    time("pix16", &pix, &closest);
    packets("pix16p", &pix, false);
    time("bnc16", &pix_bounce, &closest);
    packets("bnc16p", &pix_bounce, false);
    time("shd16", &pix_shadow, &|ray, tmax| g.occluded(ray, 0.0, tmax));
    packets("shd16p", &pix_shadow, true);
    let mut bounce = Vec::new();
    let mut shadow = Vec::new();
    for (ray, _) in &primary {
        let Some(h) = g.intersect(ray, 0.0, f32::INFINITY) else {
            continue;
        };
        let n = if h.ng.dot(ray.d) < 0.0 { h.ng } else { -h.ng };
        let o = h.p + n * 1e-4 * (1.0 + h.p.x.abs().max(h.p.y.abs()).max(h.p.z.abs()));
        let f = Frame::new(n);
        bounce.push((
            Ray::new(o, f.to_world(cosine_hemisphere(rng.f32(), rng.f32()))),
            f32::INFINITY,
        ));
        let pick = r.lights.pick_at(ShadingPoint {
            p: h.p,
            n,
            two_sided: false,
            solid_angle: false,
        });
        if let Some(ls) = r.lights.sample(g, &pick, rng.f32(), rng.f32(), rng.f32()) {
            let tmax = if ls.dist.is_finite() {
                ls.dist * (1.0 - 1e-3)
            } else {
                f32::INFINITY
            };
            shadow.push((Ray::new(o, ls.wi), tmax));
        }
    }
    time("bounce", &bounce, &closest);
    time("shadow", &shadow, &|ray, tmax| g.occluded(ray, 0.0, tmax));
}

/// CPU seconds this thread has run (Linux `schedstat`; 0 elsewhere).
fn thread_cpu_s() -> f64 {
    schedstat_s("/proc/thread-self/schedstat")
}

/// CPU seconds all threads of this process have run (Linux `schedstat`; 0 elsewhere).
fn process_cpu_s() -> f64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    dir.flatten()
        .map(|e| schedstat_s(&e.path().join("schedstat").to_string_lossy()))
        .sum()
}

fn schedstat_s(path: &str) -> f64 {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse::<u64>().ok()))
        .map_or(0.0, |ns| ns as f64 * 1e-9)
}
