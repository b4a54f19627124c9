//! Outputs that never destroy anything: checks made before any work, and cleanup on interruption.
//!
//! - [`check_output`]: an output *file* is checked before a command starts working: its
//!   extension is one the command writes (the extension decides the format, so `x.png` never
//!   receives EXR bytes), its folder exists and is writable, it is not a folder, and it is not one
//!   of the command's inputs (compared as files: symbolic links and hard links to an input are
//!   caught; an output that does not exist yet is compared by its canonical folder and name).
//!   An existing output file is allowed: [`crate::io::atomic_write`] replaces it only once the new
//!   one is complete.
//! - [`check_output_dir`]: the same for an output *folder* (a scene, a data set): it may be
//!   missing (it is created; its nearest existing ancestor must be a writable folder) or empty; a
//!   non-empty folder is refused unless the caller passes `force` (`--force`), and none of the
//!   files the command writes in it may be one of its inputs, even with `force`.
//! - **Live paths**: every temporary file of [`crate::io::atomic_write`], and every folder or file
//!   a [`Provisional`] set creates, is registered here while it exists. [`remove_live_paths_and_exit`]
//!   removes them all and ends the process; the `pixl` binary calls it from its SIGINT / SIGTERM /
//!   SIGHUP handler, so an interrupted command leaves no temporary file and no half-made folder,
//!   and every file it was replacing keeps its old content. The registry's lock is held from the
//!   removal to the exit, and [`crate::io::atomic_write`] renames under the same lock, so a file is
//!   either renamed complete or removed, never both.
//! - [`Provisional`]: paths a command creates that must disappear unless it finishes (a failed
//!   `pixl synth` removes the scene folders it made): removed when the set is dropped without
//!   [`Provisional::keep`], and on interruption.
//!
//! Test hook: with the environment variable `PIXL_TEST_SLOW_WRITE_MS=N`, every atomic write
//! pauses `N` milliseconds after creating its temporary file, so that a test can interrupt a
//! write at a known moment. Unset (the normal case) it costs one environment lookup per process.
use crate::error::{CoreError, Result};
use crate::io::extension;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, MutexGuard};

/// What a checked output file will be.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OutputKind {
    /// Lower-case extension, one of the allowed ones (decides the format).
    pub ext: String,
    /// A file is already there; it will be replaced atomically.
    pub replaces: bool,
}

/// What a checked output folder is before the command writes into it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OutputDir {
    /// Not there yet: it will be created.
    Missing,
    /// There and empty.
    Empty,
    /// There with files in it, which the command may replace (`force` was given).
    Replacing,
}

/// The folder a file path lives in (`.` for a bare file name).
pub fn parent_dir(path: &Path) -> PathBuf {
    match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_owned(),
        _ => PathBuf::from("."),
    }
}

fn list_exts(allowed: &[&str]) -> String {
    let dotted: Vec<String> = allowed.iter().map(|e| format!(".{e}")).collect();
    match dotted.as_slice() {
        [] => String::new(),
        [one] => one.clone(),
        [init @ .., last] => format!("{} or {last}", init.join(", ")),
    }
}

