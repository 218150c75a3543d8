//! D per track and for the ensemble of a tracks table: what `scanloc
//! diffusion` and the Python bindings' `scanloc.diffusion` both compute
//! (one implementation; docs/tracking.md, docs/python.md).

use super::Estimate;
use super::{
    ENSEMBLE_GATE, Exposure, Method, RecordingEstimates, ScanGeometry, Series,
    attach_detection_profile, estimate_recording,
};
use crate::error::{input_error, readable};
use crate::types::Track;

/// How D is estimated from a tracks table (the flags of `scanloc
/// diffusion`, with its defaults).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TableSettings {
    /// Which part of the scan a localisation averages.
    pub exposure: Exposure,
    /// A track's own estimate needs this many localisations (≥ 2).
    pub min_points: usize,
    /// Tell the estimators where the localiser misses particles.
    pub detection_profile: bool,
    /// The share of each link's gate the ML ensemble keeps its steps within.
    pub ensemble_gate: f64,
    /// The ML ensemble uses steps this many pixels inside the field.
    pub ensemble_margin_px: f64,
    /// Use the table's sigma_x, sigma_y as given localisation errors.
    pub given_sigma: bool,
}

impl TableSettings {
    /// The defaults of `scanloc diffusion` for a scan of `geometry`.
    pub fn for_geometry(geometry: &ScanGeometry) -> Self {
        Self {
            exposure: geometry.auto_exposure(),
            min_points: 3,
            detection_profile: true,
            ensemble_gate: ENSEMBLE_GATE,
            ensemble_margin_px: 0.0,
            given_sigma: false,
        }
    }

    /// Checks the settings against a scan of `geometry`, each error naming
    /// the flag: before a table is read, so a bad flag is answered first.
    pub fn check(&self, geometry: &ScanGeometry) -> anyhow::Result<()> {
        let settings = self;
        let margin = settings.ensemble_margin_px;
        if !(margin.is_finite() && margin >= 0.0) {
            return Err(input_error(format!(
                "--ensemble-margin-px: must be a finite number ≥ 0, got {}",
                readable(margin)
            )));
        }
        crate::track::pipeline::check_ensemble_margin(margin, geometry.height, geometry.width)
            .map_err(|e| input_error(format!("--ensemble-margin-px: {e}")))?;
        crate::track::pipeline::check_min_points("--min-points", settings.min_points)?;
        if !crate::track::pipeline::valid_ensemble_gate(settings.ensemble_gate) {
            return Err(input_error(format!(
                "--ensemble-gate: must be a share of the gate in (0, 0.707] or 1 (every step), got {}",
                readable(settings.ensemble_gate)
            )));
        }
        Ok(())
    }
}

/// The estimates of a tracks table by every method.
#[derive(Debug, Clone, PartialEq)]
pub struct TableEstimates {
    /// The tracks, in table order (without their σ unless asked).
    pub tracks: Vec<Track>,
    /// Each track's localisations.
    pub points: Vec<usize>,
    /// Localisations in the tracks of two localisations or more (the
    /// ensemble's).
    pub ensemble_points: usize,
    /// Per method ([`Method::ALL`]), its estimates.
    pub estimates: Vec<(Method, RecordingEstimates)>,
    /// What the user should be told beside the numbers (one line each).
    pub notes: Vec<String>,
}

/// D of each track of `tracks` (read from `source`, named in errors) and of
/// their ensemble, by every method, on a scan of `geometry`.
pub fn estimate_table(
    mut tracks: Vec<Track>,
    geometry: &ScanGeometry,
    settings: &TableSettings,
    source: &str,
) -> anyhow::Result<TableEstimates> {
    settings.check(geometry)?;
    let margin = settings.ensemble_margin_px;
    refuse_foreign_tracks(source, &tracks, geometry)?;
    let mut notes = Vec::new();
    if !settings.given_sigma && tracks.iter().any(|t| t.has_sigma()) {
        tracks = tracks.iter().map(|t| t.without_sigma()).collect();
        notes.push(
            "the table's sigma_x, sigma_y are not used: the localisation variance is estimated with D (--given-sigma uses them)"
                .to_string(),
        );
    }
    let mut series: Vec<Series> = tracks
        .iter()
        .map(|track| Series::new(track, geometry, settings.exposure))
        .collect();
    for (track, s) in tracks.iter().zip(&series) {
        if let Some(i) = s.first_step_shorter_than_blur() {
            return Err(input_error(format!(
                "{source}: particle {}: column time: the step from frame {} to frame {} lasts {} s, not more than the two localisations' blur ({} s): time stamps must increase with the frame, in seconds",
                track.particle,
                s.frames[i],
                s.frames[i + 1],
                readable(s.times[i + 1] - s.times[i]),
                readable(s.blur[i] + s.blur[i + 1]),
            )));
        }
    }
    if series.iter().all(|s| s.len() < 2) {
        return Err(input_error(format!(
            "{source}: no track has two localisations"
        )));
    }
    if settings.detection_profile {
        attach_detection_profile(&mut series, geometry.pixel_size_um);
    }
    let estimates: Vec<(Method, RecordingEstimates)> = Method::ALL
        .into_iter()
        .map(|method| {
            (
                method,
                estimate_recording(
                    &series,
                    method,
                    settings.min_points,
                    settings.ensemble_gate,
                    margin * geometry.pixel_size_um,
                ),
            )
        })
        .collect();
    refuse_non_finite(source, &tracks, &estimates)?;
    for (method, e) in &estimates {
        if let Some(phi) = e.dispersion.filter(|&phi| phi > 1.0) {
            notes.push(format!(
                "{}: the tracks' estimates scatter {phi:.2} times as much as the likelihood says; each track's interval is widened by that (docs/tracking.md, \"The estimators\")",
                method.name()
            ));
        }
        if let Some(phi) = e.ensemble_dispersion.filter(|&phi| phi > 1.0) {
            notes.push(format!(
                "{}: the ensemble's runs scatter {phi:.2} times as much as the likelihood says; the ensemble's interval is widened by that (docs/tracking.md, \"The estimators\")",
                method.name()
            ));
        }
    }
    for (method, e) in &estimates {
        if e.ensemble.is_none() {
            notes.push(format!(
                "{}: no ensemble estimate: too few steps{}",
                method.name(),
                if *method == Method::Ml && margin > 0.0 {
                    " inside the ensemble's margin (--ensemble-margin-px)"
                } else {
                    ""
                }
            ));
        }
    }
    let points: Vec<usize> = series.iter().map(Series::len).collect();
    let ensemble_points = points.iter().filter(|&&n| n > 1).sum();
    Ok(TableEstimates {
        tracks,
        points,
        ensemble_points,
        estimates,
        notes,
    })
}

