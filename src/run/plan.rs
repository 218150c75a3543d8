//! A manifest resolved into a plan: the ordered list of steps that make its
//! artefacts, each with its content key.
//!
//! Steps come in dependency order (every input before its users):
//! `dataset/<name>` (simulate), `model/<detector>` (train a trained
//! detector), `predictions/<detector>@<dataset>` (locate), and
//! `evaluation/<detector>@<dataset>` (score). A key is the sha256 of the
//! canonical JSON of the step's description: its resolved parameters and
//! seed, the keys of its inputs, and the versions of the code that makes it
//! and of the blob format. Names are not part of keys, except through the
//! seeds derived from them.
//!
//! Other commands (cross-validation, calibration) build plans of their own
//! from the same step kinds and run them through [`super::execute`].

use std::collections::BTreeMap;
use std::sync::Arc;

use anyhow::Context;
use serde_json::json;

use super::artefacts::FORMAT_VERSION;
use super::descriptions::{
    Describes, Keyed, LinkDescription, LocateDescription, MetricDescription, RecordingDescription,
    ScoreDescription, SimulateDescription, SubsetDescription, TrackScoreDescription,
    TrainDescription,
};
use crate::manifest::{
    DatasetSpec, DetectorEntry, LinkerEntry, Manifest, MetricsSpec, RecordingSpec,
};
use crate::metrics::ScoreReading;
use crate::registry::hashing::{canonical_json, content_key};
use crate::registry::{ArtefactKind, StepId};
use crate::sim::GENERATOR_VERSION;
use crate::sim::recording::RECORDING_VERSION;
use crate::track::pipeline::{
    BIAS_CORRECTION_VERSION, BiasCorrection, LINK_VERSION, TRACK_METRIC_VERSION, TrackScoring,
};
use crate::types::derive_seed;

/// Version of the frame-subset step (cross-validation folds).
pub(crate) const SUBSET_VERSION: &str = "scanloc-subset/1";

/// Version of the scoring step (the metric of `docs/metric.md` and its
/// `score.json`).
pub(crate) const METRIC_VERSION: &str = "scanloc-metric/5";

/// What a step does.
#[derive(Debug, Clone)]
pub enum Action {
    /// Simulate a dataset.
    Simulate { dataset: DatasetSpec },
    /// The frames `frames` (in this order, renumbered from 0) of the dataset
    /// made by step `source`, with their truth: e.g. the training part of
    /// a cross-validation fold.
    Subset {
        source: usize,
        frames: Arc<Vec<usize>>,
    },
    /// Train a detector on the dataset made by step `training`, selecting
    /// its epoch on the dataset made by step `validation` if given (else on
    /// a split of the training set).
    Train {
        detector: DetectorEntry,
        training: usize,
        validation: Option<usize>,
    },
    /// Run a detector on the dataset made by step `dataset`, with the model
    /// made by step `model` if it is trained.
    Locate {
        detector: DetectorEntry,
        dataset: usize,
        model: Option<usize>,
    },
    /// Score the predictions of step `predictions` against the truth of
    /// step `dataset`.
    Score {
        detector: String,
        dataset_name: String,
        diffusion: Option<f64>,
        dataset: usize,
        predictions: usize,
        metrics: MetricsSpec,
        /// How the detector's score is read (threshold, probability).
        reading: ScoreReading,
    },
    /// Simulate a continuous recording (a dataset of its own kind: its
    /// truth follows QDs from frame to frame).
    SimulateRecording { recording: RecordingSpec },
    /// Link the predictions of step `predictions`, made on the recording of
    /// step `recording`, into tracks: the tracking pipeline `pipeline`
    /// (`DETECTOR+LINKER`).
    Link {
        pipeline: String,
        linker: LinkerEntry,
        /// Only predictions scoring at least this are linked.
        min_score: Option<f64>,
        recording: usize,
        predictions: usize,
    },
    /// Score the tracks of step `tracks` against the truth of the recording
    /// of step `recording`: tracking measures and D.
    ScoreTracks {
        pipeline: String,
        recording_name: String,
        recording: usize,
        tracks: usize,
        scoring: TrackScoring,
        /// With a bias correction by simulation: the pipeline a simulated
        /// recording is put through.
        bias: Option<PipelineSteps>,
    },
}