/// Checks that `dir` is an existing folder this process can create files in, by creating and
/// removing a small probe file (permission bits alone say nothing for root or read-only mounts).
fn probe_writable(dir: &Path, blame: &Path) -> Result<()> {
    static N: AtomicU64 = AtomicU64::new(0);
    let probe = dir.join(format!(
        ".pixl-probe-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    let live = register(&probe, false);
    let made = std::fs::OpenOptions::new().write(true).create_new(true).open(&probe);
    match made {
        Ok(f) => {
            drop(f);
            let _ = std::fs::remove_file(&probe);
            drop(live);
            Ok(())
        }
        Err(e) => Err(CoreError::Output {
            path: blame.to_owned(),
            reason: format!("cannot create files in the folder {}: {e}", dir.display()),
        }),
    }
}

/// `path` made absolute without following its last component: the canonical form of its
/// folder joined with its name (None when the folder does not exist).
fn canonical_target(path: &Path) -> Option<PathBuf> {
    let name = path.file_name()?;
    let dir = std::fs::canonicalize(parent_dir(path)).ok()?;
    Some(dir.join(name))
}

/// Whether `a` and `b` name the same file: the same inode when both exist (links included),
/// else the same canonical folder and name.
pub fn same_file(a: &Path, b: &Path) -> bool {
    if let (Ok(ma), Ok(mb)) = (std::fs::metadata(a), std::fs::metadata(b)) {
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            return ma.dev() == mb.dev() && ma.ino() == mb.ino();
        }
        #[cfg(not(unix))]
        {
            let _ = (ma, mb);
            return std::fs::canonicalize(a).ok() == std::fs::canonicalize(b).ok();
        }
    }
    match (canonical_target(a), canonical_target(b)) {
        (Some(x), Some(y)) => x == y,
        _ => false,
    }
}

/// Checks an output file before any work (see the module docs): `allowed` lists the extensions
/// the command writes, lower case without the dot (empty: any); `inputs` are the files the
/// command reads (missing ones are skipped: reading them reports that).
pub fn check_output(path: &Path, allowed: &[&str], inputs: &[&Path]) -> Result<OutputKind> {
    if path.as_os_str().is_empty() {
        return Err(CoreError::Invalid("the output path is empty".into()));
    }
    let ext = extension(path);
    if !allowed.is_empty() && !allowed.contains(&ext.as_str()) {
        return Err(CoreError::OutputExtension {
            path: path.to_owned(),
            expected: list_exts(allowed),
        });
    }
    if path.is_dir() {
        return Err(CoreError::Output {
            path: path.to_owned(),
            reason: "is a folder; give a file name".into(),
        });
    }
    let dir = parent_dir(path);
    if !dir.exists() {
        return Err(CoreError::Output {
            path: path.to_owned(),
            reason: format!("the output folder {} does not exist", dir.display()),
        });
    }
    if !dir.is_dir() {
        return Err(CoreError::Output {
            path: path.to_owned(),
            reason: format!("{} is not a folder", dir.display()),
        });
    }
    let replaces = match std::fs::symlink_metadata(path) {
        Ok(m) if m.is_file() || m.file_type().is_symlink() => true,
        Ok(_) => {
            return Err(CoreError::Output {
                path: path.to_owned(),
                reason: "exists and is not a regular file; refusing to replace it".into(),
            })
        }
        Err(_) => false,
    };
    for input in inputs {
        if same_file(path, input) {
            return Err(CoreError::OutputIsInput {
                path: path.to_owned(),
                input: input.to_path_buf(),
            });
        }
    }
    probe_writable(&dir, path)?;
    Ok(OutputKind { ext, replaces })
}

/// Checks an output folder before any work (see the module docs). `writes` names the files the
/// command writes directly in it (checked against `inputs`); `force` allows a non-empty folder.
pub fn check_output_dir(dir: &Path, force: bool, writes: &[&str], inputs: &[&Path]) -> Result<OutputDir> {
    if dir.as_os_str().is_empty() {
        return Err(CoreError::Invalid("the output folder path is empty".into()));
    }
    let state = if dir.exists() {
        if !dir.is_dir() {
            return Err(CoreError::Output {
                path: dir.to_owned(),
                reason: "is a file, not a folder".into(),
            });
        }
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .map_err(|e| CoreError::io(dir, e))?
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        if names.is_empty() {
            OutputDir::Empty
        } else if force {
            OutputDir::Replacing
        } else {
            names.sort();
            let shown: Vec<&str> = names.iter().take(4).map(String::as_str).collect();
            return Err(CoreError::Exists {
                path: dir.to_owned(),
                what: format!(
                    "a folder with files in it ({}{})",
                    shown.join(", "),
                    if names.len() > shown.len() { ", …" } else { "" }
                ),
            });
        }
    } else {
        OutputDir::Missing
    };
    // The folder that will hold the new files, or the nearest ancestor that exists.
    let mut probe_dir = dir.to_path_buf();
    while !probe_dir.exists() {
        probe_dir = match probe_dir.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_owned(),
            _ => PathBuf::from("."),
        };
    }
    if !probe_dir.is_dir() {
        return Err(CoreError::Output {
            path: dir.to_owned(),
            reason: format!("cannot create it: {} is a file", probe_dir.display()),
        });
    }
    for name in writes {
        let target = dir.join(name);
        for input in inputs {
            if same_file(&target, input) {
                return Err(CoreError::OutputIsInput {
                    path: target,
                    input: input.to_path_buf(),
                });
            }
        }
    }
    probe_writable(&probe_dir, dir)?;
    Ok(state)
}

// ---------------------------------------------------------------------------------------------
// Live paths

struct Live {
    id: u64,
    path: PathBuf,
    is_dir: bool,
}

static LIVE: Mutex<Vec<Live>> = Mutex::new(Vec::new());
static NEXT_ID: AtomicU64 = AtomicU64::new(0);

fn live() -> MutexGuard<'static, Vec<Live>> {
    // A panic while holding the lock leaves a consistent list (every operation is one push or
    // one retain), so a poisoned lock is used as it is.
    LIVE.lock().unwrap_or_else(|e| e.into_inner())
}

/// A path registered for removal on interruption; unregistered (not removed) when dropped.
#[derive(Debug)]
pub struct LivePath {
    id: u64,
}

impl Drop for LivePath {
    fn drop(&mut self) {
        let id = self.id;
        live().retain(|l| l.id != id);
    }
}

