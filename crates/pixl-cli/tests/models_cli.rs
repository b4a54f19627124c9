//! `pixl models list | path | fetch` on fake weight folders: the lookup order (models folder,
//! then the Hugging Face cache in the Python layout), `--json`, the offline failures, and the
//! pinned SHA-256 of `pixlrelight` (a download that differs is refused and kept nowhere;
//! `path --verify` re-checks files on disk). No test touches the network: every run has
//! `PIXL_OFFLINE=1` or `--offline`, or a loopback stand-in for the Hub, and a private HOME.
mod common;
use common::{cmd_in, run, write_file};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex};

/// A Python-layout cache entry for `repo` with the DA3 files (plain files, refs/main).
fn fake_cache(hub: &Path, repo: &str, commit: &str) -> PathBuf {
    let root = hub.join(format!("models--{}", repo.replace('/', "--")));
    let snap = root.join("snapshots").join(commit);
    write_file(&snap.join("config.json"), b"{}");
    write_file(&snap.join("model.safetensors"), b"weights");
    write_file(&root.join("refs").join("main"), commit.as_bytes());
    snap
}

fn entry<'a>(list: &'a serde_json::Value, name: &str) -> &'a serde_json::Value {
    list.as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == name)
        .unwrap_or_else(|| panic!("{name} not listed: {list}"))
}

#[test]
fn list_says_what_is_where() {
    let t = common::tempdir();
    let hf = t.path().join("hf");
    let snap = fake_cache(&hf.join("hub"), "depth-anything/DA3METRIC-LARGE", "c0ffee");
    let list = |args: &[&str]| run(cmd_in(t.path()).env("HF_HOME", &hf).args(["models", "list"]).args(args)).ok();
    let v = list(&["--json"]).json();
    let m = entry(&v, "da3-metric");
    assert_eq!(m["present"], true);
    assert_eq!(m["dir"], snap.display().to_string());
    assert_eq!(m["repo"], "depth-anything/DA3METRIC-LARGE");
    assert_eq!(m["licence"], "Apache-2.0");
    assert_eq!(m["files"], serde_json::json!(["config.json", "model.safetensors"]));
    let m = entry(&v, "da3-mono");
    assert_eq!(
        (m["present"].clone(), m["dir"].clone()),
        (false.into(), serde_json::Value::Null)
    );
    assert_eq!(m["repo"], "depth-anything/DA3MONO-LARGE");

    let out = list(&[]).stdout;
    for needle in [
        "da3-metric",
        "da3-mono",
        "Apache-2.0",
        "1.4 GB",
        &snap.display().to_string(),
    ] {
        assert!(out.contains(needle), "{needle:?} missing from:\n{out}");
    }
}

/// HF_HUB_CACHE wins over HF_HOME; `path` prints the snapshot folder; `fetch` of a model on
/// disk does not download.
#[test]
fn path_and_fetch_use_the_cache_without_network() {
    let t = common::tempdir();
    let decoy = fake_cache(&t.path().join("hf/hub"), "depth-anything/DA3MONO-LARGE", "aaa");
    let snap = fake_cache(&t.path().join("cache"), "depth-anything/DA3MONO-LARGE", "bbb");
    let models = |args: &[&str]| {
        run(cmd_in(t.path())
            .env("HF_HOME", t.path().join("hf"))
            .env("HF_HUB_CACHE", t.path().join("cache"))
            .arg("models")
            .args(args))
        .ok()
    };
    let out = models(&["path", "da3-mono"]).stdout;
    assert_eq!(out.trim(), snap.display().to_string());
    assert_ne!(snap, decoy);

    let v = models(&["path", "da3-mono", "--json"]).json();
    assert_eq!(
        v["files"]["model.safetensors"],
        snap.join("model.safetensors").display().to_string()
    );
    assert!(v["source"].as_str().unwrap().contains("bbb"), "{v}");

    let o = models(&["fetch", "da3-mono", "--offline"]);
    assert!(o.stdout.contains(&snap.display().to_string()), "{}", o.stdout);
    assert!(!o.stderr.contains("downloading"), "{}", o.stderr);
}

