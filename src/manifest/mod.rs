//! Experiment manifests (`experiments/*.yaml`): what to simulate, which
//! detectors to run, how to score them. The format, every field and its
//! default are documented in `docs/manifest.md`.
//!
//! A manifest is parsed strictly: unknown fields are refused, every value is
//! validated, and every default is filled in, so the resolved [`Manifest`]
//! says everything a run will do. Errors are
//! [`InputError`](crate::error::InputError)s of the form
//! `experiments/x.yaml:14: datasets.test-1.00.frames: must be a positive integer`
//! (file, line, field path, what is wrong).
//!
//! ```yaml
//! name: smoke                 # free text, recorded with each run
//! seed: 1234                  # master seed: every artefact's seed derives from it
//! microscope:                 # simulator parameters shared by every dataset
//!   brightness: 7
//!   margin_px: 4
//! datasets:                   # name → frame count + overrides of `microscope`
//!   train: {frames: 200, diffusion_um2_s: {uniform: [0.75, 1.75]}}
//!   test-1.00: {frames: 100, diffusion_um2_s: 1.0}
//! detectors:                  # name → one of the detector kinds
//!   trackpy:
//!     crocker_grier: {diameter: 7, minmass: 0}   # TrackPy's parameter names
//!   cnn:
//!     cnn:
//!       training_set: train    # trained detectors name their training set
//!       architecture: {channels: 16}
//!       training: {epochs: 4}
//! metrics: {eps_px: [1, 2, 3], keep_curves: true, score_thresholds: {cnn: 0.5}}
//! evaluations:                # which detectors are scored on which datasets
//!   - {detector: trackpy, datasets: [test-1.00]}
//!   - {detector: cnn, datasets: [test-1.00]}
//! cross_validation: {folds: 5, detector: cnn}    # optional; run by `scanloc cv`
//! sweep:                      # optional; a grid run by `scanloc sweep run`
//!   channels: {path: detectors.cnn.cnn.architecture.channels, values: [8, 16]}
//! reference:                  # optional: published numbers printed beside ours
//!   source: Table 1
//!   rows:
//!     - {detector: trackpy, label: TrackPy, auc: {test-1.00: [0.04, 0.30, 0.61]}}
//! ```
//!
//! Seeds: each artefact's seed is [`derive_seed`](crate::types::derive_seed)`(seed, kind, name)`, a
//! hash of the master seed and the artefact's name, so adding, removing or
//! reordering other entries never changes it and no global random state is
//! involved.

mod errors;
pub(crate) mod feasibility;
pub(crate) mod locate;
mod raw;
mod resolve;
mod serde_adapters;

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{FieldError, input_error};
use crate::metrics::ScoreReading;
use crate::sim::SimParams;
use crate::types::DetectorKind;
pub use locate::LineIndex;

// The size limits are the command line's too: one definition, in `limits`.
pub use crate::limits::{MAX_DATASET_PIXELS, MAX_FRAMES};
// The rule for names is the registry's too: one definition, in `types`.
pub use crate::types::names::{MAX_NAME_LEN, is_plain_name};

/// A validated, fully resolved manifest.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Manifest {
    /// Where it was read from, as given by the user (for messages).
    pub source: String,
    /// sha256 of the manifest text, hex.
    pub manifest_sha256: String,
    pub name: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    /// The master seed.
    pub seed: u64,
    /// The shared microscope (defaults filled in).
    pub microscope: SimParams,
    /// Datasets in manifest order.
    pub datasets: Vec<DatasetSpec>,
    /// Detectors in manifest order.
    pub detectors: Vec<DetectorEntry>,
    pub metrics: MetricsSpec,
    /// Every (detector, dataset) pair to score, in manifest order.
    pub evaluations: Vec<EvaluationSpec>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cross_validation: Option<CrossValidation>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference: Option<Reference>,
    /// Continuous recordings in manifest order (docs/tracking.md).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub recordings: Vec<RecordingSpec>,
    /// Linkers in manifest order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub linkers: Vec<LinkerEntry>,
    /// The tracking pipelines to run and score, if any.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tracking: Option<TrackingSpec>,
    /// The manifest text exactly as read (recorded with runs).
    #[serde(skip)]
    pub text: String,
}

/// One simulated dataset: the microscope with this dataset's overrides.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DatasetSpec {
    pub name: String,
    pub frames: usize,
    /// `derive_seed(master, "dataset", name)`.
    pub seed: u64,
    pub params: SimParams,
}

