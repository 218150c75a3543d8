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

/// Ground truth of one QD in one frame of a continuous recording
/// (`docs/tracking.md`), in TrackPy pixel coordinates, times in seconds from
/// the first sample of frame 0.
///
/// A row is written for every QD whose trajectory centroid or seen
/// position lies in the field (`-0.5 ≤ x < W − 0.5`, `-0.5 ≤ y < H − 0.5`),
/// whatever its depth or blinking state, so tracks made from the truth are what a perfect
/// detector that also saw dark and out-of-focus QDs would give.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RecordingTruthRow {
    /// Frame index within the recording.
    pub frame: usize,
    /// Persistent QD id: the same QD keeps it from frame to frame (a QD
    /// that crosses the simulated volume's boundary comes back as a new id).
    pub qd: u64,
    /// Trajectory centroid: mean x (column) over every PSF sample of the
    /// frame, as [`TruthRow::x`].
    pub x: f64,
    /// Trajectory centroid: mean y (row) over every PSF sample.
    pub y: f64,
    /// Mean depth relative to focus over the frame, µm.
    pub z_mean: f64,
    /// Share of the frame's samples during which the QD was on (1 without
    /// blinking).
    pub on_fraction: f64,
    /// The position the beam saw: the path's mean weighted by the lateral
    /// PSF at each sample (the part of the path near the scanned rows).
    pub x_seen: f64,
    /// As `x_seen`, along y.
    pub y_seen: f64,
    /// The frame's mid-time: the mean time of its samples, s.
    pub t_mid: f64,
    /// When the beam passed the centroid: frame start + y · line time +
    /// x · dwell (x, y clamped to the field), s.
    pub t_beam: f64,
    /// The lateral-PSF-weighted mean time of the frame's samples (when the
    /// beam saw the QD, the time stamp of `x_seen, y_seen`), s.
    pub t_seen: f64,
    /// The recording's diffusion coefficient, µm²/s.
    pub diffusion: f64,
}
