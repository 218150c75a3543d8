//! Continuous recordings (`docs/tracking.md`): frames scanned back to back
//! on one clock while many QDs diffuse in 3D through a volume larger than
//! the field, entering and leaving the field and the focal volume, and
//! optionally blinking.
//!
//! The scan is the per-frame simulator's: the beam visits pixel (r, c) at
//! `r · L + c · δt` after the frame's start (line time `L = W·δt +
//! t_retrace`), the expected photons of a sample come from the same PSF
//! code ([`Precomputed::sample_photons`]) and the counts from the same
//! detector loop. What differs is time: frame `f` starts at `f · T` with
//! the frame period `T = H · L + dead_time` (the last row's retrace is the
//! flyback to the top), and every QD's walk carries on from frame to frame.
//!
//! The volume is periodic: the box `[−m, W·a + m] × [−m, H·a + m] ×
//! [−depth, depth]` µm (`m` the lateral margin) wraps around, so the QDs
//! stay uniformly spread at the set density for ever (the uniform density
//! is the stationary state of Brownian motion on a torus) and their number
//! is constant. A QD that wraps around laterally is a new QD entering
//! where the old one left: it gets a new id from the next frame on (with the
//! default margin, beyond the PSF's cut-off, it wraps where no beam can see
//! it). In the frame in which it wraps, its truth row follows its path
//! continuously (positions unwrapped), so every QD in the field has a row in
//! every frame. Wrapping in depth keeps the id: the QD stays where it was in
//! the field.
//!
//! Blinking is a two-state Markov process (continuous-time telegraph
//! process) per QD: on and off periods are independent exponentials with
//! the given means, the first state drawn from the stationary odds. A dark
//! QD moves but gives no photons.
//!
//! Determinism: the walks and the blinking draw from ChaCha8 stream 0 of the
//! recording's seed, in a fixed order (at the start: the number of QDs,
//! then per QD its x, y, z and blinking state; then per sample per QD three
//! normals and any blinking switches); the detector noise of frame `f` from
//! stream `f + 1`. The walk is one clock, so it runs on one thread; the
//! result does not depend on the thread count.

use indicatif::ProgressBar;
use rand::{Rng, RngExt};
use rand_chacha::ChaCha8Rng;

use super::gaussian::standard_normal_from_bits;
use super::noise::Detector;
use super::{Precomputed, SimParams, frame_rng, record_counts};
use crate::error::{FieldError, Stopped, input_error};
use crate::types::{FrameStack, RecordingTruthRow};

/// Version of the recording simulator (its walk, truth and frames); part
/// of every recording's content key.
pub(crate) const RECORDING_VERSION: &str = "scanloc-recording/2";

/// Most QDs a recording's volume may hold (the per-frame simulator's limit).
pub const MAX_RECORDING_QDS: u64 = super::params::MAX_EMITTERS as u64;

/// The longest dead time between frames, ms.
pub const MAX_DEAD_TIME_MS: f64 = 60_000.0;

/// What a recording's simulation holds beyond its data: the threads'
/// stacks, the allocator's arenas and the writers' buffers (measured at
/// about 3 MB on a 98 MB recording, `tests/it/tracking_defects.rs`).
const WORKING_BYTES: u64 = 16 << 20;

/// Two-state on/off blinking with exponential dwell times.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Blinking {
    /// Mean duration of an on period, ms (> 0).
    pub on_ms: f64,
    /// Mean duration of an off period, ms (> 0).
    pub off_ms: f64,
}

/// Everything that determines a recording except its seed.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingParams {
    /// The microscope and the QDs' photometry: frame size, pixel, timing,
    /// PSF, detector noise, N_qd, N_bkg and D (each of these three must be
    /// a fixed number; `emitters`, `z_start` and `margin_px` do not apply).
    pub microscope: SimParams,
    /// Number of frames.
    pub frames: usize,
    /// QDs per µm³ of the volume (their number is Poisson-drawn once).
    pub density_per_um3: f64,
    /// A set number of QDs in the volume instead of the Poisson draw of
    /// `density_per_um3` × volume (which is then not used): for a recording
    /// that must hold as many QDs as another, as when a pipeline's bias is
    /// measured on a recording like the one it estimated.
    pub qd_count: Option<u64>,
    /// How far the volume reaches beyond the field on every side, µm.
    pub lateral_margin_um: f64,
    /// The volume spans depths `[−depth, depth]` µm around the focal plane.
    pub half_depth_um: f64,
    /// Blinking, if the QDs blink.
    pub blinking: Option<Blinking>,
    /// Time between the flyback after a frame's last row and the next
    /// frame's first pixel, ms (≥ 0).
    pub dead_time_ms: f64,
}

