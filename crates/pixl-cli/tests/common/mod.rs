//! Helpers shared by the binary-level tests: a `pixl` command isolated from the user's model
//! folders and the network, and running it.
#![allow(dead_code)]
use std::path::Path;
use std::process::{Command, Output};

/// `pixl` with a private HOME, no models folder or Hugging Face cache from the environment,
/// downloads off and a closed endpoint: no test touches the network or the user's files.
pub fn pixl(home: &Path) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_pixl"));
    for v in [
        "PIXL_MODELS_DIR",
        "HF_HUB_CACHE",
        "HUGGINGFACE_HUB_CACHE",
        "HF_HOME",
        "XDG_CACHE_HOME",
        "HF_TOKEN",
        "HF_HUB_OFFLINE",
    ] {
        c.env_remove(v);
    }
    c.env("HOME", home)
        .env("PIXL_OFFLINE", "1")
        .env("HF_ENDPOINT", "http://127.0.0.1:9");
    c
}

/// Runs a command: its output, stdout and stderr.
pub fn run(c: &mut Command) -> (Output, String, String) {
    let o = c.output().expect("run pixl");
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    (o, out, err)
}

/// Copies a folder recursively.
pub fn copy_dir(src: &Path, dst: &Path) {
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        let to = dst.join(e.file_name());
        if e.path().is_dir() {
            copy_dir(&e.path(), &to);
        } else {
            std::fs::copy(e.path(), &to).unwrap();
        }
    }
}
