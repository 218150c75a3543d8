//! Making a step's artefact: one function per kind of step, reading its
//! inputs from memory or from the registry.

use std::collections::HashMap;
use std::sync::Arc;

use anyhow::Context;

use super::artefacts::Artefact;
use super::plan::{Action, PipelineSteps, Plan, Step};
use super::stored::load_step_artefact;
use crate::manifest::{
    CnnSpec, DatasetSpec, DetectorEntry, DetectorSpec, LinkerEntry, MetricsSpec, RecordingSpec,
};
use crate::registry::Registry;
use crate::track::pipeline::{
    BiasCorrection, BiasSetup, CorrectedEnsemble, TrackEvaluation, TrackScoring,
};

/// Artefacts held in memory for the steps still to come, each dropped after
/// the last step that reads it.
pub(super) struct LoadedArtefacts {
    artefacts: HashMap<usize, Artefact>,
    /// For each step, the index of the last step reading its artefact.
    last_use: Vec<usize>,
}

impl LoadedArtefacts {
    pub(super) fn new(plan: &Plan) -> Self {
        let mut last_use = vec![0usize; plan.steps.len()];
        for (index, step) in plan.steps.iter().enumerate() {
            for input in step.inputs() {
                last_use[input] = index;
            }
        }
        Self {
            artefacts: HashMap::new(),
            last_use,
        }
    }

    /// Keeps the artefact step `index` made if a later step reads it.
    pub(super) fn keep_if_read_later(&mut self, index: usize, artefact: Artefact) {
        if self.last_use[index] > index {
            self.artefacts.insert(index, artefact);
        }
    }

    /// Drops every artefact no step after `index` reads.
    pub(super) fn drop_unread_after(&mut self, index: usize) {
        let last_use = &self.last_use;
        self.artefacts.retain(|&i, _| last_use[i] > index);
    }
}

/// Makes the artefact of step `index`.
pub(super) fn compute(
    registry: &Registry,
    plan: &Plan,
    index: usize,
    loaded: &mut LoadedArtefacts,
) -> anyhow::Result<Artefact> {
    let step = &plan.steps[index];
    let mut read_input = |index: usize| input(registry, plan, index, loaded);
    match &step.action {
        Action::Simulate { dataset } => simulate(dataset),
        Action::Subset { source, frames } => {
            let source = read_input(*source)?;
            Ok(Artefact::Dataset(Arc::new(subset(
                source.dataset()?,
                frames,
            )?)))
        }
        Action::Train {
            detector,
            training,
            validation,
        } => {
            let training_set = read_input(*training)?;
            let validation_set = validation.map(&mut read_input).transpose()?;
            let fresh_frames = root_dataset(plan, *training).map(|d| &d.params);
            train(
                detector,
                &training_set,
                validation_set.as_ref(),
                fresh_frames,
            )
        }
        Action::Locate {
            detector,
            dataset,
            model,
        } => {
            let microscope = root_microscope(plan, *dataset);
            let dataset = read_input(*dataset)?;
            let model = model.map(&mut read_input).transpose()?;
            locate(step, detector, &dataset, model.as_ref(), microscope)
        }
        Action::Score {
            dataset,
            predictions,
            metrics,
            reading,
            ..
        } => {
            let dataset = read_input(*dataset)?;
            let predictions = read_input(*predictions)?;
            score(step, &dataset, &predictions, metrics, *reading)
        }
        Action::SimulateRecording { recording } => simulate_recording(recording),
        Action::Link {
            linker,
            min_score,
            recording,
            predictions,
            ..
        } => {
            let spec = recording_spec(plan, *recording)?;
            let predictions = read_input(*predictions)?;
            link(step, spec, &predictions, *min_score, linker)
        }
        Action::ScoreTracks {
            recording,
            tracks,
            scoring,
            bias,
            ..
        } => {
            let spec = recording_spec(plan, *recording)?;
            let data = read_input(*recording)?;
            let tracks = read_input(*tracks)?;
            let mut evaluation = score_tracks(step, spec, &data, &tracks, scoring)?;
            if let (BiasCorrection::Simulated { recordings }, Some(bias)) =
                (scoring.bias_correction, bias)
            {
                let setup = BiasSetup {
                    recording: &spec.params,
                    seed: step
                        .seed
                        .context("a bias correction draws from the step's seed")?,
                    recordings,
                    min_score: bias.min_score,
                    linker: &bias.linker.spec,
                    scoring,
                    bar: &|len, label| crate::progress::bar(len, label),
                    stop: &|| false,
                };
                evaluation.corrected_ensemble =
                    correct_bias(step, &setup, bias, &evaluation, &mut read_input)
                        .with_context(|| format!("correcting the bias of {}", step.name()))?;
            }
            Ok(Artefact::TrackEvaluation(Arc::new(evaluation)))
        }
    }
}

