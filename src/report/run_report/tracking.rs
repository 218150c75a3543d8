//! The report's Tracking section (runs with tracking pipelines, see
//! docs/tracking.md): the tables `scanloc run` prints, a figure of each
//! recording's tracks over one of its frames, and D estimated against the
//! true D.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;

use crate::metrics::tracking::truth_tracks;
use crate::registry::Registry;
use crate::report::figures::{
    EstimateChart, EstimateSeries, TrackPanel, estimate_chart, track_panels,
};
use crate::run::table::{CellTable, tracking_tables};
use crate::run::{RecordedTracking, load_artefact};
use crate::track::diffusion::Method;
use crate::track::pipeline::StoredEstimate;
use crate::types::Track;

/// Frames either side of the shown frame whose track points are drawn.
const TRACK_WINDOW: usize = 10;

/// Most pipelines drawn over one recording (the first in the run's order).
const MAX_PANELS: usize = 4;

/// The file of the figure of D estimated against the true D.
const DIFFUSION_FIGURE: &str = "diffusion_estimates";

/// Writes the Tracking section for the run's `tracking` evaluations (in
/// step order) and its figures into `out`; nothing for a run without.
pub(super) fn write_tracking_section(
    registry: &Registry,
    out: &Path,
    markdown: &mut String,
    tracking: &[RecordedTracking],
) -> anyhow::Result<()> {
    if tracking.is_empty() {
        return Ok(());
    }
    writeln!(markdown, "\n## Tracking\n")?;
    writeln!(
        markdown,
        "Each tracking pipeline (`DETECTOR+LINKER`: the detector's localisations on a recording, \
         linked) scored against the recording's truth: the tracking measures, then D per \
         estimator for all tracks at once (ensemble, with its standard error and error against \
         the true D) and per track (docs/tracking.md, \"The tracking experiment\").\n"
    )?;
    let rows: Vec<_> = tracking.iter().map(|t| t.row.clone()).collect();
    for table in tracking_tables(&rows) {
        write_markdown_table(markdown, &table)?;
    }
    writeln!(
        markdown,
        "**Tracks over a frame**: for each recording, the frame where most of its truth (as \
         scored) is in the field; the truth's tracks over the {TRACK_WINDOW} frames either side \
         of it in thick green, a circle where a QD is in the frame; each pipeline's tracks over \
         the same frames in thin lines, one colour per track, a cross where a track has a point \
         in the frame (up to {MAX_PANELS} pipelines per recording).\n"
    )?;
    for file in tracks_over_a_frame(registry, out, tracking)? {
        writeln!(markdown, "![tracks over a frame]({file}.png)\n")?;
    }
    diffusion_figure(out, tracking)?;
    writeln!(
        markdown,
        "**D estimated against true D**: per pipeline, the ML ensemble estimate on each \
         recording with its 95 % interval (bars, cut at the top of the chart), the per-track ML \
         estimates as light dots (those above the chart left out), and the line where the \
         estimate equals the truth; pipelines are set slightly apart along x. A pipeline whose \
         ensemble is corrected for its bias by simulation has a second series, `ML \
         bias-corrected`.\n\n\
         ![D estimated against true D]({DIFFUSION_FIGURE}.png)\n"
    )?;
    Ok(())
}

/// `table` as a Markdown table under its title in bold.
fn write_markdown_table<const N: usize>(
    markdown: &mut String,
    table: &CellTable<N>,
) -> anyhow::Result<()> {
    writeln!(markdown, "**{}**\n", table.title)?;
    writeln!(markdown, "| {} |", table.headers.join(" | "))?;
    writeln!(markdown, "|{}", "---|".repeat(N))?;
    for row in &table.cells {
        writeln!(markdown, "| {} |", row.join(" | "))?;
    }
    writeln!(markdown)?;
    Ok(())
}

