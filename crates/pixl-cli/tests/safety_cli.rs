//! Outputs that never destroy anything, and messages a user can trust: the real `pixl` binary.
//!
//! Each test is one bad case: it gets its clear error (or the right result), and nothing is
//! overwritten or left behind. The interruption tests use the test hook
//! `PIXL_TEST_SLOW_WRITE_MS` (every atomic write pauses after creating its temporary file; see
//! `pixl_core::output`) to send SIGINT while a write is in progress.
mod common;
use common::{assert_no_temp_files as no_temp_files, pixl, s, sphere_scene, tree, write_file};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

/// A temporary folder holding `scene.toml`: a 16×12 view of a sphere under a point light,
/// camera 3 m back.
fn with_scene() -> (tempfile::TempDir, PathBuf) {
    let dir = common::tempdir();
    let scene = write_file(
        &dir.path().join("scene.toml"),
        sphere_scene(
            16,
            12,
            "\n[[lights]]\ntype = \"point\"\nposition = [0.0, 2.0, 2.0]\npower = 100.0\n",
        ),
    );
    (dir, scene)
}

/// `pixl synth` of a tiny set (8 pixels, 1 sample) into `out`, then `extra`.
fn synth_args<'a>(out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    common::synth_args(out, "8", "1", extra)
}

