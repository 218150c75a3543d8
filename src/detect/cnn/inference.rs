//! Batched inference and decoding: peak finding (the peaks head) or the
//! greedy disc cover of the softmax posterior (the categorical head).

use indicatif::ProgressBar;
use rayon::prelude::*;

use super::data::normalised_input;
use super::model::{
    LOG_SIGMA_RANGE, LOG_SIGMA_X_CHANNEL, LOG_SIGMA_Y_CHANNEL, Net, OFFSET_X_CHANNEL,
    OFFSET_Y_CHANNEL, OUTPUT_CHANNELS, SCORE_CHANNEL, WITHIN_1PX_CHANNEL,
};
use super::{CnnArchitecture, CnnHead, CnnScore, TrainedCnn, TrainingSettings, inference_device};
use crate::detect::candidates::{self, Candidate, CentreSearch};
use crate::types::{FrameStack, LocalisationSigma, Prediction};

/// Most frames per forward pass (small frames; the paper's 24 × 25 pixel
/// frames go 256 at a time).
pub const INFERENCE_BATCH: usize = 256;

/// Most pixels per forward pass: the network's activations, and so the
/// memory of inference, grow with the pixels of a batch (each hidden layer
/// holds `channels` floats per pixel), so large frames go fewer at a time.
/// 2¹⁸ pixels is one 512 × 512 frame.
pub const INFERENCE_PIXEL_BUDGET: usize = 1 << 18;

/// Frames per forward pass for frames of `frame_len` pixels: as many as
/// fit in [`INFERENCE_PIXEL_BUDGET`], at least 1 and at most
/// [`INFERENCE_BATCH`]. Each frame's output does not depend on the others
/// in its batch (batch normalisation uses its stored statistics at
/// inference), so the batch size never changes a prediction.
pub fn inference_batch(frame_len: usize) -> usize {
    (INFERENCE_PIXEL_BUDGET / frame_len.max(1)).clamp(1, INFERENCE_BATCH)
}

impl TrainedCnn {
    /// Localises QDs in every frame of `frames` (any frame size), in
    /// batches of [`inference_batch`] frames; `progress` advances by one
    /// per frame.
    ///
    /// Predictions are ordered by frame, then raster order of their peak
    /// pixel. Fails (naming the frame) if the network outputs a non-finite
    /// value.
    pub fn locate(
        &self,
        frames: &FrameStack,
        progress: &ProgressBar,
    ) -> anyhow::Result<Vec<Prediction>> {
        self.locate_in_batches(frames, inference_batch(frames.frame_len()), progress)
    }

    /// [`locate`](Self::locate) with `frames_per_batch` frames per forward
    /// pass (for measurements and for checking that batching changes
    /// nothing).
    pub fn locate_in_batches(
        &self,
        frames: &FrameStack,
        frames_per_batch: usize,
        progress: &ProgressBar,
    ) -> anyhow::Result<Vec<Prediction>> {
        locate_with(
            &self.nets,
            &self.architecture,
            &self.settings,
            frames,
            frames_per_batch,
            progress,
        )
    }

    /// The architecture's receptive field etc. are public; the raw output
    /// maps of `frames` are exposed for diagnostics: row-major
    /// `[n, OUTPUT_CHANNELS, H, W]`, channels as the `*_CHANNEL` constants
    /// of [`super::model`] (score logit, x offset, y offset, ln σx, ln σy,
    /// within-1-px logit). An ensemble's are its members' combined by
    /// [`combine_members`], the maps its predictions are read from.
    pub fn raw_output(&self, frames: &FrameStack) -> anyhow::Result<Vec<f32>> {
        let device = inference_device();
        let mut out = Vec::with_capacity(frames.n * OUTPUT_CHANNELS * frames.frame_len());
        let batch = inference_batch(frames.frame_len());
        for start in (0..frames.n).step_by(batch) {
            let end = (start + batch).min(frames.n);
            let outputs = member_outputs(
                &self.nets,
                self.architecture.edge_channel,
                frames,
                start..end,
                &device,
            )?;
            out.extend(ensemble_output(outputs, frames.frame_len()));
        }
        Ok(out)
    }
}

/// Each network's raw output for the batch `frames[batch]` (normalised
/// once, with the edge channel if `edge_channel`), in member order, each
/// row-major `[n, OUTPUT_CHANNELS, height, width]`.
fn member_outputs(
    nets: &[Net],
    edge_channel: bool,
    frames: &FrameStack,
    batch: std::ops::Range<usize>,
    device: &burn::prelude::Device,
) -> anyhow::Result<Vec<Vec<f32>>> {
    let dims = [batch.len(), frames.height, frames.width];
    let input = normalised_input(
        batch.map(|i| frames.frame(i)),
        frames.frame_len(),
        edge_channel,
    );
    nets.iter()
        .map(|net| {
            net.forward_inference(&input, dims, device)
                .into_data()
                .try_to_vec::<f32>()
                .map_err(|e| anyhow::anyhow!("reading the network output: {e:?}"))
        })
        .collect()
}

