//! Speed benchmark of the native path tracer (issue 4): a 512×512 render, 16 spp, of a
//! ~500 k-triangle depth-like mesh (a bumpy height field unprojected in front of the camera,
//! as `pixl reconstruct` makes) lit by one area light and a constant environment.
//!
//! `cargo run --release -p pixl-render --example bench_render [-- GRID SPP]` (GRID = vertices
//! per side, default 500 → 498 002 triangles).
use pixl_render::integrator::Renderer;
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
    let dir = tempfile::tempdir()?;
    let mesh_path = dir.path().join("depth_mesh.ply");
    pixl_render::export::ply::write_ply(&mesh_path, &mesh)?;
    let mut scene = Scene::new(Camera::new(512, 512, 50.0));
    scene.base_dir = dir.path().to_owned();
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
    });
    scene.world = Some(World {
        color: Color::Rgb([0.1, 0.12, 0.15]),
        strength: 1.0,
        image: None,
        rotation_deg: 0.0,
    });
    let opts = RenderOptions {
        spp,
        ..Default::default()
    };
    let t0 = Instant::now();
    let r = Renderer::new(&scene, &opts)?;
    let t_build = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let film = r.render(&|_, _| {});
    let t_render = t1.elapsed().as_secs_f64();
    let comb = film.pass("Combined").ok_or("no Combined")?;
    let mean: f64 = comb.data.iter().map(|v| *v as f64).sum::<f64>() / comb.data.len() as f64;
    println!(
        "{} triangles, {} BVH nodes, {}x{} @ {} spp, {} threads: load+BVH {:.2} s, render {:.2} s (mean Combined {:.4})",
        r.geom.tris.len(),
        r.geom.bvh.num_nodes(),
        film.width,
        film.height,
        spp,
        rayon::current_num_threads(),
        t_build,
        t_render,
        mean
    );
    Ok(())
}
