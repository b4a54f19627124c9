//! `pixl weights split` / `join` on the real binary: a round trip that gives the file back byte
//! for byte, a bf16 round trip that loads, and bad inputs (a missing file, a missing part, an
//! existing output, the output being a part) failing with a message and exit code 1.
mod common;
use common::{pixl_in, s};
use std::path::{Path, PathBuf};

fn ok(home: &Path, args: &[&str]) -> String {
    pixl_in(home, args).ok().stdout
}

/// Expects exit code 1 (an error, not a panic and not a command-line error) and a message
/// starting `error: ` holding every needle.
fn fails(home: &Path, args: &[&str], needles: &[&str]) {
    let r = pixl_in(home, args);
    let err = r.fails(needles);
    assert!(err.starts_with("error: "), "{err}");
}

/// `pixl weights split W --max-part-mib MIB -o PARTS` then `extra`, expecting success: stdout.
fn split(home: &Path, w: &Path, mib: &str, parts: &Path, extra: &[&str]) -> String {
    let args = ["weights", "split", s(w), "--max-part-mib", mib, "-o", s(parts)];
    ok(home, &[&args[..], extra].concat())
}

fn tiny_weights(dir: &Path) -> PathBuf {
    common::tiny_weights(&dir.join("W.safetensors"), 3)
}

#[test]
fn split_then_join_gives_the_file_back() {
    let dir = common::tempdir();
    let home = dir.path();
    let w = tiny_weights(home);
    let parts = home.join("parts");
    let out = split(home, &w, "0.5", &parts, &["--json"]);
    let v: serde_json::Value = serde_json::from_str(&out).expect("one JSON document on stdout");
    assert_eq!(v["dtype"], "F32");
    let list = v["parts"].as_array().unwrap();
    assert!(list.len() >= 3, "{out}");
    let mut given = Vec::new();
    for (i, p) in list.iter().enumerate() {
        let path = PathBuf::from(p["path"].as_str().unwrap());
        assert!(path.ends_with(format!("W-{:05}-of-{:05}.safetensors", i + 1, list.len())));
        let bytes = std::fs::metadata(&path).unwrap().len();
        assert_eq!(p["bytes"].as_u64(), Some(bytes));
        assert!(bytes <= 512 * 1024, "{}: {bytes} bytes", path.display());
        assert!(p["tensors"].as_u64().unwrap() > 0);
        given.push(path);
    }
    given.reverse();

    let joined = home.join("J.safetensors");
    let mut args = vec!["weights", "join"];
    args.extend(given.iter().map(|p| s(p)));
    args.extend(["-o", s(&joined), "--json"]);
    let out = ok(home, &args);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(v["dtype"], "F32");
    assert_eq!(v["bytes"].as_u64(), Some(std::fs::metadata(&w).unwrap().len()));
    assert!(
        std::fs::read(&joined).unwrap() == std::fs::read(&w).unwrap(),
        "joined bytes differ"
    );

    // the same again is refused, with --force replaced
    fails(home, &args, &["J.safetensors", "already exists", "--force"]);
    args.push("--force");
    ok(home, &args);
    assert!(std::fs::read(&joined).unwrap() == std::fs::read(&w).unwrap());
}

#[test]
fn a_bf16_split_joins_into_loadable_weights() {
    let dir = common::tempdir();
    let home = dir.path();
    let w = tiny_weights(home);
    let parts = home.join("bf16");
    let out = split(home, &w, "0.25", &parts, &["--dtype", "bf16", "--json"]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(
        (v["source_dtype"].as_str(), v["dtype"].as_str()),
        (Some("F32"), Some("BF16"))
    );
    let n = v["parts"].as_array().unwrap().len();
    assert!(n >= 3, "{out}");
    // bf16 halves the data: about half as many parts as f32 at the same limit
    let f32_bytes = std::fs::metadata(&w).unwrap().len();
    assert!((n as u64) < f32_bytes / (256 * 1024), "{n} parts");
    let first = PathBuf::from(v["parts"][0]["path"].as_str().unwrap());
    // one part stands for its set
    let joined = home.join("W-bf16.safetensors");
    let out = ok(home, &["weights", "join", s(&first), "-o", s(&joined)]);
    assert!(
        out.contains(&format!("from {n} parts")) && out.contains("BF16"),
        "{out}"
    );
    let info = ok(home, &["model", "info", "--weights", s(&joined), "--json"]);
    let v: serde_json::Value = serde_json::from_str(&info).unwrap();
    assert_eq!(v["total"].as_u64(), Some(733_814));
    let (cfg, _) = pixl_model::checkpoint::load(&joined, &candle_core::Device::Cpu, candle_core::DType::F32).unwrap();
    assert_eq!(cfg, pixl_model::Config::tiny());
}

#[test]
fn bad_inputs_fail_with_a_message() {
    let dir = common::tempdir();
    let home = dir.path();
    let missing = home.join("missing.safetensors");
    let parts = home.join("parts");
    fails(
        home,
        &["weights", "split", s(&missing), "-o", s(&parts)],
        &["missing.safetensors"],
    );
    assert!(!parts.exists(), "a failed split leaves no folder");
    // not weights at all
    let junk = home.join("junk.safetensors");
    std::fs::write(&junk, b"hello").unwrap();
    fails(
        home,
        &["weights", "split", s(&junk), "-o", s(&parts)],
        &["junk.safetensors", "safetensors"],
    );

    let w = tiny_weights(home);
    fails(
        home,
        &["weights", "split", s(&w), "--max-part-mib", "0.01", "-o", s(&parts)],
        &["W.safetensors", "tensor `", "over the limit"],
    );
    split(home, &w, "0.5", &parts, &["-q"]);
    fails(
        home,
        &["weights", "split", s(&w), "-o", s(&parts)],
        &["already holds", "--force"],
    );
    let mut made: Vec<PathBuf> = std::fs::read_dir(&parts).unwrap().map(|e| e.unwrap().path()).collect();
    made.sort();
    assert!(made.len() >= 3);
    let (p1, p2) = (made[0].clone(), made[1].clone());
    let out = home.join("J.safetensors");
    // the output is one of the parts, even with --force
    fails(
        home,
        &["weights", "join", s(&p1), "-o", s(&p2), "--force"],
        &["the output is the input"],
    );
    // a part missing
    std::fs::remove_file(&p2).unwrap();
    fails(home, &["weights", "join", s(&p1), "-o", s(&out)], &[s(&p2), "missing"]);
    assert!(!out.exists());
    // no parts at all is a command-line error
    let o = pixl_in(home, &["weights", "join", "-o", s(&out)]);
    assert_eq!(o.code(), Some(2), "{}", o.stderr);
}