/// `--models DIR` (and PIXL_MODELS_DIR) come before the Hugging Face cache.
#[test]
fn models_folder_comes_first() {
    let t = common::tempdir();
    fake_cache(
        &t.path().join(".cache/huggingface/hub"),
        "depth-anything/DA3METRIC-LARGE",
        "c1",
    );
    let own = t.path().join("weights/da3-metric");
    write_file(&own.join("config.json"), b"{}");
    write_file(&own.join("model.safetensors"), b"w");
    // Without a models folder: the default cache under HOME.
    let path = |c: &mut Command| run(c).ok().stdout;
    let out = path(cmd_in(t.path()).args(["models", "path", "da3-metric"]));
    assert!(out.trim().ends_with("snapshots/c1"), "{out}");
    // With one, by flag and by variable.
    let weights = t.path().join("weights");
    let out = path(
        cmd_in(t.path())
            .args(["models", "path", "da3-metric", "--models"])
            .arg(&weights),
    );
    assert_eq!(out.trim(), own.display().to_string());
    let out = path(
        cmd_in(t.path())
            .env("PIXL_MODELS_DIR", &weights)
            .args(["models", "path", "da3-metric"]),
    );
    assert_eq!(out.trim(), own.display().to_string());
}

#[test]
fn a_models_folder_lacking_a_file_is_named() {
    let t = common::tempdir();
    write_file(&t.path().join("w/da3-mono/config.json"), b"{}");
    run(cmd_in(t.path())
        .args(["models", "fetch", "da3-mono", "--models"])
        .arg(t.path().join("w")))
    .fails(&["model.safetensors", "da3-mono"]);
}

