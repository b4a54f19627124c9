//! The fake multi-illumination scenes shared by the integration tests: a 4-pixel checker albedo
//! (values 0.2 / 0.5 / 0.8, shifted per scene and channel) under per-light linear shading
//! gradients, no residual; images are the clipped sRGB recomposition, beside their exact C_T.
#![allow(dead_code)] // each test binary uses its own subset
use pixl_core::Image;
use pixl_intrinsics::ct::{write_ct, Ct};
use std::path::Path;

/// The albedo of fake scene `scene`.
pub fn albedo(size: usize, scene: usize) -> Image {
    Image::from_fn(size, size, 3, |x, y, c| {
        0.2 + 0.6 * (((x / 4 + y / 4 + scene + c) % 3) as f32) / 2.0
    })
}

/// The shading of light `light`: light 0 falls 0.5 → 0.1 left to right, light 1 rises 0.5 → 0.7
/// downwards, further lights tilt both ways; clamped to [0.05, 1].
pub fn shading(size: usize, light: usize) -> Image {
    Image::from_fn(size, size, 3, |x, y, _| {
        let d = (x as f32 * (light as f32 - 1.0) + y as f32 * (light as f32 * 0.5)) / size as f32;
        (0.5 + 0.4 * d).clamp(0.05, 1.0)
    })
}

/// The displayed image of `ct`: `sRGB(clip(A ⊙ S + R))`.
pub fn srgb(ct: &Ct) -> Image {
    ct.recompose()
        .map(|v| pixl_core::image::linear_to_srgb(v.clamp(0.0, 1.0)))
}

/// `root/scene<s>/l<l>.png` and `l<l>.intrinsics.exr` for `scenes × lights` images of `size`².
pub fn fake_set(root: &Path, scenes: usize, lights: usize, size: usize) {
    for s in 0..scenes {
        let dir = root.join(format!("scene{s}"));
        std::fs::create_dir_all(&dir).unwrap();
        let albedo = albedo(size, s);
        for l in 0..lights {
            let ct = Ct::new(albedo.clone(), shading(size, l), Image::new(size, size, 3)).unwrap();
            pixl_core::io::write_image(&dir.join(format!("l{l}.png")), &srgb(&ct)).unwrap();
            write_ct(&dir.join(format!("l{l}.intrinsics.exr")), &ct).unwrap();
        }
    }
}
