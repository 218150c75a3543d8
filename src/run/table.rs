//! The AUC table in the paper's layout: one row per detector, columns
//! grouped by test set (labelled by its D when fixed) and, within each, one
//! column per ε. Reference rows (e.g. the paper's) follow the detector they
//! compare with. A detector whose guesses are ranked lists has a second
//! row under its own, `DETECTOR, best guess`: each frame's best guess alone
//! (its own row is the whole lists'). Evaluations of a set's first N frames
//! (`DATASET+firstN`, as the bound is run) get a table of their own per N,
//! with every detector scored on those frames (the CNN beside the bound),
//! so each table keeps the paper's columns. A table wider than the
//! terminal's 120 characters or 12 columns of figures is split into blocks
//! of test sets. Sets with empty frames get a second table, of the false
//! localisations per empty frame.

use super::{EmptyFramesRow, TrackingRow};
use crate::limits::display_cell;
use crate::manifest::Reference;
use crate::registry::AucRow;

/// The label of a detector's best-guess row.
const BEST_GUESS: &str = ", best guess";

/// The widest a printed table may be, in characters (a terminal's 120).
pub(crate) const MAX_TABLE_CHARS: usize = 120;

/// The most columns of figures a table (or one block of it) may hold.
pub(crate) const MAX_FIGURE_COLUMNS: usize = 12;

/// A scored set's name split into the test set and, for an evaluation of
/// its first N frames (`DATASET+firstN`), N.
pub(crate) fn frames_scored(dataset: &str) -> (&str, Option<usize>) {
    match dataset.rsplit_once("+first") {
        Some((base, n)) if !base.is_empty() => match n.parse() {
            Ok(n) => (base, Some(n)),
            Err(_) => (dataset, None),
        },
        _ => (dataset, None),
    }
}

/// `items` in order, cut into consecutive blocks of at most `per_block`
/// (at least one each).
pub(crate) fn blocks<T>(items: &[T], per_block: usize) -> std::slice::Chunks<'_, T> {
    items.chunks(per_block.max(1))
}

/// The test sets of one block of columns: at most [`MAX_FIGURE_COLUMNS`]
/// figures, `eps` of them per set.
pub(crate) fn sets_per_block(eps: usize) -> usize {
    (MAX_FIGURE_COLUMNS / eps.max(1)).max(1)
}

/// Renders `rows` as text; `reference` rows are printed under their
/// detector when given. A detector gets a best-guess row when one of its
/// rows has a best-guess AUC that differs from the whole lists'. The
/// whole test sets come first; each first-N-frames subset follows in a
/// table of its own.
pub(crate) fn render(rows: &[AucRow], reference: Option<&Reference>) -> String {
    if rows.is_empty() {
        return "no AUC: the manifest scores no detector on a dataset with ground truth\n"
            .to_string();
    }
    let mut subsets: Vec<Option<usize>> = Vec::new();
    for row in rows {
        let (_, first) = frames_scored(&row.dataset);
        if !subsets.contains(&first) {
            subsets.push(first);
        }
    }
    // The whole sets first, then the subsets by size.
    subsets.sort_by_key(|first| first.map_or(0, |n| n.max(1)));
    let mut out = String::new();
    for first in subsets {
        let group: Vec<&AucRow> = rows
            .iter()
            .filter(|r| frames_scored(&r.dataset).1 == first)
            .collect();
        if let Some(n) = first {
            if !out.is_empty() {
                out.push('\n');
            }
            out.push_str(&format!(
                "AUC on the first {n} frames of each set (the same frames for every row)\n"
            ));
            out.push_str(&render_group(&group, None));
        } else {
            out.push_str(&render_group(&group, reference));
            if let Some(reference) = reference
                && !reference.source.is_empty()
            {
                out.push_str(&format!("(paper: {})\n", reference.source));
            }
        }
    }
    out
}

/// The rows' detectors, test sets (the set's name as the reference knows
/// it, the scored name, D) and radii, each in the order rows first name it.
type GroupAxes<'a> = (Vec<&'a str>, Vec<(&'a str, &'a str, Option<f64>)>, Vec<f64>);

fn group_axes<'a>(rows: &[&'a AucRow]) -> GroupAxes<'a> {
    let mut detectors: Vec<&str> = Vec::new();
    let mut datasets: Vec<(&str, &str, Option<f64>)> = Vec::new();
    let mut eps: Vec<f64> = Vec::new();
    for row in rows {
        if !detectors.contains(&row.detector.as_str()) {
            detectors.push(&row.detector);
        }
        if !datasets.iter().any(|(_, d, _)| *d == row.dataset) {
            datasets.push((frames_scored(&row.dataset).0, &row.dataset, row.diffusion));
        }
        if !eps.contains(&row.eps_px) {
            eps.push(row.eps_px);
        }
    }
    (detectors, datasets, eps)
}

