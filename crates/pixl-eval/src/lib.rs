//! pixl-eval