impl DatasetSpec {
    /// The dataset's diffusion coefficient if it is the same for every
    /// frame (the AUC table's column label), `None` for a distribution.
    pub fn fixed_diffusion(&self) -> Option<f64> {
        match self.params.diffusion_um2_s {
            crate::sim::Distribution::Fixed(d) => Some(d),
            crate::sim::Distribution::Random(_) => None,
        }
    }
}

/// A continuous recording (`docs/tracking.md`): the microscope with this
/// recording's overrides, the volume's QDs and their blinking.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingSpec {
    pub name: String,
    /// `derive_seed(master, "dataset", name)`: recordings and datasets share
    /// one namespace.
    pub seed: u64,
    pub params: crate::sim::recording::RecordingParams,
}

impl RecordingSpec {
    /// Everything that determines the recording except its seed, as JSON
    /// (part of its content key; the names are the manifest's).
    pub fn params_json(&self) -> serde_json::Value {
        let p = &self.params;
        let mut json = serde_json::json!({
            "microscope": p.microscope,
            "frames": p.frames,
            "qd_density": p.density_per_um3,
            "lateral_margin_um": p.lateral_margin_um,
            "half_depth_um": p.half_depth_um,
            "dead_time_ms": p.dead_time_ms,
            "blink": p.blinking.map(|b| serde_json::json!({"on_ms": b.on_ms, "off_ms": b.off_ms})),
        });
        // Only when set, so that a recording drawn by density keeps its key.
        if let Some(count) = p.qd_count {
            json["qd_count"] = count.into();
        }
        json
    }

    /// The recording's D, µm²/s (a recording's D is a fixed number).
    pub fn diffusion(&self) -> f64 {
        self.params
            .microscope
            .diffusion_um2_s
            .fixed()
            .unwrap_or(f64::NAN)
    }

    /// The scan as the D estimators see it.
    pub fn geometry(&self) -> crate::track::diffusion::ScanGeometry {
        crate::track::diffusion::ScanGeometry::of(&self.params.microscope, self.params.dead_time_ms)
    }
}

impl Serialize for RecordingSpec {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serde_json::json!({
            "name": self.name,
            "seed": self.seed,
            "params": self.params_json(),
        })
        .serialize(serializer)
    }
}

/// A named linker.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LinkerEntry {
    pub name: String,
    pub spec: crate::track::pipeline::LinkerSpec,
}

/// The `tracking` section: how tracks are scored, and which pipelines
/// (detector, linker) run on which recordings.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrackingSpec {
    pub scoring: crate::track::pipeline::TrackScoring,
    /// Every (detector, linker, recording), in manifest order.
    pub evaluations: Vec<TrackingEvaluationSpec>,
}

/// One tracking pipeline on one recording.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrackingEvaluationSpec {
    pub detector: String,
    pub linker: String,
    pub recording: String,
    /// Only predictions scoring at least this are linked (all when absent).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_score: Option<f64>,
    /// This pipeline's bias correction, in place of the scoring's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub bias_correction: Option<crate::track::pipeline::BiasCorrection>,
}

impl TrackingEvaluationSpec {
    /// The pipeline's name, `DETECTOR+LINKER` (`+` is never part of a
    /// manifest's names, so it cannot collide with a detector's).
    pub fn pipeline(&self) -> String {
        format!("{}+{}", self.detector, self.linker)
    }
}

/// The detector kinds a manifest can declare, as a YAML mapping with one
/// key naming the kind: `{crocker_grier: {...}}` or `{cnn: {...}}`.
///
/// Each kind's parameters are its module's own serde type (strict, with
/// defaults). Adding a kind means: a variant here, its validation in
/// [`DetectorSpec::validate`], its code version in
/// [`DetectorSpec::code_version`], and its execution in `src/run/compute.rs`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum DetectorSpec {
    /// TrackPy's `locate` ([`crate::detect::crocker_grier`]); its parameters
    /// with TrackPy's names and defaults, e.g. `{diameter: 7, minmass: 0}`.
    CrockerGrier(crate::detect::crocker_grier::CrockerGrierParams),
    /// The CNN locator ([`crate::detect::cnn`]), trained on a dataset of
    /// the manifest.
    Cnn(CnnSpec),
    /// The likelihood localiser ([`crate::detect::likelihood`]): a particle
    /// filter under the evaluated dataset's microscope, e.g.
    /// `{particles: 20000, diffusion_um2_s: {uniform: [0.75, 1.75]}}`.
    Likelihood(crate::detect::likelihood::LikelihoodParams),
}