/// The output maps predictions are read from: a single network's
/// untouched (bit for bit what it was before ensembles), an ensemble's
/// members' combined by [`combine_members`].
fn ensemble_output(mut outputs: Vec<Vec<f32>>, frame_len: usize) -> Vec<f32> {
    if outputs.len() == 1 {
        outputs.pop().expect("one output")
    } else {
        combine_members(&outputs, frame_len)
    }
}

/// Combines the raw outputs of an ensemble's members (each row-major
/// `[n, OUTPUT_CHANNELS, H, W]` with `frame_len` = H·W pixels, in member
/// order) per pixel, before any peak is found:
///
/// - score logit, within-1-px logit, x and y offsets: the mean over
///   members;
/// - ln σx, ln σy: the σ of the members' mixture, σ² = mean of σ_k² +
///   the variance over members of the offset on that axis (the population
///   variance, about the mean offset), so members that disagree raise the
///   reported uncertainty; stored back as ln σ.
///
/// Computed in f64 with every sum taken in member order (deterministic),
/// the mixture through log-sum-exp so that no σ² overflows; rounded to f32
/// at the end.
pub fn combine_members(outputs: &[Vec<f32>], frame_len: usize) -> Vec<f32> {
    let Some(first) = outputs.first() else {
        return Vec::new();
    };
    let members = outputs.len() as f64;
    let mut combined = vec![0.0f32; first.len()];
    let frames = first.len() / (OUTPUT_CHANNELS * frame_len).max(1);
    let mean = |at: usize| outputs.iter().map(|o| o[at] as f64).sum::<f64>() / members;
    for frame in 0..frames {
        for pixel in 0..frame_len {
            let at = |channel: usize| (frame * OUTPUT_CHANNELS + channel) * frame_len + pixel;
            for channel in [
                SCORE_CHANNEL,
                OFFSET_X_CHANNEL,
                OFFSET_Y_CHANNEL,
                WITHIN_1PX_CHANNEL,
            ] {
                combined[at(channel)] = mean(at(channel)) as f32;
            }
            for (offset_channel, log_sigma_channel) in [
                (OFFSET_X_CHANNEL, LOG_SIGMA_X_CHANNEL),
                (OFFSET_Y_CHANNEL, LOG_SIGMA_Y_CHANNEL),
            ] {
                let offset_variance = member_variance(outputs, at(offset_channel));
                // ln(mean σ_k²) by log-sum-exp over 2 ln σ_k.
                let log_variances = || {
                    outputs
                        .iter()
                        .map(|o| 2.0 * o[at(log_sigma_channel)] as f64)
                };
                let largest = log_variances().fold(f64::NEG_INFINITY, f64::max);
                let log_mean_variance = largest
                    + (log_variances().map(|v| (v - largest).exp()).sum::<f64>() / members).ln();
                // ln(mean σ_k² + offset variance), added in log space.
                let log_total = if offset_variance > 0.0 {
                    let log_offset_variance = offset_variance.ln();
                    log_mean_variance.max(log_offset_variance)
                        + (-(log_mean_variance - log_offset_variance).abs())
                            .exp()
                            .ln_1p()
                } else {
                    log_mean_variance
                };
                combined[at(log_sigma_channel)] = (0.5 * log_total) as f32;
            }
        }
    }
    combined
}

/// Fails with the first non-finite value of `output` (a batch's raw
/// output, row-major `[n, OUTPUT_CHANNELS, H, W]`, whose frame 0 is frame
/// `first_frame` of the stack).
fn check_finite(
    output: &[f32],
    first_frame: usize,
    frame_len: usize,
) -> Result<(), NonFiniteOutput> {
    let Some(bad) = output.iter().position(|v| !v.is_finite()) else {
        return Ok(());
    };
    let frame_values = OUTPUT_CHANNELS * frame_len;
    Err(NonFiniteOutput {
        frame: first_frame + bad / frame_values,
        channel: (bad % frame_values) / frame_len,
        pixel: bad % frame_len,
    })
}

/// The network produced a NaN or infinity: its weights are damaged (a
/// corrupted model file, or a training that diverged).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct NonFiniteOutput {
    pub frame: usize,
    pub channel: usize,
    pub pixel: usize,
}

impl std::fmt::Display for NonFiniteOutput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "CNN output of frame {} is not finite (channel {}, pixel {}): the model is damaged",
            self.frame, self.channel, self.pixel
        )
    }
}

impl std::error::Error for NonFiniteOutput {}

