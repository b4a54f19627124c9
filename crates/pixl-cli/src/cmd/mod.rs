//! One module per subcommand: each has `Args` (or a `Command` enum) and `run`.
pub mod augment;
pub mod bench;
pub mod blender;
pub mod compose;
pub mod demo;
pub mod eval;
pub mod intrinsics;
pub mod light;
pub mod model;
pub mod reconstruct;
pub mod relight;
pub mod render;
pub mod synth;
pub mod train;
