//! Known-answer scenes for the path tracer: each expected value is derived by hand in the
//! comment above its check and computed independently (f64) in the test.
#![allow(clippy::needless_range_loop)]
use pixl_render::scene::{Camera, Color, Light, Material, Object, Scene, Shape, Transform, World};
use pixl_render::{render, Film, RenderOptions};
use std::f64::consts::PI;

fn no_progress(_: usize, _: usize) {}

fn opts(spp: u32, bounces: u32) -> RenderOptions {
    RenderOptions {
        spp,
        max_bounces: bounces,
        seed: 7,
        ..Default::default()
    }
}

/// A 20 m × 20 m Lambertian floor (y = 0, normal +Y) of albedo `rho`, seen from straight above.
fn floor_scene(rho: [f32; 3], w: u32) -> Scene {
    let mut cam = Camera::new(w, w, 40.0);
    cam.position = [0.0, 5.0, 0.0];
    cam.look_at = Some([0.0, 0.0, 0.0]);
    cam.up = [0.0, 0.0, -1.0];
    let mut s = Scene::new(cam);
    s.objects.push(Object {
        name: "floor".into(),
        shape: Shape::Quad { size: [20.0, 20.0] },
        transform: Transform {
            rotate_deg: [-90.0, 0.0, 0.0],
            ..Default::default()
        },
        material: Material::diffuse(rho),
    });
    s
}

/// The floor point seen through image point (px, py) of `floor_scene`'s camera (f64).
fn floor_point(px: f64, py: f64, w: u32) -> (f64, f64) {
    let f = 0.5 * w as f64 / (20f64.to_radians()).tan();
    let (cx, cy) = (0.5 * w as f64, 0.5 * w as f64);
    // Camera frame: right = +X, up = −Z, forward = −Y, at height 5.
    let x = (px - cx) / f;
    let y = (cy - py) / f;
    (5.0 * x, -5.0 * y)
}

fn px(img: &pixl_core::Image, x: usize, y: usize) -> [f32; 3] {
    [img.get(x, y, 0), img.get(x, y, 1), img.get(x, y, 2)]
}

#[test]
fn lambertian_plane_under_point_light_matches_inverse_square_cosine() {
    let w = 24;
    let rho = [0.5, 0.4, 0.3];
    let mut s = floor_scene(rho, w);
    let (lx, ly, lz, power) = (0.7f64, 2.0f64, -0.4f64, 150.0f64);
    s.lights.push(Light::Point {
        name: String::new(),
        position: [lx as f32, ly as f32, lz as f32],
        power: power as f32,
        radius: 0.0,
        color: Color::Rgb([1.0, 1.0, 1.0]),
        visible_to_camera: false,
    });
    let film = render(&s, &opts(64, 4), &no_progress).unwrap();
    let dir = film.pass("DiffDir").unwrap();
    let ind = film.pass("DiffInd").unwrap();
    let col = film.pass("DiffCol").unwrap();
    for y in 0..w as usize {
        for x in 0..w as usize {
            // E = I cosθ / r², I = P / 4π; DiffDir = (ρ/π)·E / ρ = E / π. Averaged over the pixel
            // footprint (8×8 sub-samples) since the renderer box-filters.
            let mut expect = 0.0;
            for j in 0..8 {
                for i in 0..8 {
                    let (fx, fz) = floor_point(x as f64 + (i as f64 + 0.5) / 8.0, y as f64 + (j as f64 + 0.5) / 8.0, w);
                    let (dx, dy, dz) = (lx - fx, ly, lz - fz);
                    let r2 = dx * dx + dy * dy + dz * dz;
                    let cos = dy / r2.sqrt();
                    expect += power / (4.0 * PI) * cos / r2 / PI / 64.0;
                }
            }
            let got = px(&dir, x, y);
            for c in 0..3 {
                let rel = (got[c] as f64 - expect).abs() / expect;
                // 64 jittered samples over a footprint whose irradiance varies by a few percent: ~1 % noise.
                assert!(
                    rel < 0.025,
                    "pixel ({x},{y}) ch {c}: DiffDir {} vs {expect} (rel {rel})",
                    got[c]
                );
                assert!(
                    (px(&col, x, y)[c] - rho[c]).abs() < 1e-5,
                    "DiffCol {:?}",
                    px(&col, x, y)
                );
                assert_eq!(px(&ind, x, y)[c], 0.0, "a lone plane has no indirect light");
            }
        }
    }
}

#[test]
fn lambertian_plane_under_sun_is_strength_times_cosine() {
    let w = 16;
    let mut s = floor_scene([0.8, 0.8, 0.8], w);
    let d = [0.4f64, -1.0, 0.3];
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let strength = 3.0f64;
    s.lights.push(Light::Sun {
        name: String::new(),
        direction: Some(d.map(|v| v as f32)),
        strength: strength as f32,
        angle_deg: 0.0,
        color: Color::Rgb([1.0, 0.5, 0.25]),
    });
    let film = render(&s, &opts(4, 2), &no_progress).unwrap();
    let dir = film.pass("DiffDir").unwrap();
    // E = strength·cosθ with cosθ = −d̂·n̂ (n = +Y); DiffDir = E/π per colour channel.
    let cos = -d[1] / len;
    let expect = [1.0, 0.5, 0.25].map(|c| c * strength * cos / PI);
    for y in 0..w as usize {
        for x in 0..w as usize {
            let got = px(&dir, x, y);
            for c in 0..3 {
                assert!(
                    ((got[c] as f64) - expect[c]).abs() < 5e-4 * expect[c],
                    "{got:?} vs {expect:?}"
                );
            }
        }
    }
}

