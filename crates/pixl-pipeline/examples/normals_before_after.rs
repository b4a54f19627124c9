//! What shading normals add to a coarse reconstruction: the C_T diffuse shading of the bundled
//! demo scene's reconstruction from a smooth depth (as a monocular estimator returns it) with the
//! mesh's own normals, with a normal map, and from the exact depth with the normal map.
//!
//! ```text
//! cargo run --release -p pixl-pipeline --example normals_before_after -- OUT.png \
//!     [--size 320x256] [--spp 64] [--blur 4] [--preset cool-side-flash]
//! ```
//! The demo scene (`assets/demo/scene.toml`) is path-traced once; its picture is the "photo",
//! its `Depth` pass averaged over the `(2·blur + 1)²` pixels around each within 5 % of its depth
//! the smooth depth, and its `Normal`
//! pass, turned into the camera's frame, the normal map — what a perfect normals estimator
//! (Marigold Normals in `pixl reconstruct --normals marigold`) would return. Each reconstruction
//! is built by `pixl_pipeline::reconstruct` (the code behind `pixl reconstruct`), lit by the
//! preset, rendered at `spp` and composed into C_T. Prints the PSNR of the first two shadings
//! against the third and writes `OUT.png`: photo | smooth depth, mesh normals | smooth depth,
//! normal map | exact depth, normal map (shading shown as sRGB of its [0, 1] values).
use pixl_core::Image;
use pixl_pipeline::exif::{Focal, FocalSource};
use pixl_pipeline::reconstruct::{reconstruct, Maps, MeshSettings};
use pixl_pipeline::render::{render_intrinsics, RenderSettings};
use pixl_pipeline::{Photo, Silent};
use pixl_render::depth::DepthMap;
use pixl_render::scene::Scene;
use pixl_render::RenderOptions;
use std::path::PathBuf;

type Res<T> = Result<T, Box<dyn std::error::Error>>;

struct Args {
    out: PathBuf,
    size: (usize, usize),
    spp: u32,
    blur: usize,
    preset: String,
}

fn parse() -> Res<Args> {
    let mut a = Args {
        out: PathBuf::new(),
        size: (320, 256),
        spp: 64,
        blur: 4,
        preset: "cool-side-flash".into(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(s) = it.next() {
        let mut val = || it.next().ok_or_else(|| format!("{s} needs a value"));
        match s.as_str() {
            "--size" => {
                let v = val()?;
                let (w, h) = v.split_once('x').ok_or("--size: WxH")?;
                a.size = (w.parse()?, h.parse()?);
            }
            "--spp" => a.spp = val()?.parse()?,
            "--blur" => a.blur = val()?.parse()?,
            "--preset" => a.preset = val()?,
            _ if s.starts_with('-') => return Err(format!("unknown option {s}").into()),
            _ => a.out = PathBuf::from(s),
        }
    }
    if a.out.as_os_str().is_empty() {
        return Err("usage: normals_before_after OUT.png [--size WxH] [--spp N] [--blur R] [--preset NAME]".into());
    }
    Ok(a)
}

/// Mean of the depths within `(2r + 1)²` of each pixel that lie within 5 % of its own (edges
/// stay sharp, as a monocular estimator keeps them; the surfaces' fine shape is lost).
fn blur_depth(d: &Image, r: usize) -> Image {
    let (w, h) = (d.width, d.height);
    Image::from_fn(w, h, 1, |x, y, _| {
        let centre = d.get(x, y, 0);
        let (mut sum, mut n) = (0.0f64, 0usize);
        for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
            for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                let v = d.get(xx, yy, 0);
                if v.is_finite() && v > 0.0 && v < 1e9 && (v / centre - 1.0).abs() < 0.05 {
                    sum += v as f64;
                    n += 1;
                }
            }
        }
        if n == 0 {
            d.get(x, y, 0)
        } else {
            (sum / n as f64) as f32
        }
    })
}

/// The world-space `Normal` pass in the camera's frame (X right, Y up, Z towards the camera).
fn camera_normals(world: &Image, scene: &Scene) -> Image {
    let (_, r, u, b) = scene.camera.frame();
    Image::from_fn(world.width, world.height, 3, |x, y, c| {
        let n = [world.get(x, y, 0), world.get(x, y, 1), world.get(x, y, 2)];
        let axis = [r, u, b][c];
        n[0] * axis[0] + n[1] * axis[1] + n[2] * axis[2]
    })
}

fn psnr(a: &Image, b: &Image) -> f64 {
    let mse = a
        .data
        .iter()
        .zip(&b.data)
        .map(|(x, y)| ((x.clamp(0.0, 1.0) - y.clamp(0.0, 1.0)) as f64).powi(2))
        .sum::<f64>()
        / a.data.len() as f64;
    10.0 * (1.0 / mse.max(1e-12)).log10()
}

fn main() -> Res<()> {
    let args = parse()?;
    let (w, h) = args.size;
    let scene_path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo/scene.toml");
    let scene = Scene::load(&scene_path)?;
    let opts = RenderOptions {
        spp: args.spp,
        width: Some(w as u32),
        height: Some(h as u32),
        ..RenderOptions::default()
    };
    let film = pixl_render::render(&scene, &opts, &|_, _| {})?;
    let photo_img = film.combined_srgb();
    let depth = film.pass("Depth").ok_or("no Depth pass")?;
    let normals = camera_normals(&film.pass("Normal").ok_or("no Normal pass")?, &scene);
    let focal = Focal {
        px: scene.camera.focal_for_height(h as u32) as f64,
        source: FocalSource::Flag,
    };
    let photo = Photo::from_image(photo_img.clone(), focal);
    let smooth = blur_depth(&depth, args.blur);
    let settings = RenderSettings {
        spp: args.spp,
        ..RenderSettings::default()
    };
    let shading = |d: &Image, n: Option<&Image>| -> Res<Image> {
        let map = DepthMap::new(w, h, d.data.clone())?;
        let maps = Maps {
            normals: n.cloned(),
            ..Maps::default()
        };
        let mut geo = reconstruct(&photo, &map, "the depth", &maps, &MeshSettings::default(), &Silent)?;
        pixl_render::presets::apply_preset(&mut geo.scene, &args.preset, true)?;
        let (_, composed) = render_intrinsics(&geo.scene, (w, h), &settings, &Silent)?;
        Ok(composed.ct.shading)
    };
    let before = shading(&smooth, None)?;
    let after = shading(&smooth, Some(&normals))?;
    let exact = shading(&depth, Some(&normals))?;
    println!(
        "{w}x{h}, {} spp, depth blur radius {}, preset {}: C_T shading PSNR against the exact depth with the \
         normal map: mesh normals {:.2} dB, normal map {:.2} dB",
        args.spp,
        args.blur,
        args.preset,
        psnr(&before, &exact),
        psnr(&after, &exact)
    );
    let show = |s: &Image| s.map(|v| pixl_core::image::linear_to_srgb(v.clamp(0.0, 1.0)));
    let panels = [photo_img, show(&before), show(&after), show(&exact)];
    let sheet = Image::from_fn(4 * w, h, 3, |x, y, c| panels[x / w].get(x % w, y, c));
    pixl_core::io::write_png(&args.out, &sheet, pixl_core::io::PngDepth::Eight)?;
    println!("wrote {}", args.out.display());
    Ok(())
}
