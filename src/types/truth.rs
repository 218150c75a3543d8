//! Ground truth: where each emitter was while a frame was scanned.

use serde::{Deserialize, Serialize};

use super::FrameStack;

/// Ground truth of one emitter in one frame, in TrackPy pixel coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TruthRow {
    /// Frame index within its dataset.
    pub frame: usize,
    /// Trajectory centroid: mean x (column) over every PSF sample.
    pub x: f64,
    /// Trajectory centroid: mean y (row) over every PSF sample.
    pub y: f64,
    /// Position at the first sample (the beam at pixel (0, 0)).
    pub x_start: f64,
    pub y_start: f64,
    /// Position at the last sample (the beam at the last pixel).
    pub x_end: f64,
    pub y_end: f64,
    /// Mean depth relative to focus, µm.
    pub z_mean: f64,
    /// The frame's diffusion coefficient, µm²/s.
    pub diffusion: f64,
}

impl TruthRow {
    /// A QD that stood still in focus at `(x, y)` while frame `frame` was
    /// scanned: its centroid, start and end all there, D = 0. (What a
    /// hand-worked metric case needs: the metric reads only frame, x, y.)
    pub fn stationary(frame: usize, x: f64, y: f64) -> Self {
        Self {
            frame,
            x,
            y,
            x_start: x,
            y_start: y,
            x_end: x,
            y_end: y,
            z_mean: 0.0,
            diffusion: 0.0,
        }
    }
}

/// Frames and their ground truth (one row per emitter per frame, ordered
/// by frame then emitter), as the simulator makes them.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Dataset {
    pub frames: FrameStack,
    pub truth: Vec<TruthRow>,
}
