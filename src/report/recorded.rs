//! The resolved manifest a run recorded (`RunRecord::resolved`), read back
//! typed: what reports and summaries of past runs need from it.

use anyhow::Context;
use serde::Deserialize;

use crate::manifest::{DetectorSpec, Reference};
use crate::registry::RunRecord;
use crate::sim::SimParams;

/// The parts of a recorded resolved manifest that readers use (the rest
/// of the document is ignored).
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct RecordedManifest {
    pub name: String,
    /// The master seed.
    pub seed: u64,
    pub microscope: SimParams,
    pub datasets: Vec<RecordedDataset>,
    pub detectors: Vec<RecordedDetector>,
    #[serde(default)]
    pub reference: Option<Reference>,
}

/// A dataset as the run resolved it.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct RecordedDataset {
    pub name: String,
    pub seed: u64,
    pub params: SimParams,
}

/// A detector as the run resolved it.
#[derive(Debug, Clone, Deserialize)]
pub(crate) struct RecordedDetector {
    pub name: String,
    pub spec: DetectorSpec,
}

impl RecordedManifest {
    /// The resolved manifest `record` holds; an error names the run and
    /// the column if it does not have the expected shape.
    pub(crate) fn of(record: &RunRecord) -> anyhow::Result<Self> {
        RecordedManifest::deserialize(&record.resolved).with_context(|| {
            format!(
                "run {}: column runs.resolved is not a resolved manifest this scanloc reads",
                record.id
            )
        })
    }

    pub(crate) fn dataset(&self, name: &str) -> Option<&RecordedDataset> {
        self.datasets.iter().find(|d| d.name == name)
    }

    pub(crate) fn detector(&self, name: &str) -> Option<&RecordedDetector> {
        self.detectors.iter().find(|d| d.name == name)
    }
}
