//! The AUC table in the paper's layout: one row per detector, columns
//! grouped by test set (labelled by its D when fixed) and, within each, one
//! column per ε. Reference rows (e.g. the paper's) follow the detector they
//! compare with. A detector whose guesses are ranked lists has a second
//! row under its own, `DETECTOR, best guess`: each frame's best guess alone
//! (its own row is the whole lists'). Sets with empty frames get a second
//! table, of the false localisations per empty frame.

use super::{EmptyFramesRow, TrackingRow};
use crate::limits::display_cell;
use crate::manifest::Reference;
use crate::registry::AucRow;

/// The label of a detector's best-guess row.
const BEST_GUESS: &str = ", best guess";

/// Renders `rows` as text; `reference` rows are printed under their
/// detector when given. A detector gets a best-guess row when one of its
/// rows has a best-guess AUC that differs from the whole lists'.
pub fn render(rows: &[AucRow], reference: Option<&Reference>) -> String {
    if rows.is_empty() {
        return "no AUC: the manifest scores no detector on a dataset with ground truth\n"
            .to_string();
    }
    let mut detectors: Vec<&str> = Vec::new();
    let mut datasets: Vec<(&str, Option<f64>)> = Vec::new();
    let mut eps: Vec<f64> = Vec::new();
    for row in rows {
        if !detectors.contains(&row.detector.as_str()) {
            detectors.push(&row.detector);
        }
        if !datasets.iter().any(|(d, _)| *d == row.dataset) {
            datasets.push((&row.dataset, row.diffusion));
        }
        if !eps.contains(&row.eps_px) {
            eps.push(row.eps_px);
        }
    }
    let best_guess_differs = |detector: &str| {
        rows.iter().any(|r| {
            r.detector == detector && r.auc_best_per_frame.is_some_and(|best| best != r.auc)
        })
    };
    let cell = 6;
    let group = eps.len() * (cell + 1) + 2;
    // Labels are cut to a bounded width (`display_cell`), so no recorded
    // name can make a format width overflow.
    let mut label_width = detectors
        .iter()
        .map(|d| {
            let extra = if best_guess_differs(d) {
                BEST_GUESS.len()
            } else {
                0
            };
            display_cell(d).len() + extra
        })
        .max()
        .unwrap_or(0)
        .max(10);
    if let Some(reference) = reference {
        for row in &reference.rows {
            label_width = label_width.max(display_cell(&row.label).len() + 9);
        }
    }
    let mut out = String::new();
    out.push_str(&format!("{:<label_width$}", "AUC"));
    for (name, diffusion) in &datasets {
        let title = match diffusion {
            // The paper's labels: 0.75, 1.00, 1.75.
            Some(d) if (d * 100.0).round() == d * 100.0 => format!("D = {d:.2} µm²/s"),
            Some(d) => format!("D = {d} µm²/s"),
            None => display_cell(name).into_owned(),
        };
        // Padded by hand: the group's width grows with the ε list, which
        // a format width (at most 65,535) must not be trusted with.
        out.push_str("  ");
        out.push_str(&title);
        let shown = title.chars().count();
        out.extend(std::iter::repeat_n(' ', (group - 2).saturating_sub(shown)));
    }
    out.push('\n');
    out.push_str(&format!("{:<label_width$}", "ε (px)"));
    for _ in &datasets {
        out.push_str("  ");
        for e in &eps {
            out.push_str(&format!("{:<cell$} ", format!("{e}")));
        }
    }
    out.push('\n');
    let line = |label: &str, value: &dyn Fn(&str, f64) -> Option<f64>| -> String {
        let label = display_cell(label);
        let mut text = format!("{label:<label_width$}");
        for (name, _) in &datasets {
            text.push_str("  ");
            for &e in &eps {
                let shown = match value(name, e) {
                    Some(v) => format!("{v:.3}"),
                    None => "-".to_string(),
                };
                text.push_str(&format!("{shown:<cell$} "));
            }
        }
        text.trim_end().to_string() + "\n"
    };
    for detector in &detectors {
        out.push_str(&line(detector, &|dataset, e| {
            rows.iter()
                .find(|r| r.detector == *detector && r.dataset == dataset && r.eps_px == e)
                .map(|r| r.auc)
        }));
        if best_guess_differs(detector) {
            let label = format!("{}{BEST_GUESS}", display_cell(detector));
            out.push_str(&line(&label, &|dataset, e| {
                rows.iter()
                    .find(|r| r.detector == *detector && r.dataset == dataset && r.eps_px == e)
                    .and_then(|r| r.auc_best_per_frame)
            }));
        }
        if let Some(reference) = reference {
            for row in reference.rows.iter().filter(|r| r.detector == *detector) {
                out.push_str(&line(&format!("  paper: {}", row.label), &|dataset, e| {
                    row.auc(dataset, e)
                }));
            }
        }
    }
    if let Some(reference) = reference
        && !reference.source.is_empty()
    {
        out.push_str(&format!("(paper: {})\n", reference.source));
    }
    out
}

