//! Outputs that never destroy anything, and messages a user can trust: the real `pixl` binary.
//!
//! Each test is one bad case: it gets its clear error (or the right result), and nothing is
//! overwritten or left behind. The interruption tests use the test hook
//! `PIXL_TEST_SLOW_WRITE_MS` (every atomic write pauses after creating its temporary file; see
//! `pixl_core::output`) to send SIGINT while a write is in progress.
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

fn pixl() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_pixl"));
    c.env_remove("PIXL_TEST_SLOW_WRITE_MS").env_remove("NO_COLOR");
    c
}

fn run(args: &[&str]) -> Output {
    pixl().args(args).output().expect("run pixl")
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Expects exit 1 with every needle in stderr, no panic.
fn expect_error(o: &Output, needles: &[&str]) -> String {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(1), "exit {:?}; stderr: {err}", o.status.code());
    assert!(!err.contains("panicked"), "{err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks {n:?}: {err}");
    }
    err
}

/// Every file under `dir` (relative paths, sorted), folders included.
fn tree(dir: &Path) -> Vec<String> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<String>) {
        if let Ok(rd) = std::fs::read_dir(d) {
            for e in rd.flatten() {
                let p = e.path();
                out.push(p.strip_prefix(root).unwrap_or(&p).display().to_string());
                if p.is_dir() {
                    walk(root, &p, out);
                }
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

fn no_temp_files(dir: &Path) {
    for f in tree(dir) {
        assert!(!f.contains(".tmp-") && !f.contains(".pixl-probe-"), "left behind: {f}");
    }
}

/// A 16×12 scene: a sphere under a point light, camera 3 m back.
fn scene(dir: &Path) -> PathBuf {
    let p = dir.join("scene.toml");
    std::fs::write(
        &p,
        "[camera]\nwidth = 16\nheight = 12\nfov_y_deg = 40.0\nposition = [0.0, 0.0, 3.0]\n\n\
         [[objects]]\nshape = { type = \"sphere\", radius = 1.0 }\n\n\
         [[lights]]\ntype = \"point\"\nposition = [0.0, 2.0, 2.0]\npower = 100.0\n",
    )
    .unwrap();
    p
}

#[test]
fn render_output_extension_decides_the_format() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path());
    // EXR passes under a .png name: refused before any work, nothing written.
    let png = dir.path().join("x.png");
    let o = run(&["render", s(&sc), "--spp", "1", "-o", s(&png)]);
    expect_error(&o, &["x.png", ".exr"]);
    assert!(!png.exists());
    // A preview of an unknown type: refused, and the passes are not written either.
    let out = dir.path().join("passes.exr");
    let o = run(&[
        "render",
        s(&sc),
        "--spp",
        "1",
        "-o",
        s(&out),
        "--preview",
        s(&dir.path().join("p.txt")),
    ]);
    expect_error(&o, &["p.txt", ".png, .jpg or .jpeg"]);
    assert!(!out.exists());
    // A .jpg preview is a JPEG, a .png preview a PNG, the passes an EXR.
    for (name, magic) in [("p.jpg", &b"\xff\xd8\xff"[..]), ("p.png", &b"\x89PNG"[..])] {
        let prev = dir.path().join(name);
        let o = run(&[
            "-q",
            "render",
            s(&sc),
            "--spp",
            "1",
            "-o",
            s(&out),
            "--preview",
            s(&prev),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(std::fs::read(&prev).unwrap().starts_with(magic), "{name}");
        assert!(
            std::fs::read(&out).unwrap().starts_with(&[0x76, 0x2f, 0x31, 0x01]),
            "passes are not EXR"
        );
    }
    no_temp_files(dir.path());
}

/// The output folder is checked before the scene is even read: a missing folder is the error
/// (not the missing scene, which is read after), so no render ever runs for nothing.
#[test]
fn missing_output_folder_is_reported_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("no-such-folder/passes.exr");
    let o = run(&["render", s(&dir.path().join("absent.toml")), "-o", s(&out)]);
    let err = expect_error(&o, &["passes.exr", "no-such-folder", "does not exist"]);
    assert!(!err.contains("absent.toml"), "{err}");
    assert!(!dir.path().join("no-such-folder").exists());
}

#[test]
fn an_output_that_is_an_input_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path());
    let passes = dir.path().join("passes.exr");
    let o = run(&["-q", "render", s(&sc), "--spp", "1", "-o", s(&passes)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let before = std::fs::read(&passes).unwrap();
    // compose onto its own input, spelled another way.
    std::fs::create_dir(dir.path().join("sub")).unwrap();
    let other = dir.path().join("sub/../passes.exr");
    let o = run(&["compose", s(&passes), "-o", s(&other)]);
    expect_error(&o, &["the output is the input"]);
    // ... or through a symbolic link.
    #[cfg(unix)]
    {
        let link = dir.path().join("link.exr");
        std::os::unix::fs::symlink(&passes, &link).unwrap();
        let o = run(&["compose", s(&passes), "-o", s(&link)]);
        expect_error(&o, &["link.exr", "the output is the input"]);
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
    }
    assert_eq!(std::fs::read(&passes).unwrap(), before);
    // A scene's own texture as the render output.
    let tex = dir.path().join("env.exr");
    std::fs::copy(&passes, &tex).unwrap();
    let with_world = dir.path().join("world.toml");
    let text = std::fs::read_to_string(&sc).unwrap() + "\n[world]\nimage = \"env.exr\"\nstrength = 1.0\n";
    std::fs::write(&with_world, text).unwrap();
    let o = run(&["render", s(&with_world), "--spp", "1", "-o", s(&tex)]);
    expect_error(&o, &["env.exr", "the output is the input"]);
    assert_eq!(std::fs::read(&tex).unwrap(), before);
    no_temp_files(dir.path());
}

/// An output path that is a folder: one clear message, the OS's words at most once.
#[test]
fn a_folder_as_output_is_one_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path());
    let folder = dir.path().join("out.exr");
    std::fs::create_dir(&folder).unwrap();
    let o = run(&["render", s(&sc), "--spp", "1", "-o", s(&folder)]);
    let err = expect_error(&o, &["out.exr", "is a folder"]);
    assert_eq!(err.matches("os error").count(), 0, "{err}");
    // A folder where a scene file is expected: the OS's message, once.
    // (Before: `d.toml: Is a directory (os error 21): Is a directory (os error 21)`.)
    let d = dir.path().join("d.toml");
    std::fs::create_dir(&d).unwrap();
    let o = run(&["render", s(&d), "--spp", "1", "-o", s(&dir.path().join("p.exr"))]);
    let err = expect_error(&o, &["d.toml"]);
    assert_eq!(err.matches("os error").count(), 1, "one cause, once: {err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    no_temp_files(dir.path());
}

#[test]
fn zero_counts_say_must_be_at_least_one() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path());
    let out = dir.path().join("p.exr");
    for args in [
        vec!["render", s(&sc), "--spp", "0", "-o", s(&out)],
        vec!["synth", "--spp", "0", "-o", s(&out)],
        vec!["synth", "--scenes", "0", "-o", s(&out)],
    ] {
        let o = run(&args);
        let err = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains("must be at least 1"), "{args:?}: {err}");
        assert!(!err.contains("4294967295"), "{args:?}: {err}");
    }
    let o = run(&["synth", "--lights", "1", "-o", s(&out)]);
    assert!(stderr(&o).contains("must be at least 2"), "{}", stderr(&o));
    assert!(!out.exists());
}

