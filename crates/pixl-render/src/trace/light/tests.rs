//! Tests of the lights: pick probabilities, light samples against analytic irradiance and
//! against the pdfs of BSDF hits, packets against single lanes, the spherical rectangle and the
//! world image's sampler.
use super::env::{env_peak_share, EnvSampler};
use super::pick::CACHED;
use super::rect::{acos_poly, rect_point, RectView};
use super::*;
use crate::math::V3;
use crate::scene::Scene;
use crate::trace::bvh::Ray;
use crate::trace::geometry::Geometry;
use crate::trace::sampling::uniform_sphere;
use crate::trace::texture::Texture;
use pixl_core::{Image, Rng};
use std::f32::consts::PI;

fn lights_of(src: &str) -> (Geometry, Lights) {
    let scene = Scene::from_toml_str(src).expect("scene");
    let mut geom = Geometry::build(&scene).expect("geometry");
    let lights = Lights::build(&scene, &mut geom).expect("lights");
    (geom, lights)
}

/// Eleven analytic lights (more than a pick caches) of every kind, some of which cannot reach
/// part of the space (a one-sided area light facing up, a narrow spot), and an emissive panel.
const MANY: &str = r#"
    [camera]
    width = 8
    height = 8
    fov_y_deg = 50.0
    position = [0.0, 1.0, 4.0]
    look_at = [0.0, 0.5, 0.0]

    [[objects]]
    name = "floor"
    shape = { type = "quad", size = [6.0, 6.0] }
    transform = { rotate_deg = [-90.0, 0.0, 0.0] }
    material = { base_color = [0.7, 0.6, 0.5] }

    [[objects]]
    name = "panel"
    shape = { type = "quad", size = [0.5, 0.5] }
    transform = { translate = [0.0, 1.2, -1.5] }
    material = { base_color = [0.1, 0.1, 0.1], emission_color = [1.0, 0.8, 0.6], emission_strength = 3.0 }

    [[lights]]
    type = "point"
    position = [-1.5, 1.5, 1.5]
    power = 80.0
    radius = 0.2

    [[lights]]
    type = "point"
    position = [1.5, 0.3, 0.5]
    power = 5.0

    [[lights]]
    type = "point"
    position = [0.0, 3.0, -2.0]
    power = 300.0
    radius = 0.05

    [[lights]]
    type = "spot"
    position = [0.0, 2.0, 0.0]
    direction = [0.0, -1.0, 0.0]
    spot_size_deg = 20.0
    blend = 0.0
    power = 200.0

    [[lights]]
    type = "spot"
    position = [1.0, 2.0, 1.0]
    direction = [0.0, -1.0, 0.0]
    spot_size_deg = 60.0
    blend = 0.5
    power = 100.0
    radius = 0.1

    [[lights]]
    type = "area"
    position = [1.0, 2.5, 1.0]
    look_at = [0.0, 0.0, 0.0]
    size = 1.0
    power = 150.0

    [[lights]]
    type = "area"
    position = [0.0, 0.5, 0.0]
    direction = [0.0, 1.0, 0.0]
    shape = "disk"
    size = 0.4
    power = 40.0

    [[lights]]
    type = "area"
    position = [-2.0, 1.0, 0.0]
    direction = [1.0, 0.0, 0.0]
    size = 0.5
    power = 20.0

    [[lights]]
    type = "sun"
    direction = [0.3, -1.0, -0.4]
    strength = 2.0
    angle_deg = 5.0

    [[lights]]
    type = "sun"
    direction = [-0.5, -0.2, 0.1]
    strength = 0.5

    [world]
    color = [0.2, 0.25, 0.3]
"#;

/// Whether light `i` can send any light to `p` (by any sampling technique).
fn can_reach(lights: &Lights, i: usize, p: V3) -> bool {
    match &lights.lights[i] {
        LightKind::Area { c, n, .. } => (p - *c).dot(*n) > 0.0,
        l @ LightKind::Spot { p: lp, .. } => l.spot_mask(p - *lp) > 0.0,
        // A constant world is left to BSDF samples.
        LightKind::Env => lights.env_peaked > 0.0,
        _ => true,
    }
}

