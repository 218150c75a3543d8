//! A tracking pipeline's ML ensemble corrected for the pipeline's own bias
//! by simulation (`docs/tracking.md`, "Bias correction by simulation").
//!
//! The pipeline read `D̂` on a recording. Recordings like it are simulated
//! at D = `D̂`: the same scan, photon counts, blinking and frames, and as
//! many QDs as give the recording's localisations per frame (found with a
//! pilot recording a quarter as long). The same localiser, threshold,
//! linker and ML ensemble read `D̂ₛ` on their tracks together, so near `D̂`
//! the pipeline reads D high by `D̂ₛ/D̂`, and the corrected D is `D̂²/D̂ₛ`
//! ([`CorrectedEnsemble::new`]). This is one step of indirect inference:
//! it corrects whatever the simulator reproduces (a localiser's error tails,
//! wrong links between QDs, blinking, the field's edges) without a model of
//! each, to first order in the bias.
//!
//! The procedure ([`measure_bias`]) is generic over the localiser: any
//! function from frames to predictions (a manifest's detector with its
//! trained model, or `scanloc track`'s).

use anyhow::Context;
use indicatif::ProgressBar;

use super::config::{LinkerSpec, TrackScoring};
use super::link::{link_predictions, scores_at_least};
use super::records::{CorrectedEnsemble, StoredEstimate};
use crate::sim::recording::{MAX_RECORDING_QDS, RecordingParams, simulate_recording_stoppable};
use crate::track::diffusion::ScanGeometry;
use crate::types::{FrameStack, Prediction, derive_seed};

/// Version of the bias correction (its recipe: the pilot's length, the
/// matching of the QD count, the seeds and the correction's formula; the
/// number of simulated recordings is in the scoring).
pub const BIAS_CORRECTION_VERSION: &str = "scanloc-bias-correction/1";

/// The pilot recording is this share of the recording's frames: enough to
/// measure the localisations per QD and frame to about 3 %.
const PILOT_SHARE: usize = 4;

/// A localiser: the predictions in `frames`, its progress shown under
/// the label it is given.
pub type Localiser<'a> = dyn FnMut(&str, &FrameStack) -> anyhow::Result<Vec<Prediction>> + 'a;

/// What a bias correction simulates, how it reads D there, and how it
/// shows its simulations' progress.
#[derive(Clone, Copy)]
pub struct BiasSetup<'a> {
    /// The recording as the simulator would make it: microscope, frames,
    /// volume, blinking, dead time (its D and QD count are replaced).
    pub recording: &'a RecordingParams,
    /// Every simulated recording's seed is derived from it.
    pub seed: u64,
    /// How many recordings as long as the recording are simulated.
    pub recordings: usize,
    /// Only localisations scoring at least this are linked.
    pub min_score: Option<f64>,
    pub linker: &'a LinkerSpec,
    /// The ML ensemble's gate share and margin.
    pub scoring: &'a TrackScoring,
    /// The progress bar of a simulation of `len` frames labelled `label`.
    pub bar: &'a dyn Fn(u64, &str) -> ProgressBar,
    /// Asked before each simulated frame; yes stops the correction with
    /// [`crate::error::Stopped`].
    pub stop: &'a dyn Fn() -> bool,
}

/// The scan geometry of a recording made with `params`.
pub fn recording_geometry(params: &RecordingParams) -> ScanGeometry {
    ScanGeometry::of(&params.microscope, params.dead_time_ms)
}

/// What the pipeline read on the recordings simulated at its own D̂.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimulatedBias {
    /// The ML ensemble on the simulated recordings' tracks together.
    pub estimate: StoredEstimate,
    /// QDs in the pilot and in each simulated recording.
    pub pilot_qds: u64,
    pub qds: u64,
    /// The simulated recordings' frames, all together.
    pub frames: usize,
}