impl RecordingParams {
    /// Checks every parameter; an error names the one at fault.
    pub fn validate(&self) -> Result<(), FieldError> {
        self.microscope.validate()?;
        let purpose = "a recording";
        self.microscope
            .diffusion_um2_s
            .require_fixed("diffusion_um2_s", purpose)?;
        self.microscope
            .brightness
            .require_fixed("brightness", purpose)?;
        self.microscope
            .background
            .require_fixed("background", purpose)?;
        let positive = |name: &str, value: f64| {
            if value.is_finite() && value > 0.0 {
                Ok(())
            } else {
                Err(FieldError::new(
                    name,
                    format!("must be > 0, got {}", crate::error::readable(value)),
                ))
            }
        };
        let non_negative = |name: &str, value: f64| {
            if value.is_finite() && value >= 0.0 {
                Ok(())
            } else {
                Err(FieldError::new(
                    name,
                    format!("must be ≥ 0, got {}", crate::error::readable(value)),
                ))
            }
        };
        if self.qd_count.is_none() {
            non_negative("qd_density", self.density_per_um3)?;
        }
        non_negative("lateral_margin_um", self.lateral_margin_um)?;
        positive("half_depth_um", self.half_depth_um)?;
        non_negative("dead_time_ms", self.dead_time_ms)?;
        if self.dead_time_ms > MAX_DEAD_TIME_MS {
            // Beyond it the time stamps of a long recording (f64 seconds)
            // would no longer resolve a pixel's dwell.
            return Err(FieldError::new(
                "dead_time_ms",
                format!(
                    "must be at most {MAX_DEAD_TIME_MS} ms (a minute between frames), got {}",
                    self.dead_time_ms
                ),
            ));
        }
        if let Some(blinking) = self.blinking {
            positive("blink_on_ms", blinking.on_ms)?;
            positive("blink_off_ms", blinking.off_ms)?;
        }
        crate::limits::check_dataset_size(
            "frames",
            self.frames,
            self.microscope.height,
            self.microscope.width,
        )?;
        if let Some(count) = self.qd_count
            && count > MAX_RECORDING_QDS / 2
        {
            return Err(FieldError::new(
                "qd_count",
                format!("must be at most {}, got {count}", MAX_RECORDING_QDS / 2),
            ));
        }
        let expected = self.density_per_um3 * self.volume_um3();
        if !self.volume_um3().is_finite() {
            return Err(FieldError::new(
                "lateral_margin_um",
                format!(
                    "the volume ({} µm³) must be finite",
                    crate::error::readable(self.volume_um3())
                ),
            ));
        }
        // A set count does not use the density.
        if self.qd_count.is_none()
            && (expected.is_nan() || expected > MAX_RECORDING_QDS as f64 / 2.0)
        {
            return Err(FieldError::new(
                "qd_density",
                format!(
                    "{expected:.0} QDs expected in the {:.1} µm³ volume; at most {} are allowed",
                    self.volume_um3(),
                    MAX_RECORDING_QDS / 2
                ),
            ));
        }
        Ok(())
    }

    /// The box's extent along x, y and z, µm: `(low, high)` each.
    fn bounds_um(&self) -> [(f64, f64); 3] {
        let p = &self.microscope;
        let m = self.lateral_margin_um;
        [
            (-m, p.width as f64 * p.pixel_size_um + m),
            (-m, p.height as f64 * p.pixel_size_um + m),
            (-self.half_depth_um, self.half_depth_um),
        ]
    }

