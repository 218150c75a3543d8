//! The likelihood localiser: the posterior over a QD's hidden path given one
//! frame, under the simulator's exact forward model (`docs/likelihood.md`).
//!
//! A bootstrap particle filter runs along the scan, one PSF sample at a
//! time, in the order the beam visits them. Each particle is one QD path:
//! its 3-D position (µm), its diffusion coefficient (fixed, or drawn from
//! the prior over D), its frame's brightness N_qd and background N_bkg
//! (fixed, or drawn from their priors when the microscope declares them as
//! distributions) and the running sum of its positions. At every sample
//! each particle takes the simulator's Brownian step
//! ([`ScanModel::step_sds`]: along a row, or across a retrace); at the end
//! of every pixel its weight is multiplied by the Poisson likelihood of the
//! pixel's count given the expected photons of its path
//! ([`ScanModel::sample_photons_with`] summed over the dwell, plus background).
//! When the effective sample size falls below half the particles they are
//! resampled (systematic resampling), carrying their position sums along:
//! at the end of the frame each surviving particle's sum is the centroid of
//! its whole ancestral path, so the weighted particles sample the smoothed
//! posterior of the trajectory centroid (smoothing by ancestry tracing).
//!
//! Output per frame: one prediction, the posterior mean of the trajectory
//! centroid (the truth the metric scores against), with score = the
//! posterior mass within `score_radius_px` of it; or, with
//! `max_candidates` > 1, a ranked list of guesses from the greedy disc cover
//! of the centroid's posterior ([`crate::detect::candidates`]).
//!
//! Determinism: frame `i` draws only from ChaCha8 stream `i` of the
//! detector's seed (as the simulator's frames do), particles are processed
//! in order within a frame, and frames run in parallel: the predictions are
//! the same whatever the thread count.

use indicatif::ProgressBar;
use rand::RngExt;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::detect::candidates::{self, CentreSearch, MAX_CANDIDATES};
use crate::error::{FieldError, input_error, require_positive};
use crate::sim::gaussian::standard_normal_from_bits;
use crate::sim::{DetectorNoise, Distribution, ScanModel, SimParams, frame_rng};
use crate::types::{FrameStack, Prediction};

mod kernels;
mod vector_math;

/// Version of the localiser's output, part of the content key of every
/// prediction it makes in the registry: bump it whenever a change alters
/// any prediction.
pub const CODE_VERSION: &str = "scanloc-likelihood/2";

/// Resample when the effective sample size falls below this fraction of
/// the particles (the usual choice: rare enough to keep the paths diverse,
/// often enough that the weights never collapse onto a handful).
const RESAMPLE_BELOW_ESS_FRACTION: f64 = 0.5;

/// Most particles per frame: memory is about 80 bytes per particle and
/// thread, the time linear in the count.
pub(crate) const MAX_PARTICLES: usize = 10_000_000;

/// The likelihood localiser's parameters (manifest `likelihood: {...}`).
///
/// ```yaml
/// likelihood: {particles: 20000}                             # D and N_qd of the dataset
/// likelihood: {diffusion_um2_s: {uniform: [0.75, 1.75]}}     # D unknown: a prior
/// likelihood: {brightness: {uniform: [5, 10]}}                # N_qd unknown: a prior
/// likelihood: {max_candidates: 3}                            # a ranked list of 3 guesses
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LikelihoodParams {
    /// Particles per frame.
    pub particles: usize,
    /// The diffusion coefficient the filter assumes, µm²/s: a number (D
    /// known), `{uniform: [LOW, HIGH]}` (a prior, drawn per particle, so D
    /// is marginalised), or absent: the microscope's own (in a manifest,
    /// the evaluated dataset's `diffusion_um2_s`).
    pub diffusion_um2_s: Option<Distribution>,
    /// N_qd the filter assumes: a number, `{uniform: [LOW, HIGH]}` (a
    /// prior, drawn per particle, so N_qd is marginalised), or absent: the
    /// microscope's own (a distribution there is marginalised the same way).
    pub brightness: Option<Distribution>,
    /// The score is the posterior mass within this distance (px) of the
    /// estimate.
    pub score_radius_px: f64,
    /// Guesses per frame. 1 (the default): the posterior mean, scored by
    /// `score_radius_px`, as always. More: a ranked list from the greedy
    /// disc cover of the centroid's posterior ([`candidates`]), each guess
    /// scored by the posterior mass it newly covers, ranked in
    /// [`Prediction::candidate`]; the list stops early where a further disc
    /// would cover less than [`candidates::MASS_FLOOR`]. Left out of the
    /// serialised settings when 1, so the detector's content keys stand.
    #[serde(
        default = "crate::detect::candidates::one_candidate",
        skip_serializing_if = "crate::detect::candidates::is_one_candidate"
    )]
    pub max_candidates: usize,
    /// Radius (px) of the cover's discs (> 0): the ε the list is placed
    /// for. Used only with `max_candidates` > 1; left out of the serialised
    /// settings when 1.
    #[serde(
        default = "crate::detect::candidates::unit_radius",
        skip_serializing_if = "crate::detect::candidates::is_unit_radius"
    )]
    pub candidate_radius_px: f64,
}

