//! `scanloc calibrate` as a sweep: a point per brightness, each the
//! manifest restricted to the detector with that brightness; the
//! aggregation scores each point's AUC row against the reference row and
//! names the best brightness.

use std::sync::Arc;

use serde_json::{Value, json};

use super::front_end::{Finished, FrontEnd};
use super::{Point, SweepSpec, point_auc};
use crate::manifest::Manifest;
use crate::registry::{Registry, RunKind};
use crate::run::calibrate::{self, CalibrationPoint};
use crate::run::{Plan, RunOptions};

/// A calibration of `detector` over the brightness values `brightness`
/// (point `i` is `brightness[i]`).
pub(crate) struct CalibrateSweep<'a> {
    pub detector: &'a str,
    pub brightness: &'a [f64],
}

impl FrontEnd for CalibrateSweep<'_> {
    fn name(&self) -> &'static str {
        "calibrate"
    }

    fn points(&self, base: &Arc<Manifest>, _spec: &SweepSpec) -> anyhow::Result<Vec<Point>> {
        calibrate::reference_row(base, self.detector, self.brightness)?;
        self.brightness
            .iter()
            .enumerate()
            .map(|(index, &b)| {
                let manifest = calibrate::restricted(base, self.detector, b);
                Ok(Point {
                    index,
                    label: format!("N_qd={b}"),
                    plan: Plan::from_manifest(&manifest)?,
                    manifest: Arc::new(manifest),
                    run: RunOptions {
                        kind: RunKind::Calibrate,
                        ..RunOptions::default()
                    },
                })
            })
            .collect()
    }

    fn aggregate(
        &self,
        registry: &mut Registry,
        sweep: &Finished<'_>,
    ) -> anyhow::Result<(String, Value)> {
        let reference = calibrate::reference_row(sweep.base, self.detector, self.brightness)?;
        let mut scored: Vec<CalibrationPoint> = Vec::new();
        for point in sweep.done() {
            let auc = point_auc(registry, point)?;
            let run = sweep.states[point.index].run.clone().unwrap_or_default();
            let brightness = self.brightness.get(point.index).copied();
            scored.push(calibrate::score_point(
                reference,
                brightness.unwrap_or(f64::NAN),
                run,
                &auc,
            ));
        }
        let result = calibrate::conclude(self.detector, scored);
        let mut text = format!("{:>10} {:>10} {:>14}  run\n", "N_qd", "SSE", "cells ≤ 0.05");
        for point in &result.points {
            text.push_str(&format!(
                "{:>10} {:>10.4} {:>11}/{:<2}  {}\n",
                point.brightness, point.sse, point.cells_within_0_05, point.cells, point.run
            ));
        }
        text.push_str(&format!(
            "best N_qd for {}: {}\n",
            result.detector, result.best_brightness
        ));
        let mut json = serde_json::to_value(&result)?;
        json["sweep"] = json!(sweep.file.id);
        Ok((text, json))
    }
}