    /// The bytes [`simulate_recording`] holds at its peak (saturating):
    /// the counts (4 bytes a pixel, allocated once at their final size) and
    /// the ground truth, counted as if every QD of the volume were in the
    /// field in every frame (an upper estimate: only those in the field get
    /// a row), twice over for the slack of its growing vector; plus one
    /// frame's working buffers and the process's working memory. `tests/it/tracking_defects.rs` compares it
    /// with the peak measured on a mid-sized recording. A command checks it
    /// with [`check_memory`](crate::limits::check_memory) before simulating,
    /// as `simulate` does with [`dataset_bytes`](super::dataset_bytes).
    pub fn dataset_bytes(&self) -> u64 {
        let frames = self.frames as u64;
        let pixel_bytes = frames
            .saturating_mul(self.microscope.height as u64)
            .saturating_mul(self.microscope.width as u64)
            .saturating_mul(std::mem::size_of::<u32>() as u64);
        let qds = self
            .qd_count
            .unwrap_or((self.density_per_um3 * self.volume_um3()).ceil().max(0.0) as u64);
        let truth_bytes = frames
            .saturating_mul(qds.min(MAX_RECORDING_QDS))
            .saturating_mul(2 * std::mem::size_of::<RecordingTruthRow>() as u64);
        // The expected image (f64) and the noise's two words per pixel.
        let frame_bytes = (self.microscope.height as u64)
            .saturating_mul(self.microscope.width as u64)
            .saturating_mul(3 * 8);
        pixel_bytes
            .saturating_add(truth_bytes)
            .saturating_add(frame_bytes)
            .saturating_add(WORKING_BYTES)
    }

    /// The volume of the box, µm³.
    pub fn volume_um3(&self) -> f64 {
        self.bounds_um().iter().map(|(l, h)| h - l).product()
    }

    /// Line time `L = W·δt + t_retrace`, s.
    pub fn line_time_s(&self) -> f64 {
        let p = &self.microscope;
        p.width as f64 * p.dwell_us * 1e-6 + p.retrace_ms * 1e-3
    }

    /// Frame period `T = H·L + dead_time`, s: frame `f` starts at `f · T`.
    pub fn frame_period_s(&self) -> f64 {
        self.microscope.height as f64 * self.line_time_s() + self.dead_time_ms * 1e-3
    }
}

/// A simulated recording: its frames (when rendered) and the truth rows,
/// ordered by frame then QD id.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SimulatedRecording {
    pub frames: FrameStack,
    pub truth: Vec<RecordingTruthRow>,
    /// QDs in the volume (a Poisson draw of density × volume, then constant).
    pub qds: usize,
}

/// One QD of the volume.
#[derive(Debug, Clone)]
struct Qd {
    id: u64,
    /// Position, µm.
    at: [f64; 3],
    on: bool,
    /// Time left in the current blinking state, s.
    state_left_s: f64,
    /// Whether the QD wrapped around the volume laterally during the
    /// current frame (it takes a new id at the next frame's start).
    wrapped: bool,
    /// What its wraps during the current frame took off its x and y, µm:
    /// `at + shift` is its path unwrapped.
    shift: [f64; 2],
    sums: FrameSums,
}

/// A QD's accumulators over one frame.
#[derive(Debug, Clone, Default)]
struct FrameSums {
    x: f64,
    y: f64,
    z: f64,
    on_samples: f64,
    /// Lateral-PSF weight and weighted x, y and time.
    weight: f64,
    weighted_x: f64,
    weighted_y: f64,
    weighted_t: f64,
}

/// How many mean on–off cycles past its last switch a QD's blinking clock
/// may be before its state is drawn from the telegraph process's
/// transition law rather than switch by switch ([`Blinking::run`]). At this
/// distance the law is the stationary odds to within `e^-128`; no
/// recording with blinking periods longer than a frame's dwell and retrace
/// ever gets there.
const SWITCH_BY_SWITCH_CYCLES: f64 = 32.0;

impl Blinking {
    /// The mean duration of the current state, s.
    fn mean_s(&self, on: bool) -> f64 {
        if on { self.on_ms } else { self.off_ms }.max(0.0) * 1e-3
    }