#[test]
fn render_output_extension_decides_the_format() {
    let (dir, sc) = with_scene();
    // EXR passes under a .png name: refused before any work, nothing written.
    let png = dir.path().join("x.png");
    pixl(&["render", s(&sc), "--spp", "1", "-o", s(&png)]).fails(&["x.png", ".exr"]);
    assert!(!png.exists());
    // A preview of an unknown type: refused, and the passes are not written either.
    let out = dir.path().join("passes.exr");
    // `pixl render` of the scene into `out` with the preview `prev`, then `extra`.
    let render = |prev: &Path, extra: &[&str]| {
        let args = ["render", s(&sc), "--spp", "1", "-o", s(&out), "--preview", s(prev)];
        pixl(&[&args[..], extra].concat())
    };
    render(&dir.path().join("p.txt"), &[]).fails(&["p.txt", ".png, .jpg or .jpeg"]);
    assert!(!out.exists());
    // A .jpg preview is a JPEG, a .png preview a PNG, the passes an EXR.
    for (name, magic) in [("p.jpg", &b"\xff\xd8\xff"[..]), ("p.png", &b"\x89PNG"[..])] {
        let prev = dir.path().join(name);
        render(&prev, &["-q"]).ok();
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
    let dir = common::tempdir();
    let out = dir.path().join("no-such-folder/passes.exr");
    let o = pixl(&["render", s(&dir.path().join("absent.toml")), "-o", s(&out)]);
    let err = o.fails(&["passes.exr", "no-such-folder", "does not exist"]);
    assert!(!err.contains("absent.toml"), "{err}");
    assert!(!dir.path().join("no-such-folder").exists());
}

#[test]
fn an_output_that_is_an_input_is_refused() {
    let (dir, sc) = with_scene();
    let passes = dir.path().join("passes.exr");
    pixl(&["-q", "render", s(&sc), "--spp", "1", "-o", s(&passes)]).ok();
    let before = std::fs::read(&passes).unwrap();
    // compose onto its own input, spelled another way.
    std::fs::create_dir(dir.path().join("sub")).unwrap();
    let other = dir.path().join("sub/../passes.exr");
    pixl(&["compose", s(&passes), "-o", s(&other)]).fails(&["the output is the input"]);
    // ... or through a symbolic link.
    #[cfg(unix)]
    {
        let link = dir.path().join("link.exr");
        std::os::unix::fs::symlink(&passes, &link).unwrap();
        pixl(&["compose", s(&passes), "-o", s(&link)]).fails(&["link.exr", "the output is the input"]);
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
    }
    assert_eq!(std::fs::read(&passes).unwrap(), before);
    // A scene's own texture as the render output.
    let tex = dir.path().join("env.exr");
    std::fs::copy(&passes, &tex).unwrap();
    let with_world = dir.path().join("world.toml");
    let text = std::fs::read_to_string(&sc).unwrap() + "\n[world]\nimage = \"env.exr\"\nstrength = 1.0\n";
    std::fs::write(&with_world, text).unwrap();
    pixl(&["render", s(&with_world), "--spp", "1", "-o", s(&tex)]).fails(&["env.exr", "the output is the input"]);
    assert_eq!(std::fs::read(&tex).unwrap(), before);
    no_temp_files(dir.path());
}

/// An output path that is a folder: one clear message, the OS's words at most once.
#[test]
fn a_folder_as_output_is_one_clear_error() {
    let (dir, sc) = with_scene();
    let folder = dir.path().join("out.exr");
    std::fs::create_dir(&folder).unwrap();
    let o = pixl(&["render", s(&sc), "--spp", "1", "-o", s(&folder)]);
    let err = o.fails(&["out.exr", "is a folder"]);
    assert_eq!(err.matches("os error").count(), 0, "{err}");
    // A folder where a scene file is expected: the OS's message, once.
    // (Before: `d.toml: Is a directory (os error 21): Is a directory (os error 21)`.)
    let d = dir.path().join("d.toml");
    std::fs::create_dir(&d).unwrap();
    let o = pixl(&["render", s(&d), "--spp", "1", "-o", s(&dir.path().join("p.exr"))]);
    let err = o.fails(&["d.toml"]);
    assert_eq!(err.matches("os error").count(), 1, "one cause, once: {err}");
    assert_eq!(err.lines().count(), 1, "{err}");
    no_temp_files(dir.path());
}

#[test]
fn zero_counts_say_must_be_at_least_one() {
    let (dir, sc) = with_scene();
    let out = dir.path().join("p.exr");
    for args in [
        vec!["render", s(&sc), "--spp", "0", "-o", s(&out)],
        vec!["synth", "--spp", "0", "-o", s(&out)],
        vec!["synth", "--scenes", "0", "-o", s(&out)],
    ] {
        let o = pixl(&args);
        let err = &o.stderr;
        assert_eq!(o.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains("must be at least 1"), "{args:?}: {err}");
        assert!(!err.contains("4294967295"), "{args:?}: {err}");
    }
    let o = pixl(&["synth", "--lights", "1", "-o", s(&out)]);
    assert!(o.stderr.contains("must be at least 2"), "{}", o.stderr);
    assert!(!out.exists());
}

#[test]
fn render_json_is_one_document_on_stdout() {
    let (dir, sc) = with_scene();
    let out = dir.path().join("p.exr");
    let v = pixl(&["render", s(&sc), "--spp", "2", "--seed", "3", "-o", s(&out), "--json"])
        .ok()
        .json();
    assert_eq!(v["output"], s(&out));
    assert_eq!(v["scene"], s(&sc));
    assert_eq!((v["width"].as_u64(), v["height"].as_u64()), (Some(16), Some(12)));
    assert_eq!((v["spp"].as_u64(), v["seed"].as_u64()), (Some(2), Some(3)));
    assert!(v["preview"].is_null() && v["preset"].is_null());
    assert!(v["seconds"].as_f64().is_some_and(|t| t >= 0.0));
}

/// synth and train print their documented JSON; stdout holds nothing else.
#[test]
fn synth_and_train_json() {
    let dir = common::tempdir();
    let set = dir.path().join("set");
    let v = pixl(&synth_args(s(&set), &["--json"])).ok().json();
    assert_eq!((v["scenes"].as_u64(), v["test_scenes"].as_u64()), (Some(2), Some(1)));
    assert_eq!((v["lights"].as_u64(), v["size"].as_u64()), (Some(2), Some(8)));
    assert_eq!(v["manifest"], s(&set.join("scenes.json")));
    assert!(set.join("scenes.json").is_file());
    let run_dir = dir.path().join("run");
    let cfg = write_file(
        &dir.path().join("train.toml"),
        format!(
            "[data]\ndataset = \"synth:{}\"\n[data.sampler]\nlong_side = 16\nmultiple = 8\n[optim]\nbatch_size = 1\n\
             [loss]\nperceptual_weight = 0.0\n[run]\nout_dir = \"{}\"\nsteps = 1\n",
            set.display(),
            run_dir.display()
        ),
    );
    let v = pixl(&["train", "--config", s(&cfg), "--json"]).ok().json();
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
    let dir = common::tempdir();
    let run_dir = dir.path().join("run");
    std::fs::create_dir(&run_dir).unwrap();
    let w = common::tiny_weights(&run_dir.join("model.safetensors"), 0);
    let before = std::fs::read(&w).unwrap();
    let cfg = write_file(
        &dir.path().join("train.toml"),
        format!(
            "[data]\ndataset = \"synth:{}\"\n[loss]\nperceptual_weight = 0.0\n[run]\nout_dir = \"{}\"\n",
            dir.path().join("nothing").display(),
            run_dir.display()
        ),
    );
    pixl(&["train", "--config", s(&cfg), "--init-weights", s(&w)])
        .fails(&["model.safetensors", "the output is the input"]);
    assert_eq!(std::fs::read(&w).unwrap(), before);
}

#[test]
fn synth_refuses_a_non_empty_folder_without_force() {
    let dir = common::tempdir();
    let set = dir.path().join("set");
    write_file(&set.join("notes.txt"), b"mine"); // the folder, with a file of the user's
    pixl(&synth_args(s(&set), &[])).fails(&["set", "notes.txt", "--force"]);
    assert_eq!(tree(&set), ["notes.txt"]);
}

/// A synth run that fails half-way removes the folders and files it created, and only those.
#[test]
fn failed_synth_removes_what_it_created() {
    let dir = common::tempdir();
    let set = dir.path().join("set");
    write_file(&set.join("notes.txt"), b"mine"); // the folder, with a file of the user's
                                                 // A file where the second scene's folder goes: scene 0 is made, then the run fails.
    write_file(&set.join("scene0001"), b"in the way");
    pixl(&synth_args(s(&set), &["--force"])).fails(&["scene0001"]);
    assert_eq!(tree(&set), ["notes.txt", "scene0001"]);
    assert_eq!(std::fs::read(set.join("scene0001")).unwrap(), b"in the way");
    // An output folder that cannot be made (a file is in the way): refused before any work.
    let blocker = dir.path().join("blocker");
    std::fs::write(&blocker, b"x").unwrap();
    pixl(&synth_args(s(&blocker.join("set")), &[])).fails(&["blocker", "is a file"]);
    assert_eq!(std::fs::read(&blocker).unwrap(), b"x");
}

/// Starts `pixl args` with slow writes, waits until a temporary file shows under `watch`, sends
/// SIGINT, and returns the exit status.
#[cfg(unix)]
fn interrupt_during_write(args: &[&str], watch: &Path) -> std::process::ExitStatus {
    let mut child = common::cmd()
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
    let (dir, sc) = with_scene();
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
    let dir = common::tempdir();
    let set = dir.path().join("set");
    let st = interrupt_during_write(&synth_args(s(&set), &["-q"]), dir.path());
    assert_eq!(st.code(), Some(130), "{st}");
    assert!(tree(dir.path()).is_empty(), "{:?}", tree(dir.path()));
}

/// Logs on a pipe carry no ANSI colour codes; progress bars do not draw there either.
#[test]
fn no_colour_codes_in_pipes() {
    let dir = common::tempdir();
    let sc = write_file(
        &dir.path().join("glass.toml"),
        sphere_scene(
            8,
            6,
            "material = { transmission = 1.0, roughness = 0.3 }\n\n\
             [[lights]]\ntype = \"point\"\nposition = [0.0, 2.0, 2.0]\npower = 100.0\n",
        ),
    );
    let o = pixl(&["render", s(&sc), "--spp", "1", "-o", s(&dir.path().join("p.exr"))]).ok();
    assert!(!o.stderr.contains('\x1b'), "ANSI codes in a pipe: {:?}", o.stderr);
    assert!(!o.stdout.contains('\x1b'));
    // A warning (an unlit light) on a pipe: plain text too.
    let o = pixl(&[
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
    ])
    .ok();
    let err = o.stderr;
    assert!(err.contains("gives no light"), "the warning was expected: {err}");
    assert!(!err.contains('\x1b'), "ANSI codes in a pipe: {err:?}");
}

#[test]
fn help_texts_are_self_contained() {
    let help = |args: &[&str]| {
        let o = pixl(args);
        assert!(o.success(), "{args:?}");
        o.stdout
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
        let text = pixl(&["completions", shell]).ok().stdout;
        assert!(text.contains(marker), "{shell}: {text}");
        assert!(text.contains("render") && text.contains("relight"), "{shell}");
    }
    assert_eq!(pixl(&["completions", "tcsh"]).code(), Some(2));
}