fn random_point(rng: &mut Rng) -> ShadingPoint {
    ShadingPoint {
        p: V3::new(6.0 * rng.f32() - 3.0, 3.0 * rng.f32() - 0.2, 6.0 * rng.f32() - 3.0),
        n: uniform_sphere(rng.f32(), rng.f32()),
        two_sided: rng.f32() < 0.25,
        solid_angle: rng.f32() < 0.5,
    }
}

#[test]
fn pick_probabilities_sum_to_one_and_are_positive_wherever_a_light_can_reach() {
    let (_, lights) = lights_of(MANY);
    assert!(
        lights.analytic == 11 && lights.items() > CACHED,
        "{} analytic lights",
        lights.analytic
    );
    assert!(lights.lights.len() > lights.analytic, "emissive triangles are lights");
    let mut rng = Rng::new(5);
    let (mut unreachable, mut floor_only) = (0, 0);
    for _ in 0..2000 {
        let sp = random_point(&mut rng);
        let pick = lights.pick_at(sp);
        let mut sum = 0.0f64;
        for i in 0..lights.lights.len() {
            let pmf = lights.pick_pmf_at(&pick, i);
            sum += pmf as f64;
            let reach = can_reach(&lights, i, sp.p);
            assert_eq!(
                pmf > 0.0,
                reach,
                "light {i} at {:?}: pmf {pmf}, reachable {reach}",
                sp.p
            );
            unreachable += !reach as usize;
            if i < lights.analytic && reach {
                // Every reachable light keeps at least its share of the power floor.
                assert!(pmf >= PICK_FLOOR * lights.base.pmf(i) * 0.999);
                floor_only += (lights.item_weight(i, &sp) == Some(0.0)) as usize;
            }
        }
        assert!(
            (sum - 1.0).abs() < 1e-5,
            "pick probabilities at {:?} sum to {sum}",
            sp.p
        );
    }
    // The scene exercises lights that cannot reach a point and ones whose estimate is 0
    // (facing away) but that still get the floor.
    assert!(
        unreachable > 500 && floor_only > 500,
        "{unreachable} unreachable, {floor_only} floor only"
    );
}

/// With one light (and a constant world, which is never light-sampled) the choice skips the
/// weights: the light is picked wherever it can reach the point, as the weights would say.
#[test]
fn a_single_light_is_picked_wherever_it_can_reach() {
    let src = MANY.split("[[lights]]").next().expect("head").to_string()
        + "[[lights]]\ntype = \"area\"\nposition = [1.0, 2.5, 1.0]\nlook_at = [0.0, 0.0, 0.0]\nsize = 1.0\npower = 150.0\n"
        + "[world]\ncolor = [0.2, 0.25, 0.3]\n";
    let (_, lights) = lights_of(&src.replace("emission_strength = 3.0", "emission_strength = 0.0"));
    assert_eq!((lights.items(), lights.single_item()), (2, Some(0)));
    // The pick probability the general formula gives a lone item, exactly.
    assert_eq!((1.0 - PICK_FLOOR) * (1.0 / 1.0) + PICK_FLOOR * (0.7 / 0.7), 1.0);
    let mut rng = Rng::new(2);
    for _ in 0..1000 {
        let sp = random_point(&mut rng);
        let pick = lights.pick_at(sp);
        let p = lights.pick_pmf_at(&pick, 0);
        assert_eq!(p, if can_reach(&lights, 0, sp.p) { 1.0 } else { 0.0 });
        assert_eq!(lights.item_weight(0, &sp).is_some(), lights.item_reaches(0, &sp));
        assert_eq!(lights.pick_pmf_at(&pick, 1), 0.0);
    }
}