/// One figure per recording: its middle frame with each pipeline's tracks
/// and the truth's over a window of frames around it. Returns the files.
fn tracks_over_a_frame(
    registry: &Registry,
    out: &Path,
    tracking: &[RecordedTracking],
) -> anyhow::Result<Vec<String>> {
    let mut recordings: Vec<&str> = Vec::new();
    for t in tracking {
        if !recordings.contains(&t.row.recording.as_str()) {
            recordings.push(&t.row.recording);
        }
    }
    let mut files = Vec::new();
    for recording in recordings {
        let on_it = tracking
            .iter()
            .filter(|t| t.row.recording == recording)
            .take(MAX_PANELS)
            .map(|t| {
                let key = &t.row.evaluation_key;
                let stored = registry
                    .evaluation(key)?
                    .with_context(|| format!("evaluation {key} is not in the registry"))?;
                Ok((t, stored))
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let Some((first_tracking, first)) = on_it.first() else {
            continue;
        };
        let data = load_artefact(registry, &first.dataset_key)?
            .recording()?
            .clone();
        let frames = &data.frames;
        if frames.n == 0 {
            continue;
        }
        // The truth as scored (one selection per run), and the frame
        // where most of it is in the field.
        let truth = truth_tracks(&data.truth, &first_tracking.evaluation.scoring.selection());
        let frame = busiest_frame(&truth, frames.n);
        let window = frame.saturating_sub(TRACK_WINDOW)..=frame + TRACK_WINDOW;
        let (truth, truth_now) = paths_in(&truth, &window, frame);
        let mut panels = Vec::new();
        for (t, stored) in &on_it {
            let tracks = load_artefact(registry, &stored.predictions_key)?;
            let (tracks, tracks_now) = paths_in(tracks.tracks()?, &window, frame);
            panels.push(TrackPanel {
                title: format!(
                    "{}: {}, frame {frame}",
                    crate::limits::display_cell(&t.row.pipeline),
                    crate::limits::display_cell(recording)
                ),
                height: frames.height,
                width: frames.width,
                counts: frames.frame(frame).to_vec(),
                truth: truth.clone(),
                tracks,
                truth_now: truth_now.clone(),
                tracks_now,
            });
        }
        let file = crate::io::safe_file_name(&format!("tracks_{recording}"));
        track_panels(&out.join(&file), &panels)?;
        files.push(file);
    }
    Ok(files)
}

/// The frame (of `frames`) holding the most points of `tracks`, the
/// earliest of a tie; the middle frame when they have none.
fn busiest_frame(tracks: &[Track], frames: usize) -> usize {
    let mut counts = vec![0usize; frames];
    for point in tracks.iter().flat_map(|t| &t.points) {
        if let Some(count) = counts.get_mut(point.frame) {
            *count += 1;
        }
    }
    let most = counts.iter().copied().max().unwrap_or(0);
    if most == 0 {
        return frames / 2;
    }
    counts.iter().position(|&c| c == most).unwrap_or(frames / 2)
}

/// The points of `tracks` in frames `window`, one path per track that has
/// any, and the points in frame `frame`.
#[allow(clippy::type_complexity)]
fn paths_in(
    tracks: &[Track],
    window: &std::ops::RangeInclusive<usize>,
    frame: usize,
) -> (Vec<Vec<(f64, f64)>>, Vec<(f64, f64)>) {
    let mut paths = Vec::new();
    let mut now = Vec::new();
    for track in tracks {
        let path: Vec<(f64, f64)> = track
            .points
            .iter()
            .filter(|p| window.contains(&p.frame))
            .map(|p| (p.x, p.y))
            .collect();
        if path.is_empty() {
            continue;
        }
        now.extend(
            track
                .points
                .iter()
                .filter(|p| p.frame == frame)
                .map(|p| (p.x, p.y)),
        );
        paths.push(path);
    }
    (paths, now)
}

/// The series of `series` labelled `label`, added where it is new.
fn series_named(series: &mut Vec<EstimateSeries>, label: String) -> &mut EstimateSeries {
    let index = match series.iter().position(|s| s.label == label) {
        Some(index) => index,
        None => {
            series.push(EstimateSeries {
                label,
                points: Vec::new(),
                scatter: Vec::new(),
            });
            series.len() - 1
        }
    };
    &mut series[index]
}

impl EstimateSeries {
    /// An ensemble estimate at true D `truth`, with its interval (none
    /// where there is no estimate).
    fn add(&mut self, truth: f64, estimate: Option<&StoredEstimate>) {
        if let Some(e) = estimate {
            self.points
                .push((truth, e.d, e.low, e.high.unwrap_or(f64::INFINITY)));
        }
    }
}

/// The ML estimates of D against each recording's true D, one series per
/// pipeline (and one more for a pipeline's bias-corrected ensemble).
fn diffusion_figure(out: &Path, tracking: &[RecordedTracking]) -> anyhow::Result<()> {
    let mut series: Vec<EstimateSeries> = Vec::new();
    for t in tracking {
        let Some(ml) = t.evaluation.estimator(Method::Ml) else {
            continue;
        };
        let pipeline = crate::limits::display_cell(&t.row.pipeline);
        let truth = t.row.diffusion;
        let entry = series_named(&mut series, format!("{pipeline}, ML"));
        entry.add(truth, ml.ensemble.as_ref());
        entry
            .scatter
            .extend(ml.tracks.iter().map(|track| (truth, track.estimate.d)));
        if let Some(corrected) = &t.evaluation.corrected_ensemble {
            series_named(&mut series, format!("{pipeline}, ML bias-corrected"))
                .add(truth, Some(&corrected.estimate));
        }
    }
    let finite_max = |values: &mut dyn Iterator<Item = f64>| {
        values
            .filter(|v| v.is_finite())
            .fold(0.0f64, |a, b| a.max(b))
    };
    let true_max = finite_max(&mut tracking.iter().map(|t| t.row.diffusion));
    let estimate_max = finite_max(&mut series.iter().flat_map(|s| s.points.iter().map(|p| p.1)));
    let high_max = finite_max(&mut series.iter().flat_map(|s| s.points.iter().map(|p| p.3)));
    let base = true_max.max(estimate_max).max(0.1);
    let x_max = 1.25 * true_max.max(0.08);
    let y_max = (1.15 * high_max.max(base)).clamp(x_max, 3.0 * base);
    estimate_chart(
        &out.join(DIFFUSION_FIGURE),
        &EstimateChart {
            title: "D estimated against true D".to_string(),
            x_label: "true D (µm²/s)".to_string(),
            y_label: "estimated D (µm²/s)".to_string(),
            x_max,
            y_max,
            series,
        },
    )
}
