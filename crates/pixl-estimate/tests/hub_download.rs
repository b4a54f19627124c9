//! Downloads through [`Hub::resolve`] against a stand-in for the Hub's `resolve` endpoint on a
//! loopback port (no network; `HF_ENDPOINT` is given through [`HubOptions::endpoint`]): a file
//! whose content matches its pinned SHA-256 is kept in the cache layout, one that does not is
//! rejected with [`HubError::DigestMismatch`] and leaves nothing behind, and files without a
//! pinned digest are not hashed. The expected digests are the published SHA-256 test vectors,
//! not values computed by the code under test.
use pixl_estimate::hub::{FetchObserver, Hub, HubError, HubOptions, ModelFile, ModelSpec, Source};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

const SHA256_ABC: &str = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad";
const SHA256_EMPTY: &str = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855";
const COMMIT: &str = "0123456789abcdef0123456789abcdef01234567";

/// `org/pinned` at a commit: an unpinned config and weights pinned to the digest of `abc`.
static GOOD: ModelSpec = ModelSpec {
    name: "pinned-good",
    repo: "org/pinned",
    revision: COMMIT,
    files: &[
        ModelFile {
            path: "config.json",
            alt: None,
            approx_bytes: 2,
            sha256: None,
        },
        ModelFile {
            path: "sub/w.bin",
            alt: None,
            approx_bytes: 3,
            sha256: Some(SHA256_ABC),
        },
    ],
    licence: "test",
    licence_url: "",
    purpose: "",
};

/// The same repository, but the weights pinned to the digest of the empty file.
static BAD: ModelSpec = ModelSpec {
    name: "pinned-bad",
    repo: "org/pinned",
    revision: COMMIT,
    files: &[
        ModelFile {
            path: "config.json",
            alt: None,
            approx_bytes: 2,
            sha256: None,
        },
        ModelFile {
            path: "sub/w.bin",
            alt: None,
            approx_bytes: 3,
            sha256: Some(SHA256_EMPTY),
        },
    ],
    licence: "test",
    licence_url: "",
    purpose: "",
};

/// Serves `/<repo>/resolve/<revision>/<file>` with the headers `hf-hub` reads (`etag`,
/// `x-repo-commit`, `content-range`) and `Range: bytes=A-[B]`; 404 otherwise. Returns the
/// endpoint and the log of requested paths.
fn serve(repo: &str, revision: &str, files: Vec<(&'static str, &'static [u8])>) -> (String, Arc<Mutex<Vec<String>>>) {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").expect("bind a loopback port");
    let endpoint = format!("http://{}", listener.local_addr().expect("local address"));
    let log = Arc::new(Mutex::new(Vec::new()));
    let seen = log.clone();
    let prefix = format!("/{repo}/resolve/{revision}/");
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { continue };
            let mut head = Vec::new();
            let mut chunk = [0u8; 1024];
            while !head.windows(4).any(|w| w == b"\r\n\r\n") {
                match stream.read(&mut chunk) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => head.extend_from_slice(&chunk[..n]),
                }
            }
            let head = String::from_utf8_lossy(&head).into_owned();
            let path = head.split_whitespace().nth(1).unwrap_or("").to_string();
            if let Ok(mut l) = seen.lock() {
                l.push(path.clone());
            }
            let range = head
                .lines()
                .find_map(|l| l.to_ascii_lowercase().strip_prefix("range: bytes=").map(str::to_string));
            let found = path
                .strip_prefix(&prefix)
                .and_then(|name| files.iter().find(|(n, _)| *n == name));
            let response = match found {
                Some((name, bytes)) if !bytes.is_empty() => {
                    let last = bytes.len() - 1;
                    let (a, b) = match range.as_deref().and_then(|r| r.split_once('-')) {
                        Some((a, b)) => (
                            a.trim().parse::<usize>().unwrap_or(0).min(last),
                            b.trim().parse::<usize>().unwrap_or(last).min(last),
                        ),
                        None => (0, last),
                    };
                    let mut r = format!(
                        "HTTP/1.1 206 Partial Content\r\ncontent-length: {}\r\netag: \"etag-{}\"\r\n\
x-repo-commit: {COMMIT}\r\ncontent-range: bytes {a}-{b}/{}\r\nconnection: close\r\n\r\n",
                        b + 1 - a,
                        name.replace('/', "-"),
                        bytes.len()
                    )
                    .into_bytes();
                    r.extend_from_slice(&bytes[a..=b]);
                    r
                }
                _ => b"HTTP/1.1 404 Not Found\r\ncontent-length: 0\r\nconnection: close\r\n\r\n".to_vec(),
            };
            let _ = stream.write_all(&response);
        }
    });
    (endpoint, log)
}

fn online(cache: &Path, endpoint: String) -> Hub {
    Hub::new(HubOptions {
        hf_cache: Some(cache.to_path_buf()),
        endpoint: Some(endpoint),
        ..Default::default()
    })
}

