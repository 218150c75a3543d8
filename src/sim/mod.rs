//! The point-scanning two-photon microscope simulator (`docs/simulator.md`).
//!
//! The beam sweeps the frame row by row, each row left to right, dwelling
//! `dwell_us` on every pixel and taking `retrace_ms` to return to the start of
//! the next row. Meanwhile each QD does independent 3D Brownian motion. The
//! expected photon number of a pixel is the 3D Gaussian 2PM PSF evaluated at
//! the QD's position relative to the beam (averaged over `substeps` samples
//! within the dwell) plus the background; the recorded count is drawn from
//! the detector model.
//!
//! Coordinates: the simulation runs in µm with the beam at
//! `((c + 0.5)·a, (r + 0.5)·a, 0)`; ground truth is reported in TrackPy
//! pixel coordinates, `px = µm / a − 0.5` (`x` column, `y` row).
//!
//! Determinism: frame `i` of a dataset with seed `s` draws only from
//! ChaCha8 stream `i` of key `s`, in a fixed order (diffusion coefficient;
//! the number of emitters, the brightness N_qd and the background N_bkg,
//! each only when it is drawn from a distribution; then per emitter its
//! start x, y, z and its walk; then the detector noise pixel by pixel). A
//! fixed parameter draws nothing, so datasets made before a parameter could
//! be drawn keep their frames bit for bit. Frames are therefore identical
//! whatever the thread count and however a dataset is split into calls.

pub(crate) mod gaussian;
pub mod noise;
pub(crate) mod params;
pub mod recording;

use std::ops::Range;

use indicatif::ProgressBar;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

pub use params::{
    CountChoice, DetectorNoise, Distribution, EmitterCount, RandomDistribution, SimParams,
};

use crate::error::{FieldError, input_error};
use crate::types::{Dataset, FrameStack, TruthRow};
use gaussian::standard_normal_from_bits;
use noise::Detector;

/// Version of the simulator's output for given parameters and seed. Part of
/// every dataset's content key: bump it whenever a change alters any frame.
pub const GENERATOR_VERSION: &str = "scanloc-sim/1";

/// The per-dataset constants of the inner loop, computed once.
struct Precomputed {
    /// Beam x in µm for every sample of a row (`width · substeps` values).
    beam_x: Vec<f64>,
    inv_two_sigma_xy2: f64,
    inv_two_sigma_z2: f64,
    /// Squared lateral cut-off radius in µm² (infinite without cut-off).
    cutoff2: f64,
    dwell_s: f64,
    retrace_s: f64,
    /// PSF samples per pixel dwell.
    substeps: f64,
    /// The dataset's seed: frame `i` draws from stream `i` of it.
    seed: u64,
}

impl Precomputed {
    fn new(params: &SimParams, seed: u64) -> Self {
        let a = params.pixel_size_um;
        let s = params.substeps as usize;
        let beam_x = (0..params.width * s)
            .map(|k| {
                let column = (k / s) as f64;
                let sub = (k % s) as f64;
                (column + (sub + 0.5) / s as f64) * a
            })
            .collect();
        let cutoff2 = match params.psf_cutoff_sigma {
            Some(c) => (c * params.sigma_xy_um).powi(2),
            None => f64::INFINITY,
        };
        Self {
            beam_x,
            inv_two_sigma_xy2: 1.0 / (2.0 * params.sigma_xy_um * params.sigma_xy_um),
            inv_two_sigma_z2: 1.0 / (2.0 * params.sigma_z_um * params.sigma_z_um),
            cutoff2,
            dwell_s: params.dwell_us * 1e-6,
            retrace_s: params.retrace_ms * 1e-3,
            substeps: s as f64,
            seed,
        }
    }

    /// Standard deviations (µm, per axis) of the Brownian step between two
    /// consecutive samples of a row, and of the one step from the last
    /// sample of a row to the first of the next (retrace included), at
    /// diffusion coefficient `diffusion` µm²/s: N(0, 2·D·Δt) increments.
    fn step_sds(&self, diffusion: f64) -> (f64, f64) {
        let step_sd = (2.0 * diffusion * self.dwell_s / self.substeps).sqrt();
        let retrace_sd = (2.0 * diffusion * (self.dwell_s / self.substeps + self.retrace_s)).sqrt();
        (step_sd, retrace_sd)
    }

    /// The PSF amplitude per sample of a frame whose N_qd is `brightness`:
    /// `N_qd / (2π σxy²) / √(2π σz²) / substeps`.
    fn amplitude(&self, params: &SimParams, brightness: f64) -> f64 {
        params.psf_peak_at(brightness) / self.substeps
    }

    /// Expected photons one PSF sample adds to its pixel, for an emitter at
    /// lateral offset `(dx, dy)` µm from the beam and depth `z` µm, with
    /// amplitude `amplitude` ([`Precomputed::amplitude`]); 0 beyond the
    /// cut-off. The one place the scanned PSF is evaluated: the simulator
    /// and [`static_emitter_image`] both go through it.
    #[inline(always)]
    fn sample_photons(&self, amplitude: f64, dx: f64, dy: f64, z: f64) -> f64 {
        let dy2 = dy * dy;
        if dy2 > self.cutoff2 {
            return 0.0;
        }
        let (r2, exponent) = self.psf_terms(dx, dy, z);
        if r2 > self.cutoff2 {
            return 0.0;
        }
        amplitude * exponent.exp()
    }