/// How far outside the field a localisation may lie, in σxy of the PSF:
/// beyond it no pixel of the field sees the particle.
const FIELD_REACH_SIGMAS: f64 = 3.0;

/// Refuses tracks that cannot come from the scan `geometry` describes: a
/// localisation further outside the field than the PSF reaches (tracks of a
/// larger field analysed as a smaller one, whose D would come out far too
/// low), or a step whose `time` stamps differ from its frames' distance on
/// the frame clock by more than a frame period.
fn refuse_foreign_tracks(
    source: &str,
    tracks: &[Track],
    geometry: &ScanGeometry,
) -> anyhow::Result<()> {
    let reach = FIELD_REACH_SIGMAS * geometry.sigma_xy_um / geometry.pixel_size_um;
    let period = geometry.frame_period_s();
    for track in tracks {
        for point in &track.points {
            for (name, value, size, flag) in [
                ("x", point.x, geometry.width, "--width"),
                ("y", point.y, geometry.height, "--height"),
            ] {
                let (low, high) = (-0.5 - reach, size as f64 - 0.5 + reach);
                if !(low..=high).contains(&value) {
                    return Err(input_error(format!(
                        "{source}: particle {}: frame {}: column {name}: {} px is outside the {} × {} px field \
                         (by more than the PSF's reach, {} px); give the recording's {flag}",
                        track.particle,
                        point.frame,
                        readable(value),
                        geometry.height,
                        geometry.width,
                        readable(reach),
                    )));
                }
            }
        }
        for pair in track.points.windows(2) {
            let (Some(t0), Some(t1)) = (pair[0].time_s, pair[1].time_s) else {
                continue;
            };
            let frames = pair[1].frame as f64 - pair[0].frame as f64;
            if ((t1 - t0) - frames * period).abs() > period {
                return Err(input_error(format!(
                    "{source}: particle {}: column time: the step from frame {} to frame {} lasts {} s, \
                     where the frame clock gives {} s ± one frame period ({} s)",
                    track.particle,
                    pair[0].frame,
                    pair[1].frame,
                    readable(t1 - t0),
                    readable(frames * period),
                    readable(period),
                )));
            }
        }
    }
    Ok(())
}

/// Refuses results that are not finite numbers (the upper end of an
/// interval, and so its standard error, excepted, which may be infinite):
/// never a row of NaN, or an infinite D, with exit code 0.
fn refuse_non_finite(
    source: &str,
    tracks: &[Track],
    estimates: &[(Method, RecordingEstimates)],
) -> anyhow::Result<()> {
    // An interval open above (high = +∞, and so its standard error) is
    // documented; anything else must be a finite number.
    let finite = |e: &Estimate| {
        [e.d, e.low, e.localisation_variance]
            .iter()
            .all(|v| v.is_finite())
            && !(e.high.is_nan() || e.standard_error.is_nan())
    };
    for (method, e) in estimates {
        let per_track = tracks
            .iter()
            .zip(&e.per_track)
            .filter_map(|(track, estimate)| Some((track.particle.to_string(), estimate.as_ref()?)));
        let ensemble = e
            .ensemble
            .as_ref()
            .map(|estimate| ("ensemble".to_string(), estimate));
        if let Some((label, _)) = per_track.chain(ensemble).find(|(_, e)| !finite(e)) {
            return Err(input_error(format!(
                "{source}: particle {label}: the {} estimate is not a finite number: the tracks do not \
                 fit the stated scan (--height, --width, --pixel-size-um, timing)",
                method.name()
            )));
        }
    }
    Ok(())
}