#[test]
fn lights_are_chosen_with_their_pick_probabilities() {
    let (_, lights) = lights_of(MANY);
    let mut rng = Rng::new(9);
    for _ in 0..5 {
        let pick = lights.pick_at(random_point(&mut rng));
        let mut counts = vec![0usize; lights.lights.len()];
        let n = 200_000;
        for k in 0..n {
            let u = (k as f32 + 0.5) / n as f32;
            let (i, p) = lights.choose(&pick, u).expect("a light");
            assert_eq!(p, lights.pick_pmf_at(&pick, i));
            counts[i] += 1;
        }
        for (i, c) in counts.iter().enumerate() {
            let (f, p) = (*c as f64 / n as f64, lights.pick_pmf_at(&pick, i) as f64);
            assert!((f - p).abs() < 2e-4, "light {i}: frequency {f} vs pmf {p}");
        }
    }
}

/// Light sampling at a point under a strong disk light, a weak point light off to the
/// side, a sun and a dim constant sky: the mean of `Li cos / pdf` is the analytic irradiance
/// of the lights (the sky is left to BSDF samples), and most picks go to the strong light.
#[test]
fn light_sampling_with_per_point_choice_gives_the_analytic_irradiance() {
    let (r, h, power) = (0.5f64, 1.5f64, 300.0f64);
    let (pp, pl) = ([2.0f64, 0.5, 1.0], 10.0f64);
    let (sun, sun_dir) = (0.4f64, [0.2f64, -1.0, 0.3]);
    let sky = 0.05f64;
    let src = format!(
        r#"
        [camera]
        width = 4
        height = 4
        fov_y_deg = 50.0
        position = [0.0, 5.0, 5.0]
        look_at = [0.0, 0.0, 0.0]

        [[objects]]
        name = "far"
        shape = {{ type = "quad", size = [1.0, 1.0] }}
        transform = {{ translate = [20.0, -5.0, 0.0] }}
        material = {{ base_color = [0.5, 0.5, 0.5] }}

        [[lights]]
        type = "area"
        shape = "disk"
        position = [0.0, {h}, 0.0]
        direction = [0.0, -1.0, 0.0]
        size = {d}
        power = {power}

        [[lights]]
        type = "point"
        position = [{}, {}, {}]
        power = {pl}

        [[lights]]
        type = "sun"
        direction = [{}, {}, {}]
        strength = {sun}

        [world]
        color = [{sky}, {sky}, {sky}]
        "#,
        pp[0],
        pp[1],
        pp[2],
        sun_dir[0],
        sun_dir[1],
        sun_dir[2],
        d = 2.0 * r,
    );
    let (geom, lights) = lights_of(&src);
    // At the origin, normal +Y. Disk of radiance L = P / (π · πr²) on the axis at height h:
    // E = π L r² / (h² + r²). Point: E = P/(4π) · cos / d². Sun: E = strength · cos. Sky
    // over the upper hemisphere: E = π L.
    let l_disk = power / (PI as f64 * PI as f64 * r * r);
    let e_disk = PI as f64 * l_disk * r * r / (h * h + r * r);
    let d2 = pp.iter().map(|v| v * v).sum::<f64>();
    let e_point = pl / (4.0 * PI as f64) * (pp[1] / d2.sqrt()) / d2;
    let sl = sun_dir.iter().map(|v| v * v).sum::<f64>().sqrt();
    let e_sun = sun * (-sun_dir[1] / sl);
    // The constant sky is left to BSDF samples (never light-sampled).
    let e_sky = 0.0;
    let expect = e_disk + e_point + e_sun + e_sky;
    let n = V3::new(0.0, 1.0, 0.0);
    let pick = lights.pick_at(ShadingPoint {
        p: V3::ZERO,
        n,
        two_sided: false,
        solid_angle: false,
    });
    assert!(lights.pick_pmf_at(&pick, 0) > 0.8, "the strong light gets most picks");
    let mut rng = Rng::new(11);
    let samples = 1_000_000;
    let mut sum = 0.0f64;
    for _ in 0..samples {
        if let Some(ls) = lights.sample(&geom, &pick, rng.f32(), rng.f32(), rng.f32()) {
            let cos = ls.wi.dot(n).max(0.0) as f64;
            sum += ls.li.x as f64 * cos / ls.pdf as f64;
        }
    }
    let mean = sum / samples as f64;
    assert!(
        (mean - expect).abs() < 0.005 * expect,
        "estimate {mean} vs analytic {expect} (disk {e_disk}, point {e_point}, sun {e_sun}, sky {e_sky})"
    );
}

