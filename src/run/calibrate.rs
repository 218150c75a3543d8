//! `scanloc calibrate` (`docs/metric.md`): choose the brightness N_qd for which a
//! detector's AUC row comes closest to its reference row.
//!
//! Each grid point is an ordinary recorded run (kind `calibrate`) of the
//! manifest restricted to that detector, with every dataset's brightness
//! set to the point's value; the points share dataset seeds (derived from
//! the names), so the sweep compares brightness values on common random
//! numbers. Scored by the sum of squared differences over the reference
//! cells.

use serde::Serialize;

use super::{RunOptions, execute, plan::Plan};
use crate::error::input_error;
use crate::manifest::Manifest;
use crate::registry::{Registry, RunKind};

/// One grid point of the sweep.
#[derive(Debug, Clone, Serialize)]
pub struct CalibrationPoint {
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
#[derive(Debug, Clone, Serialize)]
pub struct Calibration {
    pub detector: String,
    pub points: Vec<CalibrationPoint>,
    pub best_brightness: f64,
}

/// The manifest with only `detector`'s evaluations, every dataset at
/// `brightness`.
fn restricted(manifest: &Manifest, detector: &str, brightness: f64) -> Manifest {
    let mut point = manifest.clone();
    point.microscope.brightness = brightness;
    for dataset in &mut point.datasets {
        dataset.params.brightness = brightness;
    }
    point.evaluations.retain(|e| e.detector == detector);
    point.detectors.retain(|d| d.name == detector);
    point.cross_validation = None;
    point
}

/// Runs the sweep over `grid` for `detector`, which needs reference cells.
pub fn calibrate(
    registry: &mut Registry,
    manifest: &Manifest,
    detector: &str,
    grid: &[f64],
    progress: impl Fn(&CalibrationPoint),
) -> anyhow::Result<Calibration> {
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
    let mut points = Vec::new();
    for &brightness in grid {
        let point_manifest = restricted(manifest, detector, brightness);
        let plan = Plan::from_manifest(&point_manifest)?;
        let outcome = execute(
            registry,
            &point_manifest,
            &plan,
            &RunOptions {
                kind: RunKind::Calibrate,
                ..RunOptions::default()
            },
        )?;
        let mut table = Vec::new();
        for cell in &reference.cells {
            if let Some(row) = outcome.auc.iter().find(|r| {
                r.detector == detector && r.dataset == cell.dataset && r.eps_px == cell.eps_px
            }) {
                table.push((cell.dataset.clone(), cell.eps_px, row.auc, cell.auc));
            }
        }
        let sse = table
            .iter()
            .map(|(_, _, ours, theirs)| (ours - theirs).powi(2))
            .sum();
        let point = CalibrationPoint {
            brightness,
            run: outcome.run.clone(),
            sse,
            cells_within_0_05: table
                .iter()
                .filter(|(_, _, o, t)| (o - t).abs() <= 0.05)
                .count(),
            cells: table.len(),
            table,
        };
        progress(&point);
        points.push(point);
    }
    let best_brightness = points
        .iter()
        .min_by(|a, b| a.sse.total_cmp(&b.sse))
        .map(|p| p.brightness)
        .unwrap_or(f64::NAN);
    Ok(Calibration {
        detector: detector.to_string(),
        points,
        best_brightness,
    })
}