/// Measures the pipeline's bias at D = `recorded_d` (the ML ensemble it
/// read on the recording, where it kept `recorded_kept` localisations):
/// simulates recordings like `setup.recording` at that D, puts them
/// through `localise`, the threshold, the linker and the ML ensemble.
/// `None` (with a warning) where the pilot gives no localisation or the
/// simulated recordings no ensemble. Progress is shown under `label`.
pub fn measure_bias(
    label: &str,
    setup: &BiasSetup,
    recorded_d: f64,
    recorded_kept: usize,
    localise: &mut Localiser,
) -> anyhow::Result<Option<SimulatedBias>> {
    if !(recorded_d.is_finite() && recorded_d > 0.0) {
        return Ok(None);
    }
    let spec = setup.recording;
    let frames = spec.frames;
    let per_frame = |count: usize, frames: usize| count as f64 / frames.max(1) as f64;
    let recorded_rate = per_frame(recorded_kept, frames);
    let mut kept = |label: &str, frames: &FrameStack| -> anyhow::Result<Vec<Prediction>> {
        Ok(localise(label, frames)?
            .into_iter()
            .filter(|p| scores_at_least(p, setup.min_score))
            .collect())
    };

    // The pilot: the volume's expected number of QDs, a quarter as long.
    let pilot_qds = spec
        .qd_count
        .unwrap_or_else(|| (spec.density_per_um3 * spec.volume_um3()).round().max(1.0) as u64)
        .clamp(1, MAX_RECORDING_QDS / 2);
    let pilot_frames = frames.div_ceil(PILOT_SHARE);
    let pilot = simulate(
        setup,
        spec,
        recorded_d,
        pilot_qds,
        pilot_frames,
        derive_seed(setup.seed, "bias-correction", "pilot"),
        &format!("{label}: bias pilot"),
    )?;
    let pilot_rate = per_frame(
        kept(&format!("{label}: locating the pilot"), &pilot)?.len(),
        pilot_frames,
    );
    drop(pilot);
    if pilot_rate == 0.0 {
        tracing::warn!(
            "{label}: no bias correction: the pipeline found nothing in its pilot recording"
        );
        return Ok(None);
    }

    // As many QDs as give the recording's localisations per frame (they
    // are proportional to the QDs, false detections aside).
    let qds = (pilot_qds as f64 * recorded_rate / pilot_rate)
        .round()
        .clamp(1.0, (MAX_RECORDING_QDS / 2) as f64) as u64;
    // The simulated recordings, one at a time (each as large as the
    // recording in memory), their tracks pooled.
    let geometry = recording_geometry(spec);
    let mut tracks = Vec::new();
    for index in 1..=setup.recordings {
        let name = format!("{label}: bias recording {index}/{}", setup.recordings);
        let seed = derive_seed(setup.seed, "bias-correction", &format!("recording-{index}"));
        let simulated = simulate(setup, spec, recorded_d, qds, frames, seed, &name)?;
        let localisations = kept(&format!("{name}, locating"), &simulated)?;
        drop(simulated);
        let progress = crate::progress::heartbeat(&format!("{name}, linking"));
        tracks.extend(link_predictions(
            &localisations,
            None,
            setup.linker,
            &geometry,
        )?);
        progress.finish_and_clear();
    }
    let progress = crate::progress::heartbeat(&format!("{label}: bias recordings' ML ensemble"));
    let estimate = super::evaluate::ml_ensemble_of(&tracks, &geometry, setup.scoring);
    progress.finish_and_clear();
    let Some(estimate) = estimate else {
        tracing::warn!("{label}: no bias correction: no ML ensemble on the bias recordings");
        return Ok(None);
    };
    Ok(Some(SimulatedBias {
        estimate,
        pilot_qds,
        qds,
        frames: frames * setup.recordings,
    }))
}

/// `recorded` (the pipeline's ML ensemble on a recording whose true D is
/// `true_d`, NaN where unknown; `recorded_kept` localisations linked)
/// corrected by [`measure_bias`]; `None` where either gives no positive D.
pub fn correct_ensemble(
    label: &str,
    setup: &BiasSetup,
    recorded: &StoredEstimate,
    recorded_kept: usize,
    true_d: f64,
    localise: &mut Localiser,
) -> anyhow::Result<Option<CorrectedEnsemble>> {
    let Some(bias) = measure_bias(label, setup, recorded.d, recorded_kept, localise)? else {
        return Ok(None);
    };
    Ok(CorrectedEnsemble::new(
        recorded,
        &bias.estimate,
        true_d,
        (bias.pilot_qds, bias.qds),
        bias.frames,
    ))
}