#[test]
fn white_furnace_convex_box_under_constant_sky() {
    // A convex Lambertian box (albedo ρ) under a constant world of radiance L, no occluders.
    // Every visible face sees the full sky over its hemisphere: E = πL, so DiffDir = (ρ/π)·E/ρ
    // = L; convexity means no light returns to the object: DiffInd = 0. Background pixels see
    // Env = L. Combined on the box = ρ·L.
    let w = 32;
    let l = [1.0f32, 0.5, 0.25];
    let rho = 0.6f32;
    let mut cam = Camera::new(w, w, 40.0);
    cam.position = [2.0, 2.5, 3.0];
    cam.look_at = Some([0.0, 0.0, 0.0]);
    let mut s = Scene::new(cam);
    s.objects.push(Object {
        name: "box".into(),
        shape: Shape::Cuboid { size: [1.0, 1.0, 1.0] },
        transform: Transform::default(),
        material: Material::diffuse([rho; 3]),
    });
    s.world = Some(World {
        color: Color::Rgb(l),
        strength: 1.0,
        image: None,
        rotation_deg: 0.0,
    });
    let film: Film = render(&s, &opts(64, 4), &no_progress).unwrap();
    let dir = film.pass("DiffDir").unwrap();
    let ind = film.pass("DiffInd").unwrap();
    let env = film.pass("Env").unwrap();
    let depth = film.pass("Depth").unwrap();
    let (mut sum, mut n) = ([0.0f64; 3], 0usize);
    for y in 0..w as usize {
        for x in 0..w as usize {
            if depth.get(x, y, 0) >= 1e9 {
                for c in 0..3 {
                    assert!((env.get(x, y, c) - l[c]).abs() < 1e-6);
                }
                continue;
            }
            // Only pixels fully on the box (all samples hit: env contribution 0).
            if env.get(x, y, 0) != 0.0 {
                continue;
            }
            n += 1;
            for c in 0..3 {
                sum[c] += dir.get(x, y, c) as f64;
                assert_eq!(ind.get(x, y, c), 0.0, "convex object has no indirect light");
            }
        }
    }
    assert!(n > 100, "box covers {n} pixels");
    for c in 0..3 {
        let mean = sum[c] / n as f64;
        assert!(
            (mean - l[c] as f64).abs() < 0.02 * l[c] as f64,
            "channel {c}: mean DiffDir {mean} vs L {}",
            l[c]
        );
    }
}

#[test]
fn closed_emissive_box_furnace_sums_the_neumann_series() {
    // Camera inside a closed box whose walls are Lambertian (albedo ρ) and emit Le. Radiance is
    // uniform; with B bounces light is gathered at B+1 vertices, so the outgoing radiance is
    // Lo = Le·Σ_{k=0}^{B+1} ρ^k. Passes: Emit = Le; DiffDir = irradiance from emitters / π = Le;
    // DiffInd = (Lo − Le)/ρ − Le = Le·Σ_{k=1}^{B} ρ^k; Combined = Lo.
    let (le, rho, b) = (1.0f64, 0.5f64, 6u32);
    let mut cam = Camera::new(8, 8, 60.0);
    cam.position = [0.1, 0.2, 0.3];
    cam.look_at = Some([0.5, 0.0, -1.0]);
    let mut s = Scene::new(cam);
    let mut m = Material::diffuse([rho as f32; 3]);
    m.emission_color = Color::Rgb([1.0, 1.0, 1.0]);
    m.emission_strength = le as f32;
    s.objects.push(Object {
        name: "room".into(),
        shape: Shape::Cuboid { size: [2.0, 2.0, 2.0] },
        transform: Transform::default(),
        material: m,
    });
    let film = render(&s, &opts(256, b), &no_progress).unwrap();
    let mean = |name: &str| {
        let img = film.pass(name).unwrap();
        img.data.iter().map(|v| *v as f64).sum::<f64>() / img.data.len() as f64
    };
    let series = |from: u32, to: u32| (from..=to).map(|k| rho.powi(k as i32)).sum::<f64>() * le;
    let (emit, dir, ind) = (mean("Emit"), mean("DiffDir"), mean("DiffInd"));
    assert!((emit - le).abs() < 1e-6, "Emit {emit}");
    assert!((dir - le).abs() < 0.02 * le, "DiffDir {dir} vs {le}");
    let ind_expect = series(1, b);
    assert!(
        (ind - ind_expect).abs() < 0.03 * ind_expect,
        "DiffInd {ind} vs {ind_expect}"
    );
    let comb = mean("Combined") * 4.0 / 3.0 - 1.0 / 3.0; // RGBA mean: alpha = 1
    let comb_expect = series(0, b + 1);
    assert!(
        (comb - comb_expect).abs() < 0.02 * comb_expect,
        "Combined {comb} vs {comb_expect}"
    );
}

#[test]
fn emissive_quad_seen_head_on_emits_its_strength() {
    // Emission pass = radiance of the surface = strength × colour, whatever the view.
    let mut cam = Camera::new(16, 16, 30.0);
    cam.position = [0.0, 0.0, 3.0];
    let mut s = Scene::new(cam);
    let (strength, color) = (4.0f32, [1.0f32, 0.5, 0.2]);
    s.objects.push(Object {
        name: "panel".into(),
        shape: Shape::Quad { size: [4.0, 4.0] },
        transform: Transform::default(),
        material: Material::emissive(color, strength),
    });
    let film = render(&s, &opts(2, 2), &no_progress).unwrap();
    let emit = film.pass("Emission").unwrap();
    let comb = film.pass("Combined").unwrap();
    for y in 0..16 {
        for x in 0..16 {
            for c in 0..3 {
                assert!((emit.get(x, y, c) - strength * color[c]).abs() < 1e-5);
                assert!(
                    (comb.get(x, y, c) - strength * color[c]).abs() < 1e-5,
                    "black panel: Combined = Emit"
                );
            }
        }
    }
}

#[test]
fn area_light_in_view_is_seen_by_the_camera_only_when_asked() {
    // A 2 m square area light 3 m in front of the camera, facing it, filling the view (half-width
    // of the view at 3 m: 3·tan 15° ≈ 0.8 m < 1 m), over a world of radiance w. Its radiance is
    // P / (π A) · colour = 8π / (π · 4) = 2 W/(m² sr). Blender's default (camera visibility off):
    // the camera looks through it, Emit = 0 and Combined = Env = w. Visible: Emit = 2 and, since a
    // light does not block the ray (as in Cycles), Combined = 2 + w. Either way it lights nothing
    // here (no surfaces), so every other pass is 0.
    let w = [0.1f32, 0.2, 0.3];
    let scene = |visible: bool| {
        let mut cam = Camera::new(12, 12, 30.0);
        cam.position = [0.0, 0.0, 3.0];
        let mut s = Scene::new(cam);
        s.lights.push(Light::Area {
            name: "panel".into(),
            position: [0.0, 0.0, 0.0],
            direction: Some([0.0, 0.0, 1.0]),
            look_at: None,
            shape: pixl_render::scene::AreaShape::Square,
            size: 2.0,
            size_y: None,
            power: 8.0 * PI as f32,
            color: Color::Rgb([1.0, 1.0, 1.0]),
            visible_to_camera: visible,
        });
        s.world = Some(World {
            color: Color::Rgb(w),
            strength: 1.0,
            image: None,
            rotation_deg: 0.0,
        });
        s
    };
    for visible in [false, true] {
        let film = render(&scene(visible), &opts(2, 2), &no_progress).unwrap();
        let (emit, env, comb) = (
            film.pass("Emit").unwrap(),
            film.pass("Env").unwrap(),
            film.pass("Combined").unwrap(),
        );
        let radiance = if visible { 2.0 } else { 0.0 };
        for y in 0..12 {
            for x in 0..12 {
                for c in 0..3 {
                    let (e, b, k) = (emit.get(x, y, c), env.get(x, y, c), comb.get(x, y, c));
                    assert!((e - radiance).abs() < 1e-5, "visible {visible}: Emit {e}");
                    assert!((b - w[c]).abs() < 1e-6, "visible {visible}: Env {b}");
                    assert!((k - (radiance + w[c])).abs() < 1e-5, "visible {visible}: Combined {k}");
                }
            }
        }
        for p in ["DiffDir", "DiffInd", "GlossDir", "GlossInd"] {
            assert!(film.pass(p).unwrap().data.iter().all(|v| *v == 0.0), "{p}");
        }
    }
}

