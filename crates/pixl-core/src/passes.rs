//! Cycles render-pass names, defined once for the renderer (which writes them) and the
//! compositor (which reads them).
//!
//! Blender 4/5 write long names with spaces (`ViewLayer.Diffuse Direct.R`); older Blender and
//! its compositor use the short ones (`ViewLayer.DiffDir.R`). Readers accept both; our renderer
//! writes the long names, as current Blender does.

/// A render pass: its short (legacy) name, its long (Blender 4/5) name, and its channels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Pass {
    pub short: &'static str,
    pub long: &'static str,
    pub channels: &'static [&'static str],
}

const RGB: &[&str] = &["R", "G", "B"];

macro_rules! passes {
    ($($id:ident = $short:literal, $long:literal, $ch:expr;)*) => {
        $(pub const $id: Pass = Pass { short: $short, long: $long, channels: $ch };)*
        /// Every pass this project reads or writes.
        pub const ALL: &[Pass] = &[$($id),*];
    };
}

passes! {
    DIFF_COL = "DiffCol", "Diffuse Color", RGB;
    DIFF_DIR = "DiffDir", "Diffuse Direct", RGB;
    DIFF_IND = "DiffInd", "Diffuse Indirect", RGB;
    GLOSS_COL = "GlossCol", "Glossy Color", RGB;
    GLOSS_DIR = "GlossDir", "Glossy Direct", RGB;
    GLOSS_IND = "GlossInd", "Glossy Indirect", RGB;
    TRANS_COL = "TransCol", "Transmission Color", RGB;
    TRANS_DIR = "TransDir", "Transmission Direct", RGB;
    TRANS_IND = "TransInd", "Transmission Indirect", RGB;
    VOLUME_DIR = "VolumeDir", "Volume Direct", RGB;
    VOLUME_IND = "VolumeInd", "Volume Indirect", RGB;
    EMIT = "Emit", "Emission", RGB;
    ENV = "Env", "Environment", RGB;
    COMBINED = "Combined", "Combined", &["R", "G", "B", "A"];
    DEPTH = "Depth", "Depth", &["Z"];
    NORMAL = "Normal", "Normal", &["X", "Y", "Z"];
}

/// The diffuse passes `pixl compose` requires.
pub const REQUIRED_FOR_COMPOSE: &[Pass] = &[DIFF_COL, DIFF_DIR, DIFF_IND];
/// The non-diffuse passes `pixl compose` uses when present (missing = zero).
pub const OPTIONAL_FOR_COMPOSE: &[Pass] = &[
    GLOSS_COL, GLOSS_DIR, GLOSS_IND, TRANS_COL, TRANS_DIR, TRANS_IND, VOLUME_DIR, VOLUME_IND, EMIT,
];

/// The pass a name (short or long, case-sensitive) refers to.
pub fn by_name(name: &str) -> Option<Pass> {
    ALL.iter().copied().find(|p| p.short == name || p.long == name)
}

/// The default Cycles view-layer name.
pub const VIEW_LAYER: &str = "ViewLayer";
