//! pixl-intrinsics
