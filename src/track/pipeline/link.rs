//! Predictions into tracks: the score threshold, the linking, and the
//! tracks prepared for the D estimators.

use std::collections::BTreeMap;

use super::config::LinkerSpec;
use crate::error::input_error;
use crate::track::diffusion::{
    ENSEMBLE_GATE, ScanGeometry, Series, attach_detection_profile, ml, within_gates,
};
use crate::track::{Detection, Linking, lap, trackpy};
use crate::types::{Prediction, Track, TrackPoint};

/// The ML ensemble's D (µm²/s) over all `tracks` as `scanloc diffusion`
/// reads it with its defaults: σ² profiled, the tracks' detection
/// profile, steps within [`ENSEMBLE_GATE`] of their gates, each run
/// given its first step.
pub(super) fn ensemble_ml(tracks: &[Track], geometry: &ScanGeometry) -> Option<f64> {
    let series = within_gates(&series_of(tracks, geometry), ENSEMBLE_GATE);
    let all: Vec<&Series> = series.iter().filter(|s| s.len() > 1).collect();
    ml::ensemble_estimate(&all).map(|e| e.d)
}

/// `tracks` prepared for the D estimators, with the exposure the scan
/// implies, their localisations' own σ left out ([`Track::without_sigma`]):
/// σ² is profiled. Each series carries the detection profile of all the
/// tracks' localisations.
pub fn series_of(tracks: &[Track], geometry: &ScanGeometry) -> Vec<Series> {
    let exposure = geometry.auto_exposure();
    let mut series: Vec<Series> = tracks
        .iter()
        .map(|track| Series::new(&track.without_sigma(), geometry, exposure))
        .collect();
    attach_detection_profile(&mut series, geometry.pixel_size_um);
    series
}

/// The tracks of `detections` as `linking` labelled them: one per label,
/// in label order, points in frame order, with the gates that admitted
/// their steps.
pub fn tracks_of(detections: &[Detection], linking: &Linking) -> Vec<Track> {
    let mut by_particle: BTreeMap<usize, Vec<TrackPoint>> = BTreeMap::new();
    for (i, (detection, &label)) in detections.iter().zip(&linking.particle).enumerate() {
        let gate = linking.gates.as_ref().and_then(|gates| gates[i]);
        by_particle.entry(label).or_default().push(TrackPoint {
            frame: detection.frame,
            x: detection.x,
            y: detection.y,
            sigma: detection.sigma.map(|s| (s.x, s.y)),
            time_s: None,
            gate: gate.map(|[x, y]| (x, y)),
        });
    }
    by_particle
        .into_iter()
        .map(|(label, mut points)| {
            points.sort_by_key(|p| p.frame);
            Track {
                particle: i64::try_from(label).unwrap_or(i64::MAX),
                points,
            }
        })
        .collect()
}

/// Whether `prediction` is linked under the score threshold `min_score`
/// (it scores at least that; every prediction without one).
pub fn scores_at_least(prediction: &Prediction, min_score: Option<f64>) -> bool {
    min_score.is_none_or(|least| prediction.score >= least)
}

/// Links the predictions scoring at least `min_score` (all when `None`)
/// into tracks: one per particle, labelled 0, 1, … in the linker's order,
/// points in frame order with the predictions' uncertainty.
pub fn link_predictions(
    predictions: &[Prediction],
    min_score: Option<f64>,
    linker: &LinkerSpec,
    geometry: &ScanGeometry,
) -> anyhow::Result<Vec<Track>> {
    let kept: Vec<&Prediction> = predictions
        .iter()
        .filter(|p| scores_at_least(p, min_score))
        .collect();
    let detections: Vec<Detection> = kept
        .iter()
        .map(|p| Detection {
            frame: p.frame,
            x: p.x,
            y: p.y,
            sigma: p.sigma,
        })
        .collect();
    let linking = linker.link(&detections, geometry)?;
    Ok(tracks_of(&detections, &linking))
}

impl LinkerSpec {
    /// Links `detections` of a recording with scan `geometry` (whose frame
    /// period and pixel size turn a diffusion coefficient into a step).
    pub fn link(
        &self,
        detections: &[Detection],
        geometry: &ScanGeometry,
    ) -> anyhow::Result<Linking> {
        match self {
            LinkerSpec::Trackpy(s) => trackpy::link(
                detections,
                &trackpy::TrackpyParams {
                    search_range: s.search_range,
                    memory: s.memory,
                },
            ),
            LinkerSpec::Lap(s) => {
                let gated = |params: lap::LapParams| lap::LapParams {
                    gate_sigmas: s.gate_sigmas.unwrap_or(lap::GATE_SIGMAS),
                    ..params
                };
                let with_diffusion = |d: f64| {
                    gated(lap::LapParams::from_diffusion(
                        d,
                        geometry.frame_period_s() * 1e3,
                        geometry.pixel_size_um,
                        s.max_gap,
                    ))
                };
                let params = match (s.search_range, s.diffusion_um2_s) {
                    (Some(range), _) => gated(lap::LapParams::from_search_range(range, s.max_gap)),
                    (None, Some(d)) => with_diffusion(d),
                    (None, None) => {
                        return Err(input_error(
                            "the lap linker needs search_range or diffusion_um2_s",
                        ));
                    }
                };
                let first = lap::link(detections, &params)?;
                if !s.relink {
                    return Ok(first);
                }
                // The second pass, with the first pass's D; if it gives
                // none (no step), the first pass stands.
                let tracks = tracks_of(detections, &first);
                match ensemble_ml(&tracks, geometry) {
                    Some(d) if d.is_finite() && d > 0.0 => {
                        lap::link(detections, &with_diffusion(d))
                    }
                    _ => Ok(first),
                }
            }
        }
    }
}