impl Default for LikelihoodParams {
    fn default() -> Self {
        Self {
            particles: 20_000,
            diffusion_um2_s: None,
            brightness: None,
            score_radius_px: 1.0,
            max_candidates: 1,
            candidate_radius_px: 1.0,
        }
    }
}

impl LikelihoodParams {
    /// Checks every parameter, naming the one at fault.
    pub fn validate(&self) -> Result<(), FieldError> {
        if self.particles < 2 || self.particles > MAX_PARTICLES {
            return Err(FieldError::new(
                "particles",
                format!(
                    "must be between 2 and {MAX_PARTICLES}, got {}",
                    self.particles
                ),
            ));
        }
        if let Some(diffusion) = &self.diffusion_um2_s {
            diffusion.validate("diffusion_um2_s", true)?;
        }
        if let Some(brightness) = &self.brightness {
            brightness.validate("brightness", true)?;
        }
        require_positive("score_radius_px", self.score_radius_px)?;
        if !(1..=MAX_CANDIDATES).contains(&self.max_candidates) {
            return Err(FieldError::new(
                "max_candidates",
                format!(
                    "must be between 1 and {MAX_CANDIDATES}, got {}",
                    self.max_candidates
                ),
            ));
        }
        require_positive("candidate_radius_px", self.candidate_radius_px)?;
        Ok(())
    }

    /// The microscope the filter assumes: `microscope` with this detector's
    /// diffusion coefficient and brightness where it sets them. Its
    /// background is the microscope's: a distribution there is a prior the
    /// filter marginalises (drawn per particle).
    pub fn assumed_microscope(&self, microscope: &SimParams) -> SimParams {
        SimParams {
            diffusion_um2_s: self.diffusion_um2_s.unwrap_or(microscope.diffusion_um2_s),
            brightness: self.brightness.unwrap_or(microscope.brightness),
            ..microscope.clone()
        }
    }

    /// Why the filter cannot model frames of `microscope`, if it cannot: it
    /// assumes Poisson counts.
    pub fn check_microscope(&self, microscope: &SimParams) -> Result<(), FieldError> {
        if let DetectorNoise::Pmt { .. } = microscope.detector_noise {
            return Err(FieldError::new(
                "detector_noise",
                "the likelihood detector models Poisson counts only, not a PMT's excess noise",
            ));
        }
        Ok(())
    }
}

/// The filter for one microscope, shared by every frame.
struct Filter<'a> {
    scan: ScanModel,
    microscope: SimParams,
    settings: &'a LikelihoodParams,
    seed: u64,
}

/// The particles of one frame, one entry per particle in each vector, and
/// the buffers resampling copies into (reused from frame to frame).
#[derive(Default)]
struct Particles {
    /// Position, µm.
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    /// Sum of the positions over the samples so far, µm.
    sum_x: Vec<f64>,
    sum_y: Vec<f64>,
    /// Brownian step standard deviations (µm): along a row, across a retrace.
    step_sd: Vec<f64>,
    retrace_sd: Vec<f64>,
    /// The particle's N_qd over the scan model's; empty when N_qd is fixed
    /// (the model's own).
    brightness_scale: Vec<f64>,
    /// The particle's N_bkg; empty when the background is fixed.
    background: Vec<f64>,
    /// Expected signal photons of the current pixel so far.
    signal: Vec<f64>,
    /// Importance weights, relative (rescaled whenever they are summed).
    weight: Vec<f64>,
    /// Resampling's destination, swapped with the vectors above.
    spare: Vec<Vec<f64>>,
    /// Bulk random bits of one sample's Brownian steps.
    bits: Vec<u32>,
}

impl Particles {
    /// The per-particle vectors resampling copies (everything but the
    /// weights and the pixel accumulator, which it resets); the photometry
    /// vectors are empty, and left so, when their parameter is fixed.
    fn carried(&mut self) -> [&mut Vec<f64>; 9] {
        [
            &mut self.x,
            &mut self.y,
            &mut self.z,
            &mut self.sum_x,
            &mut self.sum_y,
            &mut self.step_sd,
            &mut self.retrace_sd,
            &mut self.brightness_scale,
            &mut self.background,
        ]
    }

    /// Systematic resampling: `n` ancestors at the points `(u + j) / n` of
    /// the weights' cumulative distribution, one uniform `u` per resampling.
    /// `total` is the weights' sum.
    fn resample(&mut self, rng: &mut ChaCha8Rng, total: f64) {
        let n = self.weight.len();
        let step = total / n as f64;
        let mut point = step * rng.random::<f64>();
        let mut ancestors = Vec::with_capacity(n);
        let mut cumulative = 0.0;
        for (index, weight) in self.weight.iter().enumerate() {
            cumulative += weight;
            while point < cumulative && ancestors.len() < n {
                ancestors.push(index);
                point += step;
            }
        }
        // Rounding can leave the last points just beyond the total.
        while ancestors.len() < n {
            ancestors.push(n - 1);
        }
        let mut spare = std::mem::take(&mut self.spare);
        spare.resize_with(9, Vec::new);
        for (source, destination) in self.carried().into_iter().zip(spare.iter_mut()) {
            if source.is_empty() {
                continue;
            }
            destination.clear();
            destination.extend(ancestors.iter().map(|&a| source[a]));
            std::mem::swap(source, destination);
        }
        self.spare = spare;
        self.weight.fill(1.0);
    }
}