/// Runs `nets` (one network, or an ensemble's members, combined by
/// [`combine_members`]) over `frames` in batches of `batch` and extracts
/// the peaks. Fails if any member outputs a non-finite value.
pub(crate) fn locate_with(
    nets: &[Net],
    arch: &CnnArchitecture,
    settings: &TrainingSettings,
    frames: &FrameStack,
    batch: usize,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<Prediction>> {
    let device = inference_device();
    let (height, width) = (frames.height, frames.width);
    let len = frames.frame_len();
    let mut predictions = Vec::new();
    crate::limits::check_frame_not_empty(height, width)?;
    let score_floor = settings.score_floor;
    // The floor compared on logits (sigmoid is monotone), so no pixel's
    // sigmoid needs computing unless it is a candidate.
    let logit_floor = if score_floor > 0.0 {
        (score_floor / (1.0 - score_floor)).ln()
    } else {
        f64::NEG_INFINITY
    };
    for start in (0..frames.n).step_by(batch.max(1)) {
        let end = (start + batch).min(frames.n);
        let outputs = member_outputs(nets, arch.edge_channel, frames, start..end, &device)?;
        // Each member checked on its own: the combination could hide a
        // member's damage (a σ of 0 adds nothing to the mixture).
        for output in &outputs {
            check_finite(output, start, len)?;
        }
        let combined = (outputs.len() > 1).then(|| combine_members(&outputs, len));
        let output = combined.as_deref().unwrap_or(&outputs[0]);
        let decoder = FrameDecoder {
            arch,
            sigma_source: SigmaSource::of(settings),
            score_floor,
            logit_floor,
            height,
            width,
            outputs: &outputs,
            first_frame: start,
        };
        let frame_predictions = |(offset, maps): (usize, &[f32])| decoder.predictions(offset, maps);
        // The cover of the categorical head costs far more than the peak
        // search, so its frames are decoded in parallel (each frame's on its
        // own: the order, and every bit, is the sequential one).
        let per_frame: Vec<Vec<Prediction>> = if arch.head == CnnHead::Categorical {
            output
                .par_chunks_exact(OUTPUT_CHANNELS * len)
                .enumerate()
                .map(frame_predictions)
                .collect()
        } else {
            output
                .chunks_exact(OUTPUT_CHANNELS * len)
                .enumerate()
                .map(frame_predictions)
                .collect()
        };
        for list in per_frame {
            predictions.extend(list);
            progress.inc(1);
        }
    }
    Ok(predictions)
}

/// How the predictions of one batch's frames are read from their output
/// maps.
struct FrameDecoder<'a> {
    arch: &'a CnnArchitecture,
    sigma_source: SigmaSource,
    score_floor: f64,
    /// `score_floor` as a logit.
    logit_floor: f64,
    height: usize,
    width: usize,
    /// Every member's output maps of the batch (their spread is the σ of
    /// an ensemble's within-1-px head).
    outputs: &'a [Vec<f32>],
    /// The frame number of the batch's first frame.
    first_frame: usize,
}

/// One frame's output channels.
struct FrameMaps<'a> {
    logits: &'a [f32],
    dx: &'a [f32],
    dy: &'a [f32],
    log_sigma_x: &'a [f32],
    log_sigma_y: &'a [f32],
    within: &'a [f32],
}