    /// Runs a QD's blinking clock for `dt_s`: `on` is its state and
    /// `state_left_s` the time left in it, both updated.
    ///
    /// Switch by switch, one exponential per period; but once the clock is
    /// more than [`SWITCH_BY_SWITCH_CYCLES`] cycles past the switch it has
    /// reached (a long dead time, or periods far shorter than a sample),
    /// the state at the end is drawn from the transition law instead. That
    /// is exact, not an approximation: the process is Markov, so the state
    /// after a time `t` from a switch into state `s` is on with probability
    /// `π_on + (1[s = on] − π_on)·e^{−t(1/τ_on + 1/τ_off)}`, and the time
    /// left in the state drawn is a fresh exponential. It keeps the cost of
    /// any step bounded, where one draw per switch would not end for
    /// periods of 1e-300 ms.
    fn run<R: Rng + ?Sized>(&self, rng: &mut R, on: &mut bool, state_left_s: &mut f64, dt_s: f64) {
        *state_left_s -= dt_s;
        while *state_left_s <= 0.0 {
            *on = !*on;
            let since_switch_s = -*state_left_s;
            let (on_s, off_s) = (self.mean_s(true), self.mean_s(false));
            if since_switch_s > SWITCH_BY_SWITCH_CYCLES * (on_s + off_s) {
                let stationary_on = on_s / (on_s + off_s);
                let start = if *on { 1.0 } else { 0.0 };
                let relax = (-since_switch_s * (1.0 / on_s + 1.0 / off_s)).exp();
                *on = rng.random::<f64>() < stationary_on + (start - stationary_on) * relax;
                *state_left_s = exponential(rng, self.mean_s(*on));
                if *state_left_s <= 0.0 {
                    // A zero draw (periods below f64's resolution): the
                    // state holds until the next step.
                    *state_left_s = f64::MIN_POSITIVE;
                }
                return;
            }
            *state_left_s += exponential(rng, self.mean_s(*on));
        }
    }
}

/// An exponential duration of mean `mean_s`.
fn exponential<R: Rng + ?Sized>(rng: &mut R, mean_s: f64) -> f64 {
    -mean_s * (1.0 - rng.random::<f64>()).ln()
}

/// The walk's state: the QDs and their random stream.
struct Walk<'a> {
    params: &'a RecordingParams,
    pre: Precomputed,
    rng: ChaCha8Rng,
    qds: Vec<Qd>,
    next_id: u64,
    bounds: [(f64, f64); 3],
    amplitude: f64,
    diffusion: f64,
}

impl<'a> Walk<'a> {
    /// The volume at time 0: a Poisson number of QDs placed uniformly, each
    /// in its stationary blinking state.
    fn new(params: &'a RecordingParams, seed: u64) -> Self {
        let micro = &params.microscope;
        let pre = Precomputed::new(micro, seed);
        let brightness = micro.brightness.fixed().unwrap_or(0.0);
        let amplitude = pre.amplitude(micro, brightness);
        let mut rng = frame_rng(seed, 0);
        let expected = params.density_per_um3 * params.volume_um3();
        let count = match params.qd_count {
            Some(count) => count.min(MAX_RECORDING_QDS),
            None if expected > 0.0 => {
                super::noise::poisson(&mut rng, expected).min(MAX_RECORDING_QDS)
            }
            None => 0,
        };
        let bounds = params.bounds_um();
        let mut qds = Vec::with_capacity(count as usize);
        for id in 0..count {
            let mut at = [0.0; 3];
            for (value, (low, high)) in at.iter_mut().zip(bounds) {
                *value = low + (high - low) * rng.random::<f64>();
            }
            let (on, state_left_s) = match params.blinking {
                Some(b) => {
                    let on = rng.random::<f64>() < b.on_ms / (b.on_ms + b.off_ms);
                    let mean = if on { b.on_ms } else { b.off_ms } * 1e-3;
                    (on, exponential(&mut rng, mean))
                }
                None => (true, f64::INFINITY),
            };
            qds.push(Qd {
                id,
                at,
                on,
                state_left_s,
                wrapped: false,
                shift: [0.0; 2],
                sums: FrameSums::default(),
            });
        }
        Self {
            params,
            pre,
            rng,
            qds,
            next_id: count,
            bounds,
            amplitude,
            diffusion: micro.diffusion_um2_s.fixed().unwrap_or(0.0),
        }
    }