/// Offline with nothing on disk: an immediate error naming `pixl models fetch NAME` and
/// `--models DIR`, whichever way offline was asked for.
#[test]
fn offline_without_weights_names_the_fetch_command() {
    let t = common::tempdir();
    /// Extra flags, and an environment variable to set.
    type Case<'a> = (&'a [&'a str], Option<(&'a str, &'a str)>);
    let cases: [Case; 3] = [
        (&["--offline"], None),
        (&[], Some(("PIXL_OFFLINE", "1"))),
        (&[], Some(("HF_HUB_OFFLINE", "1"))),
    ];
    for (flags, var) in cases {
        let mut c = cmd_in(t.path());
        c.env_remove("PIXL_OFFLINE");
        if let Some((k, v)) = var {
            c.env(k, v);
        }
        let start = std::time::Instant::now();
        let o = run(c.args(["models", "fetch", "da3-mono"]).args(flags));
        let err = &o.stderr;
        assert_eq!(o.code(), Some(1), "{flags:?} {var:?}: {err}");
        assert!(
            err.contains("pixl models fetch da3-mono") && err.contains("--models DIR"),
            "{flags:?} {var:?}: {err}"
        );
        assert!(!err.contains("downloading"), "{err}");
        // No network attempt: it fails at once.
        assert!(start.elapsed().as_secs() < 20);
    }
    // `path` never downloads: not on disk is an error naming the fetch command.
    let o = run(cmd_in(t.path())
        .env_remove("PIXL_OFFLINE")
        .args(["models", "path", "da3-metric"]));
    assert_eq!(o.code(), Some(1), "{}", o.stderr);
    assert!(
        o.stderr.contains("not on this machine") && o.stderr.contains("pixl models fetch da3-metric"),
        "{}",
        o.stderr
    );
    let o = run(cmd_in(t.path()).args(["models", "path", "da3"]));
    assert_eq!(o.code(), Some(1));
    assert!(
        o.stderr.contains("unknown model `da3`") && o.stderr.contains("da3-metric"),
        "{}",
        o.stderr
    );
}

/// A stand-in for the Hub's `resolve` endpoint on a loopback port (no network): serves
/// `/<repo>/resolve/<revision>/<file>` for the given files with the headers `hf-hub` reads (`etag`,
/// `x-repo-commit`, `content-range`), honouring `Range: bytes=A-[B]`; 404 otherwise. Returns the
/// endpoint and the log of requested paths.
fn serve(
    repo: &str,
    revision: &str,
    files: Vec<(&'static str, Vec<u8>)>,
    commit: &'static str,
) -> (String, Arc<Mutex<Vec<String>>>) {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let endpoint = format!("http://{}", listener.local_addr().unwrap());
    let log = Arc::new(Mutex::new(Vec::new()));
    let log2 = log.clone();
    let prefix = format!("/{repo}/resolve/{revision}/");
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { continue };
            let mut buf = Vec::new();
            let mut chunk = [0u8; 1024];
            while !buf.windows(4).any(|w| w == b"\r\n\r\n") {
                match stream.read(&mut chunk) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => buf.extend_from_slice(&chunk[..n]),
                }
            }
            let req = String::from_utf8_lossy(&buf).into_owned();
            let path = req.split_whitespace().nth(1).unwrap_or("").to_string();
            log2.lock().unwrap().push(path.clone());
            let range = req
                .lines()
                .find_map(|l| l.to_ascii_lowercase().strip_prefix("range: bytes=").map(str::to_string));
            let file = path
                .strip_prefix(&prefix)
                .and_then(|name| files.iter().find(|(n, _)| *n == name));
            let response = match file {
                Some((name, bytes)) => {
                    let len = bytes.len();
                    let (a, b) = match range.as_deref().and_then(|r| r.split_once('-')) {
                        Some((a, b)) => (
                            a.trim().parse().unwrap_or(0),
                            b.trim().parse().unwrap_or(len - 1).min(len - 1),
                        ),
                        None => (0, len - 1),
                    };
                    let mut r = format!(
                        "HTTP/1.1 206 Partial Content\r\ncontent-length: {}\r\netag: \"etag-{name}\"\r\n\
x-repo-commit: {commit}\r\ncontent-range: bytes {a}-{b}/{len}\r\nconnection: close\r\n\r\n",
                        b + 1 - a
                    )
                    .into_bytes();
                    r.extend_from_slice(&bytes[a..=b]);
                    r
                }
                None => b"HTTP/1.1 404 Not Found\r\ncontent-length: 0\r\nconnection: close\r\n\r\n".to_vec(),
            };
            let _ = stream.write_all(&response);
        }
    });
    (endpoint, log)
}

/// The download path end to end, against a loopback stand-in for the Hub: the licence and size
/// are printed first, the files land in the Python cache layout (a later lookup finds them with
/// no request), and `pixl estimate depth` then runs on the downloaded checkpoint.
#[test]
fn downloads_on_first_use_then_reuses_the_cache() {
    let tiny = common::repo_path("fixtures/da3/tiny");
    let config = std::fs::read(tiny.join("config.json")).unwrap();
    let weights = std::fs::read(tiny.join("model.safetensors")).unwrap();
    let (endpoint, log) = serve(
        "depth-anything/DA3MONO-LARGE",
        "main",
        vec![("config.json", config.clone()), ("model.safetensors", weights.clone())],
        "0123456789abcdef0123456789abcdef01234567",
    );
    let t = common::tempdir();
    // Online, against the stand-in.
    let online = || {
        let mut c = cmd_in(t.path());
        c.env_remove("PIXL_OFFLINE").env("HF_ENDPOINT", &endpoint);
        c
    };
    // Into a models folder.
    let weights_dir = t.path().join("weights");
    let fetch = || {
        run(online()
            .args(["models", "fetch", "da3-mono", "--models"])
            .arg(&weights_dir))
        .ok()
    };
    let first = fetch();
    let (out, err) = (&first.stdout, &first.stderr);
    let notice = err
        .find("licence: Apache-2.0")
        .unwrap_or_else(|| panic!("no licence notice: {err}"));
    assert!(
        err[..notice].contains("downloading `da3-mono`") && err.contains("1.4 GB"),
        "{err}"
    );
    let snap =
        weights_dir.join("models--depth-anything--DA3MONO-LARGE/snapshots/0123456789abcdef0123456789abcdef01234567");
    assert_eq!(std::fs::read(snap.join("config.json")).unwrap(), config);
    assert_eq!(std::fs::read(snap.join("model.safetensors")).unwrap(), weights);
    assert!(out.contains(&snap.display().to_string()), "{out}");
    let requests = log.lock().unwrap().len();
    assert!(requests >= 2, "{:?}", log.lock().unwrap());
    // Found again offline, and a second fetch asks nothing.
    let out = run(cmd_in(t.path())
        .args(["models", "path", "da3-mono", "--models"])
        .arg(&weights_dir))
    .ok()
    .stdout;
    assert_eq!(out.trim(), snap.display().to_string());
    let err = fetch().stderr;
    assert!(!err.contains("downloading"), "{err}");
    assert_eq!(log.lock().unwrap().len(), requests);

    // On first use by `estimate depth`, into the Hugging Face cache (HF_HOME).
    let photo = tiny.join("input_b.png");
    let depth = t.path().join("d.exr");
    let err = run(online()
        .env("HF_HOME", t.path().join("hf"))
        .args(["estimate", "depth"])
        .arg(&photo)
        .arg("-o")
        .arg(&depth)
        .args(["--model", "da3-mono", "--process-res", "98"]))
    .ok()
    .stderr;
    assert!(err.contains("licence: Apache-2.0"), "{err}");
    assert!(t
        .path()
        .join("hf/hub/models--depth-anything--DA3MONO-LARGE/refs/main")
        .is_file());
    assert!(depth.is_file());
}