/// The pdf a light sample reports is the one the BSDF side computes for the same direction
/// (pick probability × direction pdf), for every light hit by rays.
#[test]
fn light_sample_pdfs_match_the_pdfs_of_bsdf_hits() {
    // With an image world (a constant one is not light-sampled).
    let dir = tempfile::tempdir().expect("temp dir");
    let sky = dir.path().join("sky.exr");
    pixl_core::io::write_image(&sky, spot_image().image()).expect("sky image");
    let src = MANY.replace(
        "color = [0.2, 0.25, 0.3]",
        &format!("image = {:?}\nstrength = 0.2", sky),
    );
    let (geom, lights) = lights_of(&src);
    assert!(lights.env_sampler.is_some() && lights.env_peaked > 0.0);
    let mut rng = Rng::new(3);
    let mut checked = [0usize; 4];
    for _ in 0..20_000 {
        let sp = random_point(&mut rng);
        let pick = lights.pick_at(sp);
        let Some(ls) = lights.sample(&geom, &pick, rng.f32(), rng.f32(), rng.f32()) else {
            continue;
        };
        if ls.delta {
            continue;
        }
        let ray = Ray::new(sp.p, ls.wi);
        let clear = if ls.dist.is_finite() {
            ls.dist * (1.0 - 1e-3)
        } else {
            f32::INFINITY
        };
        if geom.occluded(&ray, 0.0, clear) {
            continue;
        }
        let mut found = Vec::new();
        let tmax = if ls.dist.is_finite() {
            ls.dist * 1.001
        } else {
            f32::INFINITY
        };
        lights.area_hits(&ray, tmax, |_, i, pdf, t| {
            found.push((lights.pick_pmf_at(&pick, i) * lights.area_dir_pdf(&pick, i, pdf), t, 0))
        });
        if !ls.dist.is_finite() {
            found.push((lights.env_pdf(&pick, ls.wi), f32::INFINITY, 1));
            lights.sun_hits(ls.wi, |_, i, pdf| {
                found.push((lights.pick_pmf_at(&pick, i) * pdf, f32::INFINITY, 2))
            });
        }
        let tri = geom
            .intersect(&ray, 0.0, tmax)
            .filter(|h| geom.attrs[h.prim as usize].light != u32::MAX);
        if let Some(h) = tri {
            found.push((lights.tri_pdf(&geom, &pick, h.prim, h.t, ls.wi.dot(h.ng).abs()), h.t, 3));
        }
        // The sampled light is the one at the sampled distance; its pdf must agree.
        let same = found.iter().find(|(pdf, t, _)| {
            ((t - ls.dist).abs() <= 1e-3 * ls.dist.max(1.0) || (t.is_infinite() && ls.dist.is_infinite()))
                && (pdf - ls.pdf).abs() <= 2e-3 * ls.pdf
        });
        let Some((_, _, kind)) = same else {
            panic!(
                "no BSDF-side pdf matches the light sample's {} at {:?}: {found:?}",
                ls.pdf, sp.p
            );
        };
        checked[*kind] += 1;
    }
    assert!(
        checked.iter().all(|&c| c > 100),
        "area/sphere, world, sun, triangle: {checked:?}"
    );
}

