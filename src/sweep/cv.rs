//! `scanloc cv` as a sweep: a point per fold; the aggregation runs the
//! whole cross-validation's plan (every fold's artefacts are then cached),
//! records it as a run of kind `cv` and prints its table.

use std::sync::Arc;

use serde_json::{Value, json};

use super::front_end::{Finished, FrontEnd};
use super::{Point, PointState, SweepSpec};
use crate::manifest::Manifest;
use crate::registry::{CrossValidationPlan, Registry, RunKind};
use crate::run::cross_validation::{self, CrossValidationOutcome};
use crate::run::{RunOptions, execute};

/// A cross-validation of `detector` with `folds` folds.
pub(crate) struct CvSweep<'a> {
    pub detector: &'a str,
    pub folds: usize,
}

impl CvSweep<'_> {
    /// The plan of the whole cross-validation (every fold).
    fn whole(&self) -> CrossValidationPlan {
        CrossValidationPlan {
            detector: self.detector.to_string(),
            folds: self.folds,
            fold: None,
        }
    }

    /// Runs the whole cross-validation over the cached folds: its outcome.
    fn conclude(
        &self,
        registry: &mut Registry,
        base: &Manifest,
    ) -> anyhow::Result<CrossValidationOutcome> {
        let cv = self.whole();
        let plan = cross_validation::plan(base, &cv)?;
        let run = execute(
            registry,
            base,
            &plan,
            &RunOptions {
                kind: RunKind::Cv,
                cross_validation: Some(cv.clone()),
                ..RunOptions::default()
            },
        )?;
        let training_set = cross_validation::training_set(base, self.detector)?;
        Ok(CrossValidationOutcome {
            detector: self.detector.to_string(),
            folds: self.folds,
            cells: cross_validation::summarise(&run.auc, &cv, training_set),
            run,
        })
    }
}

impl FrontEnd for CvSweep<'_> {
    fn name(&self) -> &'static str {
        "cv"
    }

    fn points(&self, base: &Arc<Manifest>, _spec: &SweepSpec) -> anyhow::Result<Vec<Point>> {
        // The whole plan checks the detector and fold count once.
        cross_validation::plan(base, &self.whole())?;
        (1..=self.folds)
            .map(|fold| {
                let cv = CrossValidationPlan {
                    fold: Some(fold),
                    ..self.whole()
                };
                Ok(Point {
                    index: fold - 1,
                    label: format!("fold {fold}"),
                    manifest: base.clone(),
                    plan: cross_validation::plan(base, &cv)?,
                    run: RunOptions {
                        kind: RunKind::Cv,
                        cross_validation: Some(cv),
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
        let (detector, folds, states) = (self.detector, self.folds, sweep.states);
        let done = sweep.done().len();
        if done < folds {
            return Ok((
                format!(
                    "{folds}-fold cross-validation of {detector}: no table, {} of {folds} folds did not finish\n",
                    folds - done
                ),
                json!({"sweep": sweep.file.id, "detector": detector, "folds": folds, "points": states}),
            ));
        }
        let outcome = self.conclude(registry, sweep.base)?;
        let sum = |f: fn(&PointState) -> usize| states.iter().map(f).sum::<usize>();
        Ok((
            cross_validation::render(&outcome),
            json!({
                "run": outcome.run.run,
                "detector": outcome.detector,
                "folds": outcome.folds,
                "cells": outcome.cells,
                "cached_steps": outcome.run.counts.cached + sum(|s| s.cached_steps),
                "computed_steps": outcome.run.counts.computed + sum(|s| s.computed_steps),
                "sweep": sweep.file.id,
                "points": states,
            }),
        ))
    }
}
