//! Tracks scored against a recording's truth: the tracking measures and,
//! per estimator, D for the ensemble and per track.

use super::config::TrackScoring;
use super::link::series_of;
use super::records::{EstimatorScore, StoredEstimate, TrackEstimate, TrackEvaluation};
use crate::metrics::diffusion::{DiffusionInterval, score_diffusion};
use crate::metrics::tracking::{score_tracks, truth_tracks};
use crate::track::diffusion::{Estimate, Method, ScanGeometry, Series, estimate_recording};
use crate::types::{RecordingTruthRow, Track};

/// Scores `tracks` against a recording's `truth` (true D `true_d`, scan
/// `geometry`, the exposure [`ScanGeometry::auto_exposure`] picks; σ²
/// profiled by every estimator, see [`series_of`]).
pub fn evaluate(
    truth: &[RecordingTruthRow],
    tracks: &[Track],
    geometry: &ScanGeometry,
    scoring: &TrackScoring,
    true_d: f64,
    progress: &indicatif::ProgressBar,
) -> anyhow::Result<TrackEvaluation> {
    progress.set_length(1 + Method::ALL.len() as u64);
    let truth_tracks = truth_tracks(truth, &scoring.selection());
    let tracking = score_tracks(&truth_tracks, tracks, scoring.gate_px)?;
    progress.inc(1);
    let series = series_of(tracks, geometry);
    let diffusion = Method::ALL
        .into_iter()
        .map(|method| {
            let estimates = estimate_recording(
                &series,
                method,
                scoring.min_points,
                scoring.ensemble_gate,
                scoring.ensemble_margin_px * geometry.pixel_size_um,
            );
            let ensemble = estimates.ensemble.map(StoredEstimate::from);
            let per_track = track_estimates(tracks, &series, estimates.per_track);
            let valid: Vec<DiffusionInterval> = per_track
                .iter()
                .filter(|t| t.estimate.interval_valid)
                .map(|t| t.estimate.interval())
                .collect();
            progress.inc(1);
            EstimatorScore {
                method,
                ensemble_relative_error: ensemble.map(|e| e.d / true_d - 1.0),
                ensemble,
                per_track: score_diffusion(&valid, true_d),
                tracks: per_track,
                dispersion: estimates.dispersion,
                ensemble_dispersion: estimates.ensemble_dispersion,
            }
        })
        .collect();
    Ok(TrackEvaluation {
        tracking,
        true_diffusion_um2_s: true_d,
        scoring: *scoring,
        diffusion,
        corrected_ensemble: None,
    })
}

/// The estimates of `tracks` (whose series are `series`) that got one,
/// from `per_track` (one entry per track, in order), as stored: by
/// particle, with the track's localisations.
pub fn track_estimates(
    tracks: &[Track],
    series: &[Series],
    per_track: Vec<Option<Estimate>>,
) -> Vec<TrackEstimate> {
    per_track
        .into_iter()
        .enumerate()
        .filter_map(|(index, e)| {
            e.map(|e| TrackEstimate {
                particle: tracks[index].particle,
                points: series[index].len(),
                estimate: e.into(),
            })
        })
        .collect()
}