/// Records the files announced, downloaded and hashed.
#[derive(Default)]
struct Record {
    announced: Vec<String>,
    started: Vec<String>,
    checked: Vec<(String, u64)>,
}

impl FetchObserver for Record {
    fn before_download(&mut self, _spec: &ModelSpec, missing: &[ModelFile], _into: &Path) {
        self.announced = missing.iter().map(|f| f.path.to_string()).collect();
    }
    fn file_started(&mut self, file: &str, _bytes: u64) {
        self.started.push(file.to_string());
    }
    fn file_checking(&mut self, file: &str, bytes: u64) {
        self.checked.push((file.to_string(), bytes));
    }
}

/// Every regular file under `dir` (links not followed).
fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let t = e.file_type().expect("file type");
            if t.is_dir() {
                todo.push(e.path());
            } else if t.is_file() {
                out.push(e.path());
            }
        }
    }
    out
}

#[test]
fn a_download_matching_its_pinned_digest_is_kept() {
    let (endpoint, log) = serve(
        "org/pinned",
        COMMIT,
        vec![("config.json", b"{}"), ("sub/w.bin", b"abc")],
    );
    let t = tempfile::tempdir().expect("tempdir");
    let cache = t.path().join("hub");
    let hub = online(&cache, endpoint);
    let mut rec = Record::default();
    let r = hub.resolve(&GOOD, &mut rec).expect("download");
    let root = cache.join("models--org--pinned");
    let snap = root.join("snapshots").join(COMMIT);
    assert_eq!(r.dir, snap);
    assert_eq!(
        r.source,
        Source::Downloaded {
            cache: cache.clone(),
            commit: COMMIT.into()
        }
    );
    assert_eq!(rec.announced, ["config.json", "sub/w.bin"]);
    // Only the pinned file is hashed.
    assert_eq!(rec.checked, [("sub/w.bin".to_string(), 3)]);
    assert_eq!(std::fs::read(snap.join("config.json")).expect("config"), b"{}");
    assert_eq!(std::fs::read(snap.join("sub/w.bin")).expect("weights"), b"abc");
    assert_eq!(
        std::fs::read_to_string(root.join("refs").join(COMMIT)).expect("ref"),
        COMMIT
    );
    // The Python layout: a relative link into blobs/, and no staging folder left.
    #[cfg(unix)]
    assert_eq!(
        std::fs::read_link(snap.join("sub/w.bin")).expect("link"),
        Path::new("../../../blobs/etag-sub-w.bin")
    );
    assert!(!root.join(".pixl-incoming").exists());

    // Found again without a request; `verify` agrees with the pinned digest.
    let requests = log.lock().expect("log").len();
    let again = hub.resolve(&GOOD, &mut Record::default()).expect("lookup");
    assert_eq!(again.dir, snap);
    assert_eq!(log.lock().expect("log").len(), requests);
    let checks = again.verify(&mut Record::default()).expect("verify");
    assert_eq!(checks[1].sha256.as_deref(), Some(SHA256_ABC));
    assert_eq!(checks[0].sha256, None);
}

#[test]
fn a_download_with_another_digest_is_rejected_and_removed() {
    let (endpoint, _log) = serve(
        "org/pinned",
        COMMIT,
        vec![("config.json", b"{}"), ("sub/w.bin", b"abc")],
    );
    let t = tempfile::tempdir().expect("tempdir");
    let cache = t.path().join("hub");
    let hub = online(&cache, endpoint);
    let mut rec = Record::default();
    let e = hub.resolve(&BAD, &mut rec).expect_err("a digest mismatch");
    match &e {
        HubError::DigestMismatch {
            model,
            file,
            expected,
            found,
        } => {
            assert_eq!((model.as_str(), file.as_str()), ("pinned-bad", "sub/w.bin"));
            assert_eq!(expected, SHA256_EMPTY);
            assert_eq!(found, SHA256_ABC);
        }
        other => panic!("expected DigestMismatch, got {other:?}"),
    }
    let msg = e.to_string();
    assert!(
        msg.contains("sub/w.bin") && msg.contains(SHA256_EMPTY) && msg.contains(SHA256_ABC),
        "{msg}"
    );
    assert_eq!(rec.checked, [("sub/w.bin".to_string(), 3)]);
    // The rejected content is nowhere in the cache (neither in place nor staged), the model is
    // not found, and the snapshot lacks the file.
    let left = files_under(&cache);
    assert!(
        left.iter()
            .all(|p| std::fs::read(p).map(|b| b != b"abc").unwrap_or(true)),
        "{left:?}"
    );
    let root = cache.join("models--org--pinned");
    assert!(std::fs::symlink_metadata(root.join("snapshots").join(COMMIT).join("sub/w.bin")).is_err());
    assert!(!root.join(".pixl-incoming").exists());
    let offline = Hub::new(HubOptions {
        hf_cache: Some(cache.clone()),
        offline: true,
        ..Default::default()
    });
    assert_eq!(offline.locate(&BAD).expect("locate"), None);
}
