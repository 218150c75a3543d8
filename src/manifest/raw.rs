//! The manifest as written: the serde targets YAML is first read into,
//! before names are checked, references followed and defaults filled in
//! (by [`super::resolve`]).
//!
//! Sections whose fields are checked one by one (the microscope and the
//! datasets' overrides of it) stay YAML mappings here.

use serde::Deserialize;

use super::serde_adapters::{Named, SingletonMap};
use super::{CrossValidation, DetectorSpec, MetricsSpec};

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawManifest {
    pub name: String,
    #[serde(default)]
    pub description: Option<String>,
    pub seed: u64,
    #[serde(default)]
    pub microscope: serde_yaml::Mapping,
    #[serde(default)]
    pub datasets: Named<serde_yaml::Mapping>,
    #[serde(default)]
    pub detectors: Named<SingletonMap<DetectorSpec>>,
    #[serde(default)]
    pub metrics: MetricsSpec,
    #[serde(default)]
    pub evaluations: Vec<RawEvaluation>,
    #[serde(default)]
    pub cross_validation: Option<CrossValidation>,
    #[serde(default)]
    pub reference: Option<RawReference>,
    /// Continuous recordings: name → frames, overrides of the microscope
    /// and the volume's settings.
    #[serde(default)]
    pub recordings: Named<serde_yaml::Mapping>,
    #[serde(default)]
    pub linkers: Named<SingletonMap<crate::track::pipeline::LinkerSpec>>,
    #[serde(default)]
    pub tracking: Option<RawTracking>,
    /// A parameter grid for `scanloc sweep run`, read by the sweep
    /// module (a plain run ignores it).
    #[serde(default, rename = "sweep")]
    pub _sweep: Option<serde::de::IgnoredAny>,
}

/// One entry of `evaluations`: a detector and the datasets it is scored on.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawEvaluation {
    pub detector: String,
    pub datasets: Vec<String>,
    /// Score on only the first this many frames of each dataset.
    #[serde(default)]
    pub frames: Option<usize>,
}

/// The `tracking` section as written.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTracking {
    #[serde(default)]
    pub scoring: crate::track::pipeline::TrackScoring,
    pub evaluations: Vec<RawTrackingEvaluation>,
}

/// One entry of `tracking.evaluations`: a detector, a linker and the
/// recordings they run on.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawTrackingEvaluation {
    pub detector: String,
    pub linker: String,
    pub recordings: Vec<String>,
    #[serde(default)]
    pub min_score: Option<f64>,
    /// This pipeline's bias correction, in place of the scoring's.
    #[serde(default, with = "serde_yaml::with::singleton_map_recursive")]
    pub bias_correction: Option<crate::track::pipeline::BiasCorrection>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawReference {
    #[serde(default)]
    pub source: String,
    pub rows: Vec<RawReferenceRow>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawReferenceRow {
    pub detector: String,
    #[serde(default)]
    pub label: Option<String>,
    /// dataset name → one AUC per ε of `metrics.eps_px`.
    pub auc: Named<Vec<f64>>,
}
