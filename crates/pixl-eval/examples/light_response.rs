//! The light-response score of relit images against the renders of the same lightings, from files:
//! for any photo relit under several lightings with `pixl relight --keep`, whose `render.png` is
//! the path-traced render of the photo's coarse scene (the module docs of `pixl_eval::response`).
//!
//!     cargo run --release -p pixl-eval --example light_response -- \
//!         RELIT_1.png RENDER_1.png RELIT_2.png RENDER_2.png [...]
//!
//! Prints one JSON object: gain, correlation, pairs, pixels. Relit images of another size than
//! their render (the network works at a capped size; the render is at the photo's) are an error:
//! relight at the render's size.
use pixl_core::io::read_rgb;
use std::path::PathBuf;
use std::process::ExitCode;

fn main() -> ExitCode {
    let files: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    if files.len() < 4 || !files.len().is_multiple_of(2) {
        eprintln!("usage: light_response RELIT_1 RENDER_1 RELIT_2 RENDER_2 [...] (two lightings or more)");
        return ExitCode::from(2);
    }
    let mut images = Vec::with_capacity(files.len());
    for f in &files {
        match read_rgb(f) {
            Ok(img) => images.push(img),
            Err(e) => {
                eprintln!("{}: {e}", f.display());
                return ExitCode::FAILURE;
            }
        }
    }
    let relit: Vec<_> = images.iter().step_by(2).collect();
    let renders: Vec<_> = images.iter().skip(1).step_by(2).collect();
    match pixl_eval::light_response(&relit, &renders) {
        Ok(r) => {
            println!(
                "{{\"gain\": {:.4}, \"correlation\": {:.4}, \"pairs\": {}, \"pixels\": {}}}",
                r.gain, r.correlation, r.pairs, r.pixels
            );
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("light response: {e}");
            ExitCode::FAILURE
        }
    }
}