    /// The squared lateral distance (µm²) of offset `(dx, dy)` µm and the
    /// scanned PSF's exponent there at depth `z` µm: within the cut-off a
    /// sample's photons are the amplitude times the exponent's exponential.
    #[inline(always)]
    fn psf_terms(&self, dx: f64, dy: f64, z: f64) -> (f64, f64) {
        let r2 = dx * dx + dy * dy;
        (
            r2,
            -(r2 * self.inv_two_sigma_xy2) - z * z * self.inv_two_sigma_z2,
        )
    }
}

/// The intervals (TrackPy pixels, `(low, high)`) a QD's start x and y are
/// drawn uniformly from: the field shrunk by `margin_px` on every side.
fn start_ranges_px(params: &SimParams) -> ((f64, f64), (f64, f64)) {
    let margin = params.margin_px;
    (
        (-0.5 + margin, params.width as f64 - 0.5 - margin),
        (-0.5 + margin, params.height as f64 - 0.5 - margin),
    )
}

/// The simulator's forward model one PSF sample at a time, for models that
/// follow a QD through a frame in scan order (the likelihood detector,
/// `docs/likelihood.md`): the same code the simulator renders frames with,
/// so the two cannot drift apart.
///
/// Positions are in µm as inside the simulator (the beam of pixel (r, c) at
/// `((c + 0.5)·a, (r + 0.5)·a, 0)`); [`ScanModel::um_to_px`] converts to
/// TrackPy pixels. Samples are counted along a row: `samples_per_row` =
/// `width · substeps`, sample `k` belongs to column `k / substeps`.
///
/// The model's N_qd is the largest `params.brightness` can take (the
/// value, when it is fixed); a model of frames of another N_qd scales
/// [`ScanModel::sample_photons_with`] by the ratio (photons are proportional to
/// N_qd).
pub(crate) struct ScanModel {
    pre: Precomputed,
    /// PSF amplitude per sample at the model's N_qd.
    amplitude: f64,
    pixel_size_um: f64,
    start_ranges_px: ((f64, f64), (f64, f64)),
}

impl ScanModel {
    /// The model of the microscope `params` (assumed valid).
    pub(crate) fn new(params: &SimParams) -> Self {
        let pre = Precomputed::new(params, 0);
        Self {
            amplitude: pre.amplitude(params, params.brightness.bounds().1),
            pre,
            pixel_size_um: params.pixel_size_um,
            start_ranges_px: start_ranges_px(params),
        }
    }

    /// The beam's x (µm) at every sample of a row.
    pub(crate) fn beam_x_um(&self) -> &[f64] {
        &self.pre.beam_x
    }

    /// The beam's y (µm) along row `row`.
    pub(crate) fn beam_y_um(&self, row: usize) -> f64 {
        (row as f64 + 0.5) * self.pixel_size_um
    }

    /// Expected photons one PSF sample adds to its pixel (already divided
    /// by `substeps`, so a pixel's signal is the sum over its samples), for
    /// a QD of the model's N_qd at lateral offset `(dx, dy)` µm from the
    /// beam and depth `z` µm: the simulator's PSF terms with the
    /// exponential supplied by the caller (a vectorisable one in the
    /// likelihood detector's inner loop), `amplitude · exp(exponent)` within
    /// the cut-off, exactly 0 beyond it, without a branch.
    #[inline(always)]
    pub(crate) fn sample_photons_with(
        &self,
        dx: f64,
        dy: f64,
        z: f64,
        exp: impl Fn(f64) -> f64,
    ) -> f64 {
        let (r2, exponent) = self.pre.psf_terms(dx, dy, z);
        let photons = self.amplitude * exp(exponent);
        if r2 <= self.pre.cutoff2 { photons } else { 0.0 }
    }

    /// Standard deviations (µm per axis) of the Brownian step between two
    /// samples of a row and of the step across a retrace (from the last
    /// sample of a row to the first of the next), at `diffusion` µm²/s.
    pub(crate) fn step_sds(&self, diffusion: f64) -> (f64, f64) {
        self.pre.step_sds(diffusion)
    }

    /// The intervals (TrackPy pixels) a QD's start x and y are drawn
    /// uniformly from.
    pub(crate) fn start_ranges_px(&self) -> ((f64, f64), (f64, f64)) {
        self.start_ranges_px
    }

    /// A coordinate in TrackPy pixels as the simulator's µm.
    pub(crate) fn px_to_um(&self, px: f64) -> f64 {
        (px + 0.5) * self.pixel_size_um
    }

    /// A coordinate in the simulator's µm as TrackPy pixels.
    pub(crate) fn um_to_px(&self, um: f64) -> f64 {
        um / self.pixel_size_um - 0.5
    }
}

/// The random stream of frame `index` of a dataset with seed `seed`.
pub(crate) fn frame_rng(seed: u64, index: usize) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(index as u64);
    rng
}

