//! The training loop: Adam on a CenterNet-style focal loss (score map) plus
//! an L1 loss on the sub-pixel offsets, a Gaussian negative log-likelihood
//! for the σ maps and a cross-entropy for the within-1-px head (both
//! against the realised error of the offsets, which they do not move), with
//! seeded shuffling, optional freshly simulated frames every epoch,
//! optional posterior-mean targets from the likelihood detector (a
//! teacher), and selection of the epoch with the best validation AUC.

use burn::optim::AdamConfig;
use burn::prelude::*;
use indicatif::ProgressBar;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;

use super::data::{Source, truth_by_frame};
use super::ensemble::{Member, member_seed};
use super::inference::{NonFiniteOutput, inference_batch, locate_with};
use super::loss::{BatchLoss, LossValues, batch_loss};
use super::model::Net;
use super::streams::{
    STREAM_FRESH, STREAM_INIT, STREAM_SHUFFLE, STREAM_SPLIT, STREAM_TEACHER, stream,
};
pub use super::teacher::teacher_targets;
use super::teacher::{Lesson, Teacher, fixed_lesson};
use super::{CnnArchitecture, CnnHead, EpochRecord, TrainedCnn, TrainingRecord, TrainingSettings};
use crate::sim::{self, EmitterCount, SimParams};
use crate::types::{Dataset, FrameStack, Prediction, TruthRow};

/// The score a validation pass judges an epoch by: from a model's
/// predictions on the validation dataset, one AUC per matching radius (in
/// [0, 1], higher is better); the epoch with the best mean is kept. The
/// caller chooses the metric (the paper's is `metrics::paper_aucs`), so the
/// detector does not depend on the metric's layer.
pub type ValidationScore = dyn Fn(&[Prediction], &Dataset) -> anyhow::Result<Vec<f64>>;

/// How the epoch to keep is chosen: the score, and the frames it is
/// computed on.
#[derive(Clone, Copy)]
struct Selection<'a> {
    score: &'a ValidationScore,
    /// A validation dataset of its own; `None`: split
    /// `settings.validation_fraction` of the training frames off.
    external: Option<&'a Dataset>,
}

/// Fisher–Yates shuffle driven by `rng` (explicit, so the order is fixed by
/// this code and not by a library's implementation).
pub(super) fn shuffle<T>(items: &mut [T], rng: &mut ChaCha8Rng) {
    for i in (1..items.len()).rev() {
        let j = rng.random_range(0..=i);
        items.swap(i, j);
    }
}

/// Frames `indices` of `dataset` as a new dataset, frames renumbered 0…
pub(super) fn subset(dataset: &Dataset, indices: &[usize]) -> anyhow::Result<Dataset> {
    let frames = &dataset.frames;
    let mut data = Vec::with_capacity(indices.len() * frames.frame_len());
    let mut position = vec![usize::MAX; frames.n];
    for (new, &old) in indices.iter().enumerate() {
        data.extend_from_slice(frames.frame(old));
        position[old] = new;
    }
    let mut truth: Vec<TruthRow> = dataset
        .truth
        .iter()
        .filter(|row| position.get(row.frame).is_some_and(|&p| p != usize::MAX))
        .map(|row| TruthRow {
            frame: position[row.frame],
            ..*row
        })
        .collect();
    truth.sort_by_key(|row| row.frame);
    Ok(Dataset {
        frames: FrameStack::from_vec(indices.len(), frames.height, frames.width, data)?,
        truth,
    })
}

/// The validation score of `net` on `validation`, one value per matching
/// radius (empty when there are no validation frames).
fn validate(
    net: &Net,
    arch: &CnnArchitecture,
    settings: &TrainingSettings,
    validation: &Dataset,
    score: &ValidationScore,
) -> anyhow::Result<Vec<f64>> {
    if validation.frames.n == 0 {
        return Ok(Vec::new());
    }
    let predictions = locate_with(
        std::slice::from_ref(net),
        arch,
        settings,
        &validation.frames,
        inference_batch(validation.frames.frame_len()),
        &ProgressBar::hidden(),
    )?;
    score(&predictions, validation)
}

