//! pixl-train