const PIXLRELIGHT_COMMIT: &str = "5def370459c15ee36c524068bb8338b3f6c6d6c0";
const PIXLRELIGHT_CONFIG_SHA256: &str = "a3ef2cada8a223aee15b2e85d6627980962ea5446242d0d8ec24791ec2e21021";
const PIXLRELIGHT_WEIGHTS_SHA256: &str = "69c2bd11c2f272754f7080bc33e4b049fd334ea5d596df0c475f51c93699710e";
/// SHA-256 of `abc` (FIPS 180-2), the content the tests put where the real files belong.
const SHA256_ABC: &str = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad";
const NON_COMMERCIAL: &str = "CC BY-NC 4.0 — non-commercial use only";

/// Every regular file under `dir` (links not followed).
fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let t = e.file_type().unwrap();
            if t.is_dir() {
                todo.push(e.path());
            } else if t.is_file() {
                out.push(e.path());
            }
        }
    }
    out
}

/// The released checkpoint is listed with its pinned commit, its non-commercial licence and
/// the digest of each file.
#[test]
fn list_shows_pixlrelight_pinned_and_non_commercial() {
    let t = common::tempdir();
    let v = run(cmd_in(t.path()).args(["models", "list", "--json"])).ok().json();
    let m = entry(&v, "pixlrelight");
    assert_eq!(m["repo"], "mlfarinha/pixlrelight");
    assert_eq!(m["revision"], PIXLRELIGHT_COMMIT);
    assert_eq!(m["licence"], NON_COMMERCIAL);
    assert_eq!(m["licence_url"], "https://huggingface.co/mlfarinha/pixlrelight");
    assert_eq!(m["files"], serde_json::json!(["config.yaml", "model.safetensors"]));
    assert_eq!(
        m["sha256"],
        serde_json::json!({
            "config.yaml": PIXLRELIGHT_CONFIG_SHA256,
            "model.safetensors": PIXLRELIGHT_WEIGHTS_SHA256,
        })
    );
    assert_eq!(
        m["purpose"],
        "PIXLRelight (the paper's released model): relights a photo from target intrinsics"
    );
    let bytes = m["approx_bytes"].as_u64().unwrap();
    assert!((2_500_000_000..2_600_000_000).contains(&bytes), "{bytes}");
    assert_eq!(m["present"], false);
    // Models without pinned digests list none.
    assert_eq!(entry(&v, "da3-metric")["sha256"], serde_json::json!({}));

    let out = run(cmd_in(t.path()).args(["models", "list"])).ok().stdout;
    let row = out
        .lines()
        .find(|l| l.starts_with("pixlrelight "))
        .unwrap_or_else(|| panic!("no pixlrelight row:\n{out}"));
    assert!(
        row.contains("mlfarinha/pixlrelight") && row.contains(NON_COMMERCIAL) && row.contains("2.6 GB"),
        "{row}"
    );
}