/// The ML ensemble of `tracks` as [`evaluate`] takes it under `scoring`
/// (its gate share and margin), without the truth: what a bias correction
/// measures on a simulated recording.
pub fn ml_ensemble_of(
    tracks: &[Track],
    geometry: &ScanGeometry,
    scoring: &TrackScoring,
) -> Option<StoredEstimate> {
    let series = series_of(tracks, geometry);
    let (estimate, _) = crate::track::diffusion::ml_ensemble(
        &series,
        scoring.ensemble_gate,
        scoring.ensemble_margin_px * geometry.pixel_size_um,
    )?;
    Some(estimate.into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::SimParams;
    use crate::sim::recording::{RecordingParams, simulate_recording};
    use crate::track::pipeline::{LapSettings, LinkerSpec, TrackpySettings, link_predictions};
    use crate::types::Prediction;

    fn geometry(params: &SimParams) -> ScanGeometry {
        ScanGeometry::of(params, 0.0)
    }

    #[test]
    fn true_positions_linked_by_either_linker_give_good_tracks_and_d() {
        // The truth positions of a recording (no detector): the pipeline
        // must find nearly every link and an ensemble D within a few
        // standard errors of the truth.
        let params = RecordingParams {
            microscope: SimParams {
                diffusion_um2_s: 1.0.into(),
                ..SimParams::default()
            },
            frames: 1500,
            density_per_um3: 0.05,
            qd_count: None,
            lateral_margin_um: 0.3,
            half_depth_um: 4.0,
            blinking: None,
            dead_time_ms: 0.0,
        };
        let recording = simulate_recording(&params, 5, false).unwrap();
        let scoring = TrackScoring {
            gate_px: 1.0,
            max_depth_um: Some(1.36),
            split_gaps_over: Some(2),
            ..TrackScoring::default()
        };
        let predictions: Vec<Prediction> = recording
            .truth
            .iter()
            .filter(|r| r.z_mean.abs() <= 1.36)
            .map(|r| Prediction::new(r.frame, r.x, r.y, 1.0))
            .collect();
        let geometry = geometry(&params.microscope);
        for linker in [
            LinkerSpec::Trackpy(TrackpySettings {
                search_range: 10.0,
                memory: 2,
            }),
            LinkerSpec::Lap(LapSettings {
                gate_sigmas: None,
                search_range: None,
                diffusion_um2_s: Some(1.0),
                max_gap: 2,
                relink: false,
            }),
            LinkerSpec::Lap(LapSettings {
                gate_sigmas: None,
                search_range: Some(10.0),
                diffusion_um2_s: None,
                max_gap: 2,
                relink: true,
            }),
        ] {
            let tracks = link_predictions(&predictions, None, &linker, &geometry).unwrap();
            let scored = evaluate(
                &recording.truth,
                &tracks,
                &geometry,
                &scoring,
                1.0,
                &crate::progress::hidden(),
            )
            .unwrap();
            let recall = scored.tracking.link_recall.unwrap();
            assert!(recall > 0.9, "{linker:?}: link recall {recall}");
            let ml = scored.estimator(Method::Ml).unwrap();
            let ensemble = ml.ensemble.unwrap();
            let error = ml.ensemble_relative_error.unwrap();
            // Tolerance: 4 standard errors of the ensemble estimate.
            assert!(
                error.abs() < 4.0 * ensemble.standard_error,
                "{linker:?}: D {} (SE {})",
                ensemble.d,
                ensemble.standard_error
            );
            let per_track = ml.per_track.unwrap();
            assert!(per_track.count >= 5, "{per_track:?}");
            // Round trip through the stored JSON (NaN ≠ NaN, so compared
            // as JSON).
            let json = serde_json::to_vec(&scored).unwrap();
            let back: TrackEvaluation = serde_json::from_slice(&json).unwrap();
            assert_eq!(serde_json::to_vec(&back).unwrap(), json);
        }
    }

    #[test]
    fn a_score_threshold_drops_predictions_before_linking() {
        let predictions = vec![
            Prediction::new(0, 5.0, 5.0, 0.9),
            Prediction::new(1, 5.5, 5.0, 0.9),
            Prediction::new(1, 15.0, 15.0, 0.1),
        ];
        let geometry = geometry(&SimParams::default());
        let linker = LinkerSpec::Trackpy(TrackpySettings {
            search_range: 3.0,
            memory: 0,
        });
        let all = link_predictions(&predictions, None, &linker, &geometry).unwrap();
        assert_eq!(all.len(), 2);
        let kept = link_predictions(&predictions, Some(0.5), &linker, &geometry).unwrap();
        assert_eq!(kept.len(), 1);
        assert_eq!(kept[0].points.len(), 2);
    }

    #[test]
    fn linker_settings_are_checked() {
        let bad = LinkerSpec::Lap(LapSettings {
            gate_sigmas: None,
            search_range: Some(3.0),
            diffusion_um2_s: Some(1.0),
            max_gap: 2,
            relink: false,
        });
        assert!(bad.validate().is_err());
        let bad = LinkerSpec::Trackpy(TrackpySettings {
            search_range: f64::NAN,
            memory: 0,
        });
        assert!(bad.validate().is_err());
        let good: LinkerSpec = serde_yaml::from_str("!lap {search_range: 10}").unwrap();
        assert!(good.validate().is_ok());
        assert!(serde_yaml::from_str::<LinkerSpec>("!lap {range: 10}").is_err());
    }
}
