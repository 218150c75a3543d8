//! The training loss of one batch: a CenterNet-style focal loss on the
//! score map (or a cross-entropy over the pixels for the categorical
//! head), an L1 loss on the sub-pixel offsets, a Gaussian negative
//! log-likelihood for the σ maps and a cross-entropy for the within-1-px
//! head, each summed in a fixed order.

use burn::prelude::*;
use burn::tensor::activation::{log_sigmoid, sigmoid};

use super::data::{Source, TargetShape, normalised_input, targets};
use super::inference::{frame_log_normaliser, nearest_pixel, softmax};
use super::kernels::fixed_order_sum;
use super::model::{
    LOG_SIGMA_RANGE, LOG_SIGMA_X_CHANNEL, Net, NetworkStep, OFFSET_X_CHANNEL, SCORE_CHANNEL,
    WITHIN_1PX_CHANNEL,
};
use super::{CnnArchitecture, CnnHead, TrainingSettings};

/// The loss of one batch: the total to take the gradient of, its value
/// and its parts' (each part before its weight), and the network's step
/// that completes the backward pass.
pub(super) struct BatchLoss {
    pub(super) total: Tensor<1>,
    pub(super) values: LossValues,
    pub(super) network_step: NetworkStep,
}

/// A batch's loss values, each summed over its pixels in a fixed order
/// ([`fixed_order_sum`]): the backend's own reductions sum in an order that
/// depends on the CPU's vector width, and these values are recorded with
/// the model.
#[derive(Debug, Clone, Copy)]
pub(super) struct LossValues {
    pub(super) total: f64,
    pub(super) score: f64,
    pub(super) offset: f64,
    pub(super) sigma: f64,
    pub(super) within: f64,
}

/// The fixed-order sum of a loss map's elements.
pub(super) fn map_sum(map: &Tensor<4>) -> anyhow::Result<f64> {
    let values = map
        .clone()
        .into_data()
        .try_to_vec::<f32>()
        .map_err(|e| anyhow::anyhow!("reading a loss map: {e:?}"))?;
    Ok(fixed_order_sum(&values))
}

/// Largest distance (pixels) between a localisation and a centroid for the
/// within-1-px head's target to be 1.
pub(super) const WITHIN_RADIUS_PX: f64 = 1.0;

/// The within-1-px target of every pixel of a batch, row-major `[n, 1, H,
/// W]`: 1 where the pixel's localisation (pixel centre + its predicted
/// offset, `offsets` row-major `[n, 2, H, W]`) lies within
/// [`WITHIN_RADIUS_PX`] of any of its frame's `emitters`, else 0.
pub(super) fn within_targets(
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
pub(super) fn batch_loss(
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
    let sigma_count = (2 * positives).max(1) as f64;
    let sigma_map = sigma_nll_map(log_sigma, realised_offset.clone(), offset_target, centre);
    let sigma_loss = sigma_map.clone().sum().div_scalar(sigma_count);
    let within_map = within_map(within_logit, realised_offset, items, map)?;
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

/// The Gaussian negative log-likelihood of the offsets' error at each
/// target centre's pixel (`centre`), per axis: ln σ + e² / 2σ² (DECODE's σ
/// maps). Only there: over the whole offset window the error mostly says
/// how far a pixel is from the centre, which is not what the σ of a peak
/// should tell.
fn sigma_nll_map(
    log_sigma: Tensor<4>,
    realised_offset: Tensor<4>,
    offset_target: Tensor<4>,
    centre: Tensor<4>,
) -> Tensor<4> {
    let log_sigma = log_sigma.clamp(LOG_SIGMA_RANGE.0, LOG_SIGMA_RANGE.1);
    let squared_error = (realised_offset - offset_target).powi_scalar(2);
    let inverse_variance = log_sigma.clone().mul_scalar(-2.0).exp();
    (log_sigma + squared_error * inverse_variance.mul_scalar(0.5)) * centre
}

/// The log-likelihood map of the within-1-px head (`within_logit`) against
/// whether each pixel's localisation (its `realised_offset`) did land
/// within 1 px of one of its frame's true centroids; `map` makes a batch
/// tensor of `channels` maps.
fn within_map(
    within_logit: Tensor<4>,
    realised_offset: Tensor<4>,
    items: &[(&Source, usize)],
    map: impl Fn(Vec<f32>, usize) -> Tensor<4>,
) -> anyhow::Result<Tensor<4>> {
    let [_, _, height, width] = within_logit.dims();
    let realised = realised_offset
        .into_data()
        .try_to_vec::<f32>()
        .map_err(|e| anyhow::anyhow!("reading the offsets: {e:?}"))?;
    let true_centroids: Vec<&[(f64, f64)]> =
        items.iter().map(|(source, i)| source.truth(*i)).collect();
    let within = map(within_targets(&realised, &true_centroids, height, width), 1);
    Ok(log_sigmoid(within_logit.clone()) * within.clone()
        + log_sigmoid(within_logit.neg()) * within.neg().add_scalar(1.0))
}

/// The focal loss of the peaks head (CenterNet, α = 2, β = 4), from
/// log-sigmoids for stability, per positive pixel: the tensor to
/// differentiate and its value summed in a fixed order.
pub(super) fn focal_loss(
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
pub(super) fn categorical_loss(
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
pub(super) fn cross_entropy_and_gradient(
    logits: &[f32],
    targets: &[&[(u32, f32)]],
) -> (f64, Vec<f32>) {
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