/// Registers `path` (a file, or with `is_dir` a folder and everything in it) for removal if the
/// process is interrupted. Register *before* creating the path, so no moment exists where it is
/// there and unknown to the handler.
pub fn register(path: &Path, is_dir: bool) -> LivePath {
    let id = NEXT_ID.fetch_add(1, Ordering::Relaxed);
    live().push(Live {
        id,
        path: path.to_owned(),
        is_dir,
    });
    LivePath { id }
}

/// Runs `f` (a rename that makes a temporary file final) and unregisters `path` in one step,
/// under the registry's lock, so an interruption sees the temporary file either before (and
/// removes it) or after (and it no longer exists).
pub(crate) fn commit<R>(path: LivePath, f: impl FnOnce() -> R) -> R {
    let mut guard = live();
    let r = f();
    guard.retain(|l| l.id != path.id);
    drop(guard);
    std::mem::forget(path);
    r
}

/// Renames the registered temporary file `tmp` to `dest` and unregisters it in one step (see
/// [`commit`]): for writers that fill a temporary file themselves (a video encoder).
pub fn commit_rename(live: LivePath, tmp: &Path, dest: &Path) -> std::io::Result<()> {
    commit(live, || std::fs::rename(tmp, dest))
}

/// The registered paths (for tests and diagnostics).
pub fn live_paths() -> Vec<PathBuf> {
    live().iter().map(|l| l.path.clone()).collect()
}

/// Removes every registered path (newest first) and ends the process with `code`, holding the
/// registry's lock until the end so that no other thread registers or renames in between. For
/// signal handlers (the `pixl` binary's SIGINT / SIGTERM / SIGHUP handler exits with 130).
pub fn remove_live_paths_and_exit(code: i32) -> ! {
    let guard = live();
    for l in guard.iter().rev() {
        let _ = if l.is_dir {
            std::fs::remove_dir_all(&l.path)
        } else {
            std::fs::remove_file(&l.path)
        };
    }
    std::process::exit(code)
}

/// The test hook's pause (see the module docs), read once per process.
pub(crate) fn test_write_delay() -> Option<std::time::Duration> {
    static DELAY: std::sync::OnceLock<Option<u64>> = std::sync::OnceLock::new();
    DELAY
        .get_or_init(|| {
            std::env::var("PIXL_TEST_SLOW_WRITE_MS")
                .ok()
                .and_then(|v| v.trim().parse::<u64>().ok())
        })
        .map(std::time::Duration::from_millis)
}

/// Folders and files a command creates that must not outlive a failure (see the module docs).
/// Only what did not exist before is added, so a failure never removes older data.
#[derive(Debug, Default)]
pub struct Provisional {
    items: Vec<(PathBuf, bool, LivePath)>,
}

impl Provisional {
    pub fn new() -> Self {
        Self::default()
    }

    /// Creates `dir` and any missing ancestors; those it created are provisional.
    pub fn create_dir_all(&mut self, dir: &Path) -> Result<()> {
        let mut missing = Vec::new();
        let mut p = Some(dir);
        while let Some(d) = p {
            if d.as_os_str().is_empty() {
                break;
            }
            if d.exists() {
                if !d.is_dir() {
                    return Err(CoreError::Output {
                        path: dir.to_owned(),
                        reason: format!("cannot create the folder: {} is a file", d.display()),
                    });
                }
                break;
            }
            missing.push(d.to_owned());
            p = d.parent();
        }
        for d in missing.into_iter().rev() {
            let reg = register(&d, true);
            match std::fs::create_dir(&d) {
                Ok(()) => self.items.push((d, true, reg)),
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && d.is_dir() => drop(reg),
                Err(e) => return Err(CoreError::io(&d, e)),
            }
        }
        Ok(())
    }

    /// Marks a file about to be written as provisional if it does not exist yet.
    pub fn add_new_file(&mut self, path: &Path) {
        if !path.exists() {
            let reg = register(path, false);
            self.items.push((path.to_owned(), false, reg));
        }
    }

    /// Keeps everything: the command finished.
    pub fn keep(mut self) {
        self.items.clear();
    }
}