/// The frames of a recording like `spec` at D = `d` with `qds` QDs and
/// `frames` frames, drawn from `seed`, its progress and stop through
/// `setup`.
fn simulate(
    setup: &BiasSetup,
    spec: &RecordingParams,
    d: f64,
    qds: u64,
    frames: usize,
    seed: u64,
    label: &str,
) -> anyhow::Result<FrameStack> {
    let mut microscope = spec.microscope.clone();
    microscope.diffusion_um2_s = d.into();
    let params = RecordingParams {
        microscope,
        frames,
        qd_count: Some(qds),
        ..spec.clone()
    };
    let progress = (setup.bar)(frames as u64, label);
    let made = simulate_recording_stoppable(&params, seed, true, &progress, setup.stop)
        .with_context(|| format!("simulating {label}"))?;
    progress.finish_and_clear();
    Ok(made.frames)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::crocker_grier::{CrockerGrierParams, locate_stack, to_predictions};
    use crate::sim::SimParams;
    use crate::sim::recording::simulate_recording;
    use crate::track::pipeline::{LapSettings, evaluate::ml_ensemble_of};

    #[test]
    fn the_correction_brings_crocker_grier_closer_to_the_true_d() {
        // A recording of the paper's microscope at D = 1 located by
        // crocker-grier with a low mass cut (so false localisations
        // bias the raw D), linked by the LAP with relinking.
        let true_d = 1.0;
        let params = RecordingParams {
            microscope: SimParams {
                diffusion_um2_s: true_d.into(),
                ..SimParams::default()
            },
            frames: 3000,
            density_per_um3: 0.05,
            qd_count: None,
            lateral_margin_um: 1.5,
            half_depth_um: 4.0,
            blinking: None,
            dead_time_ms: 0.0,
        };
        let recording = simulate_recording(&params, 11, true).unwrap();
        let detector = CrockerGrierParams {
            diameter: 7,
            minmass: Some(30.0),
            ..CrockerGrierParams::default()
        };
        let mut localise = |_: &str, frames: &FrameStack| {
            let features = locate_stack(frames, &detector, &crate::progress::hidden())?;
            Ok(to_predictions(&features))
        };
        let linker = LinkerSpec::Lap(LapSettings {
            search_range: Some(14.0),
            diffusion_um2_s: None,
            max_gap: 2,
            gate_sigmas: None,
            relink: true,
        });
        let scoring = TrackScoring {
            ensemble_margin_px: 2.0,
            ..TrackScoring::default()
        };
        let geometry = recording_geometry(&params);
        let predictions = localise("", &recording.frames).unwrap();
        let tracks = link_predictions(&predictions, None, &linker, &geometry).unwrap();
        let raw = ml_ensemble_of(&tracks, &geometry, &scoring).unwrap();
        let setup = BiasSetup {
            recording: &params,
            seed: 5,
            recordings: 2,
            min_score: None,
            linker: &linker,
            scoring: &scoring,
            bar: &|_, _| ProgressBar::hidden(),
            stop: &|| false,
        };
        let corrected = correct_ensemble(
            "test",
            &setup,
            &raw,
            predictions.len(),
            true_d,
            &mut localise,
        )
        .unwrap()
        .unwrap();
        let raw_error = raw.d / true_d - 1.0;
        let error = corrected.relative_error;
        // The raw D is far off (false localisations linked into the
        // tracks); the correction, to first order in the bias, must remove
        // at least a quarter of it (measured: about half, +142 % to +75 %
        // at 8,000 frames).
        assert!(
            raw_error > 0.3,
            "raw {raw_error:+.3}: the pipeline is not biased"
        );
        assert!(
            error.abs() < 0.75 * raw_error.abs(),
            "corrected {error:+.3}, raw {raw_error:+.3}"
        );
        assert_eq!(corrected.simulated_frames, 6000);
    }
}
