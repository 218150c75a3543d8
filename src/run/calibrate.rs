//! `scanloc calibrate` (`docs/metric.md`): choose the brightness N_qd for which a
//! detector's AUC row comes closest to its reference row.
//!
//! Each grid point is an ordinary recorded run (kind `calibrate`) of the
//! manifest restricted to that detector (run as a sweep, `scanloc calibrate`), with every dataset's brightness
//! set to the point's value; the points share dataset seeds (derived from
//! the names), so the sweep compares brightness values on common random
//! numbers. Scored by the sum of squared differences over the reference
//! cells.

use serde::{Deserialize, Serialize};

use crate::error::input_error;
use crate::manifest::{Manifest, ReferenceRow};
use crate::registry::AucRow;

/// One grid point of the sweep.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct CalibrationPoint {
    pub brightness: f64,
    /// The recorded run of this point.
    pub run: String,
    /// Σ (ours − reference)² over the reference cells.
    pub sse: f64,
    /// Reference cells within 0.05 of ours.
    pub cells_within_0_05: usize,
    pub cells: usize,
    /// (dataset, ε, ours, reference) per reference cell.
    pub table: Vec<(String, f64, f64, f64)>,
}

/// The sweep's result: every point and the best one.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct Calibration {
    pub detector: String,
    pub points: Vec<CalibrationPoint>,
    pub best_brightness: f64,
}

/// The manifest with only `detector`'s evaluations, every dataset at
/// `brightness` (a brightness the manifest gives as a distribution is
/// replaced too: a grid point is one N_qd for every frame).
pub(crate) fn restricted(manifest: &Manifest, detector: &str, brightness: f64) -> Manifest {
    let mut point = manifest.clone();
    point.microscope.brightness = brightness.into();
    for dataset in &mut point.datasets {
        dataset.params.brightness = brightness.into();
    }
    point.evaluations.retain(|e| e.detector == detector);
    point.detectors.retain(|d| d.name == detector);
    point.cross_validation = None;
    point
}

/// Checks a calibration's inputs: `detector` exists and has a reference
/// row, and `grid` is a non-empty list of brightness values ≥ 0. Returns
/// the reference row.
pub(crate) fn reference_row<'a>(
    manifest: &'a Manifest,
    detector: &str,
    grid: &[f64],
) -> anyhow::Result<&'a ReferenceRow> {
    if manifest.detector(detector).is_none() {
        return Err(input_error(format!(
            "{}: detectors.{detector}: no such detector",
            manifest.source
        )));
    }
    let reference = manifest
        .reference
        .as_ref()
        .and_then(|r| r.rows.iter().find(|row| row.detector == detector))
        .ok_or_else(|| {
            input_error(format!(
                "{}: reference: no row for detector {detector} to calibrate against",
                manifest.source
            ))
        })?;
    if grid.is_empty() {
        return Err(input_error("--brightness: give at least one value"));
    }
    for &b in grid {
        crate::error::require_non_negative("--brightness", b)?;
    }
    Ok(reference)
}

/// Scores one grid point (run `run`, AUC table `auc`) against `reference`.
pub(crate) fn score_point(
    reference: &ReferenceRow,
    brightness: f64,
    run: String,
    auc: &[AucRow],
) -> CalibrationPoint {
    let mut table = Vec::new();
    for cell in &reference.cells {
        if let Some(row) = auc.iter().find(|r| {
            r.detector == reference.detector && r.dataset == cell.dataset && r.eps_px == cell.eps_px
        }) {
            table.push((cell.dataset.clone(), cell.eps_px, row.auc, cell.auc));
        }
    }
    let sse = table
        .iter()
        .map(|(_, _, ours, theirs)| (ours - theirs).powi(2))
        .sum();
    CalibrationPoint {
        brightness,
        run,
        sse,
        cells_within_0_05: table
            .iter()
            .filter(|(_, _, o, t)| (o - t).abs() <= 0.05)
            .count(),
        cells: table.len(),
        table,
    }
}

/// The sweep's result from its points: the best is the smallest SSE.
pub(crate) fn conclude(detector: &str, points: Vec<CalibrationPoint>) -> Calibration {
    let best_brightness = points
        .iter()
        .min_by(|a, b| a.sse.total_cmp(&b.sse))
        .map(|p| p.brightness)
        .unwrap_or(f64::NAN);
    Calibration {
        detector: detector.to_string(),
        points,
        best_brightness,
    }
}