/// Renders the false localisations per empty frame of `rows` (one line
/// per evaluation, in their order), under a heading; nothing without rows.
pub fn render_empty_frames(rows: &[EmptyFramesRow]) -> String {
    if rows.is_empty() {
        return String::new();
    }
    let headers = [
        "detector",
        "dataset",
        "threshold",
        "empty frames",
        "localisations",
        "per frame",
    ];
    let cells: Vec<[String; 6]> = rows
        .iter()
        .map(|row| {
            let empty = &row.empty_frames;
            [
                display_cell(&row.detector).into_owned(),
                display_cell(&row.dataset).into_owned(),
                // Without a threshold every localisation counts.
                row.threshold.map_or("none".to_string(), |t| format!("{t}")),
                empty.frames.to_string(),
                empty.localisations.to_string(),
                empty
                    .false_localisations_per_frame
                    .map_or("-".to_string(), |v| format!("{v:.3}")),
            ]
        })
        .collect();
    render_cells(
        "false localisations per empty frame (score at or above the threshold)",
        &headers,
        &cells,
    )
}

/// A titled text table of `cells` under `headers`, columns left-aligned
/// to their widest cell.
fn render_cells<const N: usize>(title: &str, headers: &[&str; N], cells: &[[String; N]]) -> String {
    let widths: Vec<usize> = (0..N)
        .map(|i| {
            cells
                .iter()
                .map(|c| c[i].chars().count())
                .chain([headers[i].chars().count()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    let line = |values: &[&str]| -> String {
        let text: Vec<String> = values
            .iter()
            .zip(&widths)
            .map(|(v, &w)| format!("{v:<w$}"))
            .collect();
        text.join("  ").trim_end().to_string() + "\n"
    };
    let mut out = format!("{title}\n");
    out.push_str(&line(headers));
    for row in cells {
        let values: Vec<&str> = row.iter().map(String::as_str).collect();
        out.push_str(&line(&values));
    }
    out
}

/// A ratio to three decimals, `-` when there was nothing to count.
fn ratio(value: Option<f64>) -> String {
    value.map_or("-".to_string(), |v| format!("{v:.3}"))
}

/// A titled table of cells, as [`tracking_tables`] gives them: printed as
/// text by [`render_tracking`] and as Markdown by the report.
#[derive(Debug, Clone, PartialEq)]
pub struct CellTable<const N: usize> {
    pub title: String,
    pub headers: [&'static str; N],
    pub cells: Vec<[String; N]>,
}

/// The tracking pipelines' figures (docs/tracking.md, "The tracking
/// experiment"): one table of the tracking measures and one of D per
/// estimator; none without rows.
pub fn tracking_tables(rows: &[TrackingRow]) -> Vec<CellTable<10>> {
    if rows.is_empty() {
        return Vec::new();
    }
    let gate = rows[0].tracking.gate_px;
    let measures = CellTable {
        title: format!("tracking measures (gate {gate} px; docs/tracking.md)"),
        headers: [
            "pipeline",
            "recording",
            "D",
            "tracks (est/truth)",
            "alpha",
            "beta",
            "JSC det",
            "JSC tracks",
            "link prec",
            "link rec",
        ],
        cells: rows
            .iter()
            .map(|row| {
                let t = &row.tracking;
                [
                    display_cell(&row.pipeline).into_owned(),
                    display_cell(&row.recording).into_owned(),
                    format!("{}", row.diffusion),
                    format!("{}/{}", t.estimated_tracks, t.truth_tracks),
                    ratio(t.alpha),
                    ratio(t.beta),
                    ratio(t.jaccard_detections),
                    ratio(t.jaccard_tracks),
                    ratio(t.link_precision),
                    ratio(t.link_recall),
                ]
            })
            .collect(),
    };
    let mut cells: Vec<[String; 10]> = Vec::new();
    for row in rows {
        for e in &row.estimators {
            let per_track = e.per_track;
            cells.push([
                display_cell(&row.pipeline).into_owned(),
                display_cell(&row.recording).into_owned(),
                format!("{}", row.diffusion),
                e.method.name().to_string(),
                e.ensemble.map_or("-".to_string(), |d| {
                    format!("{:.3} ({:.3})", d.d, d.standard_error)
                }),
                e.ensemble_relative_error
                    .map_or("-".to_string(), |v| format!("{:+.1} %", 100.0 * v)),
                per_track.map_or("0".to_string(), |p| p.count.to_string()),
                per_track.map_or("-".to_string(), |p| format!("{:+.3}", p.relative_bias)),
                per_track.map_or("-".to_string(), |p| format!("{:.3}", p.relative_rmse)),
                per_track.map_or("-".to_string(), |p| format!("{:.3}", p.coverage)),
            ]);
        }
        if let Some(corrected) = &row.corrected_ensemble {
            cells.push([
                display_cell(&row.pipeline).into_owned(),
                display_cell(&row.recording).into_owned(),
                format!("{}", row.diffusion),
                "ml, bias-corrected".to_string(),
                format!(
                    "{:.3} ({:.3})",
                    corrected.estimate.d, corrected.estimate.standard_error
                ),
                format!("{:+.1} %", 100.0 * corrected.relative_error),
                "-".to_string(),
                "-".to_string(),
                "-".to_string(),
                "-".to_string(),
            ]);
        }
    }
    let diffusion = CellTable {
        title: "diffusion coefficient, µm²/s (per track: tracks whose estimator's condition holds; bias and RMSE relative to D; coverage of the 95 % intervals)".to_string(),
        headers: [
            "pipeline",
            "recording",
            "D",
            "estimator",
            "ensemble D (SE)",
            "error",
            "tracks",
            "track bias",
            "track RMSE",
            "coverage",
        ],
        cells,
    };
    vec![measures, diffusion]
}

/// Renders the [`tracking_tables`] as text; nothing without rows.
pub fn render_tracking(rows: &[TrackingRow]) -> String {
    tracking_tables(rows)
        .iter()
        .map(|table| render_cells(&table.title, &table.headers, &table.cells))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::scenes::EmptyFrames;

    #[test]
    fn lists_empty_frames_per_evaluation() {
        assert_eq!(render_empty_frames(&[]), "");
        let rows = [
            EmptyFramesRow {
                detector: "trackpy".into(),
                dataset: "empty".into(),
                threshold: None,
                empty_frames: EmptyFrames {
                    frames: 40,
                    localisations: 6,
                    false_localisations_per_frame: Some(0.15),
                },
            },
            EmptyFramesRow {
                detector: "cnn".into(),
                dataset: "empty".into(),
                threshold: Some(0.5),
                empty_frames: EmptyFrames {
                    frames: 40,
                    localisations: 0,
                    false_localisations_per_frame: Some(0.0),
                },
            },
        ];
        let text = render_empty_frames(&rows);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4, "{text}");
        assert!(
            lines[1].starts_with("detector  dataset  threshold"),
            "{text}"
        );
        assert_eq!(
            lines[2].split_whitespace().collect::<Vec<_>>(),
            ["trackpy", "empty", "none", "40", "6", "0.150"],
            "{text}"
        );
        assert_eq!(
            lines[3].split_whitespace().collect::<Vec<_>>(),
            ["cnn", "empty", "0.5", "40", "0", "0.000"],
            "{text}"
        );
    }

    #[test]
    fn lays_out_detectors_by_dataset_and_eps() {
        let mut rows = Vec::new();
        for (detector, base) in [("trackpy", 0.1), ("cnn", 0.5)] {
            for (dataset, d) in [("t1", Some(0.75)), ("t2", None)] {
                for eps in [1.0, 2.0] {
                    rows.push(AucRow {
                        detector: detector.into(),
                        dataset: dataset.into(),
                        diffusion: d,
                        eps_px: eps,
                        auc: base + eps / 10.0,
                        auc_best_per_frame: None,
                        evaluation_key: String::new(),
                    });
                }
            }
        }
        let text = render(&rows, None);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4, "{text}");
        assert!(lines[0].contains("D = 0.75 µm²/s") && lines[0].contains("t2"));
        assert!(
            lines[2].starts_with("trackpy") && lines[2].contains("0.200  0.300    0.200  0.300"),
            "{text}"
        );
        assert!(
            lines[3].starts_with("cnn") && lines[3].contains("0.600"),
            "{text}"
        );

        // Ranked lists: a best-guess row under the detector's own, with
        // "-" where a cell has none; a best guess equal to the lists' AUC
        // everywhere (one guess per frame) adds no row.
        for row in rows.iter_mut().filter(|r| r.detector == "cnn") {
            row.auc_best_per_frame = (row.dataset == "t1").then_some(row.auc - 0.05);
        }
        for row in rows.iter_mut().filter(|r| r.detector == "trackpy") {
            row.auc_best_per_frame = Some(row.auc);
        }
        let ranked = render(&rows, None);
        let lines: Vec<&str> = ranked.lines().collect();
        assert_eq!(lines.len(), 5, "{ranked}");
        let words = |line: &str| {
            line.split_whitespace()
                .map(str::to_string)
                .collect::<Vec<_>>()
        };
        let before: Vec<Vec<String>> = text.lines().map(words).collect();
        assert_eq!(
            lines[..4].iter().map(|l| words(l)).collect::<Vec<_>>(),
            before,
            "{ranked}"
        );
        assert_eq!(
            lines[4].split_whitespace().collect::<Vec<_>>(),
            ["cnn,", "best", "guess", "0.550", "0.650", "-", "-"],
            "{ranked}"
        );
    }

    #[test]
    fn a_long_detector_name_widens_the_label_column_for_its_best_guess_row() {
        let rows = [AucRow {
            detector: "likelihood-list".into(),
            dataset: "t".into(),
            diffusion: None,
            eps_px: 1.0,
            auc: 0.5,
            auc_best_per_frame: Some(0.25),
            evaluation_key: String::new(),
        }];
        let text = render(&rows, None);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[2], "likelihood-list              0.500", "{text}");
        assert_eq!(lines[3], "likelihood-list, best guess  0.250", "{text}");
    }
}