/// What a bias correction by simulation repeats of a tracking pipeline
/// ([`BiasCorrection::Simulated`]): its localiser (and the step that
/// trained its model), its score threshold and linker, and the step of its
/// localisations on the recording, whose count per frame the simulated
/// recording is made to match.
#[derive(Debug, Clone)]
pub struct PipelineSteps {
    pub detector: DetectorEntry,
    pub model: Option<usize>,
    pub min_score: Option<f64>,
    pub linker: LinkerEntry,
    pub predictions: usize,
}

/// One step of a plan.
#[derive(Debug, Clone)]
pub struct Step {
    /// `dataset/train`, `model/cnn`, `predictions/trackpy@test-1.00`, …
    pub id: StepId,
    /// sha256 of [`Step::spec`].
    pub key: String,
    /// The canonical JSON description the key is the hash of.
    pub spec: String,
    /// Version of the code that makes the artefact.
    pub code_version: String,
    /// The seed the step draws from, if it draws.
    pub seed: Option<u64>,
    pub action: Action,
}

impl Step {
    /// The kind of artefact the step makes.
    pub fn kind(&self) -> ArtefactKind {
        self.id.kind()
    }

    /// The artefact's name: `train`, `cnn`, `trackpy@test-1.00`.
    pub fn name(&self) -> String {
        self.id.name()
    }

    /// Indices of the steps whose artefacts this one reads.
    pub fn inputs(&self) -> Vec<usize> {
        match &self.action {
            Action::Simulate { .. } => Vec::new(),
            Action::Subset { source, .. } => vec![*source],
            Action::Train {
                training,
                validation,
                ..
            } => std::iter::once(*training).chain(*validation).collect(),
            Action::Locate { dataset, model, .. } => {
                let mut inputs = vec![*dataset];
                inputs.extend(model);
                inputs
            }
            Action::Score {
                dataset,
                predictions,
                ..
            } => vec![*dataset, *predictions],
            Action::SimulateRecording { .. } => Vec::new(),
            Action::Link {
                recording,
                predictions,
                ..
            } => vec![*recording, *predictions],
            Action::ScoreTracks {
                recording,
                tracks,
                bias,
                ..
            } => {
                let mut inputs = vec![*recording, *tracks];
                if let Some(bias) = bias {
                    inputs.push(bias.predictions);
                    inputs.extend(bias.model);
                }
                inputs
            }
        }
    }
}

/// The steps of a run, in dependency order.
#[derive(Debug, Clone, Default)]
pub struct Plan {
    pub steps: Vec<Step>,
}

/// The step `id` whose key is the hash of `description` with its kind,
/// which must be the kind of artefact `id` names.
fn make_step<T: Describes>(
    id: StepId,
    code_version: &str,
    seed: Option<u64>,
    description: &T,
    action: Action,
) -> anyhow::Result<Step> {
    assert_eq!(
        id.kind(),
        T::KIND,
        "step {id} is described as making another kind of artefact"
    );
    let description = Keyed::new(description);
    Ok(Step {
        key: content_key(&description)?,
        spec: canonical_json(&description)?,
        id,
        code_version: code_version.to_string(),
        seed,
        action,
    })
}

impl Plan {
    /// Adds a step (its inputs must already be in the plan) and returns its
    /// index; a step with the same id is not added twice.
    pub fn push(&mut self, step: Step) -> usize {
        if let Some(index) = self.index_of(&step.id) {
            return index;
        }
        self.steps.push(step);
        self.steps.len() - 1
    }

    /// The index of the step with id `id`.
    pub fn index_of(&self, id: &StepId) -> Option<usize> {
        self.steps.iter().position(|s| s.id == *id)
    }

    /// Adds the step that simulates `dataset`.
    pub fn add_dataset(&mut self, dataset: &DatasetSpec) -> anyhow::Result<usize> {
        let code_version = format!("{GENERATOR_VERSION}+{FORMAT_VERSION}");
        let description = SimulateDescription {
            code: &code_version,
            params: &dataset.params,
            frames: dataset.frames,
            seed: dataset.seed,
        };
        let step = make_step(
            StepId::Dataset(dataset.name.clone()),
            &code_version,
            Some(dataset.seed),
            &description,
            Action::Simulate {
                dataset: dataset.clone(),
            },
        )?;
        Ok(self.push(step))
    }

