//! What `scanloc track` writes and prints, rendered from a
//! [`TrackResult`] for every front end (the command's files, its
//! `--json` summary; the Python package's DataFrames are read from the
//! same text): tracks.csv, diffusion.csv, settings.json.

use std::io::Write;

use super::TrackResult;
use crate::track::pipeline::StoredEstimate;

/// The files of a run, in the order [`TrackResult::files`] gives them.
pub const FILES: [&str; 3] = ["tracks.csv", "diffusion.csv", "settings.json"];

/// diffusion.csv's header (`scanloc diffusion`'s table).
pub const DIFFUSION_HEADER: &str = "particle,points,method,d_um2_s,standard_error,low_95,high_95,localisation_variance_um2,interval_valid";

impl TrackResult {
    /// tracks.csv: frame, x, y, … and particle (TrackPy's columns).
    pub fn tracks_csv(&self) -> anyhow::Result<Vec<u8>> {
        let mut out = Vec::new();
        crate::io::tracks::write_tracks_to(&mut out, &self.tracks)?;
        Ok(out)
    }

    /// diffusion.csv, as `scanloc diffusion` writes its table: one `ml`
    /// row per track with a D of its own, then `ensemble` (as read) and,
    /// with the bias correction, `ensemble-corrected`.
    pub fn diffusion_csv(&self) -> std::io::Result<Vec<u8>> {
        let mut out = Vec::new();
        writeln!(out, "{DIFFUSION_HEADER}")?;
        for t in &self.per_track {
            row(&mut out, &t.particle.to_string(), t.points, &t.estimate)?;
        }
        let points: usize = self
            .tracks
            .iter()
            .filter(|t| t.points.len() > 1)
            .map(|t| t.points.len())
            .sum();
        if let Some(e) = &self.ensemble {
            row(&mut out, "ensemble", points, e)?;
        }
        if let Some(c) = &self.corrected {
            row(&mut out, "ensemble-corrected", points, &c.estimate)?;
        }
        Ok(out)
    }

    /// settings.json: every setting the run used.
    pub fn settings_json(&self) -> anyhow::Result<String> {
        Ok(serde_json::to_string_pretty(&self.settings)? + "\n")
    }

    /// The files of [`FILES`] with their contents.
    pub fn files(&self) -> anyhow::Result<[(&'static str, Vec<u8>); 3]> {
        let [tracks, diffusion, settings] = FILES;
        Ok([
            (tracks, self.tracks_csv()?),
            (diffusion, self.diffusion_csv()?),
            (settings, self.settings_json()?.into_bytes()),
        ])
    }

    /// What the reader must know before using the ensemble D: none, or
    /// that there is none, or that its interval is not valid.
    pub fn warnings(&self) -> Vec<String> {
        match self.d() {
            None => vec!["no ensemble D: too few steps in the tracks".to_string()],
            Some(e) if !(e.standard_error.is_finite() && e.interval_valid) => vec![format!(
                "the ensemble's interval is not valid ({} steps): do not trust this D (docs/recording.md, \"When to distrust it\")",
                e.steps
            )],
            Some(_) => Vec::new(),
        }
    }

    /// The summary `scanloc track --json` prints: the ensemble D
    /// (corrected where there is a correction) with its interval, the
    /// uncorrected one, the counts, the warnings and the settings.
    pub fn summary_json(&self) -> serde_json::Value {
        serde_json::json!({
            "ensemble": self.d().as_ref().map(estimate_json),
            "bias_corrected": self.corrected.is_some(),
            "uncorrected": self.ensemble.as_ref().map(estimate_json),
            "frames": self.frames,
            "localisations": self.localisations.len(),
            "linked": self.linked,
            "tracks": self.tracks.len(),
            "tracks_with_d": self.per_track.len(),
            "warnings": self.warnings(),
            "settings": self.settings,
        })
    }
}

fn row(out: &mut Vec<u8>, label: &str, points: usize, e: &StoredEstimate) -> std::io::Result<()> {
    writeln!(
        out,
        "{label},{points},ml,{},{},{},{},{},{}",
        e.d,
        e.standard_error,
        e.low,
        e.high.unwrap_or(f64::INFINITY),
        e.localisation_variance,
        e.interval_valid
    )
}

fn estimate_json(e: &StoredEstimate) -> serde_json::Value {
    serde_json::json!({
        "d_um2_s": e.d,
        "standard_error": e.standard_error,
        "low_95": e.low,
        "high_95": e.high,
        "steps": e.steps,
        "interval_valid": e.interval_valid,
    })
}