/// Links `predictions` (those scoring at least `min_score`) on the
/// recording `spec` into tracks with `linker`.
fn link(
    step: &Step,
    spec: &RecordingSpec,
    predictions: &Artefact,
    min_score: Option<f64>,
    linker: &LinkerEntry,
) -> anyhow::Result<Artefact> {
    let progress = crate::progress::heartbeat(&step.name());
    let tracks = crate::track::pipeline::link_predictions(
        predictions.predictions()?,
        min_score,
        &linker.spec,
        &spec.geometry(),
    )
    .with_context(|| format!("linking {}", step.name()))?;
    progress.finish_and_clear();
    Ok(Artefact::Tracks(Arc::new(tracks)))
}

/// Scores `tracks` against the truth of the recording `data` (made from
/// `spec`): the tracking measures and the estimates of D.
fn score_tracks(
    step: &Step,
    spec: &RecordingSpec,
    data: &Artefact,
    tracks: &Artefact,
    scoring: &TrackScoring,
) -> anyhow::Result<TrackEvaluation> {
    let progress = crate::progress::heartbeat(&step.name());
    let evaluation = crate::track::pipeline::evaluate(
        &data.recording()?.truth,
        tracks.tracks()?,
        &spec.geometry(),
        scoring,
        spec.diffusion(),
        &progress,
    )
    .with_context(|| format!("scoring {}", step.name()))?;
    progress.finish_and_clear();
    Ok(evaluation)
}

/// The ML ensemble's estimate of D corrected for the pipeline's bias by
/// simulating recordings like this one and putting them through the same
/// localiser and linker (`bias`); `None` when the evaluation has no ML
/// ensemble to correct.
fn correct_bias(
    step: &Step,
    setup: &BiasSetup,
    bias: &PipelineSteps,
    evaluation: &TrackEvaluation,
    read_input: &mut dyn FnMut(usize) -> anyhow::Result<Artefact>,
) -> anyhow::Result<Option<CorrectedEnsemble>> {
    let predictions = read_input(bias.predictions)?;
    let model = bias.model.map(&mut *read_input).transpose()?;
    // The simulated recordings are made to have as many localisations as
    // the pipeline kept on the real one.
    let kept = predictions
        .predictions()?
        .iter()
        .filter(|p| crate::track::pipeline::scores_at_least(p, setup.min_score))
        .count();
    let model = model.as_ref();
    let microscope = &setup.recording.microscope;
    let mut localise = |label: &str, frames: &crate::types::FrameStack| {
        locate_frames(label, &bias.detector, frames, model, Some(microscope))
    };
    match evaluation
        .estimator(crate::track::diffusion::Method::Ml)
        .and_then(|e| e.ensemble)
    {
        Some(recorded) => crate::track::pipeline::correct_ensemble(
            &step.name(),
            setup,
            &recorded,
            kept,
            evaluation.true_diffusion_um2_s,
            &mut localise,
        ),
        None => Ok(None),
    }
}

/// The recording simulated by step `index`.
fn recording_spec(plan: &Plan, index: usize) -> anyhow::Result<&RecordingSpec> {
    match &plan.steps[index].action {
        Action::SimulateRecording { recording } => Ok(recording),
        _ => anyhow::bail!("{} is not a recording", plan.steps[index].id),
    }
}