/// The width of the label column: the longest detector label (with its
/// best-guess suffix where it has that row) or reference label, at least 10.
/// Labels are cut to a bounded width (`display_cell`), so no recorded name
/// can make a format width overflow.
fn label_width(
    detectors: &[&str],
    best_guess_differs: &dyn Fn(&str) -> bool,
    reference: Option<&Reference>,
) -> usize {
    let mut width = detectors
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
        for row in reference
            .rows
            .iter()
            .filter(|r| detectors.contains(&r.detector.as_str()))
        {
            width = width.max(display_cell(&row.label).len() + 9);
        }
    }
    width
}

/// The two heading lines of a block: the sets' titles over their groups of
/// columns, then the radii. Padded by hand: a group's width grows with the
/// ε list, which a format width (at most 65,535) must not be trusted with.
fn block_heading(
    titles: &[(&str, usize)],
    eps: &[f64],
    label_width: usize,
    cell: usize,
    figures: usize,
) -> String {
    let mut header = format!("{:<label_width$}", "AUC");
    let mut eps_line = format!("{:<label_width$}", "ε (px)");
    for &(title, width) in titles {
        header.push_str("  ");
        header.push_str(title);
        header.extend(std::iter::repeat_n(
            ' ',
            (width - 2).saturating_sub(title.chars().count()),
        ));
        eps_line.push_str("  ");
        for e in eps {
            eps_line.push_str(&format!("{:<cell$} ", format!("{e}")));
        }
        eps_line.extend(std::iter::repeat_n(
            ' ',
            (width - 2).saturating_sub(figures),
        ));
    }
    format!("{}\n{}\n", header.trim_end(), eps_line.trim_end())
}

/// One AUC table of `rows` (all of one subset), split into blocks of test
/// sets that fit [`MAX_TABLE_CHARS`] and [`MAX_FIGURE_COLUMNS`].
fn render_group(rows: &[&AucRow], reference: Option<&Reference>) -> String {
    let (detectors, datasets, eps) = group_axes(rows);
    let best_guess_differs = |detector: &str| {
        rows.iter().any(|r| {
            r.detector == detector && r.auc_best_per_frame.is_some_and(|best| best != r.auc)
        })
    };
    let cell = 6;
    let titles: Vec<String> = datasets
        .iter()
        .map(|(name, _, diffusion)| match diffusion {
            // The paper's labels: 0.75, 1.00, 1.75.
            Some(d) if (d * 100.0).round() == d * 100.0 => format!("D = {d:.2} µm²/s"),
            Some(d) => format!("D = {d} µm²/s"),
            None => display_cell(name).into_owned(),
        })
        .collect();
    // A group's width: its ε columns, or its title if that is wider.
    let figures = eps.len() * (cell + 1);
    let group_width = |title: &str| figures.max(title.chars().count() + 1) + 2;
    // Labels are cut to a bounded width (`display_cell`), so no recorded
    // name can make a format width overflow.
    let label_width = label_width(&detectors, &best_guess_differs, reference);
    let widest_group = titles.iter().map(|t| group_width(t)).max().unwrap_or(0);
    let fit = MAX_TABLE_CHARS.saturating_sub(label_width) / widest_group.max(1);
    let per_block = sets_per_block(eps.len()).min(fit.max(1));
    let indices: Vec<usize> = (0..datasets.len()).collect();
    let mut out = String::new();
    for (b, block) in blocks(&indices, per_block).enumerate() {
        if b > 0 {
            out.push('\n');
        }
        let titles_in_block: Vec<(&str, usize)> = block
            .iter()
            .map(|&i| (titles[i].as_str(), group_width(&titles[i])))
            .collect();
        out.push_str(&block_heading(
            &titles_in_block,
            &eps,
            label_width,
            cell,
            figures,
        ));
        let line = |label: &str, value: &dyn Fn(&str, &str, f64) -> Option<f64>| -> String {
            let label = display_cell(label);
            let mut text = format!("{label:<label_width$}");
            for &i in block {
                let (name, scored, _) = datasets[i];
                text.push_str("  ");
                for &e in &eps {
                    let shown = match value(name, scored, e) {
                        Some(v) => format!("{v:.3}"),
                        None => "-".to_string(),
                    };
                    text.push_str(&format!("{shown:<cell$} "));
                }
                let width = group_width(&titles[i]);
                text.extend(std::iter::repeat_n(
                    ' ',
                    (width - 2).saturating_sub(figures),
                ));
            }
            text.trim_end().to_string() + "\n"
        };
        let find = |detector: &str, scored: &str, e: f64| {
            rows.iter()
                .find(|r| r.detector == detector && r.dataset == scored && r.eps_px == e)
                .copied()
        };
        for detector in &detectors {
            out.push_str(&line(detector, &|_, scored, e| {
                find(detector, scored, e).map(|r| r.auc)
            }));
            if best_guess_differs(detector) {
                let label = format!("{}{BEST_GUESS}", display_cell(detector));
                out.push_str(&line(&label, &|_, scored, e| {
                    find(detector, scored, e).and_then(|r| r.auc_best_per_frame)
                }));
            }
            if let Some(reference) = reference {
                for row in reference.rows.iter().filter(|r| r.detector == *detector) {
                    out.push_str(&line(&format!("  paper: {}", row.label), &|name, _, e| {
                        row.auc(name, e)
                    }));
                }
            }
        }
    }
    out
}

