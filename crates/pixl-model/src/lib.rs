//! pixl-model