fn simulate_recording(recording: &RecordingSpec) -> anyhow::Result<Artefact> {
    let progress = crate::progress::bar(recording.params.frames as u64, &recording.name);
    let made = crate::sim::recording::simulate_recording_with_progress(
        &recording.params,
        recording.seed,
        true,
        &progress,
    )
    .with_context(|| format!("simulating recording {}", recording.name))?;
    progress.finish_and_clear();
    Ok(Artefact::Recording(Arc::new(
        super::artefacts::RecordingData {
            frames: made.frames,
            truth: made.truth,
        },
    )))
}

/// The artefact of step `index`, from memory or from the registry (then
/// kept in memory until its last reader is done).
fn input(
    registry: &Registry,
    plan: &Plan,
    index: usize,
    loaded: &mut LoadedArtefacts,
) -> anyhow::Result<Artefact> {
    if let Some(artefact) = loaded.artefacts.get(&index) {
        return Ok(artefact.clone());
    }
    let artefact = load_step_artefact(registry, plan, index)?;
    loaded.artefacts.insert(index, artefact.clone());
    Ok(artefact)
}

fn simulate(dataset: &DatasetSpec) -> anyhow::Result<Artefact> {
    let progress = crate::progress::bar(dataset.frames as u64, &dataset.name);
    let made = crate::sim::simulate(&dataset.params, dataset.seed, 0..dataset.frames, &progress)
        .with_context(|| format!("simulating dataset {}", dataset.name))?;
    progress.finish_and_clear();
    Ok(Artefact::Dataset(Arc::new(made)))
}

/// Trains `detector` on `training_set`, selecting its epoch on
/// `validation_set` if given (else on a split of the training set).
fn train(
    detector: &DetectorEntry,
    training_set: &Artefact,
    validation_set: Option<&Artefact>,
    fresh_frames: Option<&crate::sim::SimParams>,
) -> anyhow::Result<Artefact> {
    let spec: &CnnSpec = match &detector.spec {
        DetectorSpec::CrockerGrier(_) | DetectorSpec::Likelihood(_) => {
            anyhow::bail!(
                "{}: {} is not a trained detector",
                detector.name,
                detector.spec.kind()
            )
        }
        DetectorSpec::Cnn(spec) => spec,
    };
    let training_set = training_set.dataset()?;
    let progress = crate::progress::bar(0, &format!("train {}", detector.name));
    let model = match validation_set {
        Some(validation_set) => crate::detect::cnn::train_selecting_on(
            &spec.architecture,
            &spec.training,
            training_set,
            crate::detect::cnn::ValidationSet {
                dataset: validation_set.dataset()?,
                score: &crate::metrics::paper_aucs,
            },
            fresh_frames,
            detector.seed,
            &progress,
        ),
        None => crate::detect::cnn::train(
            &spec.architecture,
            &spec.training,
            training_set,
            fresh_frames,
            detector.seed,
            &crate::metrics::paper_aucs,
            &progress,
        ),
    }
    .with_context(|| format!("training {}", detector.name))?;
    progress.finish_and_clear();
    Ok(Artefact::Model(Arc::new(model.to_bytes()?)))
}

/// Runs `detector` (with its trained `model`, if it is trained) on the
/// frames of `dataset`, taken with `microscope` (the simulated dataset's
/// parameters, which the likelihood detector models).
fn locate(
    step: &Step,
    detector: &DetectorEntry,
    dataset: &Artefact,
    model: Option<&Artefact>,
    microscope: Option<&crate::sim::SimParams>,
) -> anyhow::Result<Artefact> {
    let predictions = locate_frames(&step.name(), detector, dataset.frames()?, model, microscope)?;
    Ok(Artefact::Predictions(Arc::new(predictions)))
}