    /// Moves every QD by one Brownian step of standard deviation `sd` µm
    /// per axis lasting `dt_s` (wrapping around the volume), and runs its
    /// blinking clock for `dt_s`.
    fn step(&mut self, sd: f64, dt_s: f64) {
        let blinking = self.params.blinking;
        for qd in &mut self.qds {
            if sd > 0.0 {
                for (axis, (value, (low, high))) in qd.at.iter_mut().zip(self.bounds).enumerate() {
                    let bits = self.rng.next_u32();
                    *value += sd * standard_normal_from_bits(bits, &mut self.rng);
                    let span = high - low;
                    if *value < low || *value >= high {
                        let wrapped = low + (*value - low).rem_euclid(span);
                        if axis < 2 {
                            qd.shift[axis] += *value - wrapped;
                            qd.wrapped = true;
                        }
                        *value = wrapped;
                    }
                }
            }
            if let Some(b) = blinking {
                b.run(&mut self.rng, &mut qd.on, &mut qd.state_left_s, dt_s);
            }
        }
    }

    /// One PSF sample with the beam at `(beam_x, beam_y)` µm at time `t_s`:
    /// each QD's photons (if on) go to `pixel`, its position to its sums.
    fn sample(&mut self, beam_x: f64, beam_y: f64, t_s: f64, pixel: Option<&mut f64>) {
        let mut photons = 0.0;
        for qd in &mut self.qds {
            let [x, y, z] = qd.at;
            let (path_x, path_y) = (x + qd.shift[0], y + qd.shift[1]);
            let sums = &mut qd.sums;
            sums.x += path_x;
            sums.y += path_y;
            sums.z += z;
            if qd.on {
                sums.on_samples += 1.0;
            }
            let (dx, dy) = (x - beam_x, y - beam_y);
            let r2 = dx * dx + dy * dy;
            if r2 > self.pre.cutoff2 {
                continue;
            }
            let weight = (-r2 * self.pre.inv_two_sigma_xy2).exp();
            sums.weight += weight;
            sums.weighted_x += weight * path_x;
            sums.weighted_y += weight * path_y;
            sums.weighted_t += weight * t_s;
            if qd.on {
                photons += self.pre.sample_photons(self.amplitude, dx, dy, z);
            }
        }
        if let Some(pixel) = pixel {
            *pixel += photons;
        }
    }

    /// Scans frame `frame`: steps and samples every QD at every sample,
    /// adding the expected signal to `expected` (row-major) when given,
    /// then appends the truth rows of the QDs in the field. The step into
    /// the frame's first sample covers the flyback and dead time (none
    /// before frame 0).
    fn scan_frame(
        &mut self,
        frame: usize,
        mut expected: Option<&mut [f64]>,
        truth: &mut Vec<RecordingTruthRow>,
    ) {
        let micro = &self.params.microscope;
        let s = micro.substeps as usize;
        let (step_sd, retrace_sd) = self.pre.step_sds(self.diffusion);
        let sample_dt = self.pre.dwell_s / self.pre.substeps;
        let dead_s = self.params.dead_time_ms * 1e-3;
        let dead_sd = (2.0 * self.diffusion * (sample_dt + self.pre.retrace_s + dead_s)).sqrt();
        let line_s = self.params.line_time_s();
        let start_s = frame as f64 * self.params.frame_period_s();
        for qd in &mut self.qds {
            qd.sums = FrameSums::default();
            if qd.wrapped {
                qd.id = self.next_id;
                self.next_id += 1;
            }
            qd.wrapped = false;
            qd.shift = [0.0; 2];
        }
        for row in 0..micro.height {
            let beam_y = (row as f64 + 0.5) * micro.pixel_size_um;
            for k in 0..micro.width * s {
                let (sd, dt) = match (row, k) {
                    (0, 0) if frame == 0 => (0.0, 0.0),
                    (0, 0) => (dead_sd, sample_dt + self.pre.retrace_s + dead_s),
                    (_, 0) => (retrace_sd, sample_dt + self.pre.retrace_s),
                    _ => (step_sd, sample_dt),
                };
                self.step(sd, dt);
                let t_s = start_s + row as f64 * line_s + k as f64 * sample_dt;
                let pixel = expected
                    .as_deref_mut()
                    .map(|image| &mut image[row * micro.width + k / s]);
                self.sample(self.pre.beam_x[k], beam_y, t_s, pixel);
            }
        }
        self.emit_truth(frame, start_s, truth);
    }