/// A CNN detector: what it is trained on, its network, its training.
///
/// ```yaml
/// cnn:
///   training_set: train        # a dataset of this manifest
///   architecture: {channels: 32, dilations: [1, 1, 2, 4, 2, 1]}
///   training: {epochs: 20, batch_size: 64, validation_fraction: 0.1}
/// ```
///
/// Both `architecture` and `training` default to the CNN module's defaults.
/// The training seed is the detector's derived seed; with
/// `training.fresh_frames_per_epoch > 0`, fresh frames are simulated each
/// epoch with the training set's microscope.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CnnSpec {
    pub training_set: String,
    #[serde(default)]
    pub architecture: crate::detect::cnn::CnnArchitecture,
    #[serde(default)]
    pub training: crate::detect::cnn::TrainingSettings,
}

impl DetectorSpec {
    /// The detector's kind (written in manifests as `crocker_grier`,
    /// `cnn`, `likelihood`).
    pub fn kind(&self) -> DetectorKind {
        match self {
            DetectorSpec::CrockerGrier(_) => DetectorKind::CrockerGrier,
            DetectorSpec::Cnn(_) => DetectorKind::Cnn,
            DetectorSpec::Likelihood(_) => DetectorKind::Likelihood,
        }
    }

    /// The dataset this detector is trained on, if it is trained.
    pub fn training_dataset(&self) -> Option<&str> {
        match self {
            DetectorSpec::CrockerGrier(_) | DetectorSpec::Likelihood(_) => None,
            DetectorSpec::Cnn(spec) => Some(&spec.training_set),
        }
    }

    /// Whether this detector gives a ranked list of guesses per frame
    /// ([`crate::types::Prediction::candidate`]): its run table rows are
    /// then each given twice, the whole lists' AUC and the best guess's
    /// per frame alone: the likelihood detector, and the CNN with the
    /// categorical head, each with `max_candidates` > 1. A detector that
    /// comes to rank its guesses must say so here.
    pub fn ranks_candidates(&self) -> bool {
        match self {
            DetectorSpec::Likelihood(params) => params.max_candidates > 1,
            DetectorSpec::Cnn(spec) => {
                spec.architecture.head == crate::detect::cnn::CnnHead::Categorical
                    && spec.architecture.max_candidates > 1
            }
            DetectorSpec::CrockerGrier(_) => false,
        }
    }

    /// Whether locating with this detector draws random numbers (from the
    /// detector's seed), which then belongs in its predictions' key.
    pub fn locates_at_random(&self) -> bool {
        matches!(self, DetectorSpec::Likelihood(_))
    }

    /// Whether this detector trains on fresh frames only, its training set
    /// only selecting the epoch (a CNN with `validation_fraction: 1`).
    pub fn trains_on_fresh_frames_only(&self) -> bool {
        matches!(self, DetectorSpec::Cnn(spec) if spec.training.trains_on_fresh_frames_only())
    }

    /// Checks the parameters; an error's path starts inside the kind's
    /// parameters (`training.epochs` for a CNN).
    pub fn validate(&self) -> Result<(), FieldError> {
        match self {
            DetectorSpec::CrockerGrier(params) => params.validate(),
            DetectorSpec::Cnn(spec) => {
                crate::detect::cnn::validate_recipe(&spec.architecture, &spec.training)
            }
            DetectorSpec::Likelihood(params) => params.validate(),
        }
    }

    /// Version of the code that turns this detector's inputs into its
    /// outputs; part of the content key of everything it makes.
    pub fn code_version(&self) -> &'static str {
        match self {
            DetectorSpec::CrockerGrier(_) => crate::detect::crocker_grier::CODE_VERSION,
            DetectorSpec::Cnn(spec) if spec.training.teacher_particles > 0 => {
                crate::detect::cnn::teacher_code_version(spec.architecture.head)
            }
            DetectorSpec::Cnn(_) => crate::detect::cnn::CODE_VERSION,
            DetectorSpec::Likelihood(_) => crate::detect::likelihood::CODE_VERSION,
        }
    }

    /// Version of the code that turns this detector's model (if any) and a
    /// dataset into predictions; part of their content key. The CNN's
    /// names its decoding apart from its training, so a change in how
    /// output maps become predictions keeps the trained models' keys.
    pub fn locate_code_version(&self) -> &'static str {
        match self {
            DetectorSpec::Cnn(_) => crate::detect::cnn::DECODE_VERSION,
            _ => self.code_version(),
        }
    }
}