/// Trains a localiser.
///
/// - `training`: a fixed dataset; `settings.validation_fraction` of its
///   frames (a seeded random choice) are held out for validation, the rest
///   are trained on every epoch.
/// - `fresh_frames`: simulator parameters for `settings.fresh_frames_per_epoch`
///   frames simulated anew each epoch (their frame size must match
///   `training`'s when both are used).
/// - `seed`: drives weight initialisation, the split, the batch order and
///   the fresh frames' seeds. Same inputs and seed → bit-identical weights,
///   whatever the thread count.
///
/// Each epoch ends with a validation pass scored by `score` (the paper's
/// metric: `metrics::paper_aucs`, the AUC at ε = 1, 2, 3 px); the weights
/// of the epoch with the best mean score are kept (the earliest on ties; the
/// last epoch without validation frames). With `settings.validate_from_epoch`
/// = E > 1, only epochs E and later are scored and may be kept. `progress`
/// counts optimiser steps and shows the latest loss and validation AUC after
/// its message as the training began (the caller's name for it, e.g. "train cnn"; give each
/// training a bar of its own). Fails with an error naming the epoch and
/// batch if the loss is not finite.
///
/// With `settings.members` = K > 1 (a deep ensemble), K networks are
/// trained one after another, each exactly as above (its own
/// initialisation, validation split, batch order, fresh frames and best
/// epoch): the first from `seed`, the others from seeds drawn from a
/// ChaCha stream of `seed` and the member's index. `progress` then counts
/// all K × steps and its message names the member.
pub fn train(
    arch: &CnnArchitecture,
    settings: &TrainingSettings,
    training: &Dataset,
    fresh_frames: Option<&SimParams>,
    seed: u64,
    score: &ValidationScore,
    progress: &ProgressBar,
) -> anyhow::Result<TrainedCnn> {
    let selection = Selection {
        score,
        external: None,
    };
    train_and_select(
        arch,
        settings,
        training,
        selection,
        fresh_frames,
        seed,
        progress,
    )
}

/// A validation dataset and the score it judges each epoch by (see
/// [`ValidationScore`]).
#[derive(Clone, Copy)]
pub struct ValidationSet<'a> {
    pub dataset: &'a Dataset,
    pub score: &'a ValidationScore,
}

/// Trains a localiser on every frame of `training` and keeps the epoch with
/// the best mean score on `validation`, a dataset of its own (e.g. the
/// held-out fold of a cross-validation). Nothing of `training` is held
/// out: every frame of it trains, unless `settings.validation_fraction` is
/// 1 ([`TrainingSettings::trains_on_fresh_frames_only`]), when none does
/// and the fresh frames alone train, as they would in [`train`]. Otherwise
/// as [`train`].
pub fn train_selecting_on(
    arch: &CnnArchitecture,
    settings: &TrainingSettings,
    training: &Dataset,
    validation: ValidationSet<'_>,
    fresh_frames: Option<&SimParams>,
    seed: u64,
    progress: &ProgressBar,
) -> anyhow::Result<TrainedCnn> {
    let ValidationSet {
        dataset: validation,
        score,
    } = validation;
    if validation.frames.n > 0
        && training.frames.n > 0
        && (validation.frames.height, validation.frames.width)
            != (training.frames.height, training.frames.width)
    {
        crate::bail_input!(
            "training: validation frames are {}×{} but the training frames are {}×{}",
            validation.frames.height,
            validation.frames.width,
            training.frames.height,
            training.frames.width
        );
    }
    let selection = Selection {
        score,
        external: Some(validation),
    };
    train_and_select(
        arch,
        settings,
        training,
        selection,
        fresh_frames,
        seed,
        progress,
    )
}

