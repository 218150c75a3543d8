//! Detectors: each maps a frame to predictions `(x, y, score)` in TrackPy
//! pixel coordinates (`x` column, `y` row, pixel centres at integers).

pub mod candidates;
pub mod cnn;
pub(crate) mod cpu;
pub mod crocker_grier;
pub mod likelihood;
