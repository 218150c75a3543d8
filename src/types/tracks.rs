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
}

/// One particle's localisations, ordered by frame, one per frame at most.
#[derive(Debug, Clone, PartialEq)]
pub struct Track {
    /// The particle label of the tracks table.
    pub particle: i64,
    pub points: Vec<TrackPoint>,
}