/// The training behind [`train`] (validation split off `training`) and
/// [`train_selecting_on`] (`selection.external` given): `settings.members`
/// networks trained one after another by [`train_member`], each from its
/// own [`member_seed`].
fn train_and_select(
    arch: &CnnArchitecture,
    settings: &TrainingSettings,
    training: &Dataset,
    selection: Selection<'_>,
    fresh_frames: Option<&SimParams>,
    seed: u64,
    progress: &ProgressBar,
) -> anyhow::Result<TrainedCnn> {
    super::validate_recipe(arch, settings)?;
    let fresh_params = match (settings.fresh_frames_per_epoch, fresh_frames) {
        (0, _) => None,
        (_, None) => crate::bail_input!(
            "training.fresh_frames_per_epoch: {} fresh frames per epoch need simulator parameters",
            settings.fresh_frames_per_epoch
        ),
        (fresh, Some(params)) => {
            params.validate()?;
            crate::limits::check_dataset_pixels(
                "training.fresh_frames_per_epoch",
                fresh,
                params.height,
                params.width,
            )?;
            Some(params)
        }
    };
    let teacher = match (settings.teacher_particles, fresh_frames) {
        (0, _) => None,
        (_, None) => crate::bail_input!(
            "training.teacher_particles: posterior-mean targets need the simulator parameters of the training frames (a dataset the manifest simulates, or `scanloc train`)"
        ),
        (particles, Some(microscope)) => Some(fixed_lesson(
            arch.head, training, microscope, particles, seed, progress,
        )?),
    };
    let job = Job {
        arch,
        settings,
        training,
        selection,
        fresh_params,
        teacher: teacher.as_ref(),
    };
    let mut nets = Vec::with_capacity(settings.members);
    let mut records = Vec::with_capacity(settings.members);
    // The caller's name for this training (e.g. "train cnn-cv1of5"): every
    // message the training sets keeps it, so a log says which training an
    // epoch belongs to.
    let task = progress.message();
    for index in 0..settings.members {
        let member = Member {
            task: &task,
            index,
            count: settings.members,
        };
        let (net, record) = train_member(job, member_seed(seed, index), member, progress)?;
        nets.push(net);
        records.push(record);
    }
    TrainedCnn::from_members(arch.clone(), settings.clone(), nets, records)
}

/// What every member of a training shares: the network's shape, the
/// settings, the data, how the epoch to keep is chosen and the checked
/// parameters of the fresh frames.
#[derive(Clone, Copy)]
struct Job<'a> {
    arch: &'a CnnArchitecture,
    settings: &'a TrainingSettings,
    training: &'a Dataset,
    selection: Selection<'a>,
    fresh_params: Option<&'a SimParams>,
    /// What the teacher gives `training`'s frames.
    teacher: Option<&'a Lesson>,
}