#[test]
fn render_json_is_one_document_on_stdout() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path());
    let out = dir.path().join("p.exr");
    let o = run(&["render", s(&sc), "--spp", "2", "--seed", "3", "-o", s(&out), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("stdout is one JSON document");
    assert_eq!(v["output"], s(&out));
    assert_eq!(v["scene"], s(&sc));
    assert_eq!((v["width"].as_u64(), v["height"].as_u64()), (Some(16), Some(12)));
    assert_eq!((v["spp"].as_u64(), v["seed"].as_u64()), (Some(2), Some(3)));
    assert!(v["preview"].is_null() && v["preset"].is_null());
    assert!(v["seconds"].as_f64().is_some_and(|t| t >= 0.0));
}

fn synth_args<'a>(out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let mut v = vec![
        "synth",
        "--scenes",
        "2",
        "--lights",
        "2",
        "--size",
        "8",
        "--spp",
        "1",
        "--test-every",
        "2",
        "-o",
        out,
    ];
    v.extend_from_slice(extra);
    v
}

/// synth and train print their documented JSON; stdout holds nothing else.
#[test]
fn synth_and_train_json() {
    let dir = tempfile::tempdir().unwrap();
    let set = dir.path().join("set");
    let o = run(&synth_args(s(&set), &["--json"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("synth stdout is JSON");
    assert_eq!((v["scenes"].as_u64(), v["test_scenes"].as_u64()), (Some(2), Some(1)));
    assert_eq!((v["lights"].as_u64(), v["size"].as_u64()), (Some(2), Some(8)));
    assert_eq!(v["manifest"], s(&set.join("scenes.json")));
    assert!(set.join("scenes.json").is_file());
    let run_dir = dir.path().join("run");
    let cfg = dir.path().join("train.toml");
    std::fs::write(
        &cfg,
        format!(
            "[data]\ndataset = \"synth:{}\"\n[data.sampler]\nlong_side = 16\nmultiple = 8\n[optim]\nbatch_size = 1\n\
             [loss]\nperceptual_weight = 0.0\n[run]\nout_dir = \"{}\"\nsteps = 1\n",
            set.display(),
            run_dir.display()
        ),
    )
    .unwrap();
    let o = run(&["train", "--config", s(&cfg), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("train stdout is JSON");
    assert_eq!((v["step"].as_u64(), v["start_step"].as_u64()), (Some(1), Some(0)));
    assert_eq!(v["resumed"], false);
    assert!(v["final_loss"].as_f64().is_some_and(f64::is_finite));
    assert_eq!(v["weights"], s(&run_dir.join("model.safetensors")));
    assert!(run_dir.join("model.safetensors").is_file());
}

/// Fine-tuning from weights inside the run folder under the name the run writes: refused
/// before training, the weights untouched.
#[test]
fn train_refuses_to_write_over_its_own_starting_weights() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    std::fs::create_dir(&run_dir).unwrap();
    let w = run_dir.join("model.safetensors");
    let o = run(&["model", "init", "--config", "tiny", "-o", s(&w)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let before = std::fs::read(&w).unwrap();
    let cfg = dir.path().join("train.toml");
    std::fs::write(
        &cfg,
        format!(
            "[data]\ndataset = \"synth:{}\"\n[loss]\nperceptual_weight = 0.0\n[run]\nout_dir = \"{}\"\n",
            dir.path().join("nothing").display(),
            run_dir.display()
        ),
    )
    .unwrap();
    let o = run(&["train", "--config", s(&cfg), "--init-weights", s(&w)]);
    expect_error(&o, &["model.safetensors", "the output is the input"]);
    assert_eq!(std::fs::read(&w).unwrap(), before);
}

#[test]
fn synth_refuses_a_non_empty_folder_without_force() {
    let dir = tempfile::tempdir().unwrap();
    let set = dir.path().join("set");
    std::fs::create_dir(&set).unwrap();
    std::fs::write(set.join("notes.txt"), b"mine").unwrap();
    let o = run(&synth_args(s(&set), &[]));
    expect_error(&o, &["set", "notes.txt", "--force"]);
    assert_eq!(tree(&set), ["notes.txt"]);
}

/// A synth run that fails half-way removes the folders and files it created, and only those.
#[test]
fn failed_synth_removes_what_it_created() {
    let dir = tempfile::tempdir().unwrap();
    let set = dir.path().join("set");
    std::fs::create_dir(&set).unwrap();
    std::fs::write(set.join("notes.txt"), b"mine").unwrap();
    // A file where the second scene's folder goes: scene 0 is made, then the run fails.
    std::fs::write(set.join("scene0001"), b"in the way").unwrap();
    let o = run(&synth_args(s(&set), &["--force"]));
    expect_error(&o, &["scene0001"]);
    assert_eq!(tree(&set), ["notes.txt", "scene0001"]);
    assert_eq!(std::fs::read(set.join("scene0001")).unwrap(), b"in the way");
    // An output folder that cannot be made (a file is in the way): refused before any work.
    let blocker = dir.path().join("blocker");
    std::fs::write(&blocker, b"x").unwrap();
    let o = run(&synth_args(s(&blocker.join("set")), &[]));
    expect_error(&o, &["blocker", "is a file"]);
    assert_eq!(std::fs::read(&blocker).unwrap(), b"x");
}

/// Starts `pixl args` with slow writes, waits until a temporary file shows under `watch`, sends
/// SIGINT, and returns the exit status.
#[cfg(unix)]
fn interrupt_during_write(args: &[&str], watch: &Path) -> std::process::ExitStatus {
    let mut child = pixl()
        .args(args)
        .env("PIXL_TEST_SLOW_WRITE_MS", "30000")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("spawn pixl");
    let t0 = Instant::now();
    while !tree(watch).iter().any(|f| f.contains(".tmp-")) {
        if let Some(st) = child.try_wait().unwrap() {
            panic!("pixl ended ({st}) before writing");
        }
        assert!(t0.elapsed() < Duration::from_secs(120), "no temporary file appeared");
        std::thread::sleep(Duration::from_millis(20));
    }
    let kill = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .expect("kill");
    assert!(kill.success());
    child.wait().expect("wait")
}

/// SIGINT during the write of an existing output: exit 130, the old file intact, no temporary
/// file left.
#[cfg(unix)]
#[test]
fn sigint_during_a_write_leaves_the_old_file_and_no_temporary() {
    let dir = tempfile::tempdir().unwrap();
    let sc = scene(dir.path());
    let out = dir.path().join("passes.exr");
    std::fs::write(&out, b"the previous render").unwrap();
    let st = interrupt_during_write(&["-q", "render", s(&sc), "--spp", "1", "-o", s(&out)], dir.path());
    assert_eq!(st.code(), Some(130), "{st}");
    assert_eq!(std::fs::read(&out).unwrap(), b"the previous render");
    no_temp_files(dir.path());
    assert_eq!(tree(dir.path()), ["passes.exr", "scene.toml"]);
}

/// SIGINT during `pixl synth` into a new folder: the folder is gone.
#[cfg(unix)]
#[test]
fn sigint_during_synth_removes_the_new_set() {
    let dir = tempfile::tempdir().unwrap();
    let set = dir.path().join("set");
    let st = interrupt_during_write(&synth_args(s(&set), &["-q"]), dir.path());
    assert_eq!(st.code(), Some(130), "{st}");
    assert!(tree(dir.path()).is_empty(), "{:?}", tree(dir.path()));
}

/// Logs on a pipe carry no ANSI colour codes; progress bars do not draw there either.
#[test]
fn no_colour_codes_in_pipes() {
    let dir = tempfile::tempdir().unwrap();
    let sc = dir.path().join("glass.toml");
    std::fs::write(
        &sc,
        "[camera]\nwidth = 8\nheight = 6\nfov_y_deg = 40.0\nposition = [0.0, 0.0, 3.0]\n\n\
         [[objects]]\nshape = { type = \"sphere\", radius = 1.0 }\n\
         material = { transmission = 1.0, roughness = 0.3 }\n\n\
         [[lights]]\ntype = \"point\"\nposition = [0.0, 2.0, 2.0]\npower = 100.0\n",
    )
    .unwrap();
    let o = run(&["render", s(&sc), "--spp", "1", "-o", s(&dir.path().join("p.exr"))]);
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(!err.contains('\x1b'), "ANSI codes in a pipe: {err:?}");
    assert!(!String::from_utf8_lossy(&o.stdout).contains('\x1b'));
    // A warning (an unlit light) on a pipe: plain text too.
    let o = run(&[
        "light",
        "add",
        s(&sc),
        "--type",
        "point",
        "--power",
        "0",
        "--position",
        "0,1,0",
        "-o",
        s(&dir.path().join("dark.toml")),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(err.contains("gives no light"), "the warning was expected: {err}");
    assert!(!err.contains('\x1b'), "ANSI codes in a pipe: {err:?}");
}

#[test]
fn help_texts_are_self_contained() {
    let help = |args: &[&str]| {
        let o = run(args);
        assert!(o.status.success(), "{args:?}");
        String::from_utf8_lossy(&o.stdout).into_owned()
    };
    for cmd in ["eval", "train"] {
        let h = help(&[cmd, "--help"]);
        for kind in [
            "miiw:ROOT",
            "bigtime:ROOT",
            "vidit:ROOT",
            "folder:ROOT",
            "synth:ROOT",
            "test.txt",
        ] {
            assert!(h.contains(kind), "{cmd} --help lacks {kind}");
        }
        assert!(!h.contains("pixl_train::"), "{cmd} --help points to a Rust module");
        assert!(
            !h.contains("see `pixl train --help`"),
            "{cmd} --help sends the reader away"
        );
    }
    let h = help(&["train", "--help"]);
    for key in ["[data]", "[optim.schedule]", "perceptual_weight", "out_dir"] {
        assert!(h.contains(key), "train --help lacks {key}");
    }
    let h = help(&["render", "--help"]);
    for words in ["+Y up", "-Z forward", "metres", "W/m^2", "at least 1"] {
        assert!(h.contains(words), "render --help lacks {words:?}");
    }
}

#[test]
fn shell_completions() {
    for (shell, marker) in [
        ("bash", "complete"),
        ("zsh", "#compdef pixl"),
        ("fish", "complete -c pixl"),
    ] {
        let o = run(&["completions", shell]);
        assert!(o.status.success(), "{shell}: {}", stderr(&o));
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(text.contains(marker), "{shell}: {text}");
        assert!(text.contains("render") && text.contains("relight"), "{shell}");
    }
    let o = run(&["completions", "tcsh"]);
    assert_eq!(o.status.code(), Some(2));
}