    /// Adds a step that takes frames `frames` of the dataset of step
    /// `source` as a dataset of its own, named `name`. `description` says
    /// how the frames were chosen (e.g. `{"fold": 2, "folds": 5, "part":
    /// "train", "permutation_seed": "…"}`) and goes into the key together
    /// with the sha256 of the frame list itself.
    pub fn add_subset(
        &mut self,
        source: usize,
        name: &str,
        frames: Vec<usize>,
        description: serde_json::Value,
    ) -> anyhow::Result<usize> {
        let code_version = format!("{SUBSET_VERSION}+{FORMAT_VERSION}");
        let list = frames
            .iter()
            .map(|f| f.to_string())
            .collect::<Vec<_>>()
            .join(",");
        let spec = SubsetDescription {
            code: &code_version,
            source: &self.steps[source].key,
            frames: frames.len(),
            frames_sha256: crate::registry::hashing::sha256_hex(list.as_bytes()),
            chosen_by: &description,
        };
        let step = make_step(
            StepId::Dataset(name.to_string()),
            &code_version,
            None,
            &spec,
            Action::Subset {
                source,
                frames: Arc::new(frames),
            },
        )?;
        Ok(self.push(step))
    }

    /// Adds the step that trains `detector` on the dataset of step
    /// `training`, selecting its epoch on the dataset of step `validation`
    /// when given (a cross-validation's held-out fold).
    pub fn add_training(
        &mut self,
        detector: &DetectorEntry,
        training: usize,
        validation: Option<usize>,
    ) -> anyhow::Result<usize> {
        let code_version = format!("{}+{FORMAT_VERSION}", detector.spec.code_version());
        // The validation set only when given, so that models selected on
        // a split of their training set keep the keys they always had.
        // Since 2026-12-01 such a model (a cross-validation's fold model)
        // trains on fresh frames only, none of `training`'s, when the
        // detector's recipe says so; it keeps a key apart from the models
        // trained on both before. The key of every other model is as it
        // always was.
        let description = TrainDescription {
            code: &code_version,
            detector: &detector.spec,
            training: &self.steps[training].key,
            seed: detector.seed,
            validation: validation.map(|v| self.steps[v].key.as_str()),
            trains_on: (validation.is_some() && detector.spec.trains_on_fresh_frames_only())
                .then_some("fresh frames only"),
        };
        let step = make_step(
            StepId::Model(detector.name.clone()),
            &code_version,
            Some(detector.seed),
            &description,
            Action::Train {
                detector: detector.clone(),
                training,
                validation,
            },
        )?;
        Ok(self.push(step))
    }

    /// Adds the step that runs `detector` on the dataset of step `dataset`
    /// (with the model of step `model`, for trained detectors).
    pub fn add_locate(
        &mut self,
        detector: &DetectorEntry,
        dataset: usize,
        model: Option<usize>,
    ) -> anyhow::Result<usize> {
        let code_version = format!("{}+{FORMAT_VERSION}", detector.spec.locate_code_version());
        let dataset_step = &self.steps[dataset];
        // A seed only for detectors that draw while locating, so that the
        // others keep the keys they always had.
        let seed = detector.spec.locates_at_random().then_some(detector.seed);
        let description = LocateDescription {
            code: &code_version,
            detector: &detector.spec,
            dataset: &dataset_step.key,
            model: model.map(|m| self.steps[m].key.as_str()),
            seed,
        };
        let id = StepId::Predictions {
            detector: detector.name.clone(),
            dataset: dataset_step.name(),
        };
        let step = make_step(
            id,
            &code_version,
            seed,
            &description,
            Action::Locate {
                detector: detector.clone(),
                dataset,
                model,
            },
        )?;
        Ok(self.push(step))
    }