/// Spherical-rectangle sampling: the solid angle is the area integral `∫ cos_l / d² dA`,
/// sampled points lie on the rectangle, and the mean of `cos θ / pdf` over samples is the
/// irradiance integral `∫ cos θ cos_l / d² dA` (uniform in solid angle), for points near
/// the rectangle, far off its axis and nearly in its plane.
#[test]
fn spherical_rectangle_samples_its_solid_angle_uniformly() {
    let (c, ex, ey) = (V3::new(0.2, 1.0, -0.3), V3::new(0.6, 0.0, 0.0), V3::new(0.0, 0.3, 0.4));
    let n = ex.cross(ey).normalize();
    let recv = V3::new(0.1, 0.2, 1.0).normalize();
    for o in [
        V3::new(0.0, 0.0, 1.0),
        V3::new(1.5, 1.2, 0.8),
        V3::new(-0.3, 0.9, -0.2),
        V3::new(0.2, 1.0, 0.05),
    ] {
        let view = RectView::with_frame(o, c - ex - ey, &RectFrame::new(ex * 2.0, ey * 2.0)).expect("in front");
        let r = view.solid_angle().expect("large enough");
        let (mut omega, mut irr) = (0.0f64, 0.0f64);
        let m = 400;
        let da = (4.0 * ex.length() * ey.length()) as f64 / (m * m) as f64;
        for i in 0..m {
            for j in 0..m {
                let q =
                    c + ex * (2.0 * (i as f32 + 0.5) / m as f32 - 1.0) + ey * (2.0 * (j as f32 + 0.5) / m as f32 - 1.0);
                let d = q - o;
                let d2 = d.dot(d) as f64;
                let w = d / d.length();
                let cos_l = w.dot(n).abs() as f64;
                omega += cos_l / d2 * da;
                irr += cos_l / d2 * da * w.dot(recv).abs() as f64;
            }
        }
        assert!(
            (r.omega as f64 - omega).abs() < 2e-3 * omega,
            "Ω {} vs {omega} at {o:?}",
            r.omega
        );
        let mut rng = Rng::new(4);
        let samples = 200_000;
        let mut est = 0.0f64;
        for _ in 0..samples {
            let (x, y) = rect_point(&view.r, &r, rng.f32(), rng.f32());
            let q = view.point(o, &RectFrame::new(ex * 2.0, ey * 2.0), x, y);
            let local = q - c;
            let (a, b) = (local.dot(ex) / ex.dot(ex), local.dot(ey) / ey.dot(ey));
            assert!(
                a.abs() <= 1.0 + 1e-4 && b.abs() <= 1.0 + 1e-4 && local.dot(n).abs() < 1e-4,
                "{q:?} off the rectangle"
            );
            let w = (q - o).normalize();
            est += w.dot(recv).abs() as f64 * r.omega as f64;
        }
        let est = est / samples as f64;
        assert!((est - irr).abs() < 5e-3 * irr, "irradiance {est} vs {irr} at {o:?}");
    }
}

