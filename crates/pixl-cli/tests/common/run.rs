//! Running the `pixl` binary: an isolated environment, and the result with assertions whose
//! messages name the command line, its exit status and its stderr.
use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus};

/// The binary under test.
pub const BIN: &str = env!("CARGO_BIN_EXE_pixl");

/// Variables a test run never inherits: model folders and caches (they come from HOME or the
/// test), the Hub's token and offline switch, proxies (a loopback stand-in for the Hub must be
/// reached directly), the slow-write test hook, and `NO_COLOR` (pipes must be plain without it).
const CLEARED: &[&str] = &[
    "PIXL_MODELS_DIR",
    "PIXL_OFFLINE",
    "HF_HUB_CACHE",
    "HUGGINGFACE_HUB_CACHE",
    "HF_HOME",
    "XDG_CACHE_HOME",
    "HF_TOKEN",
    "HF_HUB_OFFLINE",
    "ALL_PROXY",
    "all_proxy",
    "HTTPS_PROXY",
    "https_proxy",
    "HTTP_PROXY",
    "http_proxy",
    "PIXL_TEST_SLOW_WRITE_MS",
    "NO_COLOR",
];

/// `pixl` with HOME at `home`, none of [`CLEARED`] from the environment, downloads off and a
/// closed endpoint: no test touches the network or the user's files. A test that wants to be
/// online removes `PIXL_OFFLINE` (and points `HF_ENDPOINT` at its own stand-in).
pub fn cmd_in(home: &Path) -> Command {
    let mut c = Command::new(BIN);
    for v in CLEARED {
        c.env_remove(v);
    }
    c.env("HOME", home)
        .env("PIXL_OFFLINE", "1")
        .env("HF_ENDPOINT", "http://127.0.0.1:9");
    c
}

/// [`cmd_in`] an empty HOME shared by the tests that need none of their own (a folder under
/// Cargo's temporary directory for integration tests).
pub fn cmd() -> Command {
    cmd_in(&shared_home())
}

/// The HOME of [`cmd`].
pub fn shared_home() -> PathBuf {
    let home = Path::new(env!("CARGO_TARGET_TMPDIR")).join("pixl-cli-home");
    std::fs::create_dir_all(&home).expect("create the shared test HOME");
    home
}

/// Runs `pixl args` ([`cmd`]).
pub fn pixl(args: &[&str]) -> Run {
    run(cmd().args(args))
}

/// Runs `pixl args --quiet` ([`cmd`]).
pub fn pixl_q(args: &[&str]) -> Run {
    run(cmd().args(args).arg("--quiet"))
}

/// Runs `pixl args` with HOME at `home` ([`cmd_in`]).
pub fn pixl_in(home: &Path, args: &[&str]) -> Run {
    run(cmd_in(home).args(args))
}

/// Runs a command to its end.
#[track_caller]
pub fn run(c: &mut Command) -> Run {
    let line = std::iter::once(OsStr::new("pixl"))
        .chain(c.get_args())
        .map(|a| a.to_string_lossy().into_owned())
        .collect::<Vec<_>>()
        .join(" ");
    let o = c.output().unwrap_or_else(|e| panic!("`{line}` did not run: {e}"));
    Run {
        status: o.status,
        stdout: String::from_utf8_lossy(&o.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&o.stderr).into_owned(),
        stdout_bytes: o.stdout,
        line,
    }
}

/// What a run of `pixl` gave.
pub struct Run {
    pub status: ExitStatus,
    /// stdout, lossily decoded.
    pub stdout: String,
    /// stderr, lossily decoded.
    pub stderr: String,
    /// stdout as written.
    pub stdout_bytes: Vec<u8>,
    /// The command line, for messages.
    pub line: String,
}

impl Run {
    pub fn success(&self) -> bool {
        self.status.success()
    }

    pub fn code(&self) -> Option<i32> {
        self.status.code()
    }

    /// stdout then stderr.
    pub fn text(&self) -> String {
        format!("{}{}", self.stdout, self.stderr)
    }

    /// Asserts success.
    #[track_caller]
    pub fn ok(self) -> Self {
        assert!(
            self.success(),
            "`{}` failed ({}); stderr:\n{}",
            self.line,
            self.status,
            self.stderr
        );
        self
    }

    /// stdout as one JSON document.
    #[track_caller]
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.stdout_bytes).unwrap_or_else(|e| {
            panic!(
                "`{}`: stdout is not one JSON document ({e}):\n{}\nstderr:\n{}",
                self.line, self.stdout, self.stderr
            )
        })
    }

    /// Asserts a clean failure: exit code 1 (an error, not a command-line error), no panic, and
    /// every needle in stderr. Returns stderr.
    #[track_caller]
    pub fn fails(&self, needles: &[&str]) -> &str {
        self.clean_failure();
        for n in needles {
            assert!(
                self.stderr.contains(n),
                "`{}`: stderr lacks {n:?}: {}",
                self.line,
                self.stderr
            );
        }
        &self.stderr
    }

    /// [`Run::fails`], the needles matched whatever their case.
    #[track_caller]
    pub fn fails_ignoring_case(&self, needles: &[&str]) -> &str {
        self.clean_failure();
        let low = self.stderr.to_lowercase();
        for n in needles {
            assert!(
                low.contains(&n.to_lowercase()),
                "`{}`: stderr lacks {n:?}: {}",
                self.line,
                self.stderr
            );
        }
        &self.stderr
    }

    #[track_caller]
    fn clean_failure(&self) {
        assert_eq!(
            self.code(),
            Some(1),
            "`{}`: expected exit 1, got {}; stderr: {}",
            self.line,
            self.status,
            self.stderr
        );
        assert!(
            !self.stderr.contains("panicked"),
            "`{}` panicked: {}",
            self.line,
            self.stderr
        );
    }
}
