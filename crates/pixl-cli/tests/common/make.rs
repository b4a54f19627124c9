//! What the binary itself makes for other tests, and argument lists several tests share.
use super::run::pixl;
use super::s;
use std::path::{Path, PathBuf};

/// Fresh `tiny` weights of `seed` at `path` (`pixl model init`); returns the path.
#[track_caller]
pub fn tiny_weights(path: &Path, seed: u64) -> PathBuf {
    pixl(&[
        "-q",
        "model",
        "init",
        "--config",
        "tiny",
        "--seed",
        &seed.to_string(),
        "-o",
        s(path),
    ])
    .ok();
    path.to_owned()
}

/// `pixl synth` of a tiny set into `out`: two scenes (the second a test scene) of two lights,
/// `size` pixels square at `spp` samples a pixel, then `extra`.
pub fn synth_args<'a>(out: &'a str, size: &'a str, spp: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec![
        "synth",
        "--scenes",
        "2",
        "--lights",
        "2",
        "--size",
        size,
        "--spp",
        spp,
        "--test-every",
        "2",
        "-o",
        out,
    ];
    v.extend_from_slice(extra);
    v
}

/// `pixl relight` of a photo under a C_T with weights, into `out` (the form with `--source`).
pub fn relight_args<'a>(src: &'a Path, ct: &'a Path, weights: &'a Path, out: &'a Path) -> Vec<&'a str> {
    vec![
        "relight",
        "--source",
        s(src),
        "--intrinsics",
        s(ct),
        "--weights",
        s(weights),
        "--out",
        s(out),
    ]
}
