//! The interface every sweep front end implements: its points, and the
//! table and JSON its aggregation makes of them. The engine
//! ([`super::run`], [`super::aggregate`]) runs points and collects their
//! states without knowing which front end made them.

use std::sync::Arc;

use serde_json::Value;

use super::{Point, PointState, SweepFile, SweepSpec};
use crate::manifest::Manifest;
use crate::registry::Registry;

/// A sweep front end (`scanloc cv`, `scanloc calibrate`, `scanloc sweep
/// run`).
pub trait FrontEnd {
    /// The word that starts the sweep's id (`cv`, `calibrate`, `grid`).
    fn name(&self) -> &'static str;

    /// The points over `base` (the manifest of `spec`), in index order,
    /// each with the options its run is recorded with. Bad input (detector,
    /// folds, grid) is reported here, before anything runs.
    fn points(&self, base: &Arc<Manifest>, spec: &SweepSpec) -> anyhow::Result<Vec<Point>>;

    /// The front end's table as text (what the command prints) and its
    /// result as JSON (what it prints with `--json`), from the points that
    /// finished. The engine adds a line per point that did not.
    fn aggregate(
        &self,
        registry: &mut Registry,
        sweep: &Finished<'_>,
    ) -> anyhow::Result<(String, Value)>;
}

/// A sweep at its aggregation: every point and where it stands.
pub struct Finished<'a> {
    pub file: &'a SweepFile,
    pub base: &'a Manifest,
    pub points: &'a [Point],
    /// By point index.
    pub states: &'a [PointState],
}

impl Finished<'_> {
    /// The points whose every artefact is in the main registry.
    pub fn done(&self) -> Vec<&Point> {
        self.points
            .iter()
            .filter(|p| self.states[p.index].status.is_done())
            .collect()
    }
}