/// Renders the false localisations per empty frame of `rows` (one line
/// per evaluation, in their order), under a heading; nothing without rows.
pub(crate) fn render_empty_frames(rows: &[EmptyFramesRow]) -> String {
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
    let mut out = wrap(title, MAX_TABLE_CHARS);
    out.push_str(&line(headers));
    for row in cells {
        let values: Vec<&str> = row.iter().map(String::as_str).collect();
        out.push_str(&line(&values));
    }
    out
}

/// `text` broken at spaces into lines of at most `width` characters (a
/// word longer than that on a line of its own), each ending in a newline.
fn wrap(text: &str, width: usize) -> String {
    let mut out = String::new();
    let mut line = String::new();
    for word in text.split_whitespace() {
        if !line.is_empty() && line.chars().count() + 1 + word.chars().count() > width {
            out.push_str(&line);
            out.push('\n');
            line.clear();
        }
        if !line.is_empty() {
            line.push(' ');
        }
        line.push_str(word);
    }
    out.push_str(&line);
    out.push('\n');
    out
}

/// A ratio to three decimals, `-` when there was nothing to count.
fn ratio(value: Option<f64>) -> String {
    value.map_or("-".to_string(), |v| format!("{v:.3}"))
}

/// A titled table of cells, as [`tracking_tables`] gives them: printed as
/// text by [`render_tracking`] and as Markdown by the report.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct CellTable<const N: usize> {
    pub title: String,
    pub headers: [&'static str; N],
    pub cells: Vec<[String; N]>,
}

