//! `pixl doctor`: its JSON form against what the test finds out on its own (the machine's core
//! count and SIMD extensions, the thread variable it sets, a models folder it fills), and its
//! text form's sections.
mod common;
use common::{run, Run};
use serde_json::Value;
use std::path::Path;

/// `pixl args` with HOME at `home`, online (doctor reports the offline switch) and without
/// `RAYON_NUM_THREADS` unless `env` sets it.
fn pixl(args: &[&str], env: &[(&str, &str)], home: &Path) -> Run {
    let mut c = common::cmd_in(home);
    c.args(args).env_remove("PIXL_OFFLINE").env_remove("RAYON_NUM_THREADS");
    for (k, v) in env {
        c.env(k, v);
    }
    run(&mut c)
}

fn doctor_json(env: &[(&str, &str)], home: &Path) -> Value {
    pixl(&["doctor", "--json"], env, home).ok().json()
}

/// The strings of a JSON array.
fn strings(v: &Value) -> Vec<&str> {
    v.as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect()
}

#[test]
fn json_matches_the_machine_and_the_environment() {
    let home = common::tempdir();
    let r = doctor_json(&[], home.path());

    assert_eq!(r["version"], env!("CARGO_PKG_VERSION"));
    let features = strings(&r["build"]["features"]);
    assert_eq!(features.contains(&"cuda"), cfg!(feature = "cuda"));
    assert_eq!(
        r["build"]["target"],
        format!("{}-{}", std::env::consts::ARCH, std::env::consts::OS)
    );

    let cores = std::thread::available_parallelism().unwrap().get();
    assert_eq!(r["cpu"]["logical_cores"], cores);
    // Without RAYON_NUM_THREADS, candle's matrix kernels use one thread per physical core.
    let threads = r["cpu"]["threads"].as_u64().unwrap() as usize;
    assert!(
        (1..=cores).contains(&threads),
        "{threads} threads on {cores} logical cores"
    );
    #[cfg(target_arch = "x86_64")]
    {
        let listed = strings(&r["cpu"]["simd_features"]);
        assert_eq!(listed.contains(&"avx2"), std::arch::is_x86_feature_detected!("avx2"));
        assert_eq!(listed.contains(&"fma"), std::arch::is_x86_feature_detected!("fma"));
        assert_eq!(
            listed.contains(&"avx512f"),
            std::arch::is_x86_feature_detected!("avx512f")
        );
        let level = if std::arch::is_x86_feature_detected!("avx512f") {
            "avx512"
        } else if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            "avx2+fma"
        } else {
            "other"
        };
        if level != "other" {
            assert_eq!(r["cpu"]["simd"], level);
        }
    }
    if let (Some(total), Some(avail)) = (
        r["cpu"]["memory_total_bytes"].as_u64(),
        r["cpu"]["memory_available_bytes"].as_u64(),
    ) {
        assert!(avail <= total && total > 0);
    }

    // CUDA: a CPU build says why there is none; a CUDA build either lists devices or says why not.
    let cuda = &r["cuda"];
    assert_eq!(cuda["compiled"], cfg!(feature = "cuda"));
    if !cfg!(feature = "cuda") {
        assert!(cuda["unavailable"].as_str().unwrap().contains("no `cuda` feature"));
        assert_eq!(cuda["devices"].as_array().unwrap().len(), 0);
        assert!(cuda["driver_version"].is_null() && cuda["built_for"].is_null());
    } else {
        assert_eq!(cuda["built_for"], "13.0");
        assert!(cuda["unavailable"].is_string() || !cuda["devices"].as_array().unwrap().is_empty());
    }

    // Weights: the Hugging Face cache under HOME, nothing on disk, online.
    let w = &r["weights"];
    let hf = home.path().join(".cache").join("huggingface").join("hub");
    assert_eq!(w["hf_cache"], hf.display().to_string());
    assert!(w["models_dir"].is_null());
    assert_eq!(w["offline"], false);
    let estimators = w["estimators"].as_array().unwrap();
    assert!(estimators.iter().any(|e| e["name"] == "da3-metric"));
    assert!(estimators.iter().all(|e| e["present"] == false && e["dir"].is_null()));
}

#[test]
fn json_follows_threads_models_folder_and_offline() {
    let home = common::tempdir();
    let models = home.path().join("weights");
    // Fill DIR/da3-metric/ with the files `pixl models list` says the model has.
    let list = pixl(&["models", "list", "--json"], &[], home.path()).ok().json();
    let spec = list
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "da3-metric")
        .unwrap();
    for f in spec["files"].as_array().unwrap() {
        common::write_file(&models.join("da3-metric").join(f.as_str().unwrap()), b"{}");
    }
    let models_text = models.display().to_string();
    let r = doctor_json(
        &[
            ("RAYON_NUM_THREADS", "3"),
            ("PIXL_MODELS_DIR", &models_text),
            ("PIXL_OFFLINE", "1"),
        ],
        home.path(),
    );
    assert_eq!(r["cpu"]["threads"], 3);
    let w = &r["weights"];
    assert_eq!(w["models_dir"], models_text);
    assert_eq!(w["offline"], true);
    for e in w["estimators"].as_array().unwrap() {
        if e["name"] == "da3-metric" {
            assert_eq!(e["present"], true);
            assert_eq!(e["dir"], models.join("da3-metric").display().to_string());
        } else {
            assert_eq!(e["present"], false, "{e}");
        }
    }
}

#[test]
fn text_names_every_section() {
    let home = common::tempdir();
    let o = pixl(&["doctor"], &[], home.path()).ok();
    let text = String::from_utf8(o.stdout_bytes).unwrap();
    for section in ["pixl ", "CPU ", "SIMD ", "CUDA ", "weights ", "da3-metric"] {
        assert!(text.contains(section), "no {section:?} in:\n{text}");
    }
    // A bug report without CUDA still says why there is none.
    if !cfg!(feature = "cuda") {
        assert!(text.contains("no device"), "{text}");
    }
}
