//! Helpers shared by the binary-level tests of `pixl`: every test file says `mod common;` and
//! uses these instead of its own copies.
//!
//! - [`run`]: the `pixl` binary in an environment isolated from the user's model folders, caches
//!   and the network ([`cmd`], [`cmd_in`]), run to a [`Run`] (exit status, stdout, stderr) with
//!   assertions that name the command line on failure ([`Run::ok`], [`Run::fails`], …).
//! - [`files`]: temporary folders, paths as text, test images, depth maps, C_T files, scenes,
//!   hand-made PNG headers and `.npy` files, and checks on what a folder holds afterwards.
//! - [`make`]: what the binary itself makes for other tests: fresh `tiny` weights, a tiny
//!   synthetic set, the arguments of `pixl relight`.
//!
//! Each test binary uses only some of them.
#![allow(dead_code, unused_imports)]

pub mod files;
pub mod make;
pub mod run;

pub use files::*;
pub use make::*;
pub use run::*;
