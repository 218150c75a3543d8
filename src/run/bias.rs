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

use anyhow::Context;

use super::artefacts::Artefact;
use crate::manifest::{DetectorEntry, RecordingSpec};
use crate::sim::recording::{MAX_RECORDING_QDS, RecordingParams, simulate_recording_with_progress};
use crate::track::diffusion::Method;
use crate::track::pipeline::{
    CorrectedEnsemble, LinkerSpec, TrackEvaluation, link_predictions, ml_ensemble_of,
    scores_at_least,
};
use crate::types::{FrameStack, Prediction, derive_seed};

/// Version of the bias correction (its recipe: the pilot's length, the
/// matching of the QD count, the seeds and the correction's formula; the
/// number of simulated recordings is in the scoring).
pub const BIAS_CORRECTION_VERSION: &str = "scanloc-bias-correction/1";

/// The pilot recording is this share of the recording's frames: enough to
/// measure the localisations per QD and frame to about 3 %.
const PILOT_SHARE: usize = 4;

/// The pipeline a simulated recording is put through.
pub(super) struct Pipeline<'a> {
    pub detector: &'a DetectorEntry,
    /// The trained model of a trained detector.
    pub model: Option<&'a Artefact>,
    /// Only localisations scoring at least this are linked.
    pub min_score: Option<f64>,
    pub linker: &'a LinkerSpec,
}

impl Pipeline<'_> {
    /// The localisations of `frames` the pipeline links.
    fn kept(
        &self,
        label: &str,
        frames: &FrameStack,
        spec: &RecordingSpec,
    ) -> anyhow::Result<Vec<Prediction>> {
        let predictions = super::compute::locate_frames(
            label,
            self.detector,
            frames,
            self.model,
            Some(&spec.params.microscope),
        )?;
        Ok(predictions
            .into_iter()
            .filter(|p| scores_at_least(p, self.min_score))
            .collect())
    }
}

/// The ML ensemble of `evaluation` (the pipeline's scores on recording
/// `spec`, whose localisations were `predictions`) corrected by
/// `recordings` simulated recordings drawn from `seed`; `None` where the
/// pipeline gave no ensemble on the recording or on the simulated ones.
/// Progress is shown under `label`.
pub(super) fn correct_ensemble(
    label: &str,
    seed: u64,
    recordings: usize,
    spec: &RecordingSpec,
    pipeline: &Pipeline,
    predictions: &[Prediction],
    evaluation: &TrackEvaluation,
) -> anyhow::Result<Option<CorrectedEnsemble>> {
    let Some(recorded) = evaluation.estimator(Method::Ml).and_then(|e| e.ensemble) else {
        return Ok(None);
    };
    if !(recorded.d.is_finite() && recorded.d > 0.0) {
        return Ok(None);
    }
    let frames = spec.params.frames;
    let per_frame = |count: usize, frames: usize| count as f64 / frames.max(1) as f64;
    let recorded_rate = per_frame(
        predictions
            .iter()
            .filter(|p| scores_at_least(p, pipeline.min_score))
            .count(),
        frames,
    );

    // The pilot: the volume's expected number of QDs, a quarter as long.
    let pilot_qds = spec.params.qd_count.unwrap_or_else(|| {
        (spec.params.density_per_um3 * spec.params.volume_um3())
            .round()
            .max(1.0) as u64
    });
    let pilot_frames = frames.div_ceil(PILOT_SHARE);
    let pilot = simulate(
        spec,
        recorded.d,
        pilot_qds,
        pilot_frames,
        derive_seed(seed, "bias-correction", "pilot"),
        &format!("{label}: bias pilot"),
    )?;
    let pilot_rate = per_frame(
        pipeline
            .kept(&format!("{label}: locating the pilot"), &pilot, spec)?
            .len(),
        pilot_frames,
    );
    drop(pilot);
    if pilot_rate == 0.0 {
        eprintln!(
            "warning: {label}: no bias correction: the pipeline found nothing in its pilot recording"
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
    let geometry = spec.geometry();
    let mut tracks = Vec::new();
    for index in 1..=recordings {
        let name = format!("{label}: bias recording {index}/{recordings}");
        let seed = derive_seed(seed, "bias-correction", &format!("recording-{index}"));
        let simulated = simulate(spec, recorded.d, qds, frames, seed, &name)?;
        let localisations = pipeline.kept(&format!("{name}, locating"), &simulated, spec)?;
        drop(simulated);
        let progress = crate::progress::heartbeat(&format!("{name}, linking"));
        tracks.extend(link_predictions(
            &localisations,
            None,
            pipeline.linker,
            &geometry,
        )?);
        progress.finish_and_clear();
    }
    let progress = crate::progress::heartbeat(&format!("{label}: bias recordings' ML ensemble"));
    let estimate = ml_ensemble_of(&tracks, &geometry, &evaluation.scoring);
    progress.finish_and_clear();
    let Some(estimate) = estimate else {
        eprintln!("warning: {label}: no bias correction: no ML ensemble on the bias recordings");
        return Ok(None);
    };
    Ok(CorrectedEnsemble::new(
        &recorded,
        &estimate,
        evaluation.true_diffusion_um2_s,
        (pilot_qds, qds),
        frames * recordings,
    ))
}

/// The frames of a recording like `spec`'s at D = `d` with `qds` QDs and
/// `frames` frames, drawn from `seed`.
fn simulate(
    spec: &RecordingSpec,
    d: f64,
    qds: u64,
    frames: usize,
    seed: u64,
    label: &str,
) -> anyhow::Result<FrameStack> {
    let mut microscope = spec.params.microscope.clone();
    microscope.diffusion_um2_s = d.into();
    let params = RecordingParams {
        microscope,
        frames,
        qd_count: Some(qds),
        ..spec.params.clone()
    };
    let progress = crate::progress::bar(frames as u64, label);
    let made = simulate_recording_with_progress(&params, seed, true, &progress)
        .with_context(|| format!("simulating {label}"))?;
    progress.finish_and_clear();
    Ok(made.frames)
}