impl FrameDecoder<'_> {
    /// The predictions of the batch's frame `offset`, whose (combined)
    /// output channels are `maps`.
    fn predictions(&self, offset: usize, maps: &[f32]) -> Vec<Prediction> {
        let len = self.height * self.width;
        let channel = |c: usize| &maps[c * len..(c + 1) * len];
        let frame_maps = FrameMaps {
            logits: channel(SCORE_CHANNEL),
            dx: channel(OFFSET_X_CHANNEL),
            dy: channel(OFFSET_Y_CHANNEL),
            log_sigma_x: channel(LOG_SIGMA_X_CHANNEL),
            log_sigma_y: channel(LOG_SIGMA_Y_CHANNEL),
            within: channel(WITHIN_1PX_CHANNEL),
        };
        if self.arch.head == CnnHead::Categorical {
            self.categorical(offset, &frame_maps)
        } else {
            self.peaks(offset, &frame_maps)
        }
    }

    /// The uncertainty of the prediction at pixel `p` of the batch's frame
    /// `offset`.
    fn sigma_at(&self, offset: usize, maps: &FrameMaps<'_>, p: usize) -> LocalisationSigma {
        match self.sigma_source {
            SigmaSource::Maps => LocalisationSigma {
                x: (maps.log_sigma_x[p] as f64).exp(),
                y: (maps.log_sigma_y[p] as f64).exp(),
            },
            SigmaSource::Within1px => {
                let len = self.height * self.width;
                let frame_start = offset * OUTPUT_CHANNELS * len;
                let spread =
                    |channel: usize| member_variance(self.outputs, frame_start + channel * len + p);
                sigma_from_within(
                    maps.within[p] as f64,
                    spread(OFFSET_X_CHANNEL),
                    spread(OFFSET_Y_CHANNEL),
                )
            }
        }
    }

    /// The categorical head's ranked guesses of the frame.
    fn categorical(&self, offset: usize, maps: &FrameMaps<'_>) -> Vec<Prediction> {
        let categorical = CategoricalMaps {
            logits: maps.logits,
            dx: maps.dx,
            dy: maps.dy,
            log_sigma_x: maps.log_sigma_x,
            log_sigma_y: maps.log_sigma_y,
            width: self.width,
        };
        let guesses = categorical_guesses(&categorical, self.arch)
            .into_iter()
            .filter(|guess| guess.mass >= self.score_floor);
        (1..)
            .zip(guesses)
            .map(|(rank, guess)| {
                let pixel = nearest_pixel(guess.x, guess.y, self.height, self.width);
                Prediction {
                    frame: self.first_frame + offset,
                    x: guess.x,
                    y: guess.y,
                    score: guess.mass,
                    sigma: Some(self.sigma_at(offset, maps, pixel)),
                    candidate: Some(rank),
                }
            })
            .collect()
    }

    /// The peaks head's predictions of the frame: its score map's local
    /// maxima at or above the floor.
    fn peaks(&self, offset: usize, maps: &FrameMaps<'_>) -> Vec<Prediction> {
        let (arch, width, height) = (self.arch, self.width, self.height);
        let mut found = Vec::new();
        for (row, col) in local_maxima(maps.logits, height, width, arch.peak_radius_px) {
            let p = row * width + col;
            let logit = maps.logits[p] as f64;
            if logit < self.logit_floor {
                continue;
            }
            let (x, y) = if arch.refine_radius_px == 0 {
                (
                    col as f64 + maps.dx[p] as f64,
                    row as f64 + maps.dy[p] as f64,
                )
            } else {
                refined_position(
                    maps.logits,
                    maps.dx,
                    maps.dy,
                    width,
                    height,
                    (row, col),
                    arch.refine_radius_px,
                )
            };
            let maps_sigma = LocalisationSigma {
                x: (maps.log_sigma_x[p] as f64).exp(),
                y: (maps.log_sigma_y[p] as f64).exp(),
            };
            let score = match arch.score {
                CnnScore::Heatmap => sigmoid(logit),
                CnnScore::Within1px => sigmoid(maps.within[p] as f64),
                CnnScore::GaussianWithin1px => sigmoid(logit) * gaussian_within_1px(maps_sigma),
            };
            found.push(Prediction {
                frame: self.first_frame + offset,
                x,
                y,
                score,
                sigma: Some(self.sigma_at(offset, maps, p)),
                candidate: None,
            });
        }
        found
    }
}

/// Where a prediction's `sigma_x`, `sigma_y` come from (docs/cnn.md,
/// "Uncertainty").
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum SigmaSource {
    /// The within-1-px head, read as the σ of an isotropic Gaussian error
    /// with that probability of lying within 1 px ([`sigma_from_within`]),
    /// widened by the members' disagreement: when the head was trained.
    Within1px,
    /// The σ maps (an ensemble's as their mixture): for networks whose
    /// within-1-px head was left untrained.
    Maps,
}

impl SigmaSource {
    fn of(settings: &TrainingSettings) -> Self {
        if settings.within_loss_weight > 0.0 {
            SigmaSource::Within1px
        } else {
            SigmaSource::Maps
        }
    }
}

/// The population variance over members of the value at index `at` of
/// their raw outputs (0 for one network), summed in member order.
fn member_variance(outputs: &[Vec<f32>], at: usize) -> f64 {
    let members = outputs.len() as f64;
    let mean = outputs.iter().map(|o| o[at] as f64).sum::<f64>() / members;
    outputs
        .iter()
        .map(|o| (o[at] as f64 - mean).powi(2))
        .sum::<f64>()
        / members
}

/// A localisation's σ per axis from its within-1-px logit: the σ of the
/// isotropic 2-D Gaussian error whose probability of lying within 1 px is
/// the head's p (the Rayleigh distribution: p = 1 − exp(−1 / 2σ²), so
/// σ² = 1 / (2 · −ln(1 − p)), and −ln(1 − p) = softplus(logit), computed
/// without forming 1 − p), plus on each axis the variance of the members'
/// offsets (`spread_x`, `spread_y`; 0 for one network). ln σ stays within
/// [`LOG_SIGMA_RANGE`] (σ from 0.007 to 20 px): a head certain of a miss
/// says "20 px", not infinity.
pub(crate) fn sigma_from_within(
    within_logit: f64,
    spread_x: f64,
    spread_y: f64,
) -> LocalisationSigma {
    let softplus = within_logit.max(0.0) + (-within_logit.abs()).exp().ln_1p();
    let variance = 0.5 / softplus;
    let axis = |spread: f64| {
        let log_sigma = 0.5 * (variance + spread).ln();
        if log_sigma.is_nan() {
            LOG_SIGMA_RANGE.1.exp()
        } else {
            log_sigma.clamp(LOG_SIGMA_RANGE.0, LOG_SIGMA_RANGE.1).exp()
        }
    };
    LocalisationSigma {
        x: axis(spread_x),
        y: axis(spread_y),
    }
}

