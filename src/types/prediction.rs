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
    /// The detector's own estimate of this localisation's error, when it
    /// makes one (the CNN does; Crocker–Grier does not).
    pub sigma: Option<LocalisationSigma>,
    /// The guess's rank (1 = the frame's best) when the detector gives a
    /// ranked list of guesses for one QD (the likelihood detector with
    /// `max_candidates` > 1); `None` when each localisation stands for its
    /// own QD (a single guess per frame, or several QDs of a scene). The
    /// scene figures count rank 1 and unranked localisations only
    /// (`docs/metric.md`, "A ranked list of guesses").
    pub candidate: Option<u32>,
}

/// A localisation's expected error: the standard deviations, in pixels, of
/// the true position about the reported one along `x` (columns) and `y`
/// (rows). Both are finite and > 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalisationSigma {
    pub x: f64,
    pub y: f64,
}

impl Prediction {
    /// A localisation without an uncertainty estimate.
    pub fn new(frame: usize, x: f64, y: f64, score: f64) -> Self {
        Self {
            frame,
            x,
            y,
            score,
            sigma: None,
            candidate: None,
        }
    }
}