/// A named detector.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DetectorEntry {
    pub name: String,
    /// `derive_seed(master, "detector", name)`: the seed of its training.
    pub seed: u64,
    pub spec: DetectorSpec,
}

/// How evaluations are scored (the metric: `docs/metric.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MetricsSpec {
    /// Matching radii in pixels, in the AUC table's column order.
    pub eps_px: Vec<f64>,
    /// Keep the precision–recall curves in the stored evaluations (for
    /// reports).
    pub keep_curves: bool,
    /// The score threshold of the scene figures (recall, precision,
    /// Jaccard index, false localisations per empty frame) by detector
    /// name; a detector not listed gets [`MetricsSpec::score_reading`]'s
    /// default.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub score_thresholds: BTreeMap<String, f64>,
}

impl Default for MetricsSpec {
    fn default() -> Self {
        Self {
            eps_px: crate::metrics::PAPER_EPS_PX.to_vec(),
            keep_curves: true,
            score_thresholds: BTreeMap::new(),
        }
    }
}

impl MetricsSpec {
    /// How `detector`'s score is read: Crocker–Grier's score is the
    /// feature's mass, not a probability, so by default every localisation
    /// it reports counts (its own `minmass` is its threshold); every other
    /// kind scores a probability (the CNN's heatmap peak, a sigmoid), whose
    /// default threshold is [`ScoreReading::PROBABILITY_THRESHOLD`].
    /// `score_thresholds` overrides the threshold.
    pub fn score_reading(&self, detector: &DetectorEntry) -> ScoreReading {
        let probability = !matches!(detector.spec, DetectorSpec::CrockerGrier(_));
        let default = probability.then_some(ScoreReading::PROBABILITY_THRESHOLD);
        ScoreReading {
            threshold: self
                .score_thresholds
                .get(&detector.name)
                .copied()
                .or(default),
            probability,
        }
    }
}

/// One detector scored on one dataset.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct EvaluationSpec {
    pub detector: String,
    pub dataset: String,
    /// Only the first this many frames of the dataset are located and
    /// scored (fewer than the dataset has; absent: all of them).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub frames: Option<usize>,
}

impl EvaluationSpec {
    /// The name of the frames scored: the dataset's, or for the first `n`
    /// frames `DATASET+firstN` (`+` is never part of a manifest's names,
    /// so it cannot collide with a dataset).
    pub fn scored_dataset_name(&self) -> String {
        match self.frames {
            Some(frames) => format!("{}+first{frames}", self.dataset),
            None => self.dataset.clone(),
        }
    }
}

/// Optional k-fold cross-validation of a trained detector over its
/// training set.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CrossValidation {
    /// Number of folds k (2 to 50).
    pub folds: usize,
    /// The detector to cross-validate (one with a training set).
    pub detector: String,
}

impl CrossValidation {
    /// Checks a fold count k (2 to 50): the one place that range is
    /// enforced, for manifests and the command line alike.
    pub fn check_folds(folds: usize) -> Result<(), String> {
        if (2..=50).contains(&folds) {
            Ok(())
        } else {
            Err(format!("must be between 2 and 50, got {folds}"))
        }
    }
}

/// Published numbers to print beside ours (e.g. the paper's Table 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reference {
    pub source: String,
    pub rows: Vec<ReferenceRow>,
}

/// One published row: a detector's AUC per dataset and ε.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReferenceRow {
    /// The detector of this manifest the row compares with.
    pub detector: String,
    /// The row's name in the source (e.g. `TrackPy`).
    pub label: String,
    /// One value per (dataset, ε).
    pub cells: Vec<ReferenceCell>,
}

/// One published AUC value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReferenceCell {
    pub dataset: String,
    pub eps_px: f64,
    pub auc: f64,
}

impl Reference {
    /// The published AUC of `detector` on `dataset` at `eps_px`, from the
    /// first row that compares with `detector`.
    pub fn auc(&self, detector: &str, dataset: &str, eps_px: f64) -> Option<f64> {
        self.rows
            .iter()
            .find(|row| row.detector == detector)
            .and_then(|row| row.auc(dataset, eps_px))
    }
}