/// Pixels whose softmax probability is below this are left out of the
/// categorical head's posterior (the guesses' masses stay fractions of the
/// whole softmax): a disc of them would hold less than the cover's floor,
/// and leaving them out makes the cover about ten times faster on the
/// paper's frames with the same AUCs to three decimals (docs/cnn.md,
/// "Candidates").
pub const MIN_PIXEL_MASS: f64 = 1e-4;

/// Largest σ (px) per axis a pixel's mass is spread by: given that the
/// centroid is nearest that pixel it lies within the pixel's cell, whose
/// uniform spread is 0.29 px, so a wider σ map is an untrained value.
pub const MAX_SPREAD_SIGMA_PX: f64 = 0.5;

/// The 3-point Gauss–Hermite rule for a standard normal: nodes 0 and ±√3
/// with weights 2/3 and 1/6 each (exact for polynomials to degree 5).
pub const GAUSS_HERMITE: [(f64, f64); 3] = [
    (0.0, 2.0 / 3.0),
    (-1.732_050_807_568_877_2, 1.0 / 6.0),
    (1.732_050_807_568_877_2, 1.0 / 6.0),
];

/// One frame's maps as the categorical head reads them (row-major, the
/// frame's `width`).
pub(crate) struct CategoricalMaps<'a> {
    pub logits: &'a [f32],
    pub dx: &'a [f32],
    pub dy: &'a [f32],
    pub log_sigma_x: &'a [f32],
    pub log_sigma_y: &'a [f32],
    pub width: usize,
}

/// The categorical head's ranked guesses in one frame: its softmax over
/// the pixels is the posterior probability that the centroid is nearest
/// each pixel; given that, the centroid is at the pixel's centre plus its
/// offsets, with the σ maps' error per axis (the σ maps learn the offsets'
/// error at the centroid's pixel, which is that conditional spread). Each
/// pixel's mass (those of at least [`MIN_PIXEL_MASS`]) becomes the 3 × 3
/// Gauss–Hermite points of that Gaussian (σ at most
/// [`MAX_SPREAD_SIGMA_PX`]), and the points are covered greedily by discs of
/// `arch.candidate_radius_px` ([`candidates::greedy_disc_cover`]), up to
/// `arch.max_candidates` of them, each with the mass it newly covers, in
/// falling order of mass (the cover's centre search is a heuristic, so a
/// later disc may hold a little more than an earlier one; the rank follows
/// the score, so rank 1 is the frame's best guess).
pub(crate) fn categorical_guesses(
    maps: &CategoricalMaps<'_>,
    arch: &CnnArchitecture,
) -> Vec<Candidate> {
    let mut points: Vec<(f64, f64, f64)> = Vec::new();
    let mut kept = 0.0;
    for (p, mass) in softmax(maps.logits).into_iter().enumerate() {
        if mass < MIN_PIXEL_MASS {
            continue;
        }
        kept += mass;
        let (row, col) = (p / maps.width, p % maps.width);
        let x = col as f64 + maps.dx[p] as f64;
        let y = row as f64 + maps.dy[p] as f64;
        let sigma = |log_sigma: f32| {
            (log_sigma as f64)
                .clamp(LOG_SIGMA_RANGE.0, LOG_SIGMA_RANGE.1)
                .exp()
                .min(MAX_SPREAD_SIGMA_PX)
        };
        let (sx, sy) = (sigma(maps.log_sigma_x[p]), sigma(maps.log_sigma_y[p]));
        for (v, wv) in GAUSS_HERMITE {
            for (u, wu) in GAUSS_HERMITE {
                points.push((x + u * sx, y + v * sy, mass * wu * wv));
            }
        }
    }
    let mut guesses = candidates::greedy_disc_cover(
        &points,
        arch.max_candidates,
        arch.candidate_radius_px,
        CentreSearch::CellsWithMeanShift,
    );
    // The cover's masses are fractions of the points kept; as fractions of
    // the whole softmax they are probabilities.
    for guess in &mut guesses {
        guess.mass *= kept;
    }
    // Stable: equal masses keep the cover's order.
    guesses.sort_by(|a, b| b.mass.total_cmp(&a.mass));
    guesses
}