/// Trains one network from `seed` (its initialisation, validation split,
/// batch order and fresh frames) and keeps its best epoch: the whole of a
/// single network's training, one member of an ensemble's. `progress`
/// counts the steps of all members.
fn train_member(
    job: Job<'_>,
    seed: u64,
    member: Member<'_>,
    progress: &ProgressBar,
) -> anyhow::Result<(Net, TrainingRecord)> {
    let Job {
        arch,
        settings,
        training,
        selection,
        ..
    } = job;
    let emitters = truth_by_frame(&training.truth, training.frames.n)?;
    let split = split_frames(job, seed)?;
    let training_indices = split.training;
    let validation = selection
        .external
        .or(split.held_out.as_ref())
        .expect("frames are held out unless the job brings a validation set");
    let samples_per_epoch = check_trainable(job, &emitters, &training_indices, split.n_split_off)?;
    let fixed = fixed_source(job, emitters);
    let device = super::inference_device().autodiff();
    let init_seed = stream(seed, STREAM_INIT, 0).random::<u64>();
    let mut net = Net::new(arch, init_seed, &device);
    let mut optimiser = AdamConfig::new().init();
    let steps_per_epoch = samples_per_epoch.div_ceil(settings.batch_size);
    let total_steps = steps_per_epoch * settings.epochs;
    start_progress(progress, member, total_steps);
    let label = member.label();

    let mut epochs = Vec::with_capacity(settings.epochs);
    let mut best = BestEpoch::default();
    let mut step = 0usize;
    for epoch in 1..=settings.epochs {
        let fresh_dataset = fresh_frames(job, seed, epoch)?;
        let fresh = fresh_source(job, seed, epoch, &fresh_dataset, &label, progress)?;
        let mut items: Vec<(&Source, usize)> = training_indices
            .iter()
            .map(|&i| (&fixed, i))
            .chain((0..fresh_dataset.frames.n).map(|i| (&fresh, i)))
            .collect();
        shuffle(&mut items, &mut stream(seed, STREAM_SHUFFLE, epoch as u64));

        let epoch_learning_rate = learning_rate(settings, step, total_steps);
        let mut sums = LossSums::default();
        for (batch_index, batch) in items.chunks(settings.batch_size).enumerate() {
            let BatchLoss {
                total: loss,
                values,
                network_step,
            } = batch_loss(&net, arch, settings, batch, &device)?;
            let loss_value = values.total;
            if !loss_value.is_finite() {
                // The settings (usually the learning rate) are at fault: bad input.
                crate::bail_input!(
                    "training diverged: {label}non-finite loss ({loss_value}) at epoch {epoch}, batch {} of {steps_per_epoch}; lower training.learning_rate",
                    batch_index + 1
                );
            }
            sums.add(&values);
            let gradients = network_step.gradients(loss.backward(), &net);
            net = optimiser.step(learning_rate(settings, step, total_steps), net, gradients);
            step += 1;
            progress.inc(1);
        }
        let valid_net = net.valid();
        // Epochs before `validate_from_epoch` are neither scored nor kept.
        let candidate = epoch >= settings.validate_from_epoch;
        let scored = if candidate {
            validation
        } else {
            &Dataset::default()
        };
        let validation_auc =
            validate_epoch(job, &valid_net, scored, &label, epoch, steps_per_epoch)?;
        let record = sums.record(
            epoch,
            items.len(),
            epoch_learning_rate,
            steps_per_epoch as f64,
            validation_auc,
        );
        report_epoch(&record, settings, &label, progress);
        if candidate {
            best.offer(record.validation_mean_auc, epoch, valid_net);
        }
        epochs.push(record);
    }
    let (best_epoch, best_net) = best.take().expect("at least one epoch ran");
    let record = TrainingRecord {
        seed,
        training_frames: training_indices.len(),
        validation_frames: validation.frames.n,
        epochs,
        best_epoch,
    };
    Ok((best_net, record))
}

/// The training set as a source: its truth per frame (`truth`) and what
/// the teacher gives it.
fn fixed_source(job: Job<'_>, truth: Vec<Vec<(f64, f64)>>) -> Source<'_> {
    taught_source(&job.training.frames, truth, job.teacher.cloned())
}

/// Frames as a source: their truth per frame (`truth`), or what the teacher
/// gives them with the truth beside it.
fn taught_source(
    frames: &FrameStack,
    truth: Vec<Vec<(f64, f64)>>,
    lesson: Option<Lesson>,
) -> Source<'_> {
    let (emitters, true_centroids, posterior) = match lesson {
        None => (truth, None, None),
        Some(Lesson::Means(means)) => (means, Some(truth), None),
        Some(Lesson::Pixels(pixels)) => (truth, None, Some(pixels)),
    };
    Source {
        frames,
        emitters,
        true_centroids,
        posterior,
    }
}

/// A member's frames: the indices of `training` it trains on, and the
/// frames split off to select its epoch on (none when the job brings a
/// validation set of its own).
struct SplitFrames {
    training: Vec<usize>,
    held_out: Option<Dataset>,
    n_split_off: usize,
}