/// What the signal rendering of one frame hands on to its noise draws.
struct RenderedSignal {
    /// The frame's random stream, positioned for the detector noise.
    rng: ChaCha8Rng,
    /// The frame's N_bkg, expected background photons per pixel.
    background: f64,
}

/// Adds the expected signal of every emitter of frame `index` to `expected`
/// (row-major, `height · width`), appends their truth rows, and returns the
/// frame's random stream positioned for the noise draws with the frame's
/// background. With `paths`, also appends each emitter's position at every
/// PSF sample, in pixels.
fn render_signal(
    params: &SimParams,
    pre: &Precomputed,
    index: usize,
    expected: &mut [f64],
    bits: &mut Vec<u32>,
    truth: &mut Vec<TruthRow>,
    mut paths: Option<&mut Vec<Vec<(f64, f64)>>>,
) -> RenderedSignal {
    let mut rng = frame_rng(pre.seed, index);
    let diffusion = params.diffusion_um2_s.sample(&mut rng);
    let emitters = params.emitters.sample(&mut rng);
    // Drawn after the count (and only for a distribution), so fixed values
    // leave every later draw where it was.
    let brightness = params.brightness.sample(&mut rng);
    let background = params.background.sample(&mut rng);
    let amplitude = pre.amplitude(params, brightness);
    let a = params.pixel_size_um;
    let s = params.substeps as usize;
    let samples_per_row = params.width * s;
    let total_samples = (params.height * samples_per_row) as f64;
    let (step_sd, retrace_sd) = pre.step_sds(diffusion);
    let moving = diffusion > 0.0;
    let (x_range, y_range) = start_ranges_px(params);

    for _ in 0..emitters {
        let x0 = x_range.0 + (x_range.1 - x_range.0) * rng.random::<f64>();
        let y0 = y_range.0 + (y_range.1 - y_range.0) * rng.random::<f64>();
        let z0 = params.z_start.sample(&mut rng);
        let (mut x, mut y, mut z) = ((x0 + 0.5) * a, (y0 + 0.5) * a, z0);
        let (mut sum_x, mut sum_y, mut sum_z) = (0.0, 0.0, 0.0);
        let mut path = paths
            .as_mut()
            .map(|_| Vec::with_capacity(params.height * samples_per_row));
        for row in 0..params.height {
            let beam_y = (row as f64 + 0.5) * a;
            let pixels = &mut expected[row * params.width..(row + 1) * params.width];
            // The row's Brownian steps draw their first 32 bits in one bulk
            // fill: three per step, and no step before the very first sample.
            let first_step = usize::from(row == 0);
            if moving {
                bits.resize(3 * (samples_per_row - first_step), 0);
                rng.fill(&mut bits[..]);
            }
            for (k, &beam_x) in pre.beam_x.iter().enumerate() {
                if moving && k >= first_step {
                    // The first sample of a row follows a retrace: one exact
                    // draw covers it (Brownian increments add).
                    let sd = if k == 0 { retrace_sd } else { step_sd };
                    let step = &bits[3 * (k - first_step)..3 * (k - first_step) + 3];
                    x += sd * standard_normal_from_bits(step[0], &mut rng);
                    y += sd * standard_normal_from_bits(step[1], &mut rng);
                    z += sd * standard_normal_from_bits(step[2], &mut rng);
                }
                sum_x += x;
                sum_y += y;
                sum_z += z;
                if let Some(path) = path.as_mut() {
                    path.push((x / a - 0.5, y / a - 0.5));
                }
                pixels[k / s] += pre.sample_photons(amplitude, x - beam_x, y - beam_y, z);
            }
        }
        truth.push(TruthRow {
            frame: index,
            x: sum_x / total_samples / a - 0.5,
            y: sum_y / total_samples / a - 0.5,
            x_start: x0,
            y_start: y0,
            x_end: x / a - 0.5,
            y_end: y / a - 0.5,
            z_mean: sum_z / total_samples,
            diffusion,
        });
        if let (Some(paths), Some(path)) = (paths.as_mut(), path) {
            paths.push(path);
        }
    }
    RenderedSignal { rng, background }
}

/// An emitter's position at every PSF sample, pixels.
pub type Path = Vec<(f64, f64)>;

/// Everything one frame's walk produces without detector noise: the
/// expected signal image, the frame's background, the truth rows and each
/// emitter's path.
fn replay_frame(
    params: &SimParams,
    seed: u64,
    index: usize,
) -> (Vec<f64>, f64, Vec<TruthRow>, Vec<Path>) {
    let pre = Precomputed::new(params, seed);
    let mut expected = vec![0.0; params.height * params.width];
    let mut truth = Vec::new();
    let mut paths = Vec::new();
    let rendered = render_signal(
        params,
        &pre,
        index,
        &mut expected,
        &mut Vec::new(),
        &mut truth,
        Some(&mut paths),
    );
    (expected, rendered.background, truth, paths)
}