#[test]
fn no_light_leaks_through_a_close_cover_and_no_acne_far_from_the_origin() {
    // A floor (y = 0) around x = 1000 m, a sun straight down (angle 0) of strength 3, and a camera
    // 5 mm above the floor looking along −Z. Rays leave a surface exactly at the hit point and
    // skip the triangle they leave (Cycles' rule), so:
    // - without a cover, every floor pixel gets DiffDir = strength / π exactly as in
    //   `lambertian_plane_under_sun_is_strength_times_cosine` (no self-shadowing "acne" from
    //   the floor's other triangle, even where float error in the hit point is ~1e-4 m);
    // - with an opaque cover 1 cm above the floor, no sunlight reaches the floor: DiffDir = 0
    //   (an offset of 1e-4·(1 + |p|) ≈ 0.1 m here, the old rule, started the shadow ray above
    //   the cover and lit the floor).
    let scene = |cover: bool| {
        let mut cam = Camera::new(16, 12, 40.0);
        cam.position = [1000.0, 0.005, 0.0];
        cam.look_at = Some([1000.0, 0.005, -1.0]);
        let mut s = Scene::new(cam);
        let quad = |name: &str, y: f32| Object {
            name: name.into(),
            shape: Shape::Quad { size: [200.0, 200.0] },
            transform: Transform {
                translate: [1000.0, y, 0.0],
                rotate_deg: [-90.0, 0.0, 0.0],
                ..Default::default()
            },
            material: Material::diffuse([0.8, 0.8, 0.8]),
        };
        s.objects.push(quad("floor", 0.0));
        if cover {
            s.objects.push(quad("cover", 0.01));
        }
        s.lights.push(Light::Sun {
            name: String::new(),
            direction: Some([0.0, -1.0, 0.0]),
            strength: 3.0,
            angle_deg: 0.0,
            color: Color::Rgb([1.0, 1.0, 1.0]),
        });
        s
    };
    for cover in [false, true] {
        let film = render(&scene(cover), &opts(4, 1), &no_progress).unwrap();
        let (dir, depth) = (film.pass("DiffDir").unwrap(), film.pass("Depth").unwrap());
        let mut floor_pixels = 0;
        for y in 0..12 {
            for x in 0..16 {
                // Rows below the horizon see the floor (within 0.5 m; the cover, when there, is
                // above the horizon).
                if y < 7 || depth.get(x, y, 0) > 1.0 {
                    continue;
                }
                floor_pixels += 1;
                let want = if cover { 0.0 } else { 3.0 / PI };
                for c in 0..3 {
                    let got = dir.get(x, y, c) as f64;
                    assert!(
                        (got - want).abs() <= 5e-4 * want,
                        "cover {cover}: pixel ({x}, {y}) DiffDir {got} vs {want}"
                    );
                }
            }
        }
        assert!(floor_pixels >= 16 * 4, "only {floor_pixels} floor pixels");
    }
}