/// The packet form of the light sampling gives each lane what sampling it alone gives
/// (bit for bit), whatever the other lanes hold: lights of every kind, rectangles sampled
/// by solid angle (near) and by area (screened: far), and lanes without a sample.
#[test]
fn light_samples_of_a_packet_are_those_of_each_lane_alone() {
    // MANY's camera and objects, with a near rectangle and a far one instead of its lights.
    let far = MANY.split("[[lights]]").next().expect("head").to_string()
        + r#"
        [[lights]]
        type = "area"
        shape = "rectangle"
        position = [0.0, 2.0, 0.0]
        direction = [0.0, -1.0, 0.0]
        size = 1.0
        size_y = 0.5
        power = 100.0
        [[lights]]
        type = "area"
        position = [400.0, 3.0, 0.0]
        direction = [-1.0, 0.0, 0.0]
        size = 0.1
        power = 100.0
        "#;
    const L: usize = 16;
    for src in [MANY, far.as_str()] {
        let (geom, lights) = lights_of(src);
        let mut rng = Rng::new(11);
        for _ in 0..200 {
            let picks: Vec<LightPick> = (0..L).map(|_| lights.pick_at(random_point(&mut rng))).collect();
            let mut sampled = picks.clone();
            let us: Vec<[f32; 3]> = (0..L).map(|_| [rng.f32(), rng.f32(), rng.f32()]).collect();
            let live: Vec<bool> = (0..L).map(|_| rng.f32() < 0.8).collect();
            let mut it = sampled.iter_mut().enumerate();
            let lanes: [Option<(&mut LightPick, [f32; 3])>; L] = std::array::from_fn(|_| {
                let (l, pick) = it.next().expect("L picks");
                live[l].then_some((pick, us[l]))
            });
            let mut packet = [None; L];
            lights.sample_lanes(&geom, lanes, &mut packet);
            for l in 0..L {
                let alone = live[l]
                    .then(|| lights.sample(&geom, &picks[l], us[l][0], us[l][1], us[l][2]))
                    .flatten();
                let key = |s: &Option<LightSample>| {
                    s.map(|s| (s.wi.to_arr().map(f32::to_bits), s.dist.to_bits(), s.pdf.to_bits()))
                };
                assert_eq!(key(&packet[l]), key(&alone), "lane {l}");
                // The solid angle kept in the pick is the one computed afresh.
                for i in 0..lights.lights.len() {
                    assert_eq!(
                        lights.area_dir_pdf(&sampled[l], i, 0.5).to_bits(),
                        lights.area_dir_pdf(&picks[l], i, 0.5).to_bits()
                    );
                }
            }
        }
    }
}

#[test]
fn polynomial_arccos_is_within_5e7_of_f64() {
    // Every 2^-20 step over [−1, 1], the ends and their neighbours included.
    let mut worst = 0.0f64;
    let n = 1i32 << 20;
    for i in -n..=n {
        let x = i as f32 / n as f32;
        let err = (acos_poly(x) as f64 - (x as f64).acos()).abs();
        worst = worst.max(err);
    }
    for x in [1.0f32, -1.0, 1.0 - f32::EPSILON, -1.0 + f32::EPSILON, 0.0, -0.0] {
        worst = worst.max((acos_poly(x) as f64 - (x as f64).acos()).abs());
    }
    assert!(worst < 5e-7, "max error {worst}");
}

fn spot_image() -> Texture {
    // A dim gradient, a black band and a bright 2×2 spot.
    Texture::from_image(Image::from_fn(32, 16, 3, |x, y, c| {
        if (20..22).contains(&x) && (4..6).contains(&y) {
            [50.0, 40.0, 30.0][c]
        } else if (8..12).contains(&x) {
            0.0
        } else {
            0.05 + 0.01 * y as f32
        }
    }))
}

#[test]
fn only_the_light_of_a_world_above_its_mean_draws_light_samples() {
    let flat = Texture::from_image(Image::from_fn(16, 8, 3, |_, _, _| 0.3));
    assert!(env_peak_share(&flat).abs() < 1e-6);
    let peaked = env_peak_share(&spot_image());
    assert!(peaked > 0.5 && peaked < 1.0, "{peaked}");
    // A constant world is never light-sampled (BSDF samples find it).
    let (_, lights) = lights_of(MANY);
    let env = lights.env_index.expect("a world");
    let sp = ShadingPoint {
        p: V3::new(0.0, 0.01, 0.0),
        n: V3::new(0.0, 1.0, 0.0),
        two_sided: false,
        solid_angle: true,
    };
    let pick = lights.pick_at(sp);
    assert_eq!(lights.item_weight(env, &sp), None);
    assert_eq!(lights.pick_pmf_at(&pick, env), 0.0);
    assert_eq!(lights.env_pdf(&pick, V3::new(0.0, 1.0, 0.0)), 0.0);
}