/// The tracking pipelines' figures (docs/tracking.md, "The tracking
/// experiment"): one table of the tracking measures and one of D per
/// estimator; none without rows.
pub(crate) fn tracking_tables(rows: &[TrackingRow]) -> Vec<CellTable<10>> {
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
pub(crate) fn render_tracking(rows: &[TrackingRow]) -> String {
    tracking_tables(rows)
        .iter()
        .map(|table| render_cells(&table.title, &table.headers, &table.cells))
        .collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::manifest::{ReferenceCell, ReferenceRow};
    use crate::metrics::scenes::EmptyFrames;

    /// The paper manifest's test sets, ε and reference (Table 1's TrackPy
    /// and FCNN rows).
    pub(crate) const SETS: [(&str, f64); 3] =
        [("test-0.75", 0.75), ("test-1.00", 1.0), ("test-1.75", 1.75)];

    pub(crate) fn paper_reference() -> Reference {
        let row = |detector: &str, label: &str, auc: [[f64; 3]; 3]| ReferenceRow {
            detector: detector.into(),
            label: label.into(),
            cells: SETS
                .iter()
                .zip(auc)
                .flat_map(|((set, _), per_eps)| {
                    (0..3).map(move |i| ReferenceCell {
                        dataset: set.to_string(),
                        eps_px: (i + 1) as f64,
                        auc: per_eps[i],
                    })
                })
                .collect(),
        };
        Reference {
            source: "Netterstrøm, Kutuzov et al., Table 1 (AUC at ε = 70, 140, 210 nm)".into(),
            rows: vec![
                row(
                    "trackpy",
                    "TrackPy",
                    [[0.06, 0.42, 0.73], [0.04, 0.30, 0.61], [0.02, 0.19, 0.47]],
                ),
                row(
                    "cnn",
                    "FCNN",
                    [[0.48, 0.91, 0.99], [0.41, 0.87, 0.98], [0.26, 0.72, 0.92]],
                ),
            ],
        }
    }

    /// The evaluations of the paper manifest, in its order, with made-up
    /// figures in the paper run's shape (not its results): (detector,
    /// frames scored, ranked lists, AUC per set and ε, best guess's AUC).
    pub(crate) type PaperEvaluation = (
        &'static str,
        Option<usize>,
        bool,
        [[f64; 3]; 3],
        [[f64; 3]; 3],
    );

    pub(crate) fn paper_evaluations() -> Vec<PaperEvaluation> {
        let trackpy = [
            [0.061, 0.418, 0.731],
            [0.043, 0.302, 0.612],
            [0.021, 0.188, 0.474],
        ];
        let list = [
            [0.583, 0.970, 0.998],
            [0.521, 0.946, 0.996],
            [0.360, 0.840, 0.972],
        ];
        let best = [
            [0.460, 0.941, 0.995],
            [0.396, 0.907, 0.992],
            [0.252, 0.765, 0.949],
        ];
        let known = [
            [0.483, 0.950, 0.995],
            [0.413, 0.918, 0.994],
            [0.288, 0.793, 0.955],
        ];
        let marginal = [
            [0.479, 0.947, 0.996],
            [0.403, 0.916, 0.993],
            [0.289, 0.792, 0.952],
        ];
        let bound_list = [
            [0.601, 0.975, 0.999],
            [0.540, 0.950, 0.997],
            [0.392, 0.861, 0.975],
        ];
        let shift = |a: [[f64; 3]; 3], by: f64| a.map(|r| r.map(|v: f64| (v + by).min(1.0)));
        vec![
            ("trackpy", None, false, trackpy, trackpy),
            ("cnn", None, true, list, best),
            ("bound-known-d", Some(300), false, known, known),
            ("bound-marginal-d", Some(300), false, marginal, marginal),
            (
                "cnn",
                Some(300),
                true,
                shift(list, 0.004),
                shift(best, 0.004),
            ),
            (
                "bound-list-marginal-d",
                Some(1000),
                true,
                bound_list,
                shift(marginal, 0.001),
            ),
            (
                "cnn",
                Some(1000),
                true,
                shift(list, -0.003),
                shift(best, -0.003),
            ),
        ]
    }

    /// The run's AUC rows of [`paper_evaluations`].
    fn paper_rows() -> Vec<AucRow> {
        let mut rows = Vec::new();
        for (detector, first, ranked, auc, best) in paper_evaluations() {
            for (s, (set, d)) in SETS.iter().enumerate() {
                for i in 0..3 {
                    rows.push(AucRow {
                        detector: detector.into(),
                        dataset: match first {
                            Some(n) => format!("{set}+first{n}"),
                            None => set.to_string(),
                        },
                        diffusion: Some(*d),
                        eps_px: (i + 1) as f64,
                        auc: auc[s][i],
                        auc_best_per_frame: ranked.then_some(best[s][i]),
                        evaluation_key: String::new(),
                    });
                }
            }
        }
        rows
    }

    /// The widest line of `text`, in characters.
    fn widest(text: &str) -> usize {
        text.lines().map(|l| l.chars().count()).max().unwrap_or(0)
    }

    #[test]
    fn the_paper_run_table_keeps_nine_cells_a_row_and_the_bound_subsets_apart() {
        let text = render(&paper_rows(), Some(&paper_reference()));
        assert!(widest(&text) <= MAX_TABLE_CHARS, "{text}");
        insta::assert_snapshot!(text);
    }

    #[test]
    fn frames_scored_reads_the_first_n_frames_suffix() {
        assert_eq!(
            frames_scored("test-0.75+first300"),
            ("test-0.75", Some(300))
        );
        assert_eq!(frames_scored("test-0.75"), ("test-0.75", None));
        assert_eq!(frames_scored("a+firstx"), ("a+firstx", None));
        assert_eq!(frames_scored("+first3"), ("+first3", None));
    }

    #[test]
    fn a_wide_table_is_split_into_blocks_of_test_sets() {
        // Six sets of three ε: 18 figures, two blocks of at most 12.
        let rows: Vec<AucRow> = (0..6)
            .flat_map(|s| {
                (1..=3).map(move |e| AucRow {
                    detector: "cnn".into(),
                    dataset: format!("set-{s}"),
                    diffusion: None,
                    eps_px: e as f64,
                    auc: 0.1 * e as f64 + 0.01 * s as f64,
                    auc_best_per_frame: None,
                    evaluation_key: String::new(),
                })
            })
            .collect();
        let text = render(&rows, None);
        assert!(widest(&text) <= MAX_TABLE_CHARS, "{text}");
        insta::assert_snapshot!(text);
    }

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
        insta::assert_snapshot!(render_empty_frames(&rows));
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
        insta::assert_snapshot!("plain", text);

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
        let words = |line: &str| {
            line.split_whitespace()
                .map(str::to_string)
                .collect::<Vec<_>>()
        };
        let mut lines: Vec<Vec<String>> = ranked.lines().map(words).collect();
        assert_eq!(
            lines.remove(4),
            ["cnn,", "best", "guess", "0.550", "0.650", "-", "-"],
            "{ranked}"
        );
        // Otherwise the same table (the label column wider).
        assert_eq!(
            lines,
            text.lines().map(words).collect::<Vec<_>>(),
            "{ranked}"
        );
        insta::assert_snapshot!("ranked", ranked);
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
        insta::assert_snapshot!(render(&rows, None));
    }
}