/// `detector`'s localisations in `frames` (with its trained `model`; the
/// `microscope` the frames were made with, for the likelihood detector),
/// its progress shown as `label`.
fn locate_frames(
    label: &str,
    detector: &DetectorEntry,
    frames: &crate::types::FrameStack,
    model: Option<&Artefact>,
    microscope: Option<&crate::sim::SimParams>,
) -> anyhow::Result<Vec<crate::types::Prediction>> {
    let progress = crate::progress::bar(frames.n as u64, label);
    let predictions = match &detector.spec {
        DetectorSpec::CrockerGrier(params) => {
            let features = crate::detect::crocker_grier::locate_stack(frames, params, &progress)
                .with_context(|| format!("locating with {}", detector.name))?;
            crate::detect::crocker_grier::to_predictions(&features)
        }
        DetectorSpec::Cnn(_) => {
            let bytes = model
                .context("the cnn detector needs its trained model")?
                .model()?;
            crate::detect::cnn::TrainedCnn::from_bytes(bytes)?
                .locate(frames, &progress)
                .with_context(|| format!("locating with {}", detector.name))?
        }
        DetectorSpec::Likelihood(params) => {
            let microscope =
                microscope.context("the likelihood detector needs the dataset's microscope")?;
            crate::detect::likelihood::locate_stack(
                frames,
                microscope,
                params,
                detector.seed,
                &progress,
            )
            .with_context(|| format!("locating with {}", detector.name))?
        }
    };
    progress.finish_and_clear();
    Ok(predictions)
}

/// Scores `predictions` against the truth of `dataset`, the score read as
/// `reading`.
fn score(
    step: &Step,
    dataset: &Artefact,
    predictions: &Artefact,
    metrics: &MetricsSpec,
    reading: crate::metrics::ScoreReading,
) -> anyhow::Result<Artefact> {
    let dataset = dataset.dataset()?;
    let score = crate::metrics::score_read_as(
        predictions.predictions()?,
        &dataset.truth,
        dataset.frames.n,
        &metrics.eps_px,
        metrics.keep_curves,
        reading,
    )
    .with_context(|| format!("scoring {}", step.name()))?;
    Ok(Artefact::Evaluation(Arc::new(score)))
}

/// The step that simulated the frames of step `index`: itself, or the
/// source of a subset.
fn root_step(plan: &Plan, mut index: usize) -> &Action {
    while let Action::Subset { source, .. } = &plan.steps[index].action {
        index = *source;
    }
    &plan.steps[index].action
}

/// The simulated dataset step `index` comes from (itself, or the source of
/// a subset).
pub(super) fn root_dataset(plan: &Plan, index: usize) -> Option<&DatasetSpec> {
    match root_step(plan, index) {
        Action::Simulate { dataset } => Some(dataset),
        _ => None,
    }
}

/// The microscope of the frames step `index` makes: a dataset's (or its
/// source's) or a recording's.
fn root_microscope(plan: &Plan, index: usize) -> Option<&crate::sim::SimParams> {
    match root_step(plan, index) {
        Action::Simulate { dataset } => Some(&dataset.params),
        Action::SimulateRecording { recording } => Some(&recording.params.microscope),
        _ => None,
    }
}

/// Frames `frames` of `source` (renumbered 0, 1, … in the given order) and
/// their truth rows.
pub fn subset(
    source: &crate::types::Dataset,
    frames: &[usize],
) -> anyhow::Result<crate::types::Dataset> {
    let stack = &source.frames;
    let mut data = Vec::with_capacity(frames.len() * stack.frame_len());
    let mut position = vec![None; stack.n];
    for (new, &old) in frames.iter().enumerate() {
        anyhow::ensure!(
            old < stack.n,
            "subset: frame {old} of a {}-frame dataset",
            stack.n
        );
        anyhow::ensure!(position[old].is_none(), "subset: frame {old} twice");
        position[old] = Some(new);
        data.extend_from_slice(stack.frame(old));
    }
    let mut truth: Vec<crate::types::TruthRow> = source
        .truth
        .iter()
        .filter_map(|row| {
            position.get(row.frame).copied().flatten().map(|new| {
                let mut row = *row;
                row.frame = new;
                row
            })
        })
        .collect();
    // Frame order, emitters in their original order within a frame.
    truth.sort_by_key(|row| row.frame);
    Ok(crate::types::Dataset {
        frames: crate::types::FrameStack::from_vec(frames.len(), stack.height, stack.width, data)?,
        truth,
    })
}