#[test]
fn world_image_sampling_pdf_integrates_to_one_matches_a_histogram_and_covers_every_lit_direction() {
    let tex = spot_image();
    let rot = 30f32.to_radians();
    let s = EnvSampler::new(&tex, rot).expect("sampler");
    let env = Environment {
        radiance: V3::ONE,
        image: Some(tex),
        rotation: rot,
    };
    // ∫ pdf dω over the sphere, midpoint rule on a fine (θ, φ) grid.
    let (nt, np) = (400, 800);
    let mut integral = 0.0f64;
    for i in 0..nt {
        let theta = PI as f64 * (i as f64 + 0.5) / nt as f64;
        for j in 0..np {
            let phi = 2.0 * PI as f64 * (j as f64 + 0.5) / np as f64;
            let d = V3::new(
                (theta.sin() * phi.cos()) as f32,
                theta.cos() as f32,
                (theta.sin() * phi.sin()) as f32,
            );
            integral += s.pdf(d) as f64 * theta.sin() * (PI as f64 / nt as f64) * (2.0 * PI as f64 / np as f64);
        }
    }
    assert!((integral - 1.0).abs() < 2e-3, "∫ pdf = {integral}");
    // Samples: the reported pdf is the pdf of the direction, every sampled direction sees
    // light, and the sample counts per image cell follow the pdf.
    let mut rng = Rng::new(1);
    let n = 400_000;
    let (mut counts, mut lit, mut agree) = (vec![0usize; 32 * 16], 0, 0);
    let mut mc = 0.0f64;
    for _ in 0..n {
        let (d, pdf) = s.sample(rng.f32(), rng.f32()).expect("a direction");
        agree += ((s.pdf(d) - pdf).abs() <= 1e-3 * pdf) as usize;
        lit += (env.eval(d).luminance() > 0.0) as usize;
        mc += env.eval(d).luminance() as f64 / pdf as f64;
        let (sn, cs) = (-rot).sin_cos();
        let r = V3::new(cs * d.x + sn * d.z, d.y, -sn * d.x + cs * d.z);
        let u = 0.5 - (-r.z).atan2(r.x) / (2.0 * PI);
        let v = 0.5 - r.y.atan2((r.x * r.x + r.z * r.z).sqrt()) / PI;
        let (x, y) = (((u * 32.0) as usize).min(31), ((v * 16.0) as usize).min(15));
        counts[y * 32 + x] += 1;
    }
    assert!(agree as f64 > 0.999 * n as f64, "{agree} of {n} pdfs agree");
    // (Half of each cell next to the black band lies in the dark: a few samples are wasted.)
    assert!(
        lit as f64 > 0.995 * n as f64,
        "{lit} of {n} sampled directions see light"
    );
    for y in 0..16 {
        for x in 0..32 {
            let p = s.dist.pdf((x as f32 + 0.5) / 32.0, (y as f32 + 0.5) / 16.0) as f64 / (32.0 * 16.0);
            let f = counts[y * 32 + x] as f64 / n as f64;
            let sigma = (p * (1.0 - p) / n as f64).sqrt();
            assert!((f - p).abs() < 5.0 * sigma + 1e-5, "cell ({x}, {y}): {f} vs {p}");
            if (9..11).contains(&x) {
                assert_eq!(counts[y * 32 + x], 0, "the black band is never sampled");
            }
        }
    }
    // ∫ L dω: the importance-sampled estimate against the midpoint rule.
    let mut exact = 0.0f64;
    for i in 0..nt {
        let theta = PI as f64 * (i as f64 + 0.5) / nt as f64;
        for j in 0..np {
            let phi = 2.0 * PI as f64 * (j as f64 + 0.5) / np as f64;
            let d = V3::new(
                (theta.sin() * phi.cos()) as f32,
                theta.cos() as f32,
                (theta.sin() * phi.sin()) as f32,
            );
            let l = env.eval(d).luminance();
            // Wherever the world sends light, the sampler can sample it.
            assert!(!(l > 0.0) || s.pdf(d) > 0.0, "radiance {l} but pdf 0 along {d:?}");
            exact += l as f64 * theta.sin() * (PI as f64 / nt as f64) * (2.0 * PI as f64 / np as f64);
        }
    }
    let mc = mc / n as f64;
    assert!((mc - exact).abs() < 0.01 * exact, "{mc} vs {exact}");
}