impl ReferenceRow {
    /// This row's AUC on `dataset` at `eps_px`.
    pub fn auc(&self, dataset: &str, eps_px: f64) -> Option<f64> {
        self.cells
            .iter()
            .find(|c| c.dataset == dataset && c.eps_px == eps_px)
            .map(|c| c.auc)
    }
}

impl Manifest {
    /// The dataset named `name`.
    pub fn dataset(&self, name: &str) -> Option<&DatasetSpec> {
        self.datasets.iter().find(|d| d.name == name)
    }

    /// The detector named `name`.
    pub fn detector(&self, name: &str) -> Option<&DetectorEntry> {
        self.detectors.iter().find(|d| d.name == name)
    }

    /// The resolved manifest as YAML (what `scanloc check` prints).
    pub fn to_resolved_yaml(&self) -> anyhow::Result<String> {
        // Through JSON so enums print as `{variant: value}` maps, the way
        // manifests write them, rather than as YAML tags.
        Ok(serde_yaml::to_string(&serde_json::to_value(self)?)?)
    }
}

/// The text of the manifest at `path`, at most
/// [`MAX_MANIFEST_BYTES`](crate::limits::MAX_MANIFEST_BYTES) of it (a
/// larger file, or an endless device, is refused).
fn read_manifest_text(path: &Path) -> anyhow::Result<String> {
    use std::io::Read;
    let source = path.display();
    let limit = crate::limits::MAX_MANIFEST_BYTES;
    let file = std::fs::File::open(path)
        .map_err(|e| input_error(format!("{source}: cannot read: {e}")))?;
    let mut bytes = Vec::new();
    file.take(limit + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| input_error(format!("{source}: cannot read: {e}")))?;
    if bytes.len() as u64 > limit {
        return Err(input_error(format!(
            "{source}: larger than {} MiB; not a manifest",
            limit >> 20
        )));
    }
    String::from_utf8(bytes).map_err(|e| input_error(format!("{source}: not UTF-8 text: {e}")))
}

/// Reads and resolves the manifest at `path`.
pub fn load(path: &Path) -> anyhow::Result<Manifest> {
    let source = path.display().to_string();
    let text = read_manifest_text(path)?;
    parse(&text, &source)
}

/// Parses and resolves manifest `text`; `source` names it in errors.
pub fn parse(text: &str, source: &str) -> anyhow::Result<Manifest> {
    // Editors on Windows save UTF-8 with a byte-order mark; YAML allows it
    // but serde_yaml takes it for the start of a second document.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    // First as plain YAML: syntax errors and duplicate keys, with lines.
    let document: serde_yaml::Value =
        serde_yaml::from_str(text).map_err(|e| errors::located_yaml_error(source, e))?;
    if !document.is_mapping() {
        return Err(input_error(format!(
            "{source}:1: a manifest must be a YAML mapping with name, seed, datasets, …"
        )));
    }
    let raw: raw::RawManifest =
        serde_yaml::from_str(text).map_err(|e| errors::located_yaml_error(source, e))?;
    resolve::resolve(raw, text, source)
        .map_err(|e| errors::located_field_error(source, &LineIndex::new(text), &e))
}

/// The `microscope:` section of the manifest-style YAML file at `path`
/// (its other sections are not read) over `base`, a command's defaults:
/// the simulator parameters, not yet validated, and the names of the
/// fields the section sets. Errors name the file, line and field, as a
/// manifest's do.
pub fn load_microscope(path: &Path, base: &SimParams) -> anyhow::Result<(SimParams, Vec<String>)> {
    let source = path.display().to_string();
    let text = read_manifest_text(path)?;
    microscope_from_text(&source, &text, base)
}