/// The row-major index of the pixel whose centre is nearest `(x, y)`
/// (pixel centres at integers), clamped into the `height × width` frame.
pub(crate) fn nearest_pixel(x: f64, y: f64, height: usize, width: usize) -> usize {
    let clamp = |v: f64, size: usize| {
        if v.is_nan() {
            0
        } else {
            v.round().clamp(0.0, (size - 1) as f64) as usize
        }
    };
    clamp(y, height) * width + clamp(x, width)
}

/// `ln Σ exp(logit)` over a frame's logits, in f64, summed in raster order.
pub(crate) fn frame_log_normaliser(logits: &[f32]) -> f64 {
    let largest = logits
        .iter()
        .fold(f64::NEG_INFINITY, |m, &l| m.max(l as f64));
    let mut total = 0.0;
    for &l in logits {
        total += (l as f64 - largest).exp();
    }
    largest + total.ln()
}

/// The softmax of a frame's logits, in f64, its normaliser summed in
/// raster order (the categorical head's posterior over the pixels).
pub(crate) fn softmax(logits: &[f32]) -> Vec<f64> {
    let log_total = frame_log_normaliser(logits);
    logits
        .iter()
        .map(|&l| (l as f64 - log_total).exp())
        .collect()
}

fn sigmoid(logit: f64) -> f64 {
    1.0 / (1.0 + (-logit).exp())
}

/// The probability that a 2-D Gaussian error of standard deviations
/// `sigma` lies within 1 px: `1 − exp(−1 / (2 σx σy))`, exact when σx = σy
/// (the Rayleigh distribution) and the isotropic approximation with the
/// same area otherwise.
fn gaussian_within_1px(sigma: LocalisationSigma) -> f64 {
    1.0 - (-1.0 / (2.0 * sigma.x * sigma.y)).exp()
}

/// The score-weighted mean of pixel + offset over the window of `radius`
/// around `peak` (clipped at the edges).
fn refined_position(
    logits: &[f32],
    dx: &[f32],
    dy: &[f32],
    width: usize,
    height: usize,
    (row, col): (usize, usize),
    radius: usize,
) -> (f64, f64) {
    let (mut sum_w, mut sum_x, mut sum_y) = (0.0, 0.0, 0.0);
    for r in row.saturating_sub(radius)..(row + radius + 1).min(height) {
        for c in col.saturating_sub(radius)..(col + radius + 1).min(width) {
            let p = r * width + c;
            let w = sigmoid(logits[p] as f64);
            sum_w += w;
            sum_x += w * (c as f64 + dx[p] as f64);
            sum_y += w * (r as f64 + dy[p] as f64);
        }
    }
    // The peak itself has weight > 0, so sum_w > 0.
    (sum_x / sum_w, sum_y / sum_w)
}

/// Pixels `(row, col)` of a row-major `height × width` map that are the
/// maximum of the `(2·radius + 1)²` window around them (clipped at the
/// edges). A plateau yields one pixel: a pixel must be strictly greater than
/// window neighbours earlier in raster order and at least equal to later
/// ones. Returned in raster order.
pub(crate) fn local_maxima(
    map: &[f32],
    height: usize,
    width: usize,
    radius: usize,
) -> Vec<(usize, usize)> {
    let mut peaks = Vec::new();
    for row in 0..height {
        let rows = row.saturating_sub(radius)..(row + radius + 1).min(height);
        'pixel: for col in 0..width {
            let value = map[row * width + col];
            let cols = col.saturating_sub(radius)..(col + radius + 1).min(width);
            for r in rows.clone() {
                for c in cols.clone() {
                    let other = map[r * width + c];
                    let earlier = (r, c) < (row, col);
                    if other > value || (earlier && other == value) {
                        continue 'pixel;
                    }
                }
            }
            peaks.push((row, col));
        }
    }
    peaks
}

#[cfg(test)]
mod tests {
    use super::{
        CategoricalMaps, categorical_guesses, combine_members, gaussian_within_1px, local_maxima,
        sigma_from_within,
    };
    use crate::detect::candidates::Candidate;
    use crate::detect::cnn::model::{
        LOG_SIGMA_X_CHANNEL, LOG_SIGMA_Y_CHANNEL, OFFSET_X_CHANNEL, OFFSET_Y_CHANNEL,
        OUTPUT_CHANNELS, SCORE_CHANNEL, WITHIN_1PX_CHANNEL,
    };
    use crate::detect::cnn::{CnnArchitecture, CnnHead};