impl Drop for Provisional {
    fn drop(&mut self) {
        for (path, is_dir, reg) in self.items.drain(..).rev() {
            let _ = if is_dir {
                std::fs::remove_dir_all(&path)
            } else {
                std::fs::remove_file(&path)
            };
            drop(reg);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_output_refuses_wrong_extension_missing_folder_folder_and_input() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.png");
        std::fs::write(&input, b"x").unwrap();
        let e = check_output(&dir.path().join("x.png"), &["exr"], &[]).unwrap_err();
        assert!(matches!(e, CoreError::OutputExtension { .. }), "{e}");
        assert!(e.to_string().contains("must end in .exr"), "{e}");
        let e = check_output(&dir.path().join("x.txt"), &["png", "jpg", "exr"], &[]).unwrap_err();
        assert!(e.to_string().contains(".png, .jpg or .exr"), "{e}");
        let e = check_output(&dir.path().join("no/such/x.exr"), &["exr"], &[]).unwrap_err();
        assert!(e.to_string().contains("does not exist"), "{e}");
        let sub = dir.path().join("sub.exr");
        std::fs::create_dir(&sub).unwrap();
        let e = check_output(&sub, &["exr"], &[]).unwrap_err();
        assert!(e.to_string().contains("is a folder"), "{e}");
        // The same file under another spelling.
        let other = dir.path().join("sub.exr/../in.png");
        let e = check_output(&other, &["png"], &[&input]).unwrap_err();
        assert!(matches!(e, CoreError::OutputIsInput { .. }), "{e}");
        // Fine: a new file, and an existing one (replaced atomically later).
        let k = check_output(&dir.path().join("new.png"), &["png"], &[&input]).unwrap();
        assert_eq!(
            k,
            OutputKind {
                ext: "png".into(),
                replaces: false
            }
        );
        let k = check_output(&input, &["png"], &[]).unwrap();
        assert!(k.replaces);
        // The probe file is gone.
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        assert_eq!(names.len(), 2, "{names:?}");
    }

    #[cfg(unix)]
    #[test]
    fn links_to_an_input_are_the_input() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.exr");
        std::fs::write(&input, b"x").unwrap();
        let hard = dir.path().join("hard.exr");
        std::fs::hard_link(&input, &hard).unwrap();
        let soft = dir.path().join("soft.exr");
        std::os::unix::fs::symlink(&input, &soft).unwrap();
        for p in [&hard, &soft] {
            assert!(check_output(p, &["exr"], &[&input]).is_err(), "{}", p.display());
        }
        assert!(!same_file(&dir.path().join("a.exr"), &input));
    }

    #[test]
    fn check_output_dir_needs_force_for_a_non_empty_folder() {
        let dir = tempfile::tempdir().unwrap();
        let scene = dir.path().join("scene");
        assert_eq!(check_output_dir(&scene, false, &[], &[]).unwrap(), OutputDir::Missing);
        assert_eq!(
            check_output_dir(&scene.join("deeper/still"), false, &[], &[]).unwrap(),
            OutputDir::Missing
        );
        std::fs::create_dir(&scene).unwrap();
        assert_eq!(check_output_dir(&scene, false, &[], &[]).unwrap(), OutputDir::Empty);
        std::fs::write(scene.join("scene.toml"), b"x").unwrap();
        let e = check_output_dir(&scene, false, &[], &[]).unwrap_err();
        assert!(
            e.to_string().contains("--force") && e.to_string().contains("scene.toml"),
            "{e}"
        );
        assert_eq!(check_output_dir(&scene, true, &[], &[]).unwrap(), OutputDir::Replacing);
        // Even with force, a file the command writes may not be an input.
        let photo = scene.join("photo.png");
        std::fs::write(&photo, b"x").unwrap();
        let e = check_output_dir(&scene, true, &["photo.png"], &[&photo]).unwrap_err();
        assert!(matches!(e, CoreError::OutputIsInput { .. }), "{e}");
        // A file where the folder should be, or above it.
        let e = check_output_dir(&photo, true, &[], &[]).unwrap_err();
        assert!(e.to_string().contains("not a folder"), "{e}");
        let e = check_output_dir(&photo.join("x"), true, &[], &[]).unwrap_err();
        assert!(e.to_string().contains("is a file"), "{e}");
    }

    #[test]
    fn provisional_removes_what_it_created_unless_kept() {
        let dir = tempfile::tempdir().unwrap();
        let old = dir.path().join("old");
        std::fs::create_dir(&old).unwrap();
        std::fs::write(old.join("keep.txt"), b"x").unwrap();
        {
            let mut p = Provisional::new();
            p.create_dir_all(&dir.path().join("a/b")).unwrap();
            p.create_dir_all(&old).unwrap();
            let f = old.join("new.txt");
            p.add_new_file(&f);
            std::fs::write(&f, b"y").unwrap();
            p.add_new_file(&old.join("keep.txt"));
            assert!(live_paths().iter().any(|l| l.ends_with("a/b")));
        }
        let mut names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .flatten()
            .map(|e| e.file_name())
            .collect();
        names.sort();
        assert_eq!(names, vec![std::ffi::OsString::from("old")]);
        assert!(old.join("keep.txt").is_file() && !old.join("new.txt").exists());
        assert!(!live_paths().iter().any(|l| l.starts_with(dir.path())));
        let mut p = Provisional::new();
        p.create_dir_all(&dir.path().join("c")).unwrap();
        p.keep();
        assert!(dir.path().join("c").is_dir());
    }
}