/// The seeded split of the training frames into training and validation
/// frames (none held out when the validation frames are given).
fn split_frames(job: Job<'_>, seed: u64) -> anyhow::Result<SplitFrames> {
    let (settings, training, selection) = (job.settings, job.training, job.selection);
    let n = training.frames.n;
    let mut order: Vec<usize> = (0..n).collect();
    shuffle(&mut order, &mut stream(seed, STREAM_SPLIT, 0));
    let n_split_off = match selection.external {
        // The recipe in which the training set never trains keeps to it
        // when another set selects (a cross-validation's held-out fold).
        Some(_) if settings.trains_on_fresh_frames_only() => n,
        Some(_) => 0,
        None => settings.held_out_frames(n),
    };
    let held_out = match selection.external {
        Some(_) => None,
        None => {
            let mut validation_indices = order[..n_split_off].to_vec();
            validation_indices.sort_unstable();
            Some(subset(training, &validation_indices)?)
        }
    };
    Ok(SplitFrames {
        training: order[n_split_off..].to_vec(),
        held_out,
        n_split_off,
    })
}

/// The samples of one epoch, refusing a training without any and fresh
/// frames of another size than the dataset's (both go in one batch), and
/// what the head cannot learn from (`emitters`: the centroids of each of
/// the dataset's frames).
fn check_trainable(
    job: Job<'_>,
    emitters: &[Vec<(f64, f64)>],
    training_indices: &[usize],
    n_split_off: usize,
) -> anyhow::Result<usize> {
    let (settings, training) = (job.settings, job.training);
    let n = training.frames.n;
    let samples_per_epoch = training_indices.len() + settings.fresh_frames_per_epoch;
    if samples_per_epoch == 0 {
        crate::bail_input!(
            "training: no frames to train on ({n} given, {n_split_off} held out for validation, no fresh frames)"
        );
    }
    if let Some(params) = job.fresh_params
        && !training_indices.is_empty()
        && (params.height, params.width) != (training.frames.height, training.frames.width)
    {
        crate::bail_input!(
            "training: fresh frames are {}×{} but the dataset's are {}×{}; both are trained on in the same batches",
            params.height,
            params.width,
            training.frames.height,
            training.frames.width
        );
    }
    if job.arch.head == CnnHead::Categorical {
        check_categorical(job, emitters, training_indices)?;
    }
    Ok(samples_per_epoch)
}

/// The categorical head's condition on its frames: one QD in every
/// training frame, fixed or fresh (its softmax is one distribution of one
/// centroid). Its condition on the settings is checked with the recipe
/// ([`super::validate_recipe`]).
fn check_categorical(
    job: Job<'_>,
    emitters: &[Vec<(f64, f64)>],
    training_indices: &[usize],
) -> anyhow::Result<()> {
    if let Some(params) = job.fresh_params
        && job.settings.fresh_frames_per_epoch > 0
        && params.emitters != EmitterCount::Fixed(1)
    {
        crate::bail_input!(
            "emitters: the categorical head trains on frames of exactly one QD; the fresh frames' count is {:?}",
            params.emitters
        );
    }
    if let Some(&i) = training_indices.iter().find(|&&i| emitters[i].len() != 1) {
        crate::bail_input!(
            "training frames: the categorical head trains on frames of exactly one QD; frame {i} holds {}",
            emitters[i].len()
        );
    }
    Ok(())
}

/// Sets the bar over every member's steps (each member has as many) and
/// names the member now training.
fn start_progress(progress: &ProgressBar, member: Member<'_>, total_steps: usize) {
    progress.set_length((total_steps * member.count) as u64);
    if member.index == 0 {
        progress.set_position(0);
    }
    // Say who is training now: from member 2 on, the bar still shows the
    // previous member's last epoch until this member's first one ends.
    if let Some(name) = member.name() {
        progress.set_message(name);
    }
}

/// Epoch `epoch`'s fresh frames (none without fresh parameters).
fn fresh_frames(job: Job<'_>, seed: u64, epoch: usize) -> anyhow::Result<Dataset> {
    Ok(match job.fresh_params {
        Some(params) => {
            let fresh_seed = stream(seed, STREAM_FRESH, epoch as u64).random::<u64>();
            sim::simulate(
                params,
                fresh_seed,
                0..job.settings.fresh_frames_per_epoch,
                &ProgressBar::hidden(),
            )?
        }
        None => Dataset::default(),
    })
}