    /// One frame of one pixel: the six maps' values in channel order.
    fn pixel(score: f32, dx: f32, dy: f32, sigma_x: f32, sigma_y: f32, within: f32) -> Vec<f32> {
        let mut maps = vec![0.0; OUTPUT_CHANNELS];
        maps[SCORE_CHANNEL] = score;
        maps[OFFSET_X_CHANNEL] = dx;
        maps[OFFSET_Y_CHANNEL] = dy;
        maps[LOG_SIGMA_X_CHANNEL] = sigma_x.ln();
        maps[LOG_SIGMA_Y_CHANNEL] = sigma_y.ln();
        maps[WITHIN_1PX_CHANNEL] = within;
        maps
    }

    #[test]
    fn two_members_combine_as_means_and_a_mixture_sigma() {
        let first = pixel(1.0, 0.25, -0.5, 0.3, 0.5, 2.0);
        let second = pixel(3.0, 0.75, -0.5, 0.4, 0.5, -1.0);
        let combined = combine_members(&[first, second], 1);
        assert_eq!(combined.len(), OUTPUT_CHANNELS);
        assert_eq!(combined[SCORE_CHANNEL], 2.0);
        assert_eq!(combined[OFFSET_X_CHANNEL], 0.5);
        assert_eq!(combined[OFFSET_Y_CHANNEL], -0.5);
        assert_eq!(combined[WITHIN_1PX_CHANNEL], 0.5);
        // By hand: σx² = (0.3² + 0.4²) / 2 + the offsets' variance
        // ((0.25 − 0.5)² + (0.75 − 0.5)²) / 2 = 0.125 + 0.0625 = 0.1875;
        // the members agree on dy, so σy² = (0.5² + 0.5²) / 2 = 0.25.
        let sigma_x = (combined[LOG_SIGMA_X_CHANNEL] as f64).exp();
        let sigma_y = (combined[LOG_SIGMA_Y_CHANNEL] as f64).exp();
        assert!((sigma_x - 0.1875f64.sqrt()).abs() < 1e-6, "σx {sigma_x}");
        assert!((sigma_y - 0.5).abs() < 1e-6, "σy {sigma_y}");
        // Disagreement raises σ above every member's.
        assert!(sigma_x > 0.4);
    }

    #[test]
    fn the_mixture_sigma_does_not_overflow_and_frames_stay_apart() {
        // Two frames of two pixels; huge ln σ (whose σ² would overflow an
        // f64) in frame 1, pixel 0.
        let frame_len = 2;
        let mut first = vec![0.0f32; 2 * OUTPUT_CHANNELS * frame_len];
        let mut second = first.clone();
        let at = |frame: usize, channel: usize, pixel: usize| {
            (frame * OUTPUT_CHANNELS + channel) * frame_len + pixel
        };
        first[at(1, LOG_SIGMA_X_CHANNEL, 0)] = 1000.0;
        second[at(1, LOG_SIGMA_X_CHANNEL, 0)] = 1000.0;
        first[at(0, SCORE_CHANNEL, 1)] = 4.0;
        let combined = combine_members(&[first, second], frame_len);
        assert!(combined.iter().all(|v| v.is_finite()), "{combined:?}");
        assert!((combined[at(1, LOG_SIGMA_X_CHANNEL, 0)] - 1000.0).abs() < 1e-3);
        assert_eq!(combined[at(0, SCORE_CHANNEL, 1)], 2.0);
        assert_eq!(combined[at(1, SCORE_CHANNEL, 1)], 0.0);
        // σ = 1 in both members, no disagreement: ln σ stays 0.
        assert_eq!(combined[at(0, LOG_SIGMA_Y_CHANNEL, 0)], 0.0);
    }

    #[test]
    fn plateaus_give_one_peak_and_separate_peaks_all_count() {
        #[rustfmt::skip]
        let map = [
            0.0, 5.0, 5.0, 0.0, 0.0, 0.0,
            0.0, 5.0, 5.0, 0.0, 0.0, 0.0,
            0.0, 0.0, 0.0, 0.0, 0.0, 3.0,
        ];
        assert_eq!(local_maxima(&map, 3, 6, 1), vec![(0, 1), (2, 5)]);
        // A larger window lets the stronger peak suppress the weaker one.
        assert_eq!(local_maxima(&map, 3, 6, 4), vec![(0, 1)]);
    }

