//! A teacher's targets: the likelihood detector's posterior on each
//! training frame (its mean, or for the categorical head its whole
//! posterior over the pixels) in place of the simulator's truth.

use anyhow::Context;
use indicatif::ProgressBar;
use rand::RngExt;

use super::CnnHead;
use super::data::{PixelPosterior, truth_by_frame};
use super::inference::nearest_pixel;
use super::streams::{STREAM_TEACHER, stream};
use crate::sim::SimParams;
use crate::types::{Dataset, FrameStack};

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
pub(super) fn fixed_lesson(
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
pub(super) struct Teacher<'a> {
    pub(super) head: CnnHead,
    pub(super) microscope: &'a SimParams,
    pub(super) particles: usize,
    pub(super) filter_seed: u64,
}

/// What a teacher gives a stack's frames (those with one QD; the others
/// keep their truth).
#[derive(Clone)]
pub(super) enum Lesson {
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
    pub(super) fn teach(
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
pub(super) fn pixel_posterior(
    cloud: &[(f64, f64, f64)],
    height: usize,
    width: usize,
) -> PixelPosterior {
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