/// The expected photon image of frame `index` (signal plus the frame's
/// background, before detector noise) and its truth rows. Used by tests and
/// benchmarks to compare against the analytic model.
pub fn expected_frame(params: &SimParams, seed: u64, index: usize) -> (Vec<f64>, Vec<TruthRow>) {
    let (mut expected, background, truth, _) = replay_frame(params, seed, index);
    for value in &mut expected {
        *value += background;
    }
    (expected, truth)
}

/// The path of every emitter of frame `index` in pixel coordinates: its
/// position at each PSF sample, in scan order (the same walk that made the
/// frame). For figures; costs one frame's simulation.
pub fn trajectories(params: &SimParams, seed: u64, index: usize) -> Vec<Path> {
    replay_frame(params, seed, index).3
}

/// The expected image of one static emitter and its sensitivity to the
/// emitter's position: what the Cramér–Rao bound of a localiser is computed
/// from. Row-major, `height · width` values each.
#[derive(Debug, Clone, PartialEq)]
pub struct StaticEmitterImage {
    /// Expected photons per pixel: the scanned PSF plus the background.
    pub expected: Vec<f64>,
    /// ∂ expected / ∂x, photons per pixel of emitter displacement along x
    /// (columns).
    pub d_dx: Vec<f64>,
    /// ∂ expected / ∂y, photons per pixel of displacement along y (rows).
    pub d_dy: Vec<f64>,
}

/// The simulator's forward model for an emitter that does not move (D = 0)
/// at `(x, y)` in TrackPy pixel coordinates and depth `z_um` µm: the
/// expected photon image before detector noise (the scanned PSF averaged
/// over `substeps` samples per pixel, with the PSF cut-off, plus the
/// background) and its derivatives with respect to `x` and `y`. For a
/// static emitter of a simulated frame this is the frame's
/// [`expected_frame`].
///
/// The image is of one microscope: `brightness` and `background` must be
/// fixed numbers (an error names the one that is a distribution).
pub fn static_emitter_image(
    params: &SimParams,
    x: f64,
    y: f64,
    z_um: f64,
) -> Result<StaticEmitterImage, FieldError> {
    const PURPOSE: &str = "the image of a static emitter (a Cramér–Rao bound)";
    let brightness = params.brightness.require_fixed("brightness", PURPOSE)?;
    let background = params.background.require_fixed("background", PURPOSE)?;
    let pre = Precomputed::new(params, 0);
    let amplitude = pre.amplitude(params, brightness);
    let a = params.pixel_size_um;
    let s = params.substeps as usize;
    // The emitter in µm, as the simulator places it.
    let (x_um, y_um) = ((x + 0.5) * a, (y + 0.5) * a);
    // d/dx of exp(−r²/(2σ²)) is −(x − beam_x)/σ², per µm; × a per pixel.
    let slope = -2.0 * pre.inv_two_sigma_xy2 * a;
    let len = params.height * params.width;
    let mut image = StaticEmitterImage {
        expected: vec![0.0; len],
        d_dx: vec![0.0; len],
        d_dy: vec![0.0; len],
    };
    for row in 0..params.height {
        let beam_y = (row as f64 + 0.5) * a;
        for (k, &beam_x) in pre.beam_x.iter().enumerate() {
            let (dx, dy) = (x_um - beam_x, y_um - beam_y);
            let photons = pre.sample_photons(amplitude, dx, dy, z_um);
            let pixel = row * params.width + k / s;
            image.expected[pixel] += photons;
            image.d_dx[pixel] += photons * dx * slope;
            image.d_dy[pixel] += photons * dy * slope;
        }
    }
    // Added last, as `expected_frame` does, so the sums round alike.
    for value in &mut image.expected {
        *value += background;
    }
    Ok(image)
}

/// A uniform on [0, 1) from the upper 53 bits of a word, as rand's
/// `random::<f64>()` makes it.
#[inline]
fn unit_interval(word: u64) -> f64 {
    (word >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
}

/// Per-thread buffers reused from frame to frame.
#[derive(Default)]
struct Scratch {
    /// Expected signal photons per pixel.
    expected: Vec<f64>,
    /// Bulk random bits of one row's Brownian steps.
    bits: Vec<u32>,
    /// Bulk random words of the detector noise, two per pixel.
    noise_words: Vec<u64>,
}

/// What every frame of one dataset shares.
struct FrameMaker<'a> {
    params: &'a SimParams,
    pre: Precomputed,
    /// The detector of every frame when the background is fixed; a drawn
    /// background gets a detector per frame.
    fixed_detector: Option<Detector>,
}

impl FrameMaker<'_> {
    /// Simulates frame `index` into `counts` (row-major), using `expected` as
    /// scratch, and appends its truth rows.
    fn make(
        &self,
        index: usize,
        counts: &mut [u32],
        scratch: &mut Scratch,
        truth: &mut Vec<TruthRow>,
    ) -> anyhow::Result<()> {
        let params = self.params;
        let Scratch {
            expected,
            bits,
            noise_words,
        } = scratch;
        expected.fill(0.0);
        let RenderedSignal {
            mut rng,
            background,
        } = render_signal(params, &self.pre, index, expected, bits, truth, None);
        let frame_detector;
        let detector = match &self.fixed_detector {
            Some(detector) => detector,
            None => {
                frame_detector = Detector::new(params.detector_noise, background);
                &frame_detector
            }
        };
        record_counts(detector, &mut rng, expected, noise_words, counts, index)
    }
}