    #[test]
    fn the_sigma_read_from_the_within_head_inverts_its_probability() {
        for logit in [-6.0, -2.0, -0.3, 0.0, 0.7, 3.0, 8.0] {
            let p = 1.0 / (1.0 + f64::exp(-logit));
            let sigma = sigma_from_within(logit, 0.0, 0.0);
            assert_eq!(sigma.x, sigma.y);
            // The isotropic Gaussian of that σ is within 1 px with
            // probability p.
            let back = gaussian_within_1px(sigma);
            assert!(
                (back - p).abs() < 1e-12,
                "logit {logit}: {back} against {p}"
            );
        }
        // Surer of a hit, smaller σ.
        assert!(sigma_from_within(2.0, 0.0, 0.0).x < sigma_from_within(1.0, 0.0, 0.0).x);
        // Members' disagreement adds in quadrature, per axis.
        let alone = sigma_from_within(0.5, 0.0, 0.0).x;
        let spread = sigma_from_within(0.5, 0.25, 0.0);
        assert!((spread.x - (alone * alone + 0.25).sqrt()).abs() < 1e-12);
        assert_eq!(spread.y, alone);
        // Certain of a miss or of a hit: bounded to [e⁻⁵, e³] px, finite.
        assert_eq!(sigma_from_within(-1e4, 0.0, 0.0).x, 3.0f64.exp());
        assert_eq!(sigma_from_within(1e6, 0.0, 0.0).x, (-5.0f64).exp());
    }

    /// A frame's maps for the categorical head with σ maps at their floor
    /// (σ = e⁻⁵ ≈ 0.007 px): each pixel's mass stays at pixel + offset.
    fn maps<'a>(
        logits: &'a [f32],
        dx: &'a [f32],
        dy: &'a [f32],
        width: usize,
    ) -> CategoricalMaps<'a> {
        const FLOOR: &[f32] = &[-5.0; 120];
        CategoricalMaps {
            logits,
            dx,
            dy,
            log_sigma_x: &FLOOR[..logits.len()],
            log_sigma_y: &FLOOR[..logits.len()],
            width,
        }
    }

    fn categorical(max_candidates: usize) -> CnnArchitecture {
        CnnArchitecture {
            head: CnnHead::Categorical,
            max_candidates,
            ..CnnArchitecture::default()
        }
    }

    #[test]
    fn two_separated_modes_give_two_guesses_with_their_masses() {
        // A 10 × 12 frame whose softmax puts 0.6 on pixel (row 3, col 3)
        // and 0.4 on (3, 8), e⁻³⁰ on the rest; the second mode's offsets
        // move it by (+0.25, −0.5).
        let (height, width) = (10, 12);
        let mut logits = vec![-30.0f32; height * width];
        logits[3 * width + 3] = 0.6f32.ln();
        logits[3 * width + 8] = 0.4f32.ln();
        let mut dx = vec![0.0f32; height * width];
        let mut dy = vec![0.0f32; height * width];
        dx[3 * width + 8] = 0.25;
        dy[3 * width + 8] = -0.5;
        let guesses = categorical_guesses(&maps(&logits, &dx, &dy, width), &categorical(4));
        assert_eq!(guesses.len(), 2, "{guesses:?}");
        // Each guess covers its mode (any centre within the radius of it
        // covers the same mass) and holds its mass.
        let covers = |g: &Candidate, x: f64, y: f64| (g.x - x).hypot(g.y - y) <= 1.0;
        assert!(covers(&guesses[0], 3.0, 3.0), "{guesses:?}");
        assert!((guesses[0].mass - 0.6).abs() < 1e-6, "{guesses:?}");
        assert!(covers(&guesses[1], 8.25, 2.5), "{guesses:?}");
        assert!((guesses[1].mass - 0.4).abs() < 1e-6, "{guesses:?}");
        // One guess asked for: the larger mode alone.
        let one = categorical_guesses(&maps(&logits, &dx, &dy, width), &categorical(1));
        assert_eq!(one.len(), 1);
        assert!((one[0].mass - 0.6).abs() < 1e-6);
    }

    #[test]
    fn one_tight_mode_gives_one_guess_holding_almost_all_the_mass() {
        // Logit 10 at (5, 5), 0 elsewhere: that pixel holds e¹⁰ / (e¹⁰ + 119)
        // ≈ 0.9946; a further disc of radius 1 holds at most 5 of the other
        // pixels, ≈ 2.3e-4 of the mass, below the cover's floor (1e-3).
        let (height, width) = (10, 12);
        let mut logits = vec![0.0f32; height * width];
        logits[5 * width + 5] = 10.0;
        let zeros = vec![0.0f32; height * width];
        let guesses = categorical_guesses(&maps(&logits, &zeros, &zeros, width), &categorical(4));
        let expected = 10f64.exp() / (10f64.exp() + 119.0);
        assert!(!guesses.is_empty());
        assert!(
            (guesses[0].x - 5.0).hypot(guesses[0].y - 5.0) <= 1.0,
            "{guesses:?}"
        );
        assert!(guesses[0].mass >= expected - 1e-9, "{guesses:?}");
        assert!(guesses[0].mass < expected + 5.0 / (10f64.exp() + 119.0) + 1e-9);
        let rest: f64 = guesses[1..].iter().map(|g| g.mass).sum();
        assert!(rest < 1e-3, "{guesses:?}");
    }
}