/// Epoch `epoch`'s fresh frames as a source: their truth, or the
/// teacher's posterior targets when the settings say so.
fn fresh_source<'a>(
    job: Job<'_>,
    seed: u64,
    epoch: usize,
    fresh_dataset: &'a Dataset,
    label: &str,
    progress: &ProgressBar,
) -> anyhow::Result<Source<'a>> {
    let settings = job.settings;
    let fresh_truth = truth_by_frame(&fresh_dataset.truth, fresh_dataset.frames.n)?;
    let lesson = match job.fresh_params {
        Some(microscope) if settings.teacher_fresh_frames => {
            let teacher = Teacher {
                head: job.arch.head,
                microscope,
                particles: settings.teacher_particles,
                filter_seed: stream(seed, STREAM_TEACHER, epoch as u64).random::<u64>(),
            };
            Some(teacher.teach(
                &fresh_dataset.frames,
                &fresh_truth,
                &format!("{label}posterior targets of epoch {epoch}'s fresh frames"),
                progress,
            )?)
        }
        _ => None,
    };
    Ok(taught_source(&fresh_dataset.frames, fresh_truth, lesson))
}

/// The validation AUCs of the network after epoch `epoch` on `scored`; an
/// output that is not finite means the last step diverged (bad input: the
/// settings).
fn validate_epoch(
    job: Job<'_>,
    net: &Net,
    scored: &Dataset,
    label: &str,
    epoch: usize,
    steps_per_epoch: usize,
) -> anyhow::Result<Vec<f64>> {
    validate(net, job.arch, job.settings, scored, job.selection.score).map_err(|error| {
        if error.is::<NonFiniteOutput>() {
            // The last step blew the weights up; the loss that
            // step saw was still finite.
            crate::error::input_error(format!(
                "training diverged: {label}the network's output is not finite after epoch {epoch}, batch {steps_per_epoch} of {steps_per_epoch} ({error}); lower training.learning_rate"
            ))
        } else {
            error
        }
    })
}

/// An epoch's losses summed over its batches, in batch order.
#[derive(Default)]
struct LossSums {
    loss: f64,
    score: f64,
    offset: f64,
    sigma: f64,
    within: f64,
}

impl LossSums {
    fn add(&mut self, values: &LossValues) {
        self.loss += values.total;
        self.score += values.score;
        self.offset += values.offset;
        self.sigma += values.sigma;
        self.within += values.within;
    }

    /// The epoch's record: the mean losses over `batches` and the
    /// validation AUCs.
    fn record(
        &self,
        epoch: usize,
        samples: usize,
        learning_rate: f64,
        batches: f64,
        validation_auc: Vec<f64>,
    ) -> EpochRecord {
        let validation_mean_auc = (!validation_auc.is_empty())
            .then(|| validation_auc.iter().sum::<f64>() / validation_auc.len() as f64);
        EpochRecord {
            epoch,
            samples,
            learning_rate,
            loss: self.loss / batches,
            score_loss: self.score / batches,
            offset_loss: self.offset / batches,
            sigma_loss: self.sigma / batches,
            within_loss: self.within / batches,
            validation_auc,
            validation_mean_auc,
        }
    }
}

/// Logs an epoch's losses and validation AUCs and shows them on the bar.
fn report_epoch(
    record: &EpochRecord,
    settings: &TrainingSettings,
    label: &str,
    progress: &ProgressBar,
) {
    let message = format!(
        "{label}epoch {}/{}: loss {:.4} (score {:.4}, offset {:.4}, sigma {:.4}, within {:.4}){}",
        record.epoch,
        settings.epochs,
        record.loss,
        record.score_loss,
        record.offset_loss,
        record.sigma_loss,
        record.within_loss,
        match record.validation_mean_auc {
            Some(mean) => format!(
                ", validation AUC {} (mean {mean:.4})",
                record
                    .validation_auc
                    .iter()
                    .map(|a| format!("{a:.3}"))
                    .collect::<Vec<_>>()
                    .join("/")
            ),
            None => String::new(),
        }
    );
    tracing::info!("{message}");
    progress.set_message(format!(
        "{label}loss {:.3}{}",
        record.loss,
        record
            .validation_mean_auc
            .map(|m| format!(" AUC {m:.3}"))
            .unwrap_or_default()
    ));
    progress.println(&message);
}