/// [`load_microscope`] of YAML (or JSON) `text` read from `source` (the
/// name its errors give): the Python bindings' `Microscope` from a dict.
pub fn microscope_from_text(
    source: &str,
    text: &str,
    base: &SimParams,
) -> anyhow::Result<(SimParams, Vec<String>)> {
    let source = source.to_string();
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let document: serde_yaml::Value =
        serde_yaml::from_str(text).map_err(|e| errors::located_yaml_error(&source, e))?;
    let located =
        |error: FieldError| errors::located_field_error(&source, &LineIndex::new(text), &error);
    let section = match document.get("microscope") {
        Some(serde_yaml::Value::Mapping(section)) => section,
        Some(_) => {
            return Err(located(FieldError::new(
                "microscope",
                "must be a mapping of microscope fields (docs/manifest.md)",
            )));
        }
        None => {
            return Err(input_error(format!(
                "{source}: no `microscope:` section (a mapping of microscope fields, docs/manifest.md)"
            )));
        }
    };
    let params = resolve::microscope_over(section, base).map_err(located)?;
    let fields = section
        .keys()
        .filter_map(|key| key.as_str().map(str::to_string))
        .collect();
    Ok((params, fields))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::types::derive_seed;

    #[test]
    fn only_detectors_of_several_ranked_guesses_rank_candidates() {
        use crate::detect::cnn::{CnnArchitecture, CnnHead};
        use crate::detect::likelihood::LikelihoodParams;
        let likelihood = |max_candidates| {
            DetectorSpec::Likelihood(LikelihoodParams {
                max_candidates,
                ..LikelihoodParams::default()
            })
        };
        let cnn = |head, max_candidates| {
            DetectorSpec::Cnn(CnnSpec {
                training_set: "train".into(),
                architecture: CnnArchitecture {
                    head,
                    max_candidates,
                    ..CnnArchitecture::default()
                },
                training: Default::default(),
            })
        };
        let ranked = [
            (likelihood(1), false),
            (likelihood(2), true),
            (cnn(CnnHead::Peaks, 1), false),
            (cnn(CnnHead::Categorical, 1), false),
            (cnn(CnnHead::Categorical, 3), true),
            (DetectorSpec::CrockerGrier(Default::default()), false),
        ];
        for (spec, expected) in ranked {
            assert_eq!(spec.ranks_candidates(), expected, "{spec:?}");
        }
    }

    #[test]
    fn datasets_inherit_the_microscope_and_override_it() {
        let text = "name: t\nseed: 3\nmicroscope:\n  brightness: 9\n  margin_px: 4\ndatasets:\n  a:\n    frames: 5\n  b:\n    frames: 6\n    brightness: 11\n    diffusion_um2_s: {uniform: [0.75, 1.75]}\n";
        let manifest = parse(text, "t.yaml").unwrap();
        assert_eq!(
            manifest.datasets[0].params.brightness,
            crate::sim::Distribution::Fixed(9.0)
        );
        assert_eq!(manifest.datasets[0].params.margin_px, 4.0);
        assert_eq!(
            manifest.datasets[1].params.brightness,
            crate::sim::Distribution::Fixed(11.0)
        );
        assert_eq!(manifest.datasets[1].frames, 6);
        assert_eq!(manifest.datasets[1].fixed_diffusion(), None);
        assert_eq!(manifest.datasets[0].seed, derive_seed(3, "dataset", "a"));
    }

    #[test]
    fn datasets_draw_their_qd_count_from_a_choice() {
        use crate::sim::{CountChoice, EmitterCount};
        let text = "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 5\n    emitters: {choice: [0, 1, 2, 3]}\n  b:\n    frames: 5\n    emitters: {choice: [0, 2], weights: [1, 3]}\n  c:\n    frames: 5\n    emitters: 2\n";
        let manifest = parse(text, "t.yaml").unwrap();
        assert_eq!(
            manifest.datasets[0].params.emitters,
            EmitterCount::Random(CountChoice {
                choice: vec![0, 1, 2, 3],
                weights: None
            })
        );
        assert_eq!(
            manifest.datasets[1].params.emitters,
            EmitterCount::Random(CountChoice {
                choice: vec![0, 2],
                weights: Some(vec![1.0, 3.0])
            })
        );
        assert_eq!(manifest.datasets[2].params.emitters, EmitterCount::Fixed(2));
        let resolved = manifest.to_resolved_yaml().unwrap();
        assert!(resolved.contains("choice:") && resolved.contains("weights:"));
        for (emitters, expected) in [
            (
                "{choice: [0, 2], weights: [1]}",
                "x.yaml:6: datasets.a.emitters: weights must give one weight per count",
            ),
            (
                "{choice: [0, 2], wieghts: [1, 1]}",
                "x.yaml:6: datasets.a.emitters: must be a whole number or {choice",
            ),
            (
                "1.5",
                "x.yaml:6: datasets.a.emitters: must be a whole number or {choice",
            ),
            (
                "{choice: []}",
                "x.yaml:6: datasets.a.emitters: choice must list at least one count",
            ),
        ] {
            let text = format!(
                "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 2\n    emitters: {emitters}\n"
            );
            let error = parse(&text, "x.yaml").unwrap_err().to_string();
            assert!(error.starts_with(expected), "{error}");
        }
    }

    #[test]
    fn errors_name_file_line_and_path() {
        let text = "name: t\nseed: 3\ndatasets:\n  test-1.00:\n    frames: 0\n";
        let error = parse(text, "x.yaml").unwrap_err().to_string();
        assert_eq!(
            error,
            "x.yaml:5: datasets.test-1.00.frames: must be a positive integer"
        );
        let text =
            "name: t\nseed: 3\nmicroscope:\n  brightness: -1\ndatasets:\n  a:\n    frames: 2\n";
        let error = parse(text, "x.yaml").unwrap_err().to_string();
        assert!(
            error.starts_with("x.yaml:4: microscope.brightness: must be ≥ 0"),
            "{error}"
        );
        let text = "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 2\n    detector_noise: {pmt: {excess_noise_factor: 2}}\n";
        let manifest = parse(text, "x.yaml").unwrap();
        assert_eq!(
            manifest.datasets[0].params.detector_noise,
            crate::sim::DetectorNoise::Pmt {
                excess_noise_factor: 2.0
            }
        );
        assert!(manifest.to_resolved_yaml().unwrap().contains("pmt:"));
        let text = "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 2\n    brightnes: 3\n";
        let error = parse(text, "x.yaml").unwrap_err().to_string();
        assert!(
            error.starts_with("x.yaml:6: datasets.a.brightnes: unknown field"),
            "{error}"
        );
    }

    #[test]
    fn brightness_and_background_can_be_drawn_per_frame() {
        use crate::sim::{Distribution, RandomDistribution};
        let text = "name: t\nseed: 3\nmicroscope:\n  brightness: {uniform: [5, 10]}\ndatasets:\n  a: {frames: 5}\n  b: {frames: 6, brightness: 7.5, background: {uniform: [2, 12]}}\n";
        let manifest = parse(text, "t.yaml").unwrap();
        let uniform = |low, high| Distribution::Random(RandomDistribution::Uniform([low, high]));
        assert_eq!(manifest.datasets[0].params.brightness, uniform(5.0, 10.0));
        assert_eq!(
            manifest.datasets[0].params.background,
            Distribution::Fixed(8.4)
        );
        assert_eq!(
            manifest.datasets[1].params.brightness,
            Distribution::Fixed(7.5)
        );
        assert_eq!(manifest.datasets[1].params.background, uniform(2.0, 12.0));
        let yaml = manifest.to_resolved_yaml().unwrap();
        assert!(yaml.contains("uniform"), "{yaml}");
        for (field, value, message) in [
            ("brightness", "{uniform: [-1, 10]}", "must be ≥ 0, got -1"),
            (
                "background",
                "{uniform: [3, .inf]}",
                "must be a finite number",
            ),
            (
                "brightness",
                "{uniform: [9, 2]}",
                "uniform bounds must be ordered",
            ),
            (
                "background",
                "{normal: [1, 2]}",
                "must be a number or {uniform: [LOW, HIGH]}",
            ),
            (
                "brightness",
                "{uniform: [1]}",
                "must be a number or {uniform: [LOW, HIGH]}",
            ),
            (
                "emitters",
                "{poisson: 3}",
                "must be a whole number or {choice: [N, ...]}",
            ),
            (
                "emitters",
                "{choice: [1, x]}",
                "must be a whole number or {choice: [N, ...]}",
            ),
            (
                "emitters",
                "-1",
                "must be a whole number or {choice: [N, ...]}",
            ),
        ] {
            let text =
                format!("name: t\nseed: 3\ndatasets:\n  a:\n    frames: 2\n    {field}: {value}\n");
            let error = parse(&text, "x.yaml").unwrap_err().to_string();
            assert!(
                error.starts_with(&format!("x.yaml:6: datasets.a.{field}: {message}")),
                "{value}: {error}"
            );
            assert!(!error.contains('\n'), "{error}");
        }
        // A field of another type keeps serde's own word for what it takes.
        let text =
            "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 2\n    height: {uniform: [1, 2]}\n";
        let error = parse(text, "x.yaml").unwrap_err().to_string();
        assert!(
            error.starts_with("x.yaml:6: datasets.a.height: ") && !error.contains("{uniform: [LOW"),
            "{error}"
        );
    }
}