impl Filter<'_> {
    /// Draws the particles of a frame from the prior: start position uniform
    /// over the start ranges, depth from `z_start`, D from the assumed
    /// diffusion coefficient, then N_qd and N_bkg where they are
    /// distributions (one draw each per particle; a fixed parameter draws
    /// nothing, so such filters make the predictions they always made).
    fn initialise(&self, particles: &mut Particles, rng: &mut ChaCha8Rng) {
        let n = self.settings.particles;
        let ((x_low, x_high), (y_low, y_high)) = self.scan.start_ranges_px();
        let p = particles;
        for v in [
            &mut p.x,
            &mut p.y,
            &mut p.z,
            &mut p.sum_x,
            &mut p.sum_y,
            &mut p.step_sd,
            &mut p.retrace_sd,
            &mut p.brightness_scale,
            &mut p.background,
            &mut p.signal,
            &mut p.weight,
        ] {
            v.clear();
        }
        let model_brightness = self.microscope.brightness.bounds().1;
        for _ in 0..n {
            let x = x_low + (x_high - x_low) * rng.random::<f64>();
            let y = y_low + (y_high - y_low) * rng.random::<f64>();
            let z = self.microscope.z_start.sample(rng);
            let diffusion = self.microscope.diffusion_um2_s.sample(rng);
            let (step_sd, retrace_sd) = self.scan.step_sds(diffusion);
            p.x.push(self.scan.px_to_um(x));
            p.y.push(self.scan.px_to_um(y));
            p.z.push(z);
            p.step_sd.push(step_sd);
            p.retrace_sd.push(retrace_sd);
            if is_spread(&self.microscope.brightness) {
                let brightness = self.microscope.brightness.sample(rng);
                // A spread distribution has a positive upper bound.
                p.brightness_scale.push(brightness / model_brightness);
            }
            if is_spread(&self.microscope.background) {
                p.background.push(self.microscope.background.sample(rng));
            }
        }
        p.sum_x.resize(n, 0.0);
        p.sum_y.resize(n, 0.0);
        p.signal.resize(n, 0.0);
        p.weight.resize(n, 1.0);
    }

    /// Runs the filter over frame `index` with counts `counts`
    /// (row-major), leaving the weighted particles of its posterior in
    /// `particles`.
    fn filter_frame(&self, index: usize, counts: &[u32], particles: &mut Particles) {
        let mut rng = frame_rng(self.seed, index);
        self.initialise(particles, &mut rng);
        let microscope = &self.microscope;
        let (width, height) = (microscope.width, microscope.height);
        let substeps = microscope.substeps as usize;
        let background = self.pixel_background();
        let (_, high) = microscope.diffusion_um2_s.bounds();
        let moving = high > 0.0;
        let n = particles.weight.len();
        for row in 0..height {
            let beam_y = self.scan.beam_y_um(row);
            for (k, &beam_x) in self.scan.beam_x_um().iter().enumerate() {
                let p = &mut *particles;
                // No step before the very first sample, as in the simulator.
                if moving && (row, k) != (0, 0) {
                    p.bits.resize(3 * n, 0);
                    rng.fill(&mut p.bits[..]);
                    let sds = if k == 0 { &p.retrace_sd } else { &p.step_sd };
                    let positions = p.x.iter_mut().zip(&mut p.y).zip(&mut p.z);
                    for (((x, y), z), (bits, sd)) in positions.zip(p.bits.chunks_exact(3).zip(sds))
                    {
                        *x += sd * standard_normal_from_bits(bits[0], &mut rng);
                        *y += sd * standard_normal_from_bits(bits[1], &mut rng);
                        *z += sd * standard_normal_from_bits(bits[2], &mut rng);
                    }
                }
                kernels::accumulate_sample(&self.scan, beam_x, beam_y, p);
                if (k + 1) % substeps == 0 {
                    let count = f64::from(counts[row * width + k / substeps]);
                    self.weigh_pixel(p, count, background, &mut rng);
                }
            }
        }
    }

    /// How the background of a pixel is weighed: one known N_bkg for every
    /// particle, or each particle's own against a common reference.
    fn pixel_background(&self) -> PixelBackground {
        let (low, high) = self.microscope.background.bounds();
        if is_spread(&self.microscope.background) {
            PixelBackground::PerParticle {
                reference: 0.5 * (low + high),
            }
        } else {
            PixelBackground::Known(low)
        }
    }

    /// Multiplies each particle's weight by the likelihood of a pixel's
    /// `count` given its expected photons (relative to a pixel of the
    /// reference background without signal, which changes no ratio), resets
    /// the pixel accumulators, and resamples when the effective sample size
    /// is low.
    fn weigh_pixel(
        &self,
        p: &mut Particles,
        count: f64,
        background: PixelBackground,
        rng: &mut ChaCha8Rng,
    ) {
        match background {
            PixelBackground::Known(background) if background > 0.0 => {
                kernels::weigh_known_background(p, count, background);
            }
            PixelBackground::Known(_) => weigh_without_background(p, count),
            PixelBackground::PerParticle { reference } => {
                kernels::weigh_own_background(p, count, reference);
            }
        }
        let (total, total_squares) = kernels::sum_and_sum_of_squares(&p.weight);
        if !(total > 0.0 && total.is_finite() && total_squares.is_finite()) {
            // No particle explains this pixel (only possible without
            // background): the pixel is ignored rather than the frame lost.
            p.weight.fill(1.0);
            return;
        }
        let n = p.weight.len() as f64;
        if total * total < RESAMPLE_BELOW_ESS_FRACTION * n * total_squares {
            p.resample(rng, total);
        } else if !(1e-100..=1e100).contains(&total) {
            let scale = 1.0 / total;
            p.weight.iter_mut().for_each(|w| *w *= scale);
        }
    }

    /// Each particle's trajectory centroid (TrackPy pixels) and its
    /// importance weight (relative: they need not sum to 1).
    fn weighted_centroids(&self, p: &Particles) -> Vec<(f64, f64, f64)> {
        let samples = (self.microscope.height * self.scan.beam_x_um().len()) as f64;
        p.sum_x
            .iter()
            .zip(&p.sum_y)
            .zip(&p.weight)
            .map(|((sx, sy), &w)| {
                (
                    self.scan.um_to_px(sx / samples),
                    self.scan.um_to_px(sy / samples),
                    w,
                )
            })
            .collect()
    }

    /// The predictions of frame `frame` from its filtered particles: the
    /// posterior mean of the trajectory centroid and the posterior mass
    /// within the score radius of it; with `max_candidates` > 1 the greedy
    /// disc cover of the centroids instead, ranked.
    fn estimate(&self, frame: usize, p: &Particles) -> Vec<Prediction> {
        let weighted = self.weighted_centroids(p);
        if self.settings.max_candidates > 1 {
            let list = candidates::greedy_disc_cover(
                &weighted,
                self.settings.max_candidates,
                self.settings.candidate_radius_px,
                CentreSearch::CellsWithMeanShift,
            );
            return (1..)
                .zip(list)
                .map(|(rank, c)| Prediction {
                    candidate: Some(rank),
                    ..Prediction::new(frame, c.x, c.y, c.mass)
                })
                .collect();
        }
        let total: f64 = weighted.iter().map(|&(_, _, w)| w).sum();
        let (mut x, mut y) = (0.0, 0.0);
        for &(cx, cy, w) in &weighted {
            x += w * cx;
            y += w * cy;
        }
        x /= total;
        y /= total;
        let radius2 = self.settings.score_radius_px * self.settings.score_radius_px;
        let within: f64 = weighted
            .iter()
            .filter(|(cx, cy, _)| (cx - x).powi(2) + (cy - y).powi(2) <= radius2)
            .map(|&(_, _, w)| w)
            .sum();
        vec![Prediction::new(frame, x, y, within / total)]
    }
}