/// A download whose content is not the pinned one: the licence notice first, then a failure
/// (exit 1) naming the file and both digests, and the content kept nowhere in the models folder.
#[test]
fn a_pixlrelight_download_with_another_digest_is_refused() {
    let (endpoint, _log) = serve(
        "mlfarinha/pixlrelight",
        PIXLRELIGHT_COMMIT,
        vec![("config.yaml", b"abc".to_vec()), ("model.safetensors", b"abc".to_vec())],
        PIXLRELIGHT_COMMIT,
    );
    let t = common::tempdir();
    let weights_dir = t.path().join("weights");
    let o = run(cmd_in(t.path())
        .env_remove("PIXL_OFFLINE")
        .env("HF_ENDPOINT", &endpoint)
        .args(["models", "fetch", "pixlrelight", "--models"])
        .arg(&weights_dir));
    let err = &o.stderr;
    assert_eq!(o.code(), Some(1), "{err}");
    let notice = err
        .find(&format!("licence: {NON_COMMERCIAL}"))
        .unwrap_or_else(|| panic!("no licence notice: {err}"));
    assert!(err[..notice].contains("downloading `pixlrelight`"), "{err}");
    let failure = err
        .rfind("config.yaml")
        .unwrap_or_else(|| panic!("file not named: {err}"));
    assert!(failure > notice, "{err}");
    assert!(
        err.contains(PIXLRELIGHT_CONFIG_SHA256) && err.contains(SHA256_ABC),
        "expected and found digests not named: {err}"
    );
    // Nothing with the refused content anywhere under the models folder, and no snapshot entry.
    let left = files_under(&weights_dir);
    assert!(left.iter().all(|p| std::fs::read(p).unwrap() != b"abc"), "{left:?}");
    let snap = weights_dir
        .join("models--mlfarinha--pixlrelight/snapshots")
        .join(PIXLRELIGHT_COMMIT);
    assert!(std::fs::symlink_metadata(snap.join("config.yaml")).is_err());
    let o = run(cmd_in(t.path())
        .args(["models", "path", "pixlrelight", "--models"])
        .arg(&weights_dir));
    assert_eq!(o.code(), Some(1), "{}", o.stderr);
    assert!(o.stderr.contains("not on this machine"), "{}", o.stderr);
}

/// Files on disk are not hashed by a plain lookup; `path --verify` reads them and fails naming
/// the first one that differs; files without a pinned digest pass unread.
#[test]
fn path_verify_checks_files_on_disk() {
    let t = common::tempdir();
    let weights = t.path().join("w");
    let own = weights.join("pixlrelight");
    write_file(&own.join("config.yaml"), b"abc");
    write_file(&own.join("model.safetensors"), b"abc");
    let path = |args: &[&str]| {
        run(cmd_in(t.path())
            .args(["models", "path", "pixlrelight", "--models"])
            .arg(&weights)
            .args(args))
    };
    let o = path(&[]).ok();
    assert_eq!(o.stdout.trim(), own.display().to_string());
    let o = path(&["--verify"]);
    assert_eq!(o.code(), Some(1), "{}", o.stderr);
    assert!(
        o.stderr.contains(&own.join("config.yaml").display().to_string())
            && o.stderr.contains(PIXLRELIGHT_CONFIG_SHA256)
            && o.stderr.contains(SHA256_ABC)
            && o.stderr.contains("pixl models fetch pixlrelight"),
        "{}",
        o.stderr
    );
    assert!(o.stdout.trim().is_empty(), "{}", o.stdout);

    // A model without pinned digests: verified, nothing read.
    write_file(&weights.join("da3-mono/config.json"), b"{}");
    write_file(&weights.join("da3-mono/model.safetensors"), b"w");
    let o = run(cmd_in(t.path())
        .args(["models", "path", "da3-mono", "--verify", "--json", "--models"])
        .arg(&weights))
    .ok();
    let v = o.json();
    assert_eq!(
        v["verified"],
        serde_json::json!({"config.json": null, "model.safetensors": null})
    );
    assert!(o.stderr.contains("no sha256 pinned"), "{}", o.stderr);
}

