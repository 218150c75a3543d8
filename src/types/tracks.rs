//! Trajectories: localisations linked into tracks, as read from a tracks
//! table (`frame,x,y,particle`, optional `sigma_x,sigma_y,time`).

/// One localisation of a track, in TrackPy pixel coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackPoint {
    /// Frame index (≥ 0).
    pub frame: usize,
    /// Column, px.
    pub x: f64,
    /// Row, px.
    pub y: f64,
    /// The localisation's standard error along x and y, px, when the
    /// localiser gave one.
    pub sigma: Option<(f64, f64)>,
    /// The localisation's time stamp, s, when the table gave one.
    pub time_s: Option<f64>,
    /// The extent along x and y, px, of the linker's gate that admitted
    /// the step from the track's previous point (the `lap` linker's
    /// gate_x, gate_y; docs/tracking.md, "Wrong links"); the ML ensemble
    /// narrows it and conditions on it. `None`: no gate is known (a
    /// track's first point; TrackPy's linker).
    pub gate: Option<(f64, f64)>,
}

/// One particle's localisations, ordered by frame, one per frame at most.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    /// The particle label of the tracks table.
    pub particle: i64,
    pub points: Vec<TrackPoint>,
}

impl Track {
    /// The track with its localisations' own σ left out, so that an
    /// estimator estimates the localisation variance with D: a localiser
    /// that reports its posterior mean (the CNN) errs with its estimate
    /// rather than with the truth, which no σ it gives describes
    /// (docs/tracking.md, "The estimators").
    pub fn without_sigma(&self) -> Track {
        Track {
            particle: self.particle,
            points: self
                .points
                .iter()
                .map(|p| TrackPoint { sigma: None, ..*p })
                .collect(),
        }
    }

    /// Whether any localisation carries its own σ.
    pub fn has_sigma(&self) -> bool {
        self.points.iter().any(|p| p.sigma.is_some())
    }
}
