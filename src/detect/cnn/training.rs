//! The training loop: Adam on a CenterNet-style focal loss (score map) plus
//! an L1 loss on the sub-pixel offsets, a Gaussian negative log-likelihood
//! for the σ maps and a cross-entropy for the within-1-px head (both
//! against the realised error of the offsets, which they do not move), with
//! seeded shuffling, optional freshly simulated frames every epoch,
//! optional posterior-mean targets from the likelihood detector (a
//! teacher), and selection of the epoch with the best validation AUC.

use anyhow::Context;
use burn::optim::AdamConfig;
use burn::prelude::*;
use burn::tensor::activation::{log_sigmoid, sigmoid};
use indicatif::ProgressBar;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::data::{TargetShape, normalised_input, targets, truth_by_frame};
use super::inference::{
    NonFiniteOutput, frame_log_normaliser, inference_batch, locate_with, nearest_pixel, softmax,
};
use super::kernels::fixed_order_sum;
use super::model::{
    LOG_SIGMA_RANGE, LOG_SIGMA_X_CHANNEL, Net, NetworkStep, OFFSET_X_CHANNEL, SCORE_CHANNEL,
    WITHIN_1PX_CHANNEL,
};
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

/// Purposes of the random streams derived from the training seed.
const STREAM_INIT: u64 = 1;
const STREAM_SPLIT: u64 = 2;
const STREAM_SHUFFLE: u64 = 3;
const STREAM_FRESH: u64 = 4;
/// The seeds of an ensemble's members 2, 3, … (index = 0-based member).
const STREAM_MEMBER: u64 = 5;
const STREAM_TEACHER: u64 = 6;

/// A ChaCha8 stream for `purpose` (and `index`, e.g. the epoch) of `seed`.
fn stream(seed: u64, purpose: u64, index: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(purpose);
    rng.set_word_pos(u128::from(index) << 32);
    rng
}

/// Fisher–Yates shuffle driven by `rng` (explicit, so the order is fixed by
/// this code and not by a library's implementation).
fn shuffle<T>(items: &mut [T], rng: &mut ChaCha8Rng) {
    for i in (1..items.len()).rev() {
        let j = rng.random_range(0..=i);
        items.swap(i, j);
    }
}

/// Frames and their emitters, the unit batches are drawn from.
struct Source<'a> {
    frames: &'a FrameStack,
    /// Per frame, the positions the score map and the offsets learn: the
    /// true centroids, or the teacher's posterior means.
    emitters: Vec<Vec<(f64, f64)>>,
    /// Per frame, the true centroids when `emitters` are the teacher's
    /// (the within-1-px head learns whether a localisation lands within
    /// 1 px of the truth, not of the teacher); `None`: `emitters` are the
    /// truth.
    true_centroids: Option<Vec<Vec<(f64, f64)>>>,
    /// Per frame, the teacher's posterior of the centroid as the
    /// categorical head's softmax learns it: the probability that the
    /// centroid is nearest each pixel (row-major index), the pixels with
    /// none left out; empty for a frame the teacher did not label (its
    /// one true centroid's pixel is the target). `None`: no teacher, or
    /// the peaks head (whose teacher moves `emitters`).
    posterior: Option<Vec<PixelPosterior>>,
}

/// A frame's posterior over its pixels: `(row-major pixel, probability)`,
/// the probabilities summing to 1.
type PixelPosterior = Vec<(u32, f32)>;

impl Source<'_> {
    /// The true centroids of frame `i`, which the within-1-px head learns
    /// against.
    fn truth(&self, i: usize) -> &[(f64, f64)] {
        self.true_centroids.as_ref().unwrap_or(&self.emitters)[i].as_slice()
    }
}

