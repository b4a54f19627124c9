//! `pixl demo` end to end: the report exists and holds every panel for every preset, the default
//! weights are the bundled ones, and with `--exact-intrinsics` and freshly initialised weights the
//! relit image is the source and the path-traced render the ground truth, byte for byte.
mod common;

const PRESETS: [&str; 5] = [
    "cool-side-flash",
    "warm-overhead-flash",
    "dim-overhead-spot",
    "soft-frontal-sun",
    "warm-interior-sun",
];

#[test]
fn demo_writes_a_complete_report() {
    let dir = common::tempdir();
    let out = dir.path().join("demo");
    let o = common::pixl(&["demo", "--quiet", "--spp", "2", "--json", "--out", common::s(&out)]).ok();
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    let presets = PRESETS;
    assert!(
        html.contains("weights: bundled pixl-tiny-synth.safetensors"),
        "the bundled weights by default"
    );
    assert!(out.join("reconstruction").join("scene.toml").is_file());
    assert_eq!(html.matches("<section class=\"row\">").count(), presets.len());
    // The plain-language introduction, the two summary tables (a row per preset, one bold best
    // value each) and the full-size overlay come before / after the image rows.
    assert!(html.contains("<p class=\"intro\">What you see:"), "intro");
    assert_eq!(
        html.matches("<table class=\"summary\">").count(),
        3,
        "PSNR, SSIM, light response"
    );
    for p in presets {
        assert_eq!(html.matches(&format!("<tr><td>{p}</td>")).count(), 2, "{p} rows");
    }
    assert_eq!(
        html.matches("<td><b>").count(),
        2 * presets.len() + 2,
        "one best per row"
    );
    assert!(html.contains("<div id=\"zoom\">") && html.contains("addEventListener('click'"));
    let panels = [
        "source",
        "path-traced render",
        "albedo A",
        "shading S",
        "residual R",
        "relit (ours)",
        "ground truth",
    ];
    for p in panels {
        assert_eq!(
            html.matches(&format!("<img alt=\"{p}\" src=\"data:image/png;base64,iVBORw0KGgo"))
                .count(),
            presets.len(),
            "panel {p}"
        );
    }
    assert_eq!(
        html.matches("<span class=\"m\">PSNR").count(),
        3 * presets.len(),
        "PSNR under source, path-traced render and relit"
    );
    for p in presets {
        assert!(html.contains(&format!("<h2>{p}</h2>")), "{p}");
        for f in [
            "relit.png",
            "path_traced.png",
            "albedo.png",
            "shading.png",
            "residual.png",
            "CT.exr",
        ] {
            assert!(out.join(p).join(f).is_file(), "{p}/{f}");
        }
    }
    // The JSON summary carries finite metrics (or "inf" for an exact match), one entry per preset.
    let v = o.json();
    // Light response: the unchanged source responds to nothing; the relit images' score is the
    // one of the written PNGs (8-bit quantisation moves it a little).
    let lr = &v["light_response"];
    assert_eq!(lr["identity"]["gain"], 0.0);
    assert_eq!(lr["identity"]["correlation"], 0.0);
    assert_eq!(lr["relit"]["pairs"], presets.len() * (presets.len() - 1) / 2);
    let pngs = |f: &str| -> Vec<pixl_core::Image> {
        presets
            .iter()
            .map(|p| pixl_core::io::read_image(&out.join(p).join(f)).unwrap())
            .collect()
    };
    let (relit, traced) = (pngs("relit.png"), pngs("path_traced.png"));
    let from_files =
        pixl_eval::light_response(&relit.iter().collect::<Vec<_>>(), &traced.iter().collect::<Vec<_>>()).unwrap();
    let gain = lr["relit"]["gain"].as_f64().unwrap();
    assert!(
        (from_files.gain - gain).abs() < 0.02,
        "relit gain {gain} vs {} from the PNGs",
        from_files.gain
    );
    let rows = v["presets"].as_array().unwrap();
    assert_eq!(rows.len(), presets.len());
    for (r, p) in rows.iter().zip(presets) {
        let ssim = r["relit"]["ssim"].as_f64().unwrap();
        assert!(ssim.is_finite() && ssim <= 1.0 + 1e-9, "{r}");
        // The path-traced render's PSNR, recomputed here in f64 from the written 8-bit PNGs
        // (quantisation moves it by far less than 0.1 dB at these error levels).
        let load = |f: &str| pixl_core::io::read_image(&out.join(p).join(f)).unwrap();
        let (a, b) = (load("path_traced.png"), load("ground_truth.png"));
        let mse = a
            .data
            .iter()
            .zip(&b.data)
            .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
            .sum::<f64>()
            / a.data.len() as f64;
        let want = -10.0 * mse.log10();
        let got = r["path_traced"]["psnr"].as_f64().unwrap();
        assert!(
            (got - want).abs() < 0.1,
            "{p}: path-traced PSNR {got} vs {want} from the PNGs"
        );
    }
}

#[test]
fn exact_intrinsics_with_fresh_weights_relight_to_the_source() {
    let dir = common::tempdir();
    let weights = common::tiny_weights(&dir.path().join("fresh.safetensors"), 0);
    let out = dir.path().join("demo");
    let o = common::pixl(&[
        "demo",
        "--quiet",
        "--spp",
        "1",
        "--exact-intrinsics",
        "--weights",
        common::s(&weights),
        "--json",
        "--out",
        common::s(&out),
    ])
    .ok();
    // The true scene is C_T's scene: no coarse reconstruction is made.
    assert!(!out.join("reconstruction").exists());
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    assert!(
        html.contains(&format!("weights: {}", weights.display())),
        "the weights named"
    );
    let source = std::fs::read(out.join("source.png")).unwrap();
    let v = o.json();
    let rows = v["presets"].as_array().unwrap();
    assert_eq!(rows.len(), PRESETS.len());
    for (r, p) in rows.iter().zip(PRESETS) {
        assert_eq!(r["preset"], p);
        // A freshly initialised network (zero-initialised modulation) returns the source.
        let relit = std::fs::read(out.join(p).join("relit.png")).unwrap();
        assert!(relit == source, "{p}: relit.png is not the source");
        assert_eq!(r["relit"], r["source"], "{p}");
        // C_T comes from the ground truth's own render.
        let traced = std::fs::read(out.join(p).join("path_traced.png")).unwrap();
        let truth = std::fs::read(out.join(p).join("ground_truth.png")).unwrap();
        assert!(traced == truth, "{p}: path_traced.png is not the ground truth");
        assert_eq!(r["path_traced"]["psnr"], "inf", "{p}");
        assert!(out.join(p).join("CT.exr").is_file(), "{p}/CT.exr");
    }
}