#[test]
fn sun_with_an_angle_lights_a_plane_as_its_cone_does() {
    // A sun of angular diameter 20° (half-angle δ = 10°) is a cone of uniform radiance
    // L = E / Ω, Ω = 2π(1 − cos δ); it is now both light-sampled and hit by BSDF rays (MIS).
    // A cap of half-angle δ centred θ from the normal, wholly above the horizon, has projected
    // solid angle π sin²δ cos θ, so the plane's irradiance is L π sin²δ cos θ and DiffDir =
    // L sin²δ cos θ (the same expectation as light sampling alone gave before).
    let w = 16;
    let mut s = floor_scene([0.8, 0.8, 0.8], w);
    let d = [0.4f64, -1.0, 0.3];
    let cos = -d[1] / (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    let (strength, delta) = (3.0f64, 10f64.to_radians());
    s.lights.push(Light::Sun {
        name: String::new(),
        direction: Some(d.map(|v| v as f32)),
        strength: strength as f32,
        angle_deg: 20.0,
        color: Color::Rgb([1.0, 1.0, 1.0]),
    });
    let film = render(&s, &opts(64, 1), &no_progress).unwrap();
    let dir = film.pass("DiffDir").unwrap();
    let omega = 2.0 * PI * (1.0 - delta.cos());
    let expect = strength / omega * delta.sin().powi(2) * cos;
    let mean = dir.data.iter().map(|v| *v as f64).sum::<f64>() / dir.data.len() as f64;
    assert!(
        mean.is_finite() && (mean - expect).abs() < 0.01 * expect,
        "DiffDir {mean} vs {expect}"
    );
}

/// A 20 m smooth glass floor (IOR 3: F = ((3 − 1)/(3 + 1))² = 0.25 at normal incidence) seen
/// straight down from 5 m through an 8×8 camera of 2° (every view ray within 1° of vertical).
fn glass_floor_seen_from_above() -> Scene {
    let mut cam = Camera::new(8, 8, 2.0);
    cam.position = [0.0, 5.0, 0.0];
    cam.look_at = Some([0.0, 0.0, 0.0]);
    cam.up = [0.0, 0.0, -1.0];
    let mut s = Scene::new(cam);
    s.objects.push(Object {
        name: "glass".into(),
        shape: Shape::Quad { size: [20.0, 20.0] },
        transform: Transform {
            rotate_deg: [-90.0, 0.0, 0.0],
            ..Default::default()
        },
        material: Material {
            transmission: 1.0,
            roughness: 0.0,
            ior: 3.0,
            ..Default::default()
        },
    });
    s
}

#[test]
fn smooth_glass_reflects_the_sun() {
    // A smooth glass floor (IOR 3: F = ((3 − 1)/(3 + 1))² = 0.25 at normal incidence) seen
    // straight down through a narrow camera, under a sun straight down of angular diameter 60°:
    // every mirror-reflected camera ray (within 1° of vertical) lies in the sun's cone, so
    // GlossDir = L = E / Ω with Ω = 2π(1 − cos 30°) — the light the sun gives a mirror. Before
    // suns were hit by BSDF rays, smooth glass never showed the sun (GlossDir 0). The
    // reflection is chosen with probability F per sample, so the check is on the image mean.
    let mut s = glass_floor_seen_from_above();
    let strength = 2.0f64;
    s.lights.push(Light::Sun {
        name: String::new(),
        direction: Some([0.0, -1.0, 0.0]),
        strength: strength as f32,
        angle_deg: 60.0,
        color: Color::Rgb([1.0, 1.0, 1.0]),
    });
    let film = render(&s, &opts(256, 1), &no_progress).unwrap();
    let (gd, gc) = (film.pass("GlossDir").unwrap(), film.pass("GlossCol").unwrap());
    let mean = |img: &pixl_core::Image| img.data.iter().map(|v| *v as f64).sum::<f64>() / img.data.len() as f64;
    let expect = strength / (2.0 * PI * (1.0 - 30f64.to_radians().cos()));
    assert!((mean(&gc) - 0.25).abs() < 1e-3, "GlossCol {}", mean(&gc));
    assert!(
        (mean(&gd) - expect).abs() < 0.03 * expect,
        "GlossDir {} vs {expect}",
        mean(&gd)
    );
}

#[test]
fn sphere_light_lights_a_plane_like_a_point_and_glints_in_glass() {
    // A point light of radius r is a sphere of radiance L = I / (π r²), I = P / 4π (Cycles). Seen
    // from a point of the plane with the sphere wholly above its horizon it subtends a cap of
    // projected solid angle π (r/d)² cos θ, so the irradiance is exactly I cos θ / d², as for
    // the point: the image mean of DiffDir must equal the point light's closed form, now with
    // light sampling over the cone plus BSDF rays hitting the sphere (MIS).
    let w = 16u32;
    let mut s = floor_scene([0.5, 0.5, 0.5], w);
    let (lx, ly, lz, power, radius) = (0.3f64, 1.5f64, -0.2f64, 200.0f64, 0.6f32);
    s.lights.push(Light::Point {
        name: String::new(),
        position: [lx as f32, ly as f32, lz as f32],
        power: power as f32,
        radius,
        color: Color::Rgb([1.0, 1.0, 1.0]),
        visible_to_camera: false,
    });
    let film = render(&s, &opts(128, 1), &no_progress).unwrap();
    let dir = film.pass("DiffDir").unwrap();
    let (mut got, mut want) = (0.0f64, 0.0f64);
    for y in 0..w as usize {
        for x in 0..w as usize {
            got += dir.get(x, y, 0) as f64;
            for j in 0..8 {
                for i in 0..8 {
                    let (fx, fz) = floor_point(x as f64 + (i as f64 + 0.5) / 8.0, y as f64 + (j as f64 + 0.5) / 8.0, w);
                    let (dx, dy, dz) = (lx - fx, ly, lz - fz);
                    let d2 = dx * dx + dy * dy + dz * dz;
                    want += power / (4.0 * PI) * (dy / d2.sqrt()) / d2 / PI / 64.0;
                }
            }
        }
    }
    assert!(
        got.is_finite() && (got - want).abs() < 0.01 * want,
        "DiffDir sum {got} vs {want}"
    );

    // A smooth IOR-3 glass floor (F = 0.25 at normal incidence) seen straight down through a
    // narrow camera at height 5, under a sphere light of radius 3 centred 10 m up: every mirror
    // ray goes up into the sphere, so GlossDir = L = P / (4π · π r²). (The camera does not see
    // the light, lights do not occlude.) Before, point lights were never hit: GlossDir 0.
    let mut s = glass_floor_seen_from_above();
    s.lights.push(Light::Point {
        name: String::new(),
        position: [0.0, 10.0, 0.0],
        power: 1000.0,
        radius: 3.0,
        color: Color::Rgb([1.0, 1.0, 1.0]),
        visible_to_camera: false,
    });
    let film = render(&s, &opts(256, 1), &no_progress).unwrap();
    let gd = film.pass("GlossDir").unwrap();
    let mean = gd.data.iter().map(|v| *v as f64).sum::<f64>() / gd.data.len() as f64;
    let expect = 1000.0 / (4.0 * PI * PI * 9.0);
    assert!((mean - expect).abs() < 0.03 * expect, "GlossDir {mean} vs {expect}");
}

/// Least-squares slope of ln(err) against ln(n).
fn loglog_slope(ns: &[u32], errs: &[f64]) -> f64 {
    let xs: Vec<f64> = ns.iter().map(|n| (*n as f64).ln()).collect();
    let ys: Vec<f64> = errs.iter().map(|e| e.ln()).collect();
    let m = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (mx, my) = (m(&xs), m(&ys));
    let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    sxy / sxx
}

#[test]
fn area_lit_plane_converges_faster_with_the_sobol_sampler() {
    // A Lambertian floor under a 1.6 m × 1.0 m rectangular area light 1.2 m above it, facing
    // down, direct light only, seen from above through a 32×32 camera (a pixel covers ~0.11 m
    // of floor). Exact: a polygon of uniform
    // radiance L gives the irradiance E = L·|n·Φ| with Lambert's vector irradiance
    // Φ = ½ Σ_edges θ_i · unit(v_i × v_{i+1}) (v_i the unit directions to the corners, θ_i the
    // angle between consecutive ones); DiffDir = E/π; L = P / (π·area); each pixel's value is
    // the mean over its footprint (32×32 midpoint sub-samples, f64).
    //
    // The render's error (light sampling and BSDF rays MIS-combined, plus the pixel position)
    // must fall clearly faster than spp^-0.5 with the Sobol sampler and as spp^-0.5 with the
    // independent one; both are unbiased. (Measured: exponent −0.82 vs −0.50, RMSE at 256 spp
    // 9× lower. With 8×8 pixels of ~0.45 m the exponent is only −0.59: the sampler stratifies
    // each 2-D dimension, not the joint pixel position × light position, whose interaction
    // then converges as spp^-0.5 — as with any padded sampler.)
    use pixl_render::integrator::Renderer;
    use pixl_render::sampler::Sampler;
    let w = 32u32;
    let mut s = floor_scene([0.5, 0.5, 0.5], w);
    let (c, half, power) = ([0.3f64, 1.2, -0.2], [0.8f64, 0.5], 60.0f64);
    s.lights.push(Light::Area {
        name: "panel".into(),
        position: c.map(|v| v as f32),
        direction: Some([0.0, -1.0, 0.0]),
        look_at: None,
        shape: pixl_render::scene::AreaShape::Rectangle,
        size: 2.0 * half[0] as f32,
        size_y: Some(2.0 * half[1] as f32),
        power: power as f32,
        color: Color::Rgb([1.0, 1.0, 1.0]),
        visible_to_camera: false,
    });
    // A light facing −Y has its local axes along +X and −Z (`light::area_axes`); the corners in
    // order around the rectangle.
    let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        .map(|(a, b)| [c[0] + a * half[0], c[1], c[2] + b * half[1]]);
    let radiance = power / (PI * 4.0 * half[0] * half[1]);
    let dir_at = |fx: f64, fz: f64| {
        let unit = |q: [f64; 3]| {
            let d = [q[0] - fx, q[1], q[2] - fz];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            d.map(|v| v / l)
        };
        let v = corners.map(unit);
        let mut phi_y = 0.0;
        for i in 0..4 {
            let (a, b) = (v[i], v[(i + 1) % 4]);
            let cross = [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ];
            let len = (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt();
            let theta = (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0).acos();
            phi_y += 0.5 * theta * cross[1] / len;
        }
        radiance * phi_y.abs() / PI
    };
    let sub = 32;
    let exact: Vec<f64> = (0..(w * w) as usize)
        .map(|p| {
            let (x, y) = ((p % w as usize) as f64, (p / w as usize) as f64);
            let mut sum = 0.0;
            for j in 0..sub {
                for i in 0..sub {
                    let (px, py) = (x + (i as f64 + 0.5) / sub as f64, y + (j as f64 + 0.5) / sub as f64);
                    let (fx, fz) = floor_point(px, py, w);
                    sum += dir_at(fx, fz);
                }
            }
            sum / (sub * sub) as f64
        })
        .collect();
    let ns = [4u32, 8, 16, 32, 64, 128, 256];
    let seeds = 2u64;
    // Per sampler and spp: RMSE over pixels and seeds (red channel; the light is white), and
    // the mean signed error of the image means.
    let measure = |sampler: Sampler, spp: u32| {
        let (mut se, mut bias) = (0.0, 0.0);
        for seed in 0..seeds {
            let mut r = Renderer::new(&s, &RenderOptions { seed, ..opts(spp, 0) }).unwrap();
            r.sampler = sampler;
            let film = r.render(&no_progress);
            let dir = film.pass("DiffDir").unwrap();
            for (p, want) in exact.iter().enumerate() {
                let got = dir.get(p % w as usize, p / w as usize, 0) as f64;
                se += (got - want).powi(2);
                bias += got - want;
            }
        }
        let n = (seeds * (w * w) as u64) as f64;
        ((se / n).sqrt(), bias / n)
    };
    let mut slopes = Vec::new();
    let mut at_256 = Vec::new();
    for sampler in [Sampler::Sobol, Sampler::Independent] {
        let runs: Vec<(f64, f64)> = ns.iter().map(|&n| measure(sampler, n)).collect();
        let rmse: Vec<f64> = runs.iter().map(|r| r.0).collect();
        let k = loglog_slope(&ns, &rmse);
        eprintln!("{sampler:?}: DiffDir RMSE {rmse:?}, fitted exponent {k:.3}");
        // Unbiased: the mean error of the image mean, over all spp, within 4 standard errors
        // (pixels and seeds are independent: σ(mean) = RMSE / √(pixels·seeds)).
        for (n, (e, b)) in ns.iter().zip(&runs) {
            let sigma = e / ((seeds * (w * w) as u64) as f64).sqrt();
            assert!(
                b.abs() < 4.0 * sigma + 1e-5,
                "{sampler:?} {n} spp: bias {b} (σ {sigma})"
            );
        }
        slopes.push(k);
        at_256.push(rmse[ns.len() - 1]);
    }
    assert!(
        slopes[0] < -0.75,
        "Sobol exponent {} (independent {})",
        slopes[0],
        slopes[1]
    );
    assert!((slopes[1] + 0.5).abs() < 0.1, "independent exponent {}", slopes[1]);
    assert!(
        at_256[0] < at_256[1] / 4.0,
        "RMSE at 256 spp: Sobol {} vs independent {}",
        at_256[0],
        at_256[1]
    );
}

#[test]
fn sphere_light_in_view_is_seen_by_the_camera_only_when_asked() {
    // A point light of radius r = 0.5 m, 5 m in front of a 32×32, 30° camera at the origin, over a
    // world of radiance w. As in Cycles it is a sphere of radiance L = I / (π r²), I = P / 4π; with
    // P = 2π² · colour that is L = 2 · colour. Its silhouette on the image plane is the circle of
    // radius R = f · tan θ, sin θ = r / d (the cone it subtends, cut by the plane), centred on the
    // principal point. Camera visibility on: pixels wholly inside the circle have Emit = L and
    // Combined = L + w (lights do not occlude), pixels wholly outside Emit = 0, and the image sum of
    // Emit is L · πR² (the area of the circle in pixels; straddling pixels hold the covered
    // fraction). Off (Blender's default): Emit = 0 everywhere. A spot light of the same power and
    // radius is the same sphere times its cone mask: facing the camera (mask 1) it looks the
    // same, facing away (mask 0) it is not seen. Nothing is lit (no surfaces): every lobe pass is 0.
    let (n, fov, d, r) = (32usize, 30.0f64, 5.0f64, 0.5f64);
    let color = [1.0f32, 0.5, 0.25];
    let w = [0.05f32, 0.1, 0.15];
    let power = 2.0 * PI * PI;
    let radiance = power / (4.0 * PI * PI * r * r);
    let scene = |light: Light| {
        let mut s = Scene::new(Camera::new(n as u32, n as u32, fov as f32));
        s.lights.push(light);
        s.world = Some(World {
            color: Color::Rgb(w),
            strength: 1.0,
            image: None,
            rotation_deg: 0.0,
        });
        s
    };
    let point = |visible: bool| Light::Point {
        name: String::new(),
        position: [0.0, 0.0, -d as f32],
        power: power as f32,
        radius: r as f32,
        color: Color::Rgb(color),
        visible_to_camera: visible,
    };
    let spot = |towards: f32| Light::Spot {
        name: String::new(),
        position: [0.0, 0.0, -d as f32],
        direction: Some([0.0, 0.0, towards]),
        look_at: None,
        power: power as f32,
        spot_size_deg: 60.0,
        blend: 0.0,
        radius: r as f32,
        color: Color::Rgb(color),
        visible_to_camera: true,
    };
    let focal = 0.5 * n as f64 / (0.5 * fov.to_radians()).tan();
    let big_r = focal * (r / d).asin().tan();
    let c = 0.5 * n as f64;
    for (light, seen) in [
        (point(false), 0.0),
        (point(true), 1.0),
        (spot(1.0), 1.0),
        (spot(-1.0), 0.0),
    ] {
        let what = format!("{light:?}");
        let film = render(&scene(light), &opts(64, 2), &no_progress).unwrap();
        let (emit, comb) = (film.pass("Emit").unwrap(), film.pass("Combined").unwrap());
        let (mut sum, mut inside, mut outside) = (0.0f64, 0, 0);
        for y in 0..n {
            for x in 0..n {
                // Nearest and farthest points of the pixel square from the circle's centre.
                let (x0, y0) = (x as f64 - c, y as f64 - c);
                let near = |a: f64| {
                    if a > 0.0 {
                        a
                    } else if a + 1.0 < 0.0 {
                        -(a + 1.0)
                    } else {
                        0.0
                    }
                };
                let far = |a: f64| a.abs().max((a + 1.0).abs());
                let (dn, df) = (near(x0).hypot(near(y0)), far(x0).hypot(far(y0)));
                let e = emit.get(x, y, 0) as f64;
                sum += e;
                if df < big_r {
                    inside += 1;
                    let want = seen * radiance;
                    assert!(
                        (e - want).abs() < 1e-5 * radiance,
                        "{what}: pixel ({x}, {y}) Emit {e} vs {want}"
                    );
                    for ch in 0..3 {
                        let want = seen * radiance * color[ch] as f64 + w[ch] as f64;
                        let got = comb.get(x, y, ch) as f64;
                        assert!((got - want).abs() < 1e-5 * want, "{what}: Combined {got} vs {want}");
                    }
                } else if dn > big_r {
                    outside += 1;
                    assert_eq!(e, 0.0, "{what}: pixel ({x}, {y}) outside the sphere");
                }
            }
        }
        assert!(inside > 60 && outside > 800, "inside {inside}, outside {outside}");
        let want = seen * radiance * PI * big_r * big_r;
        assert!((sum - want).abs() <= 0.01 * want, "{what}: Emit sum {sum} vs {want}");
        for p in ["DiffDir", "DiffInd", "GlossDir", "GlossInd", "TransDir", "TransInd"] {
            assert!(film.pass(p).unwrap().data.iter().all(|v| *v == 0.0), "{p}");
        }
    }
}

#[test]
fn thin_lens_keeps_the_focus_plane_sharp_and_blurs_by_the_circle_of_confusion() {
    // A 64×32, 20° camera at the origin looking down −Z at the left half of a plane of emission 1
    // (x < 0, depth z = 4 m; its edge projects onto column 32). Depth of field, f/0.5: the lens
    // Blender gets (24 mm sensor height) is `lens = 12 mm / tan 10°`, so the aperture radius is
    // A = lens / (2 · 0.5) (Cycles' `lens·1e-3 / (2 fstop)`). A lens point L sends the ray of image
    // point p to where the pinhole ray of p crosses the plane in focus (depth F); it meets the
    // plane at depth z at the pinhole image p − f·L·(1/F − 1/z) (f = focal length in pixels). So
    // with F = z the emitter's edge stays a sharp step; with F = 1 m it spreads over a disk of
    // radius r = f·A·(1/F − 1/z) ≈ 4.6 px: a pixel's Emit is the mean over its width of the
    // fraction of that disk on the bright side, seg(s) = (acos(s/r) − (s/r)·√(1 − (s/r)²)) / π at
    // offset s from the edge. Checked per column on the mean of the 32 rows (Sobol, 128 spp).
    let (w, h, fov, z, fstop) = (64u32, 32u32, 20.0f64, 4.0f64, 0.5f64);
    let focal = 0.5 * h as f64 / (0.5 * fov.to_radians()).tan();
    let aperture = 12e-3 / (0.5 * fov.to_radians()).tan() / (2.0 * fstop);
    let scene = |focus: f64| {
        let mut cam = Camera::new(w, h, fov as f32);
        cam.dof = Some(pixl_render::scene::Dof {
            focus_distance: focus as f32,
            aperture_fstop: fstop as f32,
        });
        let mut s = Scene::new(cam);
        s.objects.push(Object {
            name: "half".into(),
            shape: Shape::Quad { size: [10.0, 10.0] },
            transform: Transform {
                translate: [-5.0, 0.0, -z as f32],
                ..Default::default()
            },
            material: Material::emissive([1.0, 1.0, 1.0], 1.0),
        });
        s
    };
    let seg = |s: f64, r: f64| {
        if r == 0.0 {
            return if s < 0.0 { 1.0 } else { 0.0 };
        }
        let q = (s / r).clamp(-1.0, 1.0);
        (q.acos() - q * (1.0 - q * q).sqrt()) / PI
    };
    for focus in [z, 1.0] {
        let r = focal * aperture * (1.0 / focus - 1.0 / z);
        let film = render(&scene(focus), &opts(128, 0), &no_progress).unwrap();
        let emit = film.pass("Emit").unwrap();
        let mut blurred = 0;
        for x in 0..w as usize {
            let got = (0..h as usize).map(|y| emit.get(x, y, 0) as f64).sum::<f64>() / h as f64;
            let m = 2000;
            let want = (0..m)
                .map(|i| seg(x as f64 + (i as f64 + 0.5) / m as f64 - 0.5 * w as f64, r))
                .sum::<f64>()
                / m as f64;
            assert!(
                (got - want).abs() < 0.03,
                "focus {focus} m (blur radius {r:.2} px): column {x} Emit {got} vs {want}"
            );
            blurred += (want > 0.02 && want < 0.98) as usize;
        }
        // Sharp: only the edge's own columns are partly lit; out of focus, ~2r columns.
        if focus == z {
            assert!(blurred == 0, "{blurred} blurred columns in focus");
        } else {
            assert!(blurred >= 8, "{blurred} blurred columns");
        }
    }
}

fn glass_ball(roughness: f32) -> Object {
    Object {
        name: "ball".into(),
        shape: Shape::Sphere { radius: 1.0 },
        transform: Transform::default(),
        material: Material {
            base_color: Color::Rgb([1.0, 1.0, 1.0]),
            transmission: 1.0,
            roughness,
            ior: 1.5,
            ..Default::default()
        },
    }
}

fn pass_mean(film: &Film, name: &str) -> f64 {
    let img = film.pass(name).unwrap();
    img.data.iter().map(|v| *v as f64).sum::<f64>() / img.data.len() as f64
}

#[test]
fn white_glass_ball_in_a_white_furnace_keeps_its_energy() {
    // A clear (base 1) glass ball under a constant world of radiance 1, nothing else: every path
    // from the camera ends in the world after reflections and refractions that each keep the
    // energy (F + (1 − F) = 1), so every pixel on the ball sees radiance 1 — exactly for smooth
    // glass (up to Russian roulette and the bounce limit, negligible at 32 bounces). Rough GGX
    // glass too, with its energy compensation (each interaction's albedo is 1 within 0.5 %,
    // `material` tests; without it 0.1–2.5 % would be lost per interaction at roughness 0.3 and
    // up to 24 % at 0.6).
    let mut cam = Camera::new(16, 16, 20.0);
    cam.position = [0.0, 0.0, 4.0];
    for (roughness, lo, hi) in [(0.0f32, 0.99, 1.01), (0.3, 0.985, 1.015), (0.6, 0.98, 1.02)] {
        let mut s = Scene::new(cam.clone());
        s.objects.push(glass_ball(roughness));
        s.world = Some(World {
            color: Color::Rgb([1.0, 1.0, 1.0]),
            strength: 1.0,
            image: None,
            rotation_deg: 0.0,
        });
        let film = render(&s, &opts(64, 32), &no_progress).unwrap();
        let (env, comb) = (film.pass("Env").unwrap(), film.pass("Combined").unwrap());
        let (mut sum, mut n) = (0.0f64, 0);
        for y in 0..16 {
            for x in 0..16 {
                if env.get(x, y, 0) == 0.0 {
                    sum += comb.get(x, y, 0) as f64;
                    n += 1;
                }
            }
        }
        let mean = sum / n as f64;
        assert!(n > 60, "{n} pixels on the ball");
        assert!(
            mean >= lo && mean <= hi,
            "roughness {roughness}: mean Combined {mean} on the ball"
        );
    }
}

#[test]
fn nearly_smooth_rough_glass_renders_as_smooth_glass() {
    // Roughness → 0 takes GGX glass to the smooth (delta) glass; a roughness of 0.01 (α clamped
    // at 1e-3) must give the smooth render's pass means within noise, in a scene where the glass
    // shows an area light, a sun with a cone and the world by reflection and refraction, and
    // throws caustics on a floor — so the rough glass's light sampling (its MIS with the BSDF
    // rays that hit the lights) is exercised where the smooth glass has none. Both renders use
    // the same seed (correlated samples: they agree to 0.4 %, where two seeds of the smooth
    // render differ by up to 16 % on GlossInd at 1024 spp).
    let scene = |roughness: f32| {
        let mut cam = Camera::new(32, 24, 40.0);
        cam.position = [0.0, 1.5, 4.5];
        cam.look_at = Some([0.0, 0.8, 0.0]);
        let mut s = Scene::new(cam);
        s.objects.push(Object {
            name: "floor".into(),
            shape: Shape::Quad { size: [8.0, 8.0] },
            transform: Transform {
                rotate_deg: [-90.0, 0.0, 0.0],
                ..Default::default()
            },
            material: Material::diffuse([0.6, 0.6, 0.6]),
        });
        let mut ball = glass_ball(roughness);
        ball.transform.translate = [0.0, 1.0, 0.0];
        ball.material.base_color = Color::Rgb([0.9, 0.8, 0.6]);
        s.objects.push(ball);
        s.lights.push(Light::Area {
            name: String::new(),
            position: [0.5, 3.5, 1.0],
            direction: None,
            look_at: Some([0.0, 1.0, 0.0]),
            shape: pixl_render::scene::AreaShape::Square,
            size: 3.0,
            size_y: None,
            power: 300.0,
            color: Color::Rgb([1.0, 1.0, 1.0]),
            visible_to_camera: false,
        });
        s.lights.push(Light::Sun {
            name: String::new(),
            direction: Some([-0.4, -1.0, -0.3]),
            strength: 2.0,
            angle_deg: 30.0,
            color: Color::Rgb([1.0, 0.9, 0.8]),
        });
        s.world = Some(World {
            color: Color::Rgb([0.2, 0.25, 0.3]),
            strength: 1.0,
            image: None,
            rotation_deg: 0.0,
        });
        s
    };
    let smooth = render(&scene(0.0), &opts(1024, 8), &no_progress).unwrap();
    let rough = render(&scene(0.01), &opts(1024, 8), &no_progress).unwrap();
    for (passes, tol) in [
        (&["Combined"][..], 0.02),
        (&["GlossDir", "GlossInd"][..], 0.03),
        (&["TransDir", "TransInd"][..], 0.03),
        (&["DiffDir", "DiffInd"][..], 0.02),
    ] {
        let a: f64 = passes.iter().map(|p| pass_mean(&smooth, p)).sum();
        let b: f64 = passes.iter().map(|p| pass_mean(&rough, p)).sum();
        assert!((a - b).abs() <= tol * a, "{passes:?}: smooth {a} vs roughness 0.01 {b}");
    }
}

#[test]
fn normal_map_bends_the_shading_normal_as_blenders_tangent_space() {
    // A Lambertian floor (y = 0) with a constant tangent-space normal map (EXR, linear) under a
    // delta sun of strength E. The floor is the XY quad turned −90° about X; its u grows along
    // +X and its v (0 at the texture's top row) along +Z, so Blender's v (towards the top row)
    // grows along world −Z: T = +X, B = −Z, N = +Y. A texel c encodes n = 2c − 1 in (T, B, N):
    // tilting by t = 40° towards T gives n = (sin t, cos t, 0), towards B n = (0, cos t, −sin t).
    // DiffDir = E·max(0, n·l)/π for the direction l towards the sun: E/π for a sun along n,
    // E·cos 2t/π for the sun mirrored about N (so a wrong sign of T or B swaps the two), and
    // E·cos t/π either way without the map. (A "delta" sun still spreads its directions over
    // 4.5e-4 rad, ≤ 2.6e-3 of relative spread at 80° from the normal: the tolerance.)
    let (e, t) = (3.0f64, 40f64.to_radians());
    let w = 8;
    let dir = tempfile::tempdir().unwrap();
    for (k, (ts, n)) in [
        ([t.sin(), 0.0, t.cos()], [t.sin(), t.cos(), 0.0]),
        ([0.0, t.sin(), t.cos()], [0.0, t.cos(), -t.sin()]),
    ]
    .into_iter()
    .enumerate()
    {
        let name = format!("n{k}.exr");
        let img = pixl_core::Image::from_fn(2, 2, 3, |_, _, c| (0.5 + 0.5 * ts[c]) as f32);
        pixl_core::io::write_image(&dir.path().join(&name), &img).unwrap();
        let mirrored = [-n[0], n[1], -n[2]];
        for (mapped, towards, want) in [
            (true, n, 1.0),
            (true, mirrored, (2.0 * t).cos()),
            (false, n, t.cos()),
            (false, mirrored, t.cos()),
        ] {
            let mut s = floor_scene([0.5, 0.5, 0.5], w);
            s.base_dir = dir.path().to_owned();
            if mapped {
                s.objects[0].material.normal_texture = Some(name.clone().into());
            }
            s.lights.push(Light::Sun {
                name: String::new(),
                direction: Some(towards.map(|v| -v as f32)),
                strength: e as f32,
                angle_deg: 0.0,
                color: Color::Rgb([1.0, 1.0, 1.0]),
            });
            let film = render(&s, &opts(4, 0), &no_progress).unwrap();
            let d = film.pass("DiffDir").unwrap();
            let want = e * want / PI;
            for v in d.data.iter() {
                assert!(
                    (*v as f64 - want).abs() < 3e-3 * want,
                    "map {k}, mapped {mapped}, sun towards {towards:?}: DiffDir {v} vs {want}"
                );
            }
        }
    }
}

/// Per-point light choice with MIS on a scene of one strong and several weak lights: a
/// Lambertian floor under a strong sphere light, a weak point light, a weak sun with a cone and
/// a dim constant sky. Each one's irradiance is closed-form wherever it is wholly above the
/// horizon (sphere and point: `I cos θ / d²`; sun: `E cos θ`; sky: `π L`), so the image mean of
/// DiffDir must be their sum / π, with light sampling (picked per point), BSDF rays hitting
/// the sphere, the sun and the sky, and both weighted by MIS with the per-point pick probability.
#[test]
fn strong_and_weak_lights_picked_per_point_sum_to_the_analytic_irradiance() {
    let w = 16u32;
    let mut s = floor_scene([0.5, 0.5, 0.5], w);
    let (lx, ly, lz, power, radius) = (0.3f64, 1.5f64, -0.2f64, 300.0f64, 0.4f32);
    s.lights.push(Light::Point {
        name: String::new(),
        position: [lx as f32, ly as f32, lz as f32],
        power: power as f32,
        radius,
        color: Color::Rgb([1.0, 1.0, 1.0]),
        visible_to_camera: false,
    });
    let (qx, qy, qz, qpower) = (-1.5f64, 0.8f64, 1.0f64, 8.0f64);
    s.lights.push(Light::Point {
        name: String::new(),
        position: [qx as f32, qy as f32, qz as f32],
        power: qpower as f32,
        radius: 0.0,
        color: Color::Rgb([1.0, 1.0, 1.0]),
        visible_to_camera: false,
    });
    let (sun_d, sun_e) = ([0.3f64, -1.0, 0.2], 0.3f64);
    s.lights.push(Light::Sun {
        name: String::new(),
        direction: Some(sun_d.map(|v| v as f32)),
        strength: sun_e as f32,
        angle_deg: 10.0,
        color: Color::Rgb([1.0, 1.0, 1.0]),
    });
    let sky = 0.04f64;
    s.world = Some(World {
        color: Color::Rgb([sky as f32; 3]),
        strength: 1.0,
        image: None,
        rotation_deg: 0.0,
    });
    let film = render(&s, &opts(128, 0), &no_progress).unwrap();
    let dir = film.pass("DiffDir").unwrap();
    let sl = (sun_d[0] * sun_d[0] + sun_d[1] * sun_d[1] + sun_d[2] * sun_d[2]).sqrt();
    let (mut got, mut want) = (0.0f64, 0.0f64);
    for y in 0..w as usize {
        for x in 0..w as usize {
            got += dir.get(x, y, 0) as f64;
            for j in 0..8 {
                for i in 0..8 {
                    let (fx, fz) = floor_point(x as f64 + (i as f64 + 0.5) / 8.0, y as f64 + (j as f64 + 0.5) / 8.0, w);
                    let mut e = sun_e * (-sun_d[1] / sl) + PI * sky;
                    for (px_, py_, pz_, p) in [(lx, ly, lz, power), (qx, qy, qz, qpower)] {
                        let (dx, dy, dz) = (px_ - fx, py_, pz_ - fz);
                        let d2 = dx * dx + dy * dy + dz * dz;
                        e += p / (4.0 * PI) * (dy / d2.sqrt()) / d2;
                    }
                    want += e / PI / 64.0;
                }
            }
        }
    }
    assert!(
        got.is_finite() && (got - want).abs() < 0.005 * want,
        "DiffDir sum {got} vs {want}"
    );
}

/// An image world lights a Lambertian floor with `E = ∫ L(ω) cos θ dω` over the upper
/// hemisphere (computed here by a midpoint rule through the renderer's own lookup), sampled by
/// importance (luminance × sin θ) and by the BSDF, combined with MIS; a bright small spot in
/// the image makes uniform sampling noisy, importance sampling not.
#[test]
fn image_world_lights_a_plane_with_its_cosine_weighted_integral() {
    use pixl_render::light::Environment;
    use pixl_render::texture::Texture;
    let dir = tempfile::tempdir().unwrap();
    let (iw, ih) = (64usize, 32usize);
    let img = pixl_core::Image::from_fn(iw, ih, 3, |x, y, c| {
        if (40..42).contains(&x) && (9..11).contains(&y) {
            [300.0, 200.0, 100.0][c]
        } else {
            0.02 + 0.1 * (y as f32 / ih as f32) * [1.0, 0.8, 0.6][c]
        }
    });
    pixl_core::io::write_image(&dir.path().join("sky.exr"), &img).unwrap();
    let w = 12u32;
    let mut s = floor_scene([0.5, 0.5, 0.5], w);
    s.base_dir = dir.path().to_owned();
    s.world = Some(World {
        color: Color::Rgb([1.0, 1.0, 1.0]),
        strength: 0.5,
        image: Some("sky.exr".into()),
        rotation_deg: 40.0,
    });
    let env = Environment {
        radiance: pixl_render::math::V3::splat(0.5),
        image: Some(Texture::from_image(img)),
        rotation: 40f32.to_radians(),
    };
    let (nt, np) = (600, 1200);
    let mut e = [0.0f64; 3];
    for i in 0..nt {
        let theta = 0.5 * PI * (i as f64 + 0.5) / nt as f64;
        for j in 0..np {
            let phi = 2.0 * PI * (j as f64 + 0.5) / np as f64;
            let d = pixl_render::math::V3::new(
                (theta.sin() * phi.cos()) as f32,
                theta.cos() as f32,
                (theta.sin() * phi.sin()) as f32,
            );
            // `eval(d)`: the radiance a ray travelling along `d` finds (the sky above: d.y > 0).
            let l = env.eval(d);
            let k = theta.cos() * theta.sin() * (0.5 * PI / nt as f64) * (2.0 * PI / np as f64);
            e[0] += l.x as f64 * k;
            e[1] += l.y as f64 * k;
            e[2] += l.z as f64 * k;
        }
    }
    let film = render(&s, &opts(64, 0), &no_progress).unwrap();
    let d = film.pass("DiffDir").unwrap();
    for c in 0..3 {
        let mean = (0..(w * w) as usize).map(|p| d.data[p * 3 + c] as f64).sum::<f64>() / (w * w) as f64;
        let want = e[c] / PI;
        assert!(
            (mean - want).abs() < 0.01 * want,
            "channel {c}: DiffDir {mean} vs {want}"
        );
        // Importance sampling keeps every pixel close (6 % rms when written).
        let rms = ((0..(w * w) as usize)
            .map(|p| (d.data[p * 3 + c] as f64 - want).powi(2))
            .sum::<f64>()
            / (w * w) as f64)
            .sqrt();
        // (Uniform sphere sampling finds the spot in 0.25 % of samples: ~250 % rms at 64 spp.)
        assert!(
            rms < 0.1 * want,
            "channel {c}: pixels deviate by {rms} (rms) from {want}"
        );
    }
}