/// Frames `indices` of `dataset` as a new dataset, frames renumbered 0…
fn subset(dataset: &Dataset, indices: &[usize]) -> anyhow::Result<Dataset> {
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

/// The loss of one batch: the total to take the gradient of, its value
/// and its parts' (each part before its weight), and the network's step
/// that completes the backward pass.
struct BatchLoss {
    total: Tensor<1>,
    values: LossValues,
    network_step: NetworkStep,
}

/// A batch's loss values, each summed over its pixels in a fixed order
/// ([`fixed_order_sum`]): the backend's own reductions sum in an order that
/// depends on the CPU's vector width, and these values are recorded with
/// the model.
#[derive(Debug, Clone, Copy)]
struct LossValues {
    total: f64,
    score: f64,
    offset: f64,
    sigma: f64,
    within: f64,
}

/// The fixed-order sum of a loss map's elements.
fn map_sum(map: &Tensor<4>) -> anyhow::Result<f64> {
    let values = map
        .clone()
        .into_data()
        .try_to_vec::<f32>()
        .map_err(|e| anyhow::anyhow!("reading a loss map: {e:?}"))?;
    Ok(fixed_order_sum(&values))
}

/// Largest distance (pixels) between a localisation and a centroid for the
/// within-1-px head's target to be 1.
const WITHIN_RADIUS_PX: f64 = 1.0;

/// The within-1-px target of every pixel of a batch, row-major `[n, 1, H,
/// W]`: 1 where the pixel's localisation (pixel centre + its predicted
/// offset, `offsets` row-major `[n, 2, H, W]`) lies within
/// [`WITHIN_RADIUS_PX`] of any of its frame's `emitters`, else 0.
fn within_targets(
    offsets: &[f32],
    emitters: &[&[(f64, f64)]],
    height: usize,
    width: usize,
) -> Vec<f32> {
    let len = height * width;
    let mut out = vec![0.0f32; emitters.len() * len];
    for (b, frame_emitters) in emitters.iter().enumerate() {
        let (dx, dy) = offsets[2 * b * len..2 * (b + 1) * len].split_at(len);
        for (p, target) in out[b * len..(b + 1) * len].iter_mut().enumerate() {
            let x = (p % width) as f64 + dx[p] as f64;
            let y = (p / width) as f64 + dy[p] as f64;
            let hit = frame_emitters.iter().any(|&(ex, ey)| {
                (x - ex).powi(2) + (y - ey).powi(2) <= WITHIN_RADIUS_PX * WITHIN_RADIUS_PX
            });
            *target = if hit { 1.0 } else { 0.0 };
        }
    }
    out
}

/// The loss of one batch.
fn batch_loss(
    net: &Net,
    arch: &CnnArchitecture,
    settings: &TrainingSettings,
    items: &[(&Source, usize)],
    device: &Device,
) -> anyhow::Result<BatchLoss> {
    let frames0 = items[0].0.frames;
    let (height, width) = (frames0.height, frames0.width);
    let len = height * width;
    let n = items.len();
    let input = normalised_input(
        items.iter().map(|(source, i)| source.frames.frame(*i)),
        len,
        arch.edge_channel,
    );
    let emitters: Vec<&[(f64, f64)]> = items
        .iter()
        .map(|(source, i)| source.emitters[*i].as_slice())
        .collect();
    let posteriors: Vec<&[(u32, f32)]> = items
        .iter()
        .map(|(source, i)| {
            source
                .posterior
                .as_ref()
                .map_or(&[][..], |posterior| posterior[*i].as_slice())
        })
        .collect();
    let target = targets(
        height,
        width,
        &emitters,
        TargetShape {
            sigma_px: settings.heatmap_sigma_px,
            offset_radius_px: settings.offset_radius_px,
        },
    );
    let positives = target.positive.iter().filter(|&&p| p > 0.0).count();
    let masked = target.offset_mask.iter().filter(|&&m| m > 0.0).count();
    let map = |values: Vec<f32>, channels: usize| {
        Tensor::<4>::from_data(
            TensorData::new(values, [n, channels, height, width]),
            device,
        )
    };
    let positive = map(target.positive, 1);
    let centre = positive.clone();
    let negative_weight = map(target.negative_weight, 1);
    let offset_target = map(target.offset, 2);
    let offset_mask = map(target.offset_mask, 1);

    let (output, network_step) = net.forward_training(&input, [n, height, width], device);
    let logit = output.clone().narrow(1, SCORE_CHANNEL, 1);
    let score_count = positives.max(1) as f64;
    let (score_loss, score_value) = match arch.head {
        CnnHead::Peaks => focal_loss(logit, positive, negative_weight, score_count)?,
        CnnHead::Categorical => {
            categorical_loss(logit, &emitters, &posteriors, [n, height, width], device)?
        }
    };
    let offset = output.clone().narrow(1, OFFSET_X_CHANNEL, 2);
    let log_sigma = output.clone().narrow(1, LOG_SIGMA_X_CHANNEL, 2);
    let within_logit = output.narrow(1, WITHIN_1PX_CHANNEL, 1);
    // The uncertainty heads learn the error the offsets make, not the
    // other way round: through detached offsets, the offsets keep the L1
    // loss's gradient alone.
    let realised_offset = offset.clone().detach();
    // L1 offset loss per supervised pixel (|dx| + |dy|).
    let offset_map = (offset - offset_target.clone()).abs() * offset_mask;
    let offset_count = masked.max(1) as f64;
    let offset_loss = offset_map.clone().sum().div_scalar(offset_count);
    // Gaussian NLL of the offsets' error at each target centre's pixel, per
    // axis: ln σ + e² / 2σ² (DECODE's σ maps). Only there: over the whole
    // offset window the error mostly says how far a pixel is from the
    // centre, which is not what the σ of a peak should tell.
    let log_sigma = log_sigma.clamp(LOG_SIGMA_RANGE.0, LOG_SIGMA_RANGE.1);
    let squared_error = (realised_offset.clone() - offset_target).powi_scalar(2);
    let inverse_variance = log_sigma.clone().mul_scalar(-2.0).exp();
    let sigma_map = (log_sigma + squared_error * inverse_variance.mul_scalar(0.5)) * centre;
    let sigma_count = (2 * positives).max(1) as f64;
    let sigma_loss = sigma_map.clone().sum().div_scalar(sigma_count);
    // Cross-entropy of the within-1-px head against whether each pixel's
    // localisation did land within 1 px of a centroid, per target centre
    // (as the focal loss).
    let realised = realised_offset
        .into_data()
        .try_to_vec::<f32>()
        .map_err(|e| anyhow::anyhow!("reading the offsets: {e:?}"))?;
    let true_centroids: Vec<&[(f64, f64)]> =
        items.iter().map(|(source, i)| source.truth(*i)).collect();
    let within = map(within_targets(&realised, &true_centroids, height, width), 1);
    let within_map = log_sigmoid(within_logit.clone()) * within.clone()
        + log_sigmoid(within_logit.neg()) * within.neg().add_scalar(1.0);
    let within_loss = within_map.clone().sum().neg().div_scalar(score_count);
    let total = score_loss
        + offset_loss.mul_scalar(settings.offset_loss_weight)
        + sigma_loss.mul_scalar(settings.sigma_loss_weight)
        + within_loss.mul_scalar(settings.within_loss_weight);
    let mut values = LossValues {
        total: 0.0,
        score: score_value,
        offset: map_sum(&offset_map)? / offset_count,
        sigma: map_sum(&sigma_map)? / sigma_count,
        within: -map_sum(&within_map)? / score_count,
    };
    values.total = values.score
        + values.offset * settings.offset_loss_weight
        + values.sigma * settings.sigma_loss_weight
        + values.within * settings.within_loss_weight;
    Ok(BatchLoss {
        total,
        values,
        network_step,
    })
}

/// The focal loss of the peaks head (CenterNet, α = 2, β = 4), from
/// log-sigmoids for stability, per positive pixel: the tensor to
/// differentiate and its value summed in a fixed order.
fn focal_loss(
    logit: Tensor<4>,
    positive: Tensor<4>,
    negative_weight: Tensor<4>,
    positives: f64,
) -> anyhow::Result<(Tensor<1>, f64)> {
    let probability = sigmoid(logit.clone());
    let log_p = log_sigmoid(logit.clone());
    let log_not_p = log_sigmoid(logit.neg());
    let positive_term = probability.clone().neg().add_scalar(1.0).powi_scalar(2) * log_p * positive;
    let negative_term = probability.powi_scalar(2) * log_not_p * negative_weight;
    let score_map = positive_term + negative_term;
    let value = -map_sum(&score_map)? / positives;
    Ok((score_map.sum().neg().div_scalar(positives), value))
}

/// The categorical head's loss: per frame, the cross-entropy of the
/// softmax over its pixels against the pixel nearest its one centroid
/// (`emitters`, clamped into the frame), or against the teacher's
/// posterior over the pixels where `posteriors` has one for the frame,
/// averaged over the frames.
///
/// The softmax is computed here in f64 with sums in raster order, not by
/// the backend (whose reductions sum in an order that depends on the CPU's
/// vector width): the tensor returned is `Σ logit · (softmax − onehot) / n`
/// with the bracket detached, whose gradient with respect to the logits is
/// exactly the cross-entropy's, so training stays bit-identical on every
/// CPU. The value returned is the cross-entropy itself.
fn categorical_loss(
    logit: Tensor<4>,
    emitters: &[&[(f64, f64)]],
    posteriors: &[&[(u32, f32)]],
    [n, height, width]: [usize; 3],
    device: &Device,
) -> anyhow::Result<(Tensor<1>, f64)> {
    let logits = logit
        .clone()
        .into_data()
        .try_to_vec::<f32>()
        .map_err(|e| anyhow::anyhow!("reading the score logits: {e:?}"))?;
    let mut centroid_pixels = Vec::with_capacity(n);
    for frame_emitters in emitters {
        let &[(x, y)] = *frame_emitters else {
            crate::bail_input!(
                "training frames: the categorical head trains on frames of exactly one QD; a batch frame holds {}",
                frame_emitters.len()
            );
        };
        centroid_pixels.push([(nearest_pixel(x, y, height, width) as u32, 1.0)]);
    }
    let targets: Vec<&[(u32, f32)]> = posteriors
        .iter()
        .zip(&centroid_pixels)
        .map(|(&posterior, centroid)| {
            if posterior.is_empty() {
                &centroid[..]
            } else {
                posterior
            }
        })
        .collect();
    let (value, gradient) = cross_entropy_and_gradient(&logits, &targets);
    let gradient = Tensor::<4>::from_data(TensorData::new(gradient, [n, 1, height, width]), device);
    Ok(((logit * gradient).sum(), value))
}

/// The mean over frames of the cross-entropy of each frame's softmax
/// (`logits` row-major, one frame after another, `targets.len()` frames)
/// against its target distribution over the pixels (`(pixel, probability)`
/// pairs summing to 1: one pixel of probability 1 for a true centroid),
/// and its gradient with respect to the logits, `(softmax − target) /
/// frames`; in f64, summed in raster order (a target's terms in its
/// order).
fn cross_entropy_and_gradient(logits: &[f32], targets: &[&[(u32, f32)]]) -> (f64, Vec<f32>) {
    let frames = targets.len();
    let len = logits.len() / frames.max(1);
    let mut gradient = vec![0.0f32; logits.len()];
    let mut total = 0.0;
    let mut target_map = vec![0.0f64; len];
    for (b, target) in targets.iter().enumerate() {
        let frame = &logits[b * len..(b + 1) * len];
        let log_normaliser = frame_log_normaliser(frame);
        for &(p, q) in *target {
            target_map[p as usize] += f64::from(q);
            total += f64::from(q) * (log_normaliser - frame[p as usize] as f64);
        }
        for ((g, q), t) in gradient[b * len..(b + 1) * len]
            .iter_mut()
            .zip(softmax(frame))
            .zip(&mut target_map)
        {
            *g = ((q - std::mem::take(t)) / frames as f64) as f32;
        }
    }
    (total / frames.max(1) as f64, gradient)
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

/// What the score map and the offsets of `training`'s frames learn with a
/// teacher (`settings.teacher_particles` > 0): for every frame that holds
/// exactly one QD, the likelihood detector's posterior mean of its
/// trajectory centroid given the frame (`particles` particles, under
/// `microscope`, the simulator parameters the frames were made with, its
/// distributions of D, brightness and background as the priors), in place
/// of the true centroid; frames with none or several QDs keep their truth
/// (and cost the teacher nothing).
///
/// The true centroid is one draw from the posterior around that mean, so
/// the mean is the same target without the draw's noise (at D = 1.75 the
/// draw scatters by ≈ 1.4 px): the network learns what the frame tells
/// from fewer frames. Frame `i` draws from ChaCha8 stream `i` of a seed of
/// its own derived from the training seed, so the targets, like the rest
/// of the training, are fixed by the seed. `progress` counts the frames
/// while they are computed, then is handed back as it was.
pub fn teacher_targets(
    training: &Dataset,
    microscope: &SimParams,
    particles: usize,
    seed: u64,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<Vec<(f64, f64)>>> {
    match fixed_lesson(
        CnnHead::Peaks,
        training,
        microscope,
        particles,
        seed,
        progress,
    )? {
        Lesson::Means(means) => Ok(means),
        Lesson::Pixels(_) => unreachable!("the peaks head's teacher gives means"),
    }
}

/// What the teacher of `head` gives the fixed frames of `training` (see
/// [`teacher_targets`]), under a progress message "posterior targets"
/// after the training's name.
fn fixed_lesson(
    head: CnnHead,
    training: &Dataset,
    microscope: &SimParams,
    particles: usize,
    seed: u64,
    progress: &ProgressBar,
) -> anyhow::Result<Lesson> {
    let truth = truth_by_frame(&training.truth, training.frames.n)?;
    let teacher = Teacher {
        head,
        microscope,
        particles,
        filter_seed: stream(seed, STREAM_TEACHER, 0).random::<u64>(),
    };
    let task = progress.message();
    let message = if task.is_empty() {
        "posterior targets".to_string()
    } else {
        format!("{task}: posterior targets")
    };
    teacher.teach(&training.frames, &truth, &message, progress)
}

/// The likelihood detector as a teacher of one head: how many particles,
/// under which simulator parameters (the frames' own, their distributions
/// the priors), from which seed.
struct Teacher<'a> {
    head: CnnHead,
    microscope: &'a SimParams,
    particles: usize,
    filter_seed: u64,
}

/// What a teacher gives a stack's frames (those with one QD; the others
/// keep their truth).
#[derive(Clone)]
enum Lesson {
    /// For the peaks head: per frame, the posterior mean of the centroid
    /// (the truth for frames with none or several QDs), which the score
    /// map and the offsets learn in place of the truth.
    Means(Vec<Vec<(f64, f64)>>),
    /// For the categorical head: per frame, the posterior of the centroid
    /// over the pixels (empty for frames with none or several QDs), which
    /// the softmax learns in place of the true centroid's pixel; the
    /// offsets and σ maps still learn the truth.
    Pixels(Vec<PixelPosterior>),
}

impl Teacher<'_> {
    /// The lesson for `frames` (whose true centroids are `truth`): the
    /// filter runs on the frames with one QD, frame `i` from ChaCha8
    /// stream `i` of the teacher's seed. The progress bar counts those
    /// frames under `message`, then shows what it showed.
    fn teach(
        &self,
        frames: &FrameStack,
        truth: &[Vec<(f64, f64)>],
        message: &str,
        progress: &ProgressBar,
    ) -> anyhow::Result<Lesson> {
        let settings = crate::detect::likelihood::LikelihoodParams {
            particles: self.particles,
            ..Default::default()
        };
        let taught: Vec<usize> = (0..truth.len()).filter(|&i| truth[i].len() == 1).collect();
        let (length, position, shown) =
            (progress.length(), progress.position(), progress.message());
        progress.set_length(taught.len() as u64);
        progress.set_position(0);
        progress.set_message(message.to_string());
        let lesson = match self.head {
            CnnHead::Peaks => crate::detect::likelihood::locate_frames(
                frames,
                &taught,
                self.microscope,
                &settings,
                self.filter_seed,
                progress,
            )
            .map(|means| {
                let mut targets = truth.to_vec();
                for (&index, mean) in taught.iter().zip(means) {
                    targets[index] = vec![(mean.x, mean.y)];
                }
                Lesson::Means(targets)
            }),
            CnnHead::Categorical => crate::detect::likelihood::posterior_clouds(
                frames,
                &taught,
                self.microscope,
                &settings,
                self.filter_seed,
                progress,
            )
            .map(|clouds| {
                let mut targets = vec![PixelPosterior::new(); truth.len()];
                for (&index, cloud) in taught.iter().zip(clouds) {
                    targets[index] = pixel_posterior(&cloud, frames.height, frames.width);
                }
                Lesson::Pixels(targets)
            }),
        }
        .context("training.teacher_particles: the teacher's posterior targets");
        if let Some(length) = length {
            progress.set_length(length);
        }
        progress.set_position(position);
        progress.set_message(shown);
        lesson
    }
}

/// A posterior of the centroid given as weighted points `(x, y, weight)`
/// (weights summing to 1) as the probability that the centroid is nearest
/// each pixel of a `height × width` frame (points outside clamped to the
/// border, as the categorical head's target is), in raster order.
fn pixel_posterior(cloud: &[(f64, f64, f64)], height: usize, width: usize) -> PixelPosterior {
    let mut mass = vec![0.0f64; height * width];
    for &(x, y, weight) in cloud {
        mass[nearest_pixel(x, y, height, width)] += weight;
    }
    (0..)
        .zip(mass)
        .filter(|&(_, m)| m > 0.0)
        .map(|(pixel, m)| (pixel, m as f32))
        .collect()
}

/// The seed ensemble member `index` (0-based) trains from: the training
/// seed itself for member 0, so a single network trains exactly as it
/// would without ensembles; a seed drawn from a stream of its own for the
/// others.
fn member_seed(seed: u64, index: usize) -> u64 {
    if index == 0 {
        seed
    } else {
        stream(seed, STREAM_MEMBER, index as u64).random::<u64>()
    }
}

/// Which member of how many a training run is (0-based `index`), in the
/// training the caller calls `task` (the progress bar's message when the
/// training began; may be empty).
#[derive(Clone, Copy)]
struct Member<'a> {
    task: &'a str,
    index: usize,
    count: usize,
}

impl Member<'_> {
    /// The task and, for an ensemble's member, "member 2/3": "train cnn ·
    /// member 2/3", "train cnn" for a single network; `None` when both are
    /// missing.
    fn name(self) -> Option<String> {
        let member = (self.count > 1).then(|| format!("member {}/{}", self.index + 1, self.count));
        match (self.task.is_empty(), member) {
            (true, member) => member,
            (false, None) => Some(self.task.to_string()),
            (false, Some(member)) => Some(format!("{} · {member}", self.task)),
        }
    }

    /// [`name`](Self::name) and ": " to start the member's messages (empty
    /// when there is no name).
    fn label(self) -> String {
        self.name().map(|name| name + ": ").unwrap_or_default()
    }
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
    use super::{
        CnnHead, FrameStack, Lesson, SimParams, Teacher, cross_entropy_and_gradient, member_seed,
        pixel_posterior, sim, truth_by_frame,
    };

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