/// `pixl models inspect` on the tiny checkpoint in the presumed official layout
/// (`fixtures/pixlrelight-official`): all matched, exit 0; copies with a renamed, a missing and
/// a mis-shaped tensor: each named, exit 1; our own checkpoint recognised; bad input one error.
#[test]
fn inspect_names_every_mismatch_and_exits_1() {
    let fx = common::repo_path("fixtures/pixlrelight-official");
    let t = common::tempdir();
    let inspect = |args: &[&str]| {
        run(cmd_in(t.path())
            .env("PIXL_OFFLINE", "1")
            .args(["models", "inspect"])
            .args(args))
    };
    let model = fx.join("model.safetensors");
    let ok = inspect(&[common::s(&model)]).ok();
    assert!(ok.stdout.contains("result: OK"), "{}", ok.stdout);
    assert!(ok.stdout.contains("trunk"), "parameters per part: {}", ok.stdout);
    let v = inspect(&[common::s(&model), "--json"]).ok().json();
    assert_eq!(v["ok"], true);
    assert_eq!(v["missing"].as_array().unwrap().len(), 0);
    assert_eq!(v["matched"].as_array().unwrap().len(), 222);

    let name = "net.trunk.blocks.2.mlp.fc1.weight";
    let dev = candle_core::Device::Cpu;
    for what in ["renamed", "missing", "misshaped"] {
        let dir = t.path().join(what);
        std::fs::create_dir_all(&dir).unwrap();
        let mut ts = candle_core::safetensors::load(&model, &dev).unwrap();
        match what {
            "renamed" => {
                let x = ts.remove(name).unwrap();
                ts.insert("net.trunk.blocks.2.ffn.fc1.weight".into(), x);
            }
            "missing" => {
                ts.remove(name);
            }
            _ => {
                let x = ts[name].narrow(1, 0, 16).unwrap();
                ts.insert(name.into(), x);
            }
        }
        let p = dir.join("model.safetensors");
        candle_core::safetensors::save(&ts, &p).unwrap();
        std::fs::copy(fx.join("config.yaml"), dir.join("config.yaml")).unwrap();
        let r = inspect(&[common::s(&p)]);
        r.fails(&["problem(s)"]);
        assert!(r.stdout.contains(name), "{what}: {}", r.stdout);
        assert!(r.stdout.contains("result: MISMATCH"), "{what}: {}", r.stdout);
        if what == "renamed" {
            assert!(
                r.stdout.contains("unused: `net.trunk.blocks.2.ffn.fc1.weight`"),
                "{}",
                r.stdout
            );
        }
    }
    // Our own format is recognised and checked against its stored config.
    let native = inspect(&[common::s(&fx.join("native.safetensors"))]).ok();
    assert!(native.stdout.contains("Native"), "{}", native.stdout);
    // Bad input: another model's config.yaml, a missing file, a truncated file.
    let yaml = std::fs::read_to_string(fx.join("config.yaml")).unwrap();
    let da3 = write_file(
        &t.path().join("da3.yaml"),
        yaml.replace("name: PIXLRelight", "name: DepthAnything3Net"),
    );
    inspect(&[common::s(&model), "--config", common::s(&da3)]).fails(&["DepthAnything3Net"]);
    inspect(&["nothing-here.safetensors"]).fails(&["no such file"]);
    let cut = common::truncated_copy(&model, &t.path().join("cut.safetensors"), 2);
    inspect(&[common::s(&cut)]).fails(&["interrupted download"]);
}