/// The background a pixel's likelihood is computed with.
#[derive(Debug, Clone, Copy)]
enum PixelBackground {
    /// The same N_bkg for every particle.
    Known(f64),
    /// Each particle's own N_bkg (`Particles::background`); likelihoods are
    /// relative to Poisson(`reference`), a positive constant.
    PerParticle { reference: f64 },
}

/// Whether a per-frame parameter can take more than one value, so the
/// filter draws it per particle and marginalises it.
fn is_spread(distribution: &Distribution) -> bool {
    let (low, high) = distribution.bounds();
    low < high
}

/// Multiplies each particle's weight by the Poisson likelihood of `count`
/// photons given its signal when the pixel has no background (only a
/// microscope without background: rare, so not vectorised), and resets the
/// pixel accumulators. No light expected yet photons counted is impossible:
/// weight 0.
fn weigh_without_background(p: &mut Particles, count: f64) {
    kernels::scale_signals(p);
    for (weight, signal) in p.weight.iter_mut().zip(&mut p.signal) {
        let s = std::mem::take(signal);
        if s > 0.0 {
            *weight *= (count * s.ln() - s).exp();
        } else if count > 0.0 {
            *weight = 0.0;
        }
    }
}

/// Localises the one QD of every frame of `frames`: one prediction per
/// frame, in frame order, `(x, y)` the posterior mean of its trajectory
/// centroid (TrackPy pixels), score the posterior mass within
/// `settings.score_radius_px` of it; with `settings.max_candidates` > 1,
/// per frame in frame order a ranked list of up to that many guesses
/// (`candidate` 1, 2, ...), each scored by the posterior mass it newly
/// covers.
///
/// `microscope` is the microscope the frames were taken with (its frame
/// size must be theirs); `settings` may replace its diffusion coefficient
/// and brightness. D, N_qd and N_bkg given as distributions are priors,
/// drawn per particle and so marginalised. Frame `i` draws from ChaCha8
/// stream `i` of `seed`.
/// `progress` is advanced by one per finished frame.
pub fn locate_stack(
    frames: &FrameStack,
    microscope: &SimParams,
    settings: &LikelihoodParams,
    seed: u64,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<Prediction>> {
    let all: Vec<usize> = (0..frames.n).collect();
    locate_frames(frames, &all, microscope, settings, seed, progress)
}

/// [`locate_stack`] for the frames `which` of `frames` only (indices below
/// `frames.n`), their predictions in the order given. Frame `i` still
/// draws from stream `i` of `seed`, so its prediction is the one
/// `locate_stack` gives it: leaving frames out changes no other frame's.
pub fn locate_frames(
    frames: &FrameStack,
    which: &[usize],
    microscope: &SimParams,
    settings: &LikelihoodParams,
    seed: u64,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<Prediction>> {
    let filter = Filter::checked(frames, which, microscope, settings, seed)?;
    let per_frame = filter.each_frame(frames, which, progress, |index, particles| {
        filter.estimate(index, particles)
    });
    let predictions: Vec<Prediction> = per_frame.into_iter().flatten().collect();
    refuse_non_finite(&predictions)?;
    Ok(predictions)
}

/// The filter's whole posterior of the trajectory centroid for the frames
/// `which` of `frames`, in the order given: per frame, each particle's
/// centroid `(x, y)` in TrackPy pixels and its weight, the weights summing
/// to 1. The same filter as [`locate_frames`] with the same `settings`
/// and `seed` (its predictions are summaries of these points), for callers
/// that need the posterior's shape, such as a network learning it.
pub fn posterior_clouds(
    frames: &FrameStack,
    which: &[usize],
    microscope: &SimParams,
    settings: &LikelihoodParams,
    seed: u64,
    progress: &ProgressBar,
) -> anyhow::Result<Vec<Vec<(f64, f64, f64)>>> {
    let filter = Filter::checked(frames, which, microscope, settings, seed)?;
    filter
        .each_frame(frames, which, progress, |index, particles| {
            let mut cloud = filter.weighted_centroids(particles);
            let total: f64 = cloud.iter().map(|point| point.2).sum();
            let finite = cloud
                .iter()
                .all(|&(x, y, w)| x.is_finite() && y.is_finite() && w.is_finite());
            if !(finite && total > 0.0 && total.is_finite()) {
                return Err(input_error(format!(
                    "likelihood: frame {index}: the posterior is not finite; the microscope's parameters are beyond what the filter can follow"
                )));
            }
            cloud.iter_mut().for_each(|point| point.2 /= total);
            Ok(cloud)
        })
        .into_iter()
        .collect()
}

impl<'a> Filter<'a> {
    /// The filter of `settings` under `microscope` (as `settings` assume
    /// it), once both are checked and the frames `which` of `frames` are
    /// known to be ones it can model.
    fn checked(
        frames: &FrameStack,
        which: &[usize],
        microscope: &SimParams,
        settings: &'a LikelihoodParams,
        seed: u64,
    ) -> anyhow::Result<Self> {
        settings
            .validate()
            .map_err(|e| input_error(format!("invalid likelihood parameter: {e}")))?;
        let microscope = settings.assumed_microscope(microscope);
        microscope.validate().map_err(|e| {
            input_error(format!(
                "invalid microscope for the likelihood detector: {e}"
            ))
        })?;
        settings
            .check_microscope(&microscope)
            .map_err(|e| input_error(e.to_string()))?;
        if (frames.height, frames.width) != (microscope.height, microscope.width) {
            return Err(input_error(format!(
                "the likelihood detector models {}×{} frames, got {}×{}",
                microscope.height, microscope.width, frames.height, frames.width
            )));
        }
        if let Some(&index) = which.iter().find(|&&index| index >= frames.n) {
            anyhow::bail!("frame {index} asked of a stack of {} frames", frames.n);
        }
        Ok(Filter {
            scan: ScanModel::new(&microscope),
            microscope,
            settings,
            seed,
        })
    }

    /// Runs the filter over each of the frames `which` of `frames` in
    /// parallel (each frame on its own stream, so the thread count changes
    /// nothing) and gives `summary(index, particles)` of each, in the order
    /// of `which`; `progress` advances by one per frame.
    fn each_frame<T: Send>(
        &self,
        frames: &FrameStack,
        which: &[usize],
        progress: &ProgressBar,
        summary: impl Fn(usize, &Particles) -> T + Sync,
    ) -> Vec<T> {
        which
            .par_iter()
            .map_init(Particles::default, |particles, &index| {
                self.filter_frame(index, frames.frame(index), particles);
                progress.inc(1);
                summary(index, particles)
            })
            .collect()
    }
}

/// The last guard before predictions are written: every position and
/// score must be a finite number. The microscope's checks keep the
/// filter's particles within reach of the field, so this refusal means a
/// microscope they let through by mistake; it names the frame rather than
/// writing NaN.
fn refuse_non_finite(predictions: &[Prediction]) -> anyhow::Result<()> {
    match predictions
        .iter()
        .find(|p| !(p.x.is_finite() && p.y.is_finite() && p.score.is_finite()))
    {
        Some(p) => Err(input_error(format!(
            "likelihood: frame {}: the estimate is not a finite number (x {}, y {}, score {}); the microscope's parameters are beyond what the filter can follow",
            p.frame, p.x, p.y, p.score
        ))),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn estimates_that_are_not_finite_are_refused_naming_the_frame() {
        let good = Prediction::new(3, 1.0, 2.0, 0.5);
        assert!(refuse_non_finite(&[good]).is_ok());
        for bad in [
            Prediction::new(4, f64::NAN, 2.0, 0.5),
            Prediction::new(4, 1.0, f64::INFINITY, 0.5),
            Prediction::new(4, 1.0, 2.0, f64::NAN),
        ] {
            let error = refuse_non_finite(&[good, bad]).unwrap_err();
            assert!(error.to_string().contains("frame 4"), "{error}");
            assert_eq!(crate::error::exit_code(&error), 2);
        }
    }

    /// A small microscope: frames of `side × side` pixels, QDs starting at
    /// least 3 px from the border.
    fn small(side: usize, diffusion: f64, brightness: f64) -> SimParams {
        SimParams {
            height: side,
            width: side,
            margin_px: 3.0,
            brightness: brightness.into(),
            diffusion_um2_s: Distribution::Fixed(diffusion),
            ..SimParams::default()
        }
    }

    /// `frames` frames of `microscope` (seed 7) and the filter's predictions
    /// for them with `particles` particles (seed 3) under the same model.
    fn simulate_and_locate(
        microscope: &SimParams,
        frames: usize,
        particles: usize,
    ) -> (crate::types::Dataset, Vec<Prediction>) {
        let hidden = crate::progress::hidden();
        let dataset = crate::sim::simulate(microscope, 7, 0..frames, &hidden).unwrap();
        let predictions = locate_stack(
            &dataset.frames,
            microscope,
            &settings(particles),
            3,
            &hidden,
        )
        .unwrap();
        (dataset, predictions)
    }

    fn settings(particles: usize) -> LikelihoodParams {
        LikelihoodParams {
            particles,
            ..LikelihoodParams::default()
        }
    }

    #[test]
    fn the_likelihood_ratio_is_the_poisson_probabilities_ratio() {
        let poisson =
            |k: u32, mean: f64| (1..=k).fold((-mean).exp(), |p, i| p * mean / f64::from(i));
        for (count, signal, background) in
            [(0, 0.5, 8.4), (3, 2.0, 8.4), (17, 7.4, 8.4), (2, 1.5, 0.0)]
        {
            let expected = if background > 0.0 {
                poisson(count, background + signal) / poisson(count, background)
            } else {
                // Without background: the probability times count!.
                poisson(count, signal) * (1..=count).map(f64::from).product::<f64>()
            };
            let mut p = Particles {
                weight: vec![1.0],
                signal: vec![signal],
                ..Particles::default()
            };
            if background > 0.0 {
                kernels::weigh_known_background(&mut p, f64::from(count), background);
            } else {
                weigh_without_background(&mut p, f64::from(count));
            }
            let got = p.weight[0];
            assert!(
                (got - expected).abs() <= 1e-12 * expected,
                "{got} vs {expected}"
            );
            assert_eq!(p.signal[0], 0.0, "the pixel accumulator is reset");
            // Each particle's own background, against a reference one.
            let (own, reference) = (background + 1.0, 6.0);
            let mut p = Particles {
                weight: vec![1.0],
                signal: vec![signal],
                background: vec![own],
                ..Particles::default()
            };
            kernels::weigh_own_background(&mut p, f64::from(count), reference);
            let expected = poisson(count, own + signal) / poisson(count, reference);
            assert!(
                (p.weight[0] - expected).abs() <= 1e-12 * expected,
                "{} vs {expected}",
                p.weight[0]
            );
        }
        // No light expected, yet photons counted: impossible.
        let mut p = Particles {
            weight: vec![1.0, 1.0],
            signal: vec![0.0, 0.0],
            background: vec![0.0, 0.0],
            ..Particles::default()
        };
        kernels::weigh_own_background(&mut p, 2.0, 6.0);
        assert_eq!(p.weight[0], 0.0);
        let mut p = Particles {
            weight: vec![1.0],
            signal: vec![0.0],
            ..Particles::default()
        };
        weigh_without_background(&mut p, 2.0);
        assert_eq!(p.weight[0], 0.0);
    }

    #[test]
    fn weight_sums_are_those_of_the_weights_in_any_length() {
        for n in [0usize, 1, 3, 4, 5, 9, 500] {
            let weights: Vec<f64> = (0..n).map(|i| 0.5 + i as f64).collect();
            let (sum, squares) = kernels::sum_and_sum_of_squares(&weights);
            let exact: f64 = weights.iter().sum();
            let exact_squares: f64 = weights.iter().map(|w| w * w).sum();
            assert!((sum - exact).abs() <= 1e-12 * exact.max(1.0), "{n}");
            assert!(
                (squares - exact_squares).abs() <= 1e-12 * exact_squares.max(1.0),
                "{n}"
            );
        }
    }

    #[test]
    fn drawn_brightness_and_background_weigh_each_particle_by_its_own() {
        let fixed = small(12, 1.0, 7.0);
        let settings = settings(2);
        let filter = |microscope: &SimParams| Filter {
            scan: ScanModel::new(microscope),
            microscope: microscope.clone(),
            settings: &settings,
            seed: 0,
        };
        // Fixed photometry: no per-particle values, nothing extra drawn.
        let mut p = Particles::default();
        let mut rng = frame_rng(0, 0);
        filter(&fixed).initialise(&mut p, &mut rng);
        assert!(p.brightness_scale.is_empty() && p.background.is_empty());
        // Distributions: one value per particle, within the prior.
        let drawn = SimParams {
            brightness: "uniform:5,20".parse().unwrap(),
            background: "uniform:2,10".parse().unwrap(),
            ..fixed
        };
        let filter = filter(&drawn);
        filter.initialise(&mut p, &mut rng);
        assert_eq!((p.brightness_scale.len(), p.background.len()), (2, 2));
        assert!(p.brightness_scale.iter().all(|s| (0.25..=1.0).contains(s)));
        assert!(p.background.iter().all(|b| (2.0..=10.0).contains(b)));
        // Same position (signal 8 photons at the model's N_qd = 20), one
        // particle at N_qd 20 on N_bkg 2, the other at N_qd 5 on N_bkg 10:
        // their weights are the Poisson probabilities of the count under
        // 2 + 8 and 10 + 2 expected photons.
        p.brightness_scale = vec![1.0, 0.25];
        p.background = vec![2.0, 10.0];
        p.signal = vec![8.0, 8.0];
        p.weight = vec![1.0, 1.0];
        let poisson =
            |k: u32, mean: f64| (1..=k).fold((-mean).exp(), |p, i| p * mean / f64::from(i));
        filter.weigh_pixel(&mut p, 14.0, filter.pixel_background(), &mut rng);
        let expected = poisson(14, 10.0) / poisson(14, 12.0);
        let got = p.weight[0] / p.weight[1];
        assert!(
            (got - expected).abs() <= 1e-12 * expected,
            "{got} vs {expected}"
        );
        assert_eq!(p.signal, [0.0, 0.0]);
        // No expected light, yet photons: impossible for that particle only.
        p.background = vec![0.0, 3.0];
        p.weight = vec![1.0, 1.0];
        filter.weigh_pixel(&mut p, 2.0, filter.pixel_background(), &mut rng);
        assert_eq!(p.weight[0], 0.0);
        assert!(p.weight[1] > 0.0);
    }

    #[test]
    fn a_filter_marginalising_photometry_localises_frames_of_drawn_photometry() {
        // Static QDs in frames of N_qd uniform on [10, 30] and N_bkg on
        // [4, 12]; the filter is given the same priors.
        let microscope = SimParams {
            brightness: "uniform:10,30".parse().unwrap(),
            background: "uniform:4,12".parse().unwrap(),
            ..small(14, 0.0, 7.0)
        };
        let (dataset, predictions) = simulate_and_locate(&microscope, 8, 2000);
        // End to end (the test above checks the per-particle weights
        // exactly): at N_qd ≥ 10 the Cramér–Rao floor here is below 0.3 px
        // per axis, so an RMSE of 1 px over 8 frames is a wide margin for a
        // working filter, and one whose weights went wrong misses it.
        let mse = predictions
            .iter()
            .zip(&dataset.truth)
            .map(|(p, t)| (p.x - t.x).powi(2) + (p.y - t.y).powi(2))
            .sum::<f64>()
            / predictions.len() as f64;
        assert!(mse.sqrt() < 1.0, "RMSE {} px", mse.sqrt());
    }

    #[test]
    fn predictions_do_not_depend_on_the_thread_count() {
        let microscope = small(12, 1.0, 20.0);
        let dataset =
            crate::sim::simulate(&microscope, 4, 0..5, &crate::progress::hidden()).unwrap();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    locate_stack(
                        &dataset.frames,
                        &microscope,
                        &settings(300),
                        9,
                        &crate::progress::hidden(),
                    )
                    .unwrap()
                })
        };
        let one = run(1);
        assert_eq!(one.len(), 5);
        assert_eq!(
            one.iter().map(|p| p.frame).collect::<Vec<_>>(),
            [0, 1, 2, 3, 4]
        );
        assert_eq!(one, run(3));
        // The seed matters, and each frame has its own stream.
        let other_seed = locate_stack(
            &dataset.frames,
            &microscope,
            &settings(300),
            10,
            &crate::progress::hidden(),
        )
        .unwrap();
        assert_ne!(one, other_seed);
        // Some frames only: each the prediction the whole stack gives it.
        let some = locate_frames(
            &dataset.frames,
            &[3, 1],
            &microscope,
            &settings(300),
            9,
            &crate::progress::hidden(),
        )
        .unwrap();
        assert_eq!(some, [one[3], one[1]]);
        let beyond = locate_frames(
            &dataset.frames,
            &[5],
            &microscope,
            &settings(300),
            9,
            &crate::progress::hidden(),
        );
        assert!(beyond.is_err());
    }

    #[test]
    fn a_list_of_guesses_is_ranked_and_one_guess_keeps_its_settings_and_output() {
        // At the defaults the new parameters are not serialised, so the
        // detector's content keys stand; set, they are.
        let json = serde_json::to_value(settings(500)).unwrap();
        assert!(json.get("max_candidates").is_none(), "{json}");
        assert!(json.get("candidate_radius_px").is_none(), "{json}");
        let listing = LikelihoodParams {
            max_candidates: 3,
            candidate_radius_px: 0.75,
            ..settings(500)
        };
        let json = serde_json::to_value(&listing).unwrap();
        assert_eq!(
            (
                json["max_candidates"].as_u64(),
                json["candidate_radius_px"].as_f64()
            ),
            (Some(3), Some(0.75))
        );
        let back: LikelihoodParams = serde_json::from_value(json).unwrap();
        assert_eq!(back, listing);
        // A fast QD (a spread posterior) and a static one (a tight one).
        let hidden = crate::progress::hidden();
        for diffusion in [4.0, 0.0] {
            let microscope = small(14, diffusion, 20.0);
            let dataset = crate::sim::simulate(&microscope, 5, 0..4, &hidden).unwrap();
            let single =
                locate_stack(&dataset.frames, &microscope, &settings(500), 3, &hidden).unwrap();
            assert_eq!(single.len(), 4);
            assert!(single.iter().all(|p| p.candidate.is_none()));
            let list = locate_stack(&dataset.frames, &microscope, &listing, 3, &hidden).unwrap();
            for frame in 0..4 {
                let guesses: Vec<&Prediction> = list.iter().filter(|p| p.frame == frame).collect();
                assert!((1..=3).contains(&guesses.len()), "{guesses:?}");
                let ranks: Vec<u32> = guesses.iter().map(|p| p.candidate.unwrap()).collect();
                assert_eq!(ranks, (1..=guesses.len() as u32).collect::<Vec<_>>());
                // Disjoint discs' masses: at most the whole posterior.
                let covered: f64 = guesses.iter().map(|p| p.score).sum();
                assert!(covered <= 1.0 + 1e-9, "{guesses:?}");
                assert!(guesses.iter().all(|p| p.score > 0.0));
            }
            // The list is deterministic and nested: 2 guesses are the first
            // 2 of 3.
            let two = LikelihoodParams {
                max_candidates: 2,
                ..listing.clone()
            };
            let first_two = locate_stack(&dataset.frames, &microscope, &two, 3, &hidden).unwrap();
            let expected: Vec<Prediction> = list
                .iter()
                .filter(|p| p.candidate.unwrap() <= 2)
                .copied()
                .collect();
            assert_eq!(first_two, expected);
        }
    }

    #[test]
    fn a_fast_qd_scores_lower_than_a_static_one() {
        // The score is the posterior mass within 1 px of the estimate: a
        // static QD's centroid is pinned down by the frame, a fast one's
        // path between the rows that see it is not.
        let mean_score = |diffusion: f64| {
            let (_, predictions) = simulate_and_locate(&small(14, diffusion, 20.0), 6, 1000);
            predictions.iter().map(|p| p.score).sum::<f64>() / predictions.len() as f64
        };
        let (still, fast) = (mean_score(0.0), mean_score(8.0));
        assert!(still > 0.9, "static QD: mean score {still}");
        assert!(fast < 0.5 * still, "fast {fast} against static {still}");
    }

    #[test]
    fn parameters_and_frames_that_cannot_be_modelled_are_refused() {
        let microscope = small(12, 1.0, 7.0);
        let frames = FrameStack::zeros(1, 12, 12);
        let hidden = crate::progress::hidden();
        for (bad, field) in [
            (settings(1), "particles"),
            (
                LikelihoodParams {
                    score_radius_px: 0.0,
                    ..settings(10)
                },
                "score_radius_px",
            ),
            (
                LikelihoodParams {
                    max_candidates: 0,
                    ..settings(10)
                },
                "max_candidates",
            ),
            (
                LikelihoodParams {
                    max_candidates: MAX_CANDIDATES + 1,
                    ..settings(10)
                },
                "max_candidates",
            ),
            (
                LikelihoodParams {
                    candidate_radius_px: -1.0,
                    ..settings(10)
                },
                "candidate_radius_px",
            ),
            (
                LikelihoodParams {
                    diffusion_um2_s: Some(Distribution::Fixed(-1.0)),
                    ..settings(10)
                },
                "diffusion_um2_s",
            ),
        ] {
            let error = bad.validate().unwrap_err();
            assert_eq!(error.field(), field);
            let error = locate_stack(&frames, &microscope, &bad, 0, &hidden).unwrap_err();
            assert_eq!(crate::error::exit_code(&error), 2, "{error}");
        }
        let error = locate_stack(
            &FrameStack::zeros(1, 12, 13),
            &microscope,
            &settings(10),
            0,
            &hidden,
        )
        .unwrap_err();
        assert!(
            error.to_string().contains("12×12 frames, got 12×13"),
            "{error}"
        );
        let pmt = SimParams {
            detector_noise: DetectorNoise::Pmt {
                excess_noise_factor: 2.0,
            },
            ..microscope.clone()
        };
        let error = locate_stack(&frames, &pmt, &settings(10), 0, &hidden).unwrap_err();
        assert!(error.to_string().contains("Poisson counts only"), "{error}");
        // An empty frame still gets its one prediction, inside the field.
        let predictions = locate_stack(&frames, &microscope, &settings(50), 0, &hidden).unwrap();
        assert_eq!(predictions.len(), 1);
        assert!((-0.5..11.5).contains(&predictions[0].x));
        assert!((0.0..=1.0).contains(&predictions[0].score));
    }
}