/// The epoch kept so far: the best mean validation AUC, the last epoch on
/// a tie at +∞ (no validation frames).
#[derive(Default)]
struct BestEpoch {
    best: Option<(f64, usize, Net)>,
}

impl BestEpoch {
    /// Offers the network after epoch `epoch`, of mean validation AUC
    /// `mean_auc` (`None`: not validated).
    fn offer(&mut self, mean_auc: Option<f64>, epoch: usize, net: Net) {
        let criterion = mean_auc.unwrap_or(f64::INFINITY);
        // Without validation every epoch ties at +∞ and the last one wins.
        let better = match &self.best {
            None => true,
            Some((best_criterion, _, _)) => criterion > *best_criterion || mean_auc.is_none(),
        };
        if better {
            self.best = Some((criterion, epoch, net));
        }
    }

    /// The kept epoch and its network.
    fn take(self) -> Option<(usize, Net)> {
        self.best.map(|(_, epoch, net)| (epoch, net))
    }
}

/// The learning rate of optimiser step `step` of `total`.
fn learning_rate(settings: &TrainingSettings, step: usize, total: usize) -> f64 {
    if settings.cosine_decay && total > 0 {
        let progress = step as f64 / total as f64;
        settings.learning_rate * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos())
    } else {
        settings.learning_rate
    }
}

#[cfg(test)]
mod tests {
    use super::super::ensemble::member_seed;
    use super::super::loss::cross_entropy_and_gradient;
    use super::super::teacher::{Lesson, Teacher, pixel_posterior};
    use super::{CnnHead, FrameStack, SimParams, sim, truth_by_frame};

    #[test]
    fn the_categorical_gradient_is_the_cross_entropys() {
        // Two 3×4 frames of arbitrary logits: the returned gradient against
        // central finite differences of the returned value (f32 logits, so
        // a step of 1e-2 and a tolerance of 1e-4).
        let logits: Vec<f32> = (0..24).map(|i| ((i * 7 % 11) as f32 - 5.0) * 0.4).collect();
        // The first frame's target one pixel (a true centroid), the
        // second's a posterior over three.
        let targets: [&[(u32, f32)]; 2] = [&[(5, 1.0)], &[(10, 0.5), (2, 0.3), (11, 0.2)]];
        let (value, gradient) = cross_entropy_and_gradient(&logits, &targets);
        let by_hand: f64 = targets
            .iter()
            .enumerate()
            .map(|(b, target)| {
                let frame = &logits[b * 12..(b + 1) * 12];
                let total: f64 = frame.iter().map(|&l| (l as f64).exp()).sum();
                target
                    .iter()
                    .map(|&(p, q)| q as f64 * (total.ln() - frame[p as usize] as f64))
                    .sum::<f64>()
            })
            .sum::<f64>()
            / 2.0;
        assert!((value - by_hand).abs() < 1e-9, "{value} vs {by_hand}");
        for i in 0..logits.len() {
            let step = 1e-2f32;
            let mut up = logits.clone();
            up[i] += step;
            let mut down = logits.clone();
            down[i] -= step;
            let numeric = (cross_entropy_and_gradient(&up, &targets).0
                - cross_entropy_and_gradient(&down, &targets).0)
                / (2.0 * step as f64);
            assert!(
                (numeric - gradient[i] as f64).abs() < 1e-4,
                "logit {i}: {numeric} vs {}",
                gradient[i]
            );
        }
        // Each frame's gradient sums to 0 (softmax sums to 1).
        for b in 0..2 {
            let sum: f64 = gradient[b * 12..(b + 1) * 12]
                .iter()
                .map(|&g| g as f64)
                .sum();
            assert!(sum.abs() < 1e-6, "{sum}");
        }
    }