    /// Appends the truth rows of frame `frame` (started at `start_s`) for
    /// the QDs whose centroid (of their unwrapped path) is in the field.
    fn emit_truth(&self, frame: usize, start_s: f64, truth: &mut Vec<RecordingTruthRow>) {
        let micro = &self.params.microscope;
        let a = micro.pixel_size_um;
        let s = micro.substeps as usize;
        let samples = (micro.height * micro.width * s) as f64;
        let sample_dt = self.pre.dwell_s / self.pre.substeps;
        let line_s = self.params.line_time_s();
        let mid_s = start_s
            + (micro.height as f64 - 1.0) / 2.0 * line_s
            + (micro.width * s) as f64 / 2.0 * sample_dt
            - sample_dt / 2.0;
        let (w, h) = (micro.width as f64, micro.height as f64);
        let first = truth.len();
        for qd in &self.qds {
            let sums = &qd.sums;
            let x = sums.x / samples / a - 0.5;
            let y = sums.y / samples / a - 0.5;
            let seen = |value: f64| value / sums.weight;
            let (x_seen, y_seen) = (
                seen(sums.weighted_x) / a - 0.5,
                seen(sums.weighted_y) / a - 0.5,
            );
            let inside =
                |x: f64, y: f64| (-0.5..w - 0.5).contains(&x) && (-0.5..h - 0.5).contains(&y);
            if !(inside(x, y) || inside(x_seen, y_seen)) {
                continue;
            }
            truth.push(RecordingTruthRow {
                frame,
                qd: qd.id,
                x,
                y,
                z_mean: sums.z / samples,
                on_fraction: sums.on_samples / samples,
                x_seen,
                y_seen,
                t_mid: mid_s,
                t_beam: start_s
                    + y.clamp(0.0, h - 1.0) * line_s
                    + x.clamp(0.0, w - 1.0) * self.pre.dwell_s,
                t_seen: seen(sums.weighted_t),
                diffusion: self.diffusion,
            });
        }
        truth[first..].sort_by_key(|row| row.qd);
    }
}

/// Simulates a recording with `params` and `seed`: its frames (photon
/// counts, when `render`) and truth. Without `render` no image is made and
/// no noise drawn (the walk and the truth are the same either way), which
/// is what checks of tracking and D estimation on true positions need.
pub fn simulate_recording(
    params: &RecordingParams,
    seed: u64,
    render: bool,
) -> anyhow::Result<SimulatedRecording> {
    simulate_recording_with_progress(params, seed, render, &ProgressBar::hidden())
}

/// [`simulate_recording`], advancing `progress` by one per frame scanned
/// (its length set to the recording's frames): one walk that cannot be
/// split across threads, which takes minutes on a large field (3,000
/// frames of 128 × 128 in about 50 s).
pub fn simulate_recording_with_progress(
    params: &RecordingParams,
    seed: u64,
    render: bool,
    progress: &ProgressBar,
) -> anyhow::Result<SimulatedRecording> {
    simulate_recording_stoppable(params, seed, render, progress, &|| false)
}

