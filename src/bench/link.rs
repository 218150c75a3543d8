//! `scanloc bench link`: the TrackPy linker's speed against TrackPy 0.7's
//! `link` on the same localisations, in the same run, and whether the two
//! give the same trajectories.

use std::path::Path;
use std::time::Instant;

use rand::{RngExt as _, SeedableRng as _};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution as _, Normal};

use crate::error::input_error;
use crate::io::{csv_tables, localisation_table};
use crate::track::{self, Detection, Linking, trackpy::TrackpyParams};
use crate::types::Prediction;

/// Random walks to link: particles at a set density that appear and
/// disappear, some detections missing (blinks).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct WalkSpec {
    /// Particles over the whole recording.
    pub particles: usize,
    /// Frames of the recording.
    pub frames: usize,
    /// Particles per px² of the field (the field's side follows).
    pub density_per_px2: f64,
    /// Standard deviation of a frame's step per axis, px.
    pub step_px: f64,
    /// Probability that a detection is missing.
    pub blink: f64,
    /// Seed of the ChaCha8 stream of every draw.
    pub seed: u64,
}

impl WalkSpec {
    /// Refuses specs that would make no walks or an unbounded field.
    pub(crate) fn validate(&self) -> anyhow::Result<()> {
        let limit = 10_000_000;
        if self.particles == 0
            || self.frames < 4
            || self.particles.saturating_mul(self.frames) > limit
        {
            return Err(input_error(format!(
                "--particles × --frames: need ≥ 1 particle, ≥ 4 frames and at most {limit} \
                 detections, got {} × {}",
                self.particles, self.frames
            )));
        }
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.density_per_px2)
            || !positive(self.step_px)
            || !(0.0..1.0).contains(&self.blink)
        {
            return Err(input_error(
                "--density and --step: finite numbers > 0; --blink: in [0, 1)",
            ));
        }
        Ok(())
    }
}

/// The detections of `spec`'s walks, by particle then frame (unsorted by
/// frame on purpose: the linkers sort).
pub(crate) fn random_walks(spec: &WalkSpec) -> Vec<Detection> {
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    let side = (spec.particles as f64 / spec.density_per_px2).sqrt();
    let step = Normal::new(0.0, spec.step_px).unwrap_or_else(|_| Normal::new(0.0, 1.0).unwrap());
    let mut detections = Vec::new();
    for _ in 0..spec.particles {
        let first = rng.random_range(0..spec.frames / 2);
        let last = rng.random_range(first + spec.frames / 4..=spec.frames);
        let (mut x, mut y) = (rng.random_range(0.0..side), rng.random_range(0.0..side));
        for frame in first..last {
            x += step.sample(&mut rng);
            y += step.sample(&mut rng);
            if rng.random::<f64>() >= spec.blink {
                detections.push(Detection::new(frame, x, y));
            }
        }
    }
    detections
}

/// The best time in seconds of `repeats` runs of the TrackPy linker, and
/// its result.
pub(crate) fn time_trackpy_link(
    detections: &[Detection],
    params: &TrackpyParams,
    repeats: usize,
) -> anyhow::Result<(f64, Linking)> {
    let mut best = f64::INFINITY;
    let mut result = None;
    for _ in 0..repeats.max(1) {
        let start = Instant::now();
        let linking = track::trackpy::link(detections, params)?;
        best = best.min(start.elapsed().as_secs_f64());
        result = Some(linking);
    }
    Ok((best, result.expect("at least one repeat")))
}

/// Writes `detections` as a `frame,x,y,score` table TrackPy can read.
pub(crate) fn write_detections(path: &Path, detections: &[Detection]) -> anyhow::Result<()> {
    let rows: Vec<Prediction> = detections
        .iter()
        .map(|d| Prediction::new(d.frame, d.x, d.y, 1.0))
        .collect();
    csv_tables::write_predictions(path, &rows)
}

/// The trajectory labels of TrackPy's output table (columns `row`, the
/// input row, and `particle`), indexed by input row.
pub fn read_reference_labels(path: &Path, rows: usize) -> anyhow::Result<Vec<usize>> {
    let name = path.display().to_string();
    let table = localisation_table::read_localisation_table(path)?;
    let row = table.whole_numbers("row", &name)?;
    let particle = table.whole_numbers("particle", &name)?;
    let mut labels = vec![usize::MAX; rows];
    for (&r, &p) in row.iter().zip(&particle) {
        match labels.get_mut(r) {
            Some(label) => *label = p,
            None => crate::bail_input!("{name}: row {r} is not an input row"),
        }
    }
    Ok(labels)
}