    /// Adds the step that scores the predictions of step `predictions`
    /// against the dataset of step `dataset`, the score read as `reading`.
    /// Only this detector's reading is part of the key, so another
    /// detector's threshold never changes it.
    pub fn add_score(
        &mut self,
        detector: &str,
        dataset: usize,
        diffusion: Option<f64>,
        predictions: usize,
        metrics: &MetricsSpec,
        reading: ScoreReading,
    ) -> anyhow::Result<usize> {
        let code_version = format!("{METRIC_VERSION}+{FORMAT_VERSION}");
        let description = ScoreDescription {
            code: &code_version,
            dataset: &self.steps[dataset].key,
            predictions: &self.steps[predictions].key,
            metric: MetricDescription {
                eps_px: &metrics.eps_px,
                keep_curves: metrics.keep_curves,
            },
            reading,
        };
        let dataset_name = self.steps[dataset].name();
        let id = StepId::Evaluation {
            detector: detector.to_string(),
            dataset: dataset_name.clone(),
        };
        let step = make_step(
            id,
            &code_version,
            None,
            &description,
            Action::Score {
                detector: detector.to_string(),
                dataset_name,
                diffusion,
                dataset,
                predictions,
                metrics: metrics.clone(),
                reading,
            },
        )?;
        Ok(self.push(step))
    }

    /// Adds the step that simulates `recording`.
    pub fn add_recording(&mut self, recording: &RecordingSpec) -> anyhow::Result<usize> {
        let code_version = format!("{RECORDING_VERSION}+{FORMAT_VERSION}");
        let description = RecordingDescription {
            code: &code_version,
            recording: recording.params_json(),
            seed: recording.seed,
        };
        let step = make_step(
            StepId::Dataset(recording.name.clone()),
            &code_version,
            Some(recording.seed),
            &description,
            Action::SimulateRecording {
                recording: recording.clone(),
            },
        )?;
        Ok(self.push(step))
    }

    /// Adds the step that links the predictions of step `predictions` on
    /// the recording of step `recording` with `linker`, keeping those that
    /// score at least `min_score`; `detector` names the localiser.
    pub fn add_link(
        &mut self,
        detector: &str,
        linker: &LinkerEntry,
        min_score: Option<f64>,
        recording: usize,
        predictions: usize,
    ) -> anyhow::Result<usize> {
        let code_version = format!("{LINK_VERSION}+{FORMAT_VERSION}");
        let pipeline = format!("{detector}+{}", linker.name);
        let description = LinkDescription {
            code: &code_version,
            linker: &linker.spec,
            min_score,
            recording: &self.steps[recording].key,
            predictions: &self.steps[predictions].key,
        };
        let id = StepId::Predictions {
            detector: pipeline.clone(),
            dataset: self.steps[recording].name(),
        };
        let step = make_step(
            id,
            &code_version,
            None,
            &description,
            Action::Link {
                pipeline,
                linker: linker.clone(),
                min_score,
                recording,
                predictions,
            },
        )?;
        Ok(self.push(step))
    }

    /// Adds the step that scores the tracks of step `tracks` (pipeline
    /// `pipeline`) against the recording of step `recording`; `bias` is
    /// the pipeline a bias correction by simulation repeats (needed with
    /// [`BiasCorrection::Simulated`], not read otherwise).
    pub fn add_track_score(
        &mut self,
        pipeline: &str,
        recording: usize,
        tracks: usize,
        scoring: &TrackScoring,
        bias: Option<PipelineSteps>,
    ) -> anyhow::Result<usize> {
        let code_version = format!("{TRACK_METRIC_VERSION}+{FORMAT_VERSION}");
        let mut description = TrackScoreDescription {
            code: &code_version,
            recording: &self.steps[recording].key,
            tracks: &self.steps[tracks].key,
            scoring,
            bias_correction_code: None,
            bias_correction_seed: None,
        };
        // The tracks' key holds the localiser, its model and the linker,
        // so the correction adds only its own version and seed (which the
        // pipeline's name derives: renamed, it draws other recordings); an
        // evaluation without one keeps its key.
        let (bias, seed) = match scoring.bias_correction {
            BiasCorrection::None => (None, None),
            BiasCorrection::Simulated { .. } => {
                let seed = self.steps[recording]
                    .seed
                    .map(|seed| derive_seed(seed, "bias-correction", pipeline))
                    .context("a bias correction needs a simulated recording's seed")?;
                description.bias_correction_code = Some(BIAS_CORRECTION_VERSION);
                description.bias_correction_seed = Some(seed);
                let bias = bias.context("a bias correction needs the pipeline's steps")?;
                (Some(bias), Some(seed))
            }
        };
        let recording_name = self.steps[recording].name();
        let id = StepId::Evaluation {
            detector: pipeline.to_string(),
            dataset: recording_name.clone(),
        };
        let step = make_step(
            id,
            &code_version,
            seed,
            &description,
            Action::ScoreTracks {
                pipeline: pipeline.to_string(),
                recording_name,
                recording,
                tracks,
                scoring: *scoring,
                bias,
            },
        )?;
        Ok(self.push(step))
    }