/// [`simulate_recording_with_progress`], asking `stop` before each frame
/// and failing with [`Stopped`] once it says yes (Ctrl-C in Python: the
/// walk cannot be split, so it is stopped from within).
pub fn simulate_recording_stoppable(
    params: &RecordingParams,
    seed: u64,
    render: bool,
    progress: &ProgressBar,
    stop: &dyn Fn() -> bool,
) -> anyhow::Result<SimulatedRecording> {
    params
        .validate()
        .map_err(|e| input_error(format!("invalid recording parameter: {e}")))?;
    let micro = &params.microscope;
    let frame_len = micro.height * micro.width;
    let mut walk = Walk::new(params, seed);
    let qds = walk.qds.len();
    let mut truth = Vec::new();
    // At its final size from the start: a growing vector would hold up to
    // twice the counts while it moves them.
    let mut data = Vec::with_capacity(if render { params.frames * frame_len } else { 0 });
    let mut expected = vec![0.0; if render { frame_len } else { 0 }];
    let mut noise_words = Vec::new();
    let detector = Detector::new(
        micro.detector_noise,
        micro.background.fixed().unwrap_or(0.0),
    );
    progress.set_length(params.frames as u64);
    for frame in 0..params.frames {
        if stop() {
            return Err(anyhow::Error::new(Stopped));
        }
        progress.inc(1);
        if !render {
            walk.scan_frame(frame, None, &mut truth);
            continue;
        }
        expected.fill(0.0);
        walk.scan_frame(frame, Some(&mut expected), &mut truth);
        let mut counts = vec![0u32; frame_len];
        let mut rng = frame_rng(seed, frame + 1);
        record_counts(
            &detector,
            &mut rng,
            &expected,
            &mut noise_words,
            &mut counts,
            frame,
        )?;
        data.extend_from_slice(&counts);
    }
    let frames = if render {
        FrameStack::from_vec(params.frames, micro.height, micro.width, data)?
    } else {
        FrameStack::default()
    };
    Ok(SimulatedRecording { frames, truth, qds })
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;

    use super::*;

    /// The share of `steps` steps of `dt_s` after which the clock is on,
    /// from the stationary state.
    fn on_share(blinking: Blinking, dt_s: f64, steps: usize) -> f64 {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (mut on, mut left) = (true, exponential(&mut rng, blinking.mean_s(true)));
        let mut count = 0usize;
        for _ in 0..steps {
            blinking.run(&mut rng, &mut on, &mut left, dt_s);
            assert!(left > 0.0);
            count += usize::from(on);
        }
        count as f64 / steps as f64
    }

    #[test]
    fn blinking_far_faster_than_a_step_keeps_its_odds_at_a_bounded_cost() {
        // Switch by switch these steps would take 1e300 draws each.
        let fast = Blinking {
            on_ms: 1e-300,
            off_ms: 2e-300,
        };
        let share = on_share(fast, 2e-6, 20_000);
        // Independent draws of the stationary state: SE 0.0033; 6 SE.
        assert!((share - 1.0 / 3.0).abs() < 0.02, "{share}");
    }

    #[test]
    fn both_ways_of_running_the_clock_give_the_telegraph_odds() {
        let b = Blinking {
            on_ms: 1.0,
            off_ms: 3.0,
        };
        // Switch by switch (steps of one on period) and by the transition
        // law (steps of 40 cycles); both must give π_on = 1/4. 40,000
        // steps, correlated over ≈ 1.5 of the first kind: SE ≤ 0.003,
        // tolerance 5 SE.
        for (dt_s, tolerance) in [(1e-3, 0.015), (0.16, 0.015)] {
            let share = on_share(b, dt_s, 40_000);
            assert!((share - 0.25).abs() < tolerance, "dt {dt_s}: {share}");
        }
    }

    /// A recording of the paper's microscope, `frames` long.
    fn small(frames: usize) -> RecordingParams {
        RecordingParams {
            microscope: SimParams::default(),
            frames,
            density_per_um3: 1.0,
            qd_count: None,
            lateral_margin_um: 1.0,
            half_depth_um: 2.0,
            blinking: None,
            dead_time_ms: 0.0,
        }
    }

    #[test]
    fn a_dead_time_beyond_a_minute_is_refused() {
        let params = RecordingParams {
            dead_time_ms: MAX_DEAD_TIME_MS * 2.0,
            ..small(2)
        };
        let error = params.validate().unwrap_err();
        assert!(error.to_string().contains("dead_time_ms"), "{error}");
    }

    #[test]
    fn a_stop_request_ends_the_walk_before_the_next_frame() {
        let params = small(50);
        let progress = ProgressBar::hidden();
        let stop = || progress.position() >= 3;
        let Err(error) = simulate_recording_stoppable(&params, 1, true, &progress, &stop) else {
            panic!("the walk did not stop");
        };
        assert!(error.is::<Stopped>(), "{error}");
        assert_eq!(progress.position(), 3);
        let whole = simulate_recording_stoppable(&params, 1, true, &progress, &|| false).unwrap();
        assert_eq!(whole.frames.n, 50);
    }
}