/// The bytes [`simulate`] holds in memory at its peak for `frames` frames
/// of `params` (saturating, never overflowing): the counts (4 bytes a
/// pixel), and the ground truth twice (per frame, with room for the most
/// emitters a frame can have, then gathered into one list). A command
/// checks it with [`check_memory`](crate::limits::check_memory) before
/// simulating.
pub fn dataset_bytes(params: &SimParams, frames: usize) -> u64 {
    let size = |n: usize| n as u64;
    let frames = size(frames);
    let pixel_bytes = frames
        .saturating_mul(size(params.height))
        .saturating_mul(size(params.width))
        .saturating_mul(size(std::mem::size_of::<u32>()));
    let truth_bytes = frames
        .saturating_mul(u64::from(params.emitters.max()))
        .saturating_mul(2 * size(std::mem::size_of::<TruthRow>()));
    let list_bytes = frames.saturating_mul(size(std::mem::size_of::<Vec<TruthRow>>()));
    pixel_bytes
        .saturating_add(truth_bytes)
        .saturating_add(list_bytes)
}

/// Draws the recorded count of every pixel of frame `index` from its
/// expected signal `expected` (the background is the detector's) into
/// `counts`: two uniforms per pixel (background, signal) drawn in one fill
/// into `noise_words`, then whatever further draws large means need. The
/// one noise loop of the per-frame simulator and of recordings.
fn record_counts(
    detector: &Detector,
    rng: &mut ChaCha8Rng,
    expected: &[f64],
    noise_words: &mut Vec<u64>,
    counts: &mut [u32],
    index: usize,
) -> anyhow::Result<()> {
    noise_words.resize(2 * counts.len(), 0);
    rng.fill(&mut noise_words[..]);
    for ((count, &signal), words) in counts
        .iter_mut()
        .zip(expected.iter())
        .zip(noise_words.chunks_exact(2))
    {
        if !signal.is_finite() {
            return Err(input_error(format!(
                "frame {index}: expected photon count is not finite ({signal}); check brightness and sigma"
            )));
        }
        let uniforms = [unit_interval(words[0]), unit_interval(words[1])];
        let recorded = detector.record_from_uniforms(uniforms, rng, signal);
        *count = u32::try_from(recorded).map_err(|_| {
            input_error(format!(
                "frame {index}: a count of {recorded} photons does not fit in uint32; lower brightness or background"
            ))
        })?;
    }
    Ok(())
}
/// Simulates frames `range` of the dataset with `params` and `seed`, in
/// parallel. The result depends only on `(params, seed, range)`: frame `i`
/// is the same whether made alone, in a chunk or in the whole dataset.
///
/// `progress` is advanced by one per finished frame.
pub fn simulate(
    params: &SimParams,
    seed: u64,
    range: Range<usize>,
    progress: &ProgressBar,
) -> anyhow::Result<Dataset> {
    params.validate()?;
    let n = range.len();
    let frame_len = params.height * params.width;
    let maker = FrameMaker {
        params,
        pre: Precomputed::new(params, seed),
        fixed_detector: params
            .background
            .fixed()
            .map(|background| Detector::new(params.detector_noise, background)),
    };
    let mut data = vec![0u32; n * frame_len];
    let truths: Vec<Vec<TruthRow>> = data
        .par_chunks_mut(frame_len)
        .enumerate()
        .map_init(
            || Scratch {
                expected: vec![0.0; frame_len],
                ..Scratch::default()
            },
            |scratch, (offset, counts)| {
                let mut truth = Vec::with_capacity(params.emitters.max() as usize);
                maker.make(range.start + offset, counts, scratch, &mut truth)?;
                progress.inc(1);
                Ok(truth)
            },
        )
        .collect::<anyhow::Result<_>>()?;
    Ok(Dataset {
        frames: FrameStack::from_vec(n, params.height, params.width, data)?,
        truth: truths.into_iter().flatten().collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::params::RandomDistribution;
    use rand::RngExt;

    /// A static emitter's frame, as the simulator renders it, and the
    /// emitter's truth row.
    fn static_frame(params: &SimParams, seed: u64, index: usize) -> (Vec<f64>, TruthRow) {
        let (expected, truth) = expected_frame(params, seed, index);
        assert_eq!(truth.len(), 1);
        (expected, truth[0])
    }

    #[test]
    fn static_emitter_image_is_the_simulators_expected_frame() {
        // In focus: the forward model is the simulator's sum, bit for bit,
        // with and without cut-off and sub-sampling.
        for (substeps, cutoff) in [(1, Some(6.0)), (4, None), (3, Some(2.0))] {
            let params = SimParams {
                height: 20,
                width: 23,
                diffusion_um2_s: Distribution::Fixed(0.0),
                substeps,
                psf_cutoff_sigma: cutoff,
                background: 0.3.into(),
                ..SimParams::default()
            };
            for index in 0..5 {
                let (expected, truth) = static_frame(&params, 11, index);
                let image =
                    static_emitter_image(&params, truth.x_start, truth.y_start, 0.0).unwrap();
                assert_eq!(
                    image.expected, expected,
                    "substeps {substeps}, frame {index}"
                );
            }
        }
        // Out of focus (depth drawn per frame): equal to rounding.
        let params = SimParams {
            height: 16,
            width: 16,
            diffusion_um2_s: Distribution::Fixed(0.0),
            z_start: Distribution::Random(RandomDistribution::Uniform([-0.5, 0.5])),
            ..SimParams::default()
        };
        for index in 0..5 {
            let (expected, truth) = static_frame(&params, 12, index);
            assert!(truth.z_mean.abs() > 1e-3);
            let image =
                static_emitter_image(&params, truth.x_start, truth.y_start, truth.z_mean).unwrap();
            for (model, simulated) in image.expected.iter().zip(&expected) {
                assert!((model - simulated).abs() <= 1e-12 * simulated.abs().max(1.0));
            }
        }
    }

    /// Truth rows per frame of `dataset`.
    fn counts_per_frame(dataset: &Dataset) -> Vec<usize> {
        let mut counts = vec![0; dataset.frames.n];
        for row in &dataset.truth {
            counts[row.frame] += 1;
        }
        counts
    }

    #[test]
    fn drawn_emitter_counts_are_deterministic_and_follow_their_weights() {
        let params = SimParams {
            height: 12,
            width: 12,
            emitters: EmitterCount::Random(CountChoice {
                choice: vec![0, 1, 2, 3],
                weights: Some(vec![1.0, 0.0, 2.0, 1.0]),
            }),
            ..SimParams::default()
        };
        let hidden = ProgressBar::hidden();
        let dataset = simulate(&params, 7, 0..400, &hidden).unwrap();
        let again = simulate(&params, 7, 0..400, &hidden).unwrap();
        assert_eq!(dataset.frames.data, again.frames.data);
        assert_eq!(dataset.truth, again.truth);
        // A frame is the same made alone.
        let alone = simulate(&params, 7, 123..124, &hidden).unwrap();
        assert_eq!(alone.frames.frame(0), dataset.frames.frame(123));
        let counts = counts_per_frame(&dataset);
        let share = |n: usize| counts.iter().filter(|&&c| c == n).count() as f64 / 400.0;
        assert_eq!(share(1), 0.0, "a weight of 0 is never drawn");
        // Expected shares 1/4, 1/2, 1/4: within 4.5 standard errors.
        for (n, p) in [(0, 0.25), (2, 0.5), (3, 0.25)] {
            let se = (p * (1.0 - p) / 400.0f64).sqrt();
            assert!((share(n) - p).abs() < 4.5 * se, "{n}: {}", share(n));
        }
        // Empty frames are background only: mean ≈ N_bkg.
        let empty: Vec<usize> = (0..400).filter(|&i| counts[i] == 0).collect();
        let mean = empty
            .iter()
            .flat_map(|&i| dataset.frames.frame(i))
            .map(|&c| f64::from(c))
            .sum::<f64>()
            / (empty.len() * 144) as f64;
        assert!(
            (mean - params.background.fixed().unwrap()).abs() < 0.2,
            "{mean}"
        );
    }

    #[test]
    fn a_fixed_count_draws_nothing_so_its_frames_never_change() {
        // Fixed(2) against a one-entry choice of 2: the same counts, but
        // the choice consumes a uniform, so only the fixed count keeps the
        // frames simulated before counts could be drawn.
        let fixed = SimParams {
            height: 10,
            width: 10,
            emitters: EmitterCount::Fixed(2),
            ..SimParams::default()
        };
        let drawn = SimParams {
            emitters: EmitterCount::Random(CountChoice {
                choice: vec![2],
                weights: None,
            }),
            ..fixed.clone()
        };
        let hidden = ProgressBar::hidden();
        let a = simulate(&fixed, 3, 0..5, &hidden).unwrap();
        let b = simulate(&drawn, 3, 0..5, &hidden).unwrap();
        assert_eq!(counts_per_frame(&a), vec![2; 5]);
        assert_eq!(counts_per_frame(&b), vec![2; 5]);
        assert_ne!(a.truth[0].x_start, b.truth[0].x_start);
        // The first draw after D is the first QD's start x (uniform on
        // the field): check it against the stream directly.
        let mut rng = frame_rng(3, 0);
        let _diffusion = fixed.diffusion_um2_s.sample(&mut rng);
        let x0 = -0.5 + 10.0 * rng.random::<f64>();
        assert_eq!(a.truth[0].x_start, x0);
    }

    #[test]
    fn a_negative_margin_starts_qds_outside_the_field_by_at_most_that_much() {
        // margin −4 on a 24 × 25 frame: starts uniform on [−4.5, 28.5] ×
        // [−4.5, 27.5]; the share outside the field is 1 − 600/(33·32) = 0.43,
        // so 400 starts all inside (or none beyond the grown field) would be
        // a broken range.
        let params = SimParams {
            margin_px: -4.0,
            diffusion_um2_s: Distribution::Fixed(0.0),
            ..SimParams::default()
        };
        params.validate().unwrap();
        let mut outside = 0;
        for index in 0..400 {
            let (_, truth) = expected_frame(&params, 3, index);
            let (x, y) = (truth[0].x_start, truth[0].y_start);
            assert!(
                (-4.5..=28.5).contains(&x) && (-4.5..=27.5).contains(&y),
                "{x}, {y}"
            );
            if !(-0.5..=24.5).contains(&x) || !(-0.5..=23.5).contains(&y) {
                outside += 1;
            }
        }
        // Binomial(400, 0.43): mean 172, sd 9.9; ±5 sd.
        assert!((122..=222).contains(&outside), "{outside} of 400 outside");
        // At most one frame side outside; non-finite refused.
        for margin in [-24.5, f64::NAN] {
            let error = SimParams {
                margin_px: margin,
                ..SimParams::default()
            }
            .validate()
            .unwrap_err();
            assert_eq!(error.field(), "margin_px", "{margin}: {error}");
        }
        assert!(
            SimParams {
                margin_px: -24.0,
                ..SimParams::default()
            }
            .validate()
            .is_ok()
        );
    }

    #[test]
    fn a_drawn_brightness_comes_after_the_count_and_scales_the_frame() {
        // A static, in-focus QD far from the border, no background and no
        // cut-off: a frame's expected signal is its N_qd times the image at
        // N_qd = 1. With D and the count fixed, the frame's first draw is
        // its N_qd.
        let unit = SimParams {
            height: 30,
            width: 30,
            margin_px: 12.0,
            diffusion_um2_s: Distribution::Fixed(0.0),
            background: 0.0.into(),
            brightness: 1.0.into(),
            psf_cutoff_sigma: None,
            ..SimParams::default()
        };
        let drawn = SimParams {
            brightness: "uniform:2,20".parse().unwrap(),
            ..unit.clone()
        };
        let mut seen = Vec::new();
        for index in 0..20 {
            let (expected, truth) = expected_frame(&drawn, 5, index);
            let unit_image =
                static_emitter_image(&unit, truth[0].x_start, truth[0].y_start, 0.0).unwrap();
            let ratio = expected.iter().sum::<f64>() / unit_image.expected.iter().sum::<f64>();
            let mut rng = frame_rng(5, index);
            let brightness = drawn.brightness.sample(&mut rng);
            assert!((2.0..=20.0).contains(&brightness));
            assert!(
                (ratio / brightness - 1.0).abs() < 1e-9,
                "{ratio} vs {brightness}"
            );
            // The QD's start x is the draw after it.
            let x0 = -0.5 + 12.0 + 6.0 * rng.random::<f64>();
            assert_eq!(truth[0].x_start, x0);
            seen.push(brightness);
        }
        let (low, high) = seen
            .iter()
            .fold((f64::MAX, f64::MIN), |(l, h), &b| (l.min(b), h.max(b)));
        assert!(low < 8.0 && high > 14.0, "N_qd drawn in [{low}, {high}]");
    }

    #[test]
    fn a_drawn_background_is_one_value_per_frame_within_its_bounds() {
        let params = SimParams {
            height: 8,
            width: 9,
            brightness: 0.0.into(),
            background: "uniform:2,20".parse().unwrap(),
            ..SimParams::default()
        };
        let mut seen = Vec::new();
        for index in 0..20 {
            let (expected, _) = expected_frame(&params, 8, index);
            assert!(expected.iter().all(|&e| e == expected[0]), "{expected:?}");
            assert!((2.0..=20.0).contains(&expected[0]));
            seen.push(expected[0]);
        }
        let spread = seen.iter().cloned().fold(f64::MIN, f64::max)
            - seen.iter().cloned().fold(f64::MAX, f64::min);
        assert!(spread > 6.0, "backgrounds {seen:?}");
        // The same frames from the same seed, alone or in a stack.
        let hidden = ProgressBar::hidden();
        let stack = simulate(&params, 8, 0..20, &hidden).unwrap();
        assert_eq!(stack, simulate(&params, 8, 0..20, &hidden).unwrap());
        let alone = simulate(&params, 8, 13..14, &hidden).unwrap();
        assert_eq!(alone.frames.frame(0), stack.frames.frame(13));
        // The recorded counts follow the frame's own background: the
        // frames' means spread as the draws do (Poisson noise of a 72-pixel
        // mean is ≈ 0.5 photon at most here).
        let means: Vec<f64> = (0..20)
            .map(|i| {
                stack
                    .frames
                    .frame(i)
                    .iter()
                    .map(|&c| f64::from(c))
                    .sum::<f64>()
                    / 72.0
            })
            .collect();
        for (mean, background) in means.iter().zip(&seen) {
            assert!((mean - background).abs() < 2.5, "{mean} vs {background}");
        }
    }

    /// Asserts that the frames' total counts vary more than `min_ratio`
    /// times as much (sample variance over `frames` frames) with `drawn`'s
    /// parameters as with `fixed`'s, around the same mean (within 5
    /// standard errors).
    fn assert_totals_spread_wider(
        what: &str,
        fixed: &SimParams,
        drawn: &SimParams,
        min_ratio: f64,
        frames: usize,
    ) {
        let stats = |params: &SimParams| {
            let dataset = simulate(params, 17, 0..frames, &ProgressBar::hidden()).unwrap();
            let totals: Vec<f64> = (0..frames)
                .map(|i| dataset.frames.frame(i).iter().map(|&c| f64::from(c)).sum())
                .collect();
            let mean = totals.iter().sum::<f64>() / frames as f64;
            let variance =
                totals.iter().map(|t| (t - mean).powi(2)).sum::<f64>() / (frames - 1) as f64;
            (mean, variance)
        };
        let (fixed_mean, fixed_variance) = stats(fixed);
        let (drawn_mean, drawn_variance) = stats(drawn);
        assert!(
            drawn_variance > min_ratio * fixed_variance,
            "{what}: variance {drawn_variance} drawn vs {fixed_variance} fixed"
        );
        let standard_error = ((drawn_variance + fixed_variance) / frames as f64).sqrt();
        assert!(
            (drawn_mean - fixed_mean).abs() < 5.0 * standard_error,
            "{what}: mean {drawn_mean} drawn vs {fixed_mean} fixed"
        );
    }

    #[test]
    fn drawn_photometry_spreads_the_frames_photon_totals() {
        // The paper's frame holds ≈ 60·N_qd signal photons and 600·N_bkg
        // background ones. At fixed N_qd = 11 the total's standard
        // deviation is ≈ 76 photons (Poisson); N_qd uniform on [2, 20]
        // (mean 11) adds 60 · 18/√12 ≈ 312, a variance ≈ 17 times larger.
        // With 400 frames the sample variances are within ±7 % (one
        // standard error): a ratio above 4 fails only if the draw is
        // ignored. The means agree within 5 standard errors (≈ 80 photons).
        let fixed = SimParams {
            margin_px: 4.0,
            brightness: 11.0.into(),
            ..SimParams::default()
        };
        let drawn = SimParams {
            brightness: "uniform:2,20".parse().unwrap(),
            ..fixed.clone()
        };
        assert_totals_spread_wider("N_qd", &fixed, &drawn, 4.0, 400);
        // N_bkg uniform on [2, 14.8] (mean 8.4): 600 · 12.8/√12 ≈ 2200
        // photons of standard deviation against ≈ 74.
        let drawn = SimParams {
            background: "uniform:2,14.8".parse().unwrap(),
            ..SimParams::default()
        };
        assert_totals_spread_wider("N_bkg", &SimParams::default(), &drawn, 100.0, 400);
    }

    #[test]
    fn counts_parse_print_and_refuse_bad_weights() {
        for text in ["3", "choice:0,1,2,3", "choice:0,2/weights:1,3.5"] {
            let count: EmitterCount = text.parse().unwrap();
            assert_eq!(count.to_string(), text);
        }
        assert!("choice:0,x".parse::<EmitterCount>().is_err());
        assert!("choice:0,1/w:1,2".parse::<EmitterCount>().is_err());
        assert!("-1".parse::<EmitterCount>().is_err());
        let bad = |text: &str| {
            let count: EmitterCount = text.parse().unwrap();
            count.validate("emitters", 10).unwrap_err().to_string()
        };
        assert!(bad("choice:0,1/weights:1").contains("one weight per count"));
        assert!(bad("choice:0,1/weights:0,0").contains("not all be 0"));
        assert!(bad("choice:0,1/weights:1,-1").contains("emitters"));
        assert!(bad("choice:0,11").contains("at most 10"));
        assert!(bad("11").contains("at most 10"));
        assert_eq!("choice:4,0,2".parse::<EmitterCount>().unwrap().max(), 4);
    }

    #[test]
    fn static_emitter_image_derivatives_match_finite_differences() {
        let params = SimParams {
            height: 12,
            width: 14,
            substeps: 2,
            psf_cutoff_sigma: None,
            ..SimParams::default()
        };
        let (x, y, z) = (6.3, 5.6, 0.2);
        let image = static_emitter_image(&params, x, y, z).unwrap();
        let h = 1e-5;
        let central = |plus: &StaticEmitterImage, minus: &StaticEmitterImage| -> Vec<f64> {
            plus.expected
                .iter()
                .zip(&minus.expected)
                .map(|(p, m)| (p - m) / (2.0 * h))
                .collect()
        };
        let d_dx = central(
            &static_emitter_image(&params, x + h, y, z).unwrap(),
            &static_emitter_image(&params, x - h, y, z).unwrap(),
        );
        let d_dy = central(
            &static_emitter_image(&params, x, y + h, z).unwrap(),
            &static_emitter_image(&params, x, y - h, z).unwrap(),
        );
        let peak = image.d_dx.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(peak > 0.0);
        for (analytic, numeric) in image.d_dx.iter().zip(&d_dx) {
            assert!(
                (analytic - numeric).abs() < 1e-6 * peak,
                "{analytic} vs {numeric}"
            );
        }
        for (analytic, numeric) in image.d_dy.iter().zip(&d_dy) {
            assert!(
                (analytic - numeric).abs() < 1e-6 * peak,
                "{analytic} vs {numeric}"
            );
        }
    }
}
