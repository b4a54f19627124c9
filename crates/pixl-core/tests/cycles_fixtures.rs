//! Reads the real Blender 5 Cycles renders bundled in `fixtures/cycles/`: one multi-part f32
//! file and one single-part half-float file of the same scene.
use pixl_core::exrio::read_exr_channels;
use std::path::PathBuf;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../fixtures/cycles")
        .join(name)
}

#[test]
fn multipart_and_singlepart_agree() {
    let multi = read_exr_channels(&fixture("scene256_multipart.exr")).unwrap();
    let single = read_exr_channels(&fixture("scene256_singlepart_half.exr")).unwrap();
    assert_eq!((multi.width, multi.height), (256, 256));
    assert_eq!((single.width, single.height), (256, 256));
    for name in [
        "ViewLayer.Diffuse Direct.R",
        "ViewLayer.Diffuse Color.G",
        "ViewLayer.Combined.A",
        "ViewLayer.Depth.Z",
    ] {
        assert!(
            multi.get(name).is_some(),
            "multi-part lacks {name}: {:?}",
            multi.names().collect::<Vec<_>>()
        );
        assert!(
            single.get(name).is_some(),
            "single-part lacks {name}: {:?}",
            single.names().collect::<Vec<_>>()
        );
    }
    // Same scene, same seed; half floats and ~1 % of pixels differing between renders.
    let a = multi.get("ViewLayer.Diffuse Color.G").unwrap();
    let b = single.get("ViewLayer.Diffuse Color.G").unwrap();
    let mean_abs: f64 = a.iter().zip(b).map(|(x, y)| (x - y).abs() as f64).sum::<f64>() / a.len() as f64;
    assert!(mean_abs < 0.01, "mean |multi - single| = {mean_abs}");
    assert!(a.iter().all(|v| v.is_finite()));
}

#[test]
fn truncated_file_is_an_error_not_a_panic() {
    let bytes = std::fs::read(fixture("scene256_singlepart_half.exr")).unwrap();
    for cut in [0, 4, 100, bytes.len() / 2, bytes.len() - 10] {
        let r = pixl_core::exrio::read_exr_channels_from_bytes(&bytes[..cut], std::path::Path::new("cut.exr"));
        assert!(r.is_err(), "truncated at {cut} read fine");
        assert!(r.unwrap_err().to_string().contains("cut.exr"));
    }
}