    /// The steps of a manifest's tracking pipelines: each recording, the
    /// training of each trained detector, locate, link and score.
    fn add_tracking(&mut self, manifest: &Manifest) -> anyhow::Result<()> {
        let Some(tracking) = &manifest.tracking else {
            return Ok(());
        };
        for evaluation in &tracking.evaluations {
            let detector = manifest
                .detector(&evaluation.detector)
                .expect("the manifest checked its references");
            let linker = manifest
                .linkers
                .iter()
                .find(|l| l.name == evaluation.linker)
                .expect("the manifest checked its references");
            let recording = manifest
                .recordings
                .iter()
                .find(|r| r.name == evaluation.recording)
                .expect("the manifest checked its references");
            let model = match detector.spec.training_dataset() {
                Some(training) => {
                    let training = manifest
                        .dataset(training)
                        .expect("the manifest checked its references");
                    let training = self.add_dataset(training)?;
                    Some(self.add_training(detector, training, None)?)
                }
                None => None,
            };
            let recording_step = self.add_recording(recording)?;
            let predictions = self.add_locate(detector, recording_step, model)?;
            let tracks = self.add_link(
                &detector.name,
                linker,
                evaluation.min_score,
                recording_step,
                predictions,
            )?;
            let pipeline = PipelineSteps {
                detector: detector.clone(),
                model,
                min_score: evaluation.min_score,
                linker: linker.clone(),
                predictions,
            };
            let scoring = TrackScoring {
                bias_correction: evaluation
                    .bias_correction
                    .unwrap_or(tracking.scoring.bias_correction),
                ..tracking.scoring
            };
            self.add_track_score(
                &evaluation.pipeline(),
                recording_step,
                tracks,
                &scoring,
                Some(pipeline),
            )?;
        }
        Ok(())
    }

    /// The plan of a manifest: every dataset, the training of every trained
    /// detector that is evaluated, every evaluation (locate + score), and
    /// every tracking pipeline (recording, locate, link, score).
    pub fn from_manifest(manifest: &Manifest) -> anyhow::Result<Self> {
        let mut plan = Plan::default();
        let mut dataset_steps = BTreeMap::new();
        for dataset in &manifest.datasets {
            dataset_steps.insert(dataset.name.clone(), plan.add_dataset(dataset)?);
        }
        for evaluation in &manifest.evaluations {
            let detector = manifest
                .detector(&evaluation.detector)
                .expect("the manifest checked its references");
            let model = match detector.spec.training_dataset() {
                Some(training) => {
                    Some(plan.add_training(detector, dataset_steps[training], None)?)
                }
                None => None,
            };
            let (dataset_step, diffusion) = match evaluation.frames {
                None => (
                    dataset_steps[&evaluation.dataset],
                    manifest
                        .dataset(&evaluation.dataset)
                        .and_then(DatasetSpec::fixed_diffusion),
                ),
                // The first frames as a dataset of their own (without a
                // fixed D of its own, as the registry records subsets).
                Some(frames) => (
                    plan.add_subset(
                        dataset_steps[&evaluation.dataset],
                        &evaluation.scored_dataset_name(),
                        (0..frames).collect(),
                        json!({"first": frames}),
                    )?,
                    None,
                ),
            };
            let predictions = plan.add_locate(detector, dataset_step, model)?;
            plan.add_score(
                &detector.name,
                dataset_step,
                diffusion,
                predictions,
                &manifest.metrics,
                manifest.metrics.score_reading(detector),
            )?;
        }
        plan.add_tracking(manifest)?;
        Ok(plan)
    }

    /// Every seed the plan draws from, by step id (decimal strings: seeds
    /// are unsigned 64-bit).
    pub fn seeds(&self) -> BTreeMap<String, String> {
        self.steps
            .iter()
            .filter_map(|s| s.seed.map(|seed| (s.id.to_string(), seed.to_string())))
            .collect()
    }
}