    #[test]
    fn a_posterior_cloud_becomes_the_mass_of_the_pixel_nearest_each_point() {
        // A 3 × 4 frame (pixel centres at integers): two points in pixel
        // (row 1, column 2), one in (0, 0), one beyond the right edge that
        // the border pixel (2, 3) takes, as a centroid's target is clamped.
        let cloud = [
            (2.2, 0.9, 0.3),
            (1.6, 1.4, 0.2),
            (-0.3, 0.1, 0.1),
            (5.0, 2.2, 0.4),
        ];
        let posterior = pixel_posterior(&cloud, 3, 4);
        assert_eq!(posterior, vec![(0, 0.1), (6, 0.5), (11, 0.4)]);
    }

    #[test]
    fn the_categorical_heads_teacher_gives_each_one_qd_frame_its_posterior_over_the_pixels() {
        // Bright QDs diffusing at D = 1 in 14 × 14 frames: the posterior of
        // the centroid spreads over a few pixels around the truth. The
        // frame of two QDs gets no lesson (it keeps its truth).
        let microscope = SimParams {
            height: 14,
            width: 14,
            margin_px: 3.0,
            brightness: 40.0.into(),
            diffusion_um2_s: 1.0.into(),
            ..SimParams::default()
        };
        let hidden = crate::progress::hidden();
        let single = sim::simulate(&microscope, 3, 0..5, &hidden).unwrap();
        let mut truth = truth_by_frame(&single.truth, 5).unwrap();
        truth.push(vec![(4.0, 4.0), (9.0, 9.0)]);
        let mut data = single.frames.data.clone();
        data.extend_from_slice(single.frames.frame(0));
        let frames = FrameStack::from_vec(6, 14, 14, data).unwrap();
        let teach = |filter_seed| {
            let teacher = Teacher {
                head: CnnHead::Categorical,
                microscope: &microscope,
                particles: 2000,
                filter_seed,
            };
            match teacher.teach(&frames, &truth, "", &hidden).unwrap() {
                Lesson::Pixels(pixels) => pixels,
                Lesson::Means(_) => panic!("the categorical head is taught means"),
            }
        };
        let lesson = teach(1);
        assert_eq!(lesson.len(), 6);
        assert!(lesson[5].is_empty(), "{:?}", lesson[5]);
        for (frame, posterior) in lesson[..5].iter().enumerate() {
            let total: f64 = posterior.iter().map(|&(_, q)| f64::from(q)).sum();
            assert!((total - 1.0).abs() < 1e-5, "frame {frame}: {total}");
            assert!(posterior.windows(2).all(|pair| pair[0].0 < pair[1].0));
            let [(x, y)] = truth[frame][..] else {
                unreachable!()
            };
            let near: f64 = posterior
                .iter()
                .filter(|&&(p, _)| {
                    let (px, py) = ((p % 14) as f64, (p / 14) as f64);
                    (px - x).hypot(py - y) <= 2.5
                })
                .map(|&(_, q)| f64::from(q))
                .sum();
            assert!(near > 0.9, "frame {frame}: {near:.3} within 2.5 px");
            assert!(posterior.len() >= 2, "frame {frame}: {posterior:?}");
        }
        assert_eq!(teach(1), lesson);
        assert_ne!(teach(2), lesson);
    }

    #[test]
    fn the_first_member_keeps_the_seed_and_the_others_get_their_own() {
        assert_eq!(member_seed(7, 0), 7);
        let seeds: Vec<u64> = (0..4).map(|index| member_seed(7, index)).collect();
        for (i, a) in seeds.iter().enumerate() {
            for b in &seeds[i + 1..] {
                assert_ne!(a, b, "{seeds:?}");
            }
        }
        assert_ne!(member_seed(7, 1), member_seed(8, 1));
        assert_eq!(member_seed(7, 2), member_seed(7, 2));
    }
}
