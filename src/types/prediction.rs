//! What a detector reports: one localisation per row.

/// One localisation made by a detector on one frame, in TrackPy pixel
/// coordinates (`x` column, `y` row, pixel centres at integers).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Prediction {
    /// Index of the frame in its stack.
    pub frame: usize,
    /// Column coordinate in pixels.
    pub x: f64,
    /// Row coordinate in pixels.
    pub y: f64,
    /// Confidence used to rank predictions in the metric: higher is surer.
    pub score: f64,
}
