//! The report's tables: the AUC table beside the reference, the judgement
//! of each reference cell against the test set's luck, the gap to the
//! bound, where the AUC is lost, the scene figures, calibration and
//! uncertainty.

use std::fmt::Write as _;

use rayon::prelude::*;

use crate::manifest::Reference;
use crate::metrics::paired::{AucSpread, bootstrap_auc};
use crate::registry::RunRecord;
use crate::report::recorded::RecordedManifest;
use crate::run::cross_validation;
use crate::run::table::{blocks, frames_scored, sets_per_block};
use crate::sim::Distribution;
use crate::types::DetectorKind;

use super::{Artefacts, Evaluation};

/// A cross-validation run's table (nothing for other runs): per dataset
/// and ε, the mean ± sample standard deviation of the fold models' AUC, the
/// reference beside it.
pub(super) fn write_cross_validation_table(
    markdown: &mut String,
    record: &RunRecord,
    resolved: &RecordedManifest,
) -> anyhow::Result<()> {
    let Some(cv) = &record.cross_validation else {
        return Ok(());
    };
    let reference = resolved.reference.as_ref();
    let training_set = resolved
        .detector(&cv.detector)
        .and_then(|d| d.spec.training_dataset())
        .ok_or_else(|| {
            anyhow::anyhow!(
                "run {}: the cross-validated detector {} is not a trained detector of the recorded manifest",
                record.id,
                cv.detector
            )
        })?;
    let cells = cross_validation::summarise(&record.auc, cv, training_set);
    let (detector, folds) = (&cv.detector, cv.folds);
    writeln!(
        markdown,
        "\n## {folds}-fold cross-validation of {detector}\n\n\
         Each fold's model is trained on the other {} folds of the training set and keeps the epoch \
         with the best mean AUC on its held-out fold. Cells: mean ± sample standard deviation \
         (n − 1) over the {folds} models, the reference's value where it has one, then each \
         fold's value. The folds share each test set, so the spread is the models' alone: a new \
         test set of the same size moves an AUC further (docs/metric.md, \"The test set's \
         luck\").\n",
        folds - 1
    )?;
    writeln!(
        markdown,
        "| dataset | ε (px) | AUC mean ± sd | reference | per fold |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|")?;
    for cell in &cells {
        let label = match cell.diffusion {
            Some(d) => format!("{} (D = {d})", cell.dataset),
            None => cell.dataset.clone(),
        };
        let theirs = reference
            .and_then(|r| r.auc(detector, &cell.dataset, cell.eps_px))
            .map_or("—".to_string(), |auc| format!("{auc:.2}"));
        let per_fold: Vec<String> = cell.per_fold.iter().map(|a| format!("{a:.3}")).collect();
        writeln!(
            markdown,
            "| {label} | {} | {:.3} ± {} | {theirs} | {} |",
            cell.eps_px,
            cell.mean,
            cross_validation::format_std(cell.std),
            per_fold.join(", ")
        )?;
    }
    Ok(())
}

/// The AUC table in the paper's layout: rows detectors (a ranked list's
/// best guess alone a row of its own, the reference's rows after their
/// detector with the difference, ours − theirs), columns D × ε. Evaluations of a set's first N
/// frames (`DATASET+firstN`, as the bound runs) follow in a table per N,
/// every detector scored on those frames side by side. Tables of more than
/// [`crate::run::table::MAX_FIGURE_COLUMNS`] figures are split by test set.
pub(super) fn write_auc_table(
    markdown: &mut String,
    evaluations: &[Evaluation],
    reference: Option<&Reference>,
) -> anyhow::Result<()> {
    writeln!(
        markdown,
        "## AUC (precision–recall), ours vs the reference\n"
    )?;
    // A set of empty frames has no AUC: it has no column here, and its
    // false localisations are in the scene table.
    let scored: Vec<&Evaluation> = evaluations
        .iter()
        .filter(|e| !e.score.per_eps.is_empty())
        .collect();
    if scored.is_empty() {
        writeln!(
            markdown,
            "No test set with ground truth was scored, so there is no AUC (sets of empty frames: see the table at the score threshold)."
        )?;
        return Ok(());
    }
    if let Some(reference) = reference {
        writeln!(
            markdown,
            "Reference: {}. Under each detector its reference row and the difference, ours − \
             theirs. A detector that gives a ranked list of guesses per frame has a second row, \
             its best guess alone (docs/metric.md, \"A ranked list of guesses\").\n",
            reference.source
        )?;
    }
    let mut subsets: Vec<Option<usize>> = Vec::new();
    for e in &scored {
        let first = frames_scored(&e.dataset).1;
        if !subsets.contains(&first) {
            subsets.push(first);
        }
    }
    subsets.sort_by_key(|first| first.unwrap_or(0));
    for first in subsets {
        let group: Vec<&Evaluation> = scored
            .iter()
            .copied()
            .filter(|e| frames_scored(&e.dataset).1 == first)
            .collect();
        match first {
            None => write_auc_group(markdown, &group, reference)?,
            Some(n) => {
                writeln!(
                    markdown,
                    "\n### On the first {n} frames of each test set\n\n\
                     Every detector scored on these frames, side by side (the bound is run on \
                     them; the others on the whole sets too, above).\n"
                )?;
                write_auc_group(markdown, &group, None)?;
            }
        }
    }
    Ok(())
}

/// One AUC table of `evaluations` (all of one subset), split into blocks
/// of at most [`crate::run::table::MAX_FIGURE_COLUMNS`] figures.
/// The datasets (with their D), detectors and radii of an AUC group, each
/// in the order the evaluations first name it.
type AucAxes<'a> = (Vec<(&'a str, Option<f64>)>, Vec<&'a str>, Vec<f64>);

fn auc_group_axes<'a>(evaluations: &[&'a Evaluation]) -> AucAxes<'a> {
    let mut datasets: Vec<(&str, Option<f64>)> = Vec::new();
    let mut detectors: Vec<&str> = Vec::new();
    let mut eps: Vec<f64> = Vec::new();
    for e in evaluations {
        if !datasets.iter().any(|(d, _)| *d == e.dataset) {
            datasets.push((&e.dataset, e.diffusion));
        }
        if !detectors.contains(&e.detector.as_str()) {
            detectors.push(&e.detector);
        }
        for s in &e.score.per_eps {
            if !eps.contains(&s.eps_px) {
                eps.push(s.eps_px);
            }
        }
    }
    (datasets, detectors, eps)
}

/// The heading and rule lines of one block of an AUC group: a column per
/// dataset and radius, each heading on two lines so the columns stay as
/// narrow as their figures.
fn auc_group_header(block: &[(&str, Option<f64>)], eps: &[f64]) -> anyhow::Result<String> {
    let mut header = String::from("| detector |");
    let mut rule = String::from("|---|");
    for (dataset, diffusion) in block {
        for e in eps {
            match diffusion {
                Some(d) if (d * 100.0).round() == d * 100.0 => {
                    write!(header, " D = {d:.2}<br>ε = {e} |")?
                }
                Some(d) => write!(header, " D = {d}<br>ε = {e} |")?,
                None => write!(header, " {}<br>ε = {e} |", frames_scored(dataset).0)?,
            }
            rule.push_str("---|");
        }
    }
    Ok(format!("{header}\n{rule}"))
}

fn write_auc_group(
    markdown: &mut String,
    evaluations: &[&Evaluation],
    reference: Option<&Reference>,
) -> anyhow::Result<()> {
    let (datasets, detectors, eps) = auc_group_axes(evaluations);
    let score = |detector: &str, dataset: &str, e: f64| {
        evaluations
            .iter()
            .find(|x| x.detector == detector && x.dataset == dataset)
            .and_then(|x| x.score.per_eps.iter().find(|s| s.eps_px == e))
    };
    let best_guess_differs = |detector: &str| {
        evaluations
            .iter()
            .filter(|x| x.detector == detector && x.ranks_candidates)
            .flat_map(|x| &x.score.per_eps)
            .any(|s| s.auc_best_per_frame.is_some_and(|best| best != s.auc))
    };
    for (b, block) in blocks(&datasets, sets_per_block(eps.len())).enumerate() {
        if b > 0 {
            writeln!(markdown)?;
        }
        writeln!(markdown, "{}", auc_group_header(block, &eps)?)?;
        let row = |label: &str,
                   value: &dyn Fn(&str, f64) -> Option<f64>,
                   shown: &dyn Fn(f64) -> String| {
            let mut line = format!("| {label} |");
            for (dataset, _) in block {
                for &e in &eps {
                    match value(dataset, e) {
                        Some(v) => line.push_str(&format!(" {} |", shown(v))),
                        None => line.push_str(" — |"),
                    }
                }
            }
            line
        };
        let ours = |v: f64| format!("{v:.3}");
        // A published figure as printed: two decimals.
        let theirs = |v: f64| format!("{v:.2}");
        // A difference to the reference's precision, with no "-0.00".
        let difference = |v: f64| {
            let v = if v.abs() < 0.005 { 0.0 } else { v };
            format!("{v:+.2}")
        };
        for detector in &detectors {
            let own = |dataset: &str, e: f64| score(detector, dataset, e).map(|s| s.auc);
            writeln!(markdown, "{}", row(detector, &own, &ours))?;
            if best_guess_differs(detector) {
                let best = |dataset: &str, e: f64| {
                    score(detector, dataset, e).and_then(|s| s.auc_best_per_frame)
                };
                writeln!(
                    markdown,
                    "{}",
                    row(&format!("{detector}, best guess"), &best, &ours)
                )?;
            }
            if let Some(reference) = reference {
                for r in reference.rows.iter().filter(|r| r.detector == *detector) {
                    let published = |dataset: &str, e: f64| r.auc(frames_scored(dataset).0, e);
                    writeln!(
                        markdown,
                        "{}",
                        row(&format!("{} (reference)", r.label), &published, &theirs)
                    )?;
                    let apart =
                        |dataset: &str, e: f64| Some(own(dataset, e)? - published(dataset, e)?);
                    writeln!(
                        markdown,
                        "{}",
                        row(&format!("{detector} − {}", r.label), &apart, &difference)
                    )?;
                }
            }
        }
        // Reference rows for no detector of the run.
        if let Some(reference) = reference {
            for r in reference
                .rows
                .iter()
                .filter(|r| !detectors.contains(&r.detector.as_str()))
            {
                let published = |dataset: &str, e: f64| r.auc(frames_scored(dataset).0, e);
                writeln!(
                    markdown,
                    "{}",
                    row(&format!("{} (reference)", r.label), &published, &theirs)
                )?;
            }
        }
    }
    Ok(())
}

/// Which reference rows are a test and which were fitted: `scanloc
/// calibrate` fits the brightness N_qd (which the paper does not print) to
/// the row of an untrained detector (Crocker–Grier), so that row agrees by
/// construction; only trained detectors' rows are out-of-sample.
pub(super) fn write_reference_note(
    markdown: &mut String,
    evaluations: &[Evaluation],
    reference: &Reference,
    brightness: &Distribution,
) -> anyhow::Result<()> {
    let kind_of = |detector: &str| {
        evaluations
            .iter()
            .find(|e| e.detector == detector)
            .map(|e| e.detector_kind)
    };
    let mut fitted = Vec::new();
    let mut tested = Vec::new();
    for row in &reference.rows {
        let label = format!("{} ({})", row.label, row.detector);
        match kind_of(&row.detector) {
            Some(Some(DetectorKind::CrockerGrier)) => fitted.push(label),
            Some(_) => tested.push(label),
            None => {}
        }
    }
    if fitted.is_empty() {
        return Ok(());
    }
    writeln!(
        markdown,
        "\n**Which rows are a test.** The QD brightness N_qd (here {brightness}) is not given \
         in the paper; it is fitted with `scanloc calibrate`, which picks the N_qd whose \
         {} row comes closest to the reference (docs/metric.md, \"Calibrating the \
         brightness\"). That row was fitted: its agreement checks the simulator's trend across \
         D and ε, not the locator.{}",
        fitted.join(" and "),
        if tested.is_empty() {
            String::new()
        } else {
            format!(
                " Only the {} row is an out-of-sample comparison: nothing was tuned to it.",
                tested.join(" and ")
            )
        }
    )?;
    Ok(())
}

pub(super) fn write_quality_table(
    markdown: &mut String,
    evaluations: &[Evaluation],
) -> anyhow::Result<()> {
    writeln!(markdown, "\n## Localisation quality\n")?;
    writeln!(
        markdown,
        "| detector | dataset | RMSE of top prediction (px) | frames without prediction | predictions |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|")?;
    for e in evaluations {
        writeln!(
            markdown,
            "| {} | {} | {} | {:.4} | {} |",
            e.detector,
            e.dataset,
            e.score
                .rmse_top_px
                .map_or("—".to_string(), |r| format!("{r:.3}")),
            e.score.fraction_without_prediction,
            e.score.predictions
        )?;
    }
    Ok(())
}

/// A value with 3 decimals, or a dash.
pub(super) fn or_dash(value: Option<f64>) -> String {
    value.map_or("—".to_string(), |v| format!("{v:.3}"))
}

/// Where the AUC is lost: per evaluation and ε, the AUC beside the
/// oracle-rank and random-rank AUC of the top predictions
/// (docs/metric.md, "Headroom"). Nothing for evaluations stored before
/// the metric had it.
pub(super) fn write_headroom_table(
    markdown: &mut String,
    evaluations: &[Evaluation],
) -> anyhow::Result<()> {
    let rows: Vec<(&Evaluation, &crate::metrics::EpsScore)> = evaluations
        .iter()
        .flat_map(|e| e.score.per_eps.iter().map(move |s| (e, s)))
        .filter(|(_, s)| s.headroom.is_some())
        .collect();
    if rows.is_empty() {
        return Ok(());
    }
    writeln!(markdown, "\n## Where the AUC is lost\n")?;
    writeln!(
        markdown,
        "Each frame's top prediction ranked by its true distance to the truth (oracle) and in a \
         random order (the expectation over all orders), through the same metric. The AUC is \
         that of every prediction (a ranked list of guesses whole); beside it the AUC of each \
         frame's best guess alone (its rank 1, or its top score), which ranks those same top \
         predictions in the score's order: the share of the headroom the score uses is \
         (best-guess AUC − random) / (oracle − random), between 0 and 1 for a ranked list as for \
         a single guess (docs/metric.md, \"Headroom\").\n"
    )?;
    writeln!(
        markdown,
        "| detector | dataset | ε (px) | AUC | AUC, best per frame | oracle-rank AUC | random-rank AUC | share used | top within ε |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|---|---|---|---|")?;
    for (e, per_eps) in rows {
        let Some(headroom) = &per_eps.headroom else {
            continue;
        };
        writeln!(
            markdown,
            "| {} | {} | {} | {:.3} | {} | {:.3} | {:.3} | {} | {} |",
            e.detector,
            e.dataset,
            per_eps.eps_px,
            per_eps.auc,
            per_eps
                .auc_best_per_frame
                .map_or("—".to_string(), |a| format!("{a:.3}")),
            headroom.oracle_auc,
            headroom.random_auc,
            headroom
                .share_used_by_best_guesses(per_eps.auc, per_eps.auc_best_per_frame)
                .map_or("—".to_string(), |s| format!("{:.0} %", 100.0 * s)),
            headroom
                .fraction_top_within_eps
                .map_or("—".to_string(), |f| format!("{:.1} %", 100.0 * f)),
        )?;
    }
    Ok(())
}

/// Each AUC that has a reference value, with the standard error of a
/// bootstrap over its test set's frames, and whether it is ahead of the
/// reference, behind it or level with it given both figures' luck: the
/// reference's own standard error is unknown, so it is taken to be ours (a
/// test set of the same size and kind), which makes the difference's
/// standard error √2 times ours; ahead or behind only beyond twice that
/// plus the reference's rounding (docs/metric.md, "The test set's luck").
pub(super) fn write_reference_spread_table<'k>(
    artefacts: &mut Artefacts<'_, 'k>,
    markdown: &mut String,
    evaluations: &'k [Evaluation],
    reference: &Reference,
) -> anyhow::Result<()> {
    let compared: Vec<&Evaluation> = evaluations
        .iter()
        .filter(|e| {
            e.score
                .per_eps
                .iter()
                .any(|s| reference.auc(&e.detector, &e.dataset, s.eps_px).is_some())
        })
        .collect();
    if compared.is_empty() {
        return Ok(());
    }
    writeln!(
        markdown,
        "\n## Against the reference, with the test set's luck\n"
    )?;
    writeln!(
        markdown,
        "Each AUC with the standard error and 95 % interval of a bootstrap over its test set's \
         frames ({REPORT_RESAMPLES} resamples, seed {REPORT_BOOTSTRAP_SEED}): how far a new test \
         set of the same size would move it. The reference's figure was measured on a test set \
         of its own and carries such an error too; taken to be the same as ours, the difference's \
         standard error is √2 times ours, and a cell is *ahead* or *behind* only when the \
         difference exceeds twice that plus the reference's rounding (half a unit of its last \
         decimal), *level* otherwise (docs/metric.md, \"The test set's luck\").\n"
    )?;
    writeln!(
        markdown,
        "| detector | dataset | ε (px) | AUC | standard error | 95 % interval | reference | difference | its standard error | verdict |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|---|---|---|---|---|")?;
    for (evaluation, spreads) in bootstrap_each(artefacts, compared)? {
        for spread in spreads {
            let Some(theirs) =
                reference.auc(&evaluation.detector, &evaluation.dataset, spread.eps_px)
            else {
                continue;
            };
            writeln!(
                markdown,
                "| {} | {} | {} | {:.3} | {:.3} | [{:.3}, {:.3}] | {} |",
                evaluation.detector,
                evaluation.dataset,
                spread.eps_px,
                spread.auc,
                spread.standard_error,
                spread.interval_95.0,
                spread.interval_95.1,
                judged_cells(&spread, theirs),
            )?;
        }
    }
    Ok(())
}

/// Each evaluation's AUC per ε with the standard error and 95 % interval of
/// the report's bootstrap over its test set's frames, in the evaluations'
/// order. The bootstraps run in parallel, each seeded on its own, so the
/// figures do not depend on the thread count.
fn bootstrap_each<'e>(
    artefacts: &mut Artefacts<'_, 'e>,
    evaluations: Vec<&'e Evaluation>,
) -> anyhow::Result<Vec<(&'e Evaluation, Vec<AucSpread>)>> {
    let mut inputs = Vec::with_capacity(evaluations.len());
    for evaluation in evaluations {
        let data = artefacts.dataset(&evaluation.dataset_key)?;
        let located = artefacts.predictions(&evaluation.predictions_key)?;
        inputs.push((evaluation, data, located));
    }
    let spreads: Vec<Vec<AucSpread>> = inputs
        .par_iter()
        .map(|(evaluation, data, located)| {
            let eps: Vec<f64> = evaluation.score.per_eps.iter().map(|s| s.eps_px).collect();
            bootstrap_auc(
                located,
                &data.truth,
                data.frames.n,
                &eps,
                REPORT_RESAMPLES,
                REPORT_BOOTSTRAP_SEED,
            )
        })
        .collect::<anyhow::Result<_>>()?;
    Ok(inputs
        .into_iter()
        .map(|(evaluation, _, _)| evaluation)
        .zip(spreads)
        .collect())
}

/// The last four cells of a row of either reference table: the reference
/// figure `theirs`, our AUC's difference from it, that difference's standard
/// error and the verdict ([`LuckVerdict`], the figure's [`rounding`]
/// allowed): one judgement for a detector and for a bound alike.
fn judged_cells(spread: &AucSpread, theirs: f64) -> String {
    let difference = spread.auc - theirs;
    let verdict = LuckVerdict::of(difference, spread.standard_error, rounding(theirs));
    format!(
        "{theirs} | {difference:+.3} | {:.3} | {}",
        verdict.standard_error, verdict.word
    )
}

/// A difference from a reference judged against both figures' luck.
struct LuckVerdict {
    /// √2 × our AUC's standard error.
    standard_error: f64,
    /// `ahead`, `behind` or `level` (`—` without a standard error).
    word: &'static str,
}

impl LuckVerdict {
    /// `difference` = ours − the reference; `standard_error` ours;
    /// `rounding` how far the printed reference may be from its value.
    fn of(difference: f64, standard_error: f64, rounding: f64) -> Self {
        let standard_error = std::f64::consts::SQRT_2 * standard_error;
        let margin = 2.0 * standard_error + rounding;
        let word = if !margin.is_finite() {
            "—"
        } else if difference > margin {
            "ahead"
        } else if difference < -margin {
            "behind"
        } else {
            "level"
        };
        Self {
            standard_error,
            word,
        }
    }
}

/// Half a unit of the last decimal a published figure is written with
/// (0.99 → 0.005, 0.5 → 0.05): the figure is known to that much. Read from
/// the shortest decimal form of the value, so a figure written with a
/// trailing zero (0.50) counts as its shorter form, the cautious reading.
fn rounding(published: f64) -> f64 {
    let text = published.abs().to_string();
    let decimals = text
        .split_once('.')
        .map_or(0, |(_, fraction)| fraction.len());
    0.5 * 10f64.powi(-(decimals.min(300) as i32))
}

/// Resamples of the bootstraps in the report, and their seed: fixed, so a
/// report is a function of the run.
const REPORT_RESAMPLES: usize = 1000;
const REPORT_BOOTSTRAP_SEED: u64 = 0;

/// Every other detector against the attainable bound (a `likelihood`
/// detector) on the frames both localised: per ε, the paired bootstrap of
/// the AUC difference (docs/metric.md, "Comparing two detectors"), so the
/// gap to the bound is stated with its uncertainty. Nothing when no
/// likelihood detector shares a test set with another detector.
pub(super) fn write_bound_comparison_table<'k>(
    artefacts: &mut Artefacts<'_, 'k>,
    markdown: &mut String,
    evaluations: &'k [Evaluation],
) -> anyhow::Result<()> {
    let pairs: Vec<(&Evaluation, &Evaluation)> = evaluations
        .iter()
        .filter(|bound| bound.detector_kind == Some(DetectorKind::Likelihood))
        .flat_map(|bound| {
            evaluations
                .iter()
                .filter(move |other| {
                    other.detector_kind != Some(DetectorKind::Likelihood)
                        && other.dataset_key == bound.dataset_key
                        && !other.score.per_eps.is_empty()
                })
                .map(move |other| (other, bound))
        })
        .collect();
    if pairs.is_empty() {
        return Ok(());
    }
    writeln!(markdown, "\n## Against the attainable bound\n")?;
    writeln!(
        markdown,
        "Each detector's AUC minus the likelihood bound's on the same frames, with the standard \
         error and 95 % interval of a paired bootstrap over the frames ({REPORT_RESAMPLES} \
         resamples, seed {REPORT_BOOTSTRAP_SEED}; docs/metric.md, \"Comparing two detectors\").\n"
    )?;
    writeln!(
        markdown,
        "| detector | bound | dataset | ε (px) | AUC | bound's AUC | difference | standard error | 95 % interval |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|---|---|---|---|")?;
    for (other, bound) in pairs {
        let data = artefacts.dataset(&other.dataset_key)?;
        let located = artefacts.predictions(&other.predictions_key)?;
        let bound_located = artefacts.predictions(&bound.predictions_key)?;
        let eps: Vec<f64> = other.score.per_eps.iter().map(|s| s.eps_px).collect();
        let comparison = crate::metrics::paired::paired_bootstrap(
            &located,
            &bound_located,
            &data.truth,
            data.frames.n,
            &eps,
            REPORT_RESAMPLES,
            REPORT_BOOTSTRAP_SEED,
        )?;
        for c in comparison {
            writeln!(
                markdown,
                "| {} | {} | {} | {} | {:.3} | {:.3} | {:+.3} | {:.3} | [{:+.3}, {:+.3}] |",
                other.detector,
                bound.detector,
                other.dataset,
                c.eps_px,
                c.auc,
                c.auc_compared,
                c.difference,
                c.standard_error,
                c.interval_95.0,
                c.interval_95.1,
            )?;
        }
    }
    Ok(())
}

/// Whether a reference figure can be beaten at all: each attainable bound
/// (a `likelihood` detector) scored on a test set the reference has figures
/// for, beside every reference row's figure there, judged as the reference
/// table judges a detector (the bound's bootstrap standard error, √2 times it
/// for the difference, twice that plus the reference's rounding as the
/// margin). A figure the bound is level with or behind cannot be beaten by a
/// margin on this test set by any method that sees only the frames (and is
/// told no more than the bound). Nothing without such a bound.
pub(super) fn write_reference_bound_table<'k>(
    artefacts: &mut Artefacts<'_, 'k>,
    markdown: &mut String,
    evaluations: &'k [Evaluation],
    reference: &Reference,
) -> anyhow::Result<()> {
    let bounds: Vec<&Evaluation> = evaluations
        .iter()
        .filter(|bound| {
            bound.detector_kind == Some(DetectorKind::Likelihood)
                && bound.score.per_eps.iter().any(|s| {
                    reference
                        .rows
                        .iter()
                        .any(|row| row.auc(&bound.dataset, s.eps_px).is_some())
                })
        })
        .collect();
    if bounds.is_empty() {
        return Ok(());
    }
    writeln!(
        markdown,
        "\n## The reference against the attainable bound\n"
    )?;
    writeln!(
        markdown,
        "Each likelihood bound's AUC on a test set the reference has figures for, with its \
         bootstrap standard error ({REPORT_RESAMPLES} resamples, seed {REPORT_BOOTSTRAP_SEED}), \
         beside each reference figure: the bound is *ahead* of the figure when it exceeds it by \
         more than twice √2 times that error plus the figure's rounding (as in the reference \
         table), *behind* when it falls short by as much, *level* otherwise. Where the bound is \
         level with or behind a figure, no method that sees only the frames (and is told no more \
         than the bound) can be ahead of that figure by a margin on this test set: the cell \
         cannot be won under this simulator (docs/metric.md, \"The test set's luck\").\n"
    )?;
    writeln!(
        markdown,
        "| bound | dataset | ε (px) | bound's AUC | standard error | reference | reference's AUC | bound − reference | its standard error | the bound is |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|---|---|---|---|---|")?;
    for (bound, spreads) in bootstrap_each(artefacts, bounds)? {
        for spread in spreads {
            for row in &reference.rows {
                let Some(theirs) = row.auc(&bound.dataset, spread.eps_px) else {
                    continue;
                };
                writeln!(
                    markdown,
                    "| {} | {} | {} | {:.3} | {:.3} | {} | {} |",
                    bound.detector,
                    bound.dataset,
                    spread.eps_px,
                    spread.auc,
                    spread.standard_error,
                    row.label,
                    judged_cells(&spread, theirs),
                )?;
            }
        }
    }
    Ok(())
}

/// The scene figures: per evaluation and ε, recall, precision, Jaccard
/// index and RMSE of the localisations at or above the score threshold,
/// and the false localisations per empty frame (docs/metric.md,
/// "Scenes").
pub(super) fn write_scene_table(
    markdown: &mut String,
    evaluations: &[Evaluation],
) -> anyhow::Result<()> {
    let scored: Vec<&Evaluation> = evaluations
        .iter()
        .filter(|e| e.score.reading.is_some())
        .collect();
    if scored.is_empty() {
        return Ok(());
    }
    writeln!(markdown, "\n## At the score threshold\n")?;
    writeln!(
        markdown,
        "The localisations whose score is at or above the detector's threshold (`metrics.score_thresholds`; \
         default 0.5 for a probability score, none for Crocker–Grier's mass), matched as the AUC matches \
         (docs/metric.md, \"Scenes\"). Empty frames are frames without any QD.\n"
    )?;
    writeln!(
        markdown,
        "| detector | dataset | threshold | ε (px) | recall | precision | Jaccard | RMSE of matched (px) | empty frames | false localisations per empty frame |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|---|---|---|---|---|")?;
    for e in scored {
        let threshold = e
            .score
            .reading
            .and_then(|r| r.threshold)
            .map_or("none".to_string(), |t| format!("{t}"));
        let (empty, per_empty) = e.score.empty_frames.map_or(("—".to_string(), None), |x| {
            (x.frames.to_string(), x.false_localisations_per_frame)
        });
        if e.score.per_eps.is_empty() {
            // A set of empty frames: nothing per ε is defined.
            writeln!(
                markdown,
                "| {} | {} | {threshold} | — | — | — | — | — | {empty} | {} |",
                e.detector,
                e.dataset,
                or_dash(per_empty),
            )?;
        }
        for per_eps in &e.score.per_eps {
            let Some(at) = &per_eps.at_threshold else {
                continue;
            };
            writeln!(
                markdown,
                "| {} | {} | {threshold} | {} | {:.3} | {} | {:.3} | {} | {empty} | {} |",
                e.detector,
                e.dataset,
                per_eps.eps_px,
                at.recall,
                or_dash(at.precision),
                at.jaccard,
                or_dash(at.rmse_matched_px),
                or_dash(per_empty),
            )?;
        }
    }
    Ok(())
}

/// The expected calibration error of every probability score
/// (docs/metric.md, "Calibration"); the diagrams are figures.
pub(super) fn write_calibration_table(
    markdown: &mut String,
    evaluations: &[Evaluation],
) -> anyhow::Result<()> {
    let calibrated: Vec<(&Evaluation, &crate::metrics::calibration::Reliability)> = evaluations
        .iter()
        .filter_map(|e| e.score.reliability.as_ref().map(|r| (e, r)))
        .collect();
    if calibrated.is_empty() {
        return Ok(());
    }
    writeln!(markdown, "\n## Calibration of the score\n")?;
    writeln!(
        markdown,
        "For detectors whose score is a probability: every localisation's score against whether it \
         lies within 1 px of a QD of its frame, in 10 bins (the reliability diagrams below); the \
         expected calibration error (ECE) is the bins' |mean score − observed frequency| weighted by \
         their share of localisations. Crocker–Grier's score is a mass, not a probability: it has \
         no diagram (docs/metric.md, \"Calibration\").\n"
    )?;
    writeln!(markdown, "| detector | dataset | localisations | ECE |")?;
    writeln!(markdown, "|---|---|---|---|")?;
    for (e, reliability) in calibrated {
        writeln!(
            markdown,
            "| {} | {} | {} | {} |",
            e.detector,
            e.dataset,
            reliability.localisations,
            or_dash(reliability.expected_calibration_error)
        )?;
    }
    write_rank_calibration_table(markdown, evaluations)
}

/// Per candidate rank of ranked lists: the guesses' mean score against the
/// share of them that are a QD's first guess within 1 px, and the ECE
/// (docs/metric.md, "Calibration"); absent without lists.
fn write_rank_calibration_table(
    markdown: &mut String,
    evaluations: &[Evaluation],
) -> anyhow::Result<()> {
    let ranked: Vec<&Evaluation> = evaluations
        .iter()
        .filter(|e| !e.score.reliability_by_rank.is_empty())
        .collect();
    if ranked.is_empty() {
        return Ok(());
    }
    writeln!(
        markdown,
        "\nRanked lists, per rank: a guess's score is the probability that its frame's QD lies \
         within 1 px of it and of no guess ranked above it (the posterior mass it newly covers); \
         beside the mean score, the share of the rank's guesses for which that happened.\n"
    )?;
    writeln!(
        markdown,
        "| detector | dataset | rank | guesses | mean score | observed | ECE |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|---|---|")?;
    for e in ranked {
        for by_rank in &e.score.reliability_by_rank {
            let reliability = &by_rank.reliability;
            let (mut scores, mut hits) = (0.0, 0.0);
            for bin in &reliability.bins {
                let count = bin.count as f64;
                scores += count * bin.mean_score.unwrap_or(0.0);
                hits += count * bin.observed_frequency.unwrap_or(0.0);
            }
            let n = reliability.localisations as f64;
            let share = |sum: f64| (n > 0.0).then(|| sum / n);
            writeln!(
                markdown,
                "| {} | {} | {} | {} | {} | {} | {} |",
                e.detector,
                e.dataset,
                by_rank.rank,
                reliability.localisations,
                or_dash(share(scores)),
                or_dash(share(hits)),
                or_dash(reliability.expected_calibration_error)
            )?;
        }
    }
    Ok(())
}

/// How well each detector's own uncertainty (`sigma_x`, `sigma_y`)
/// describes its localisations' error (docs/metric.md, "Calibration of
/// the uncertainty"); absent when no detector reports one.
pub(super) fn write_uncertainty_table(
    markdown: &mut String,
    evaluations: &[Evaluation],
) -> anyhow::Result<()> {
    let reported: Vec<(
        &Evaluation,
        &crate::metrics::calibration::UncertaintyCalibration,
    )> = evaluations
        .iter()
        .filter_map(|e| e.score.uncertainty.as_ref().map(|u| (e, u)))
        .collect();
    if reported.is_empty() {
        return Ok(());
    }
    writeln!(markdown, "\n## Calibration of the uncertainty\n")?;
    writeln!(
        markdown,
        "For detectors that report each localisation's expected error σx, σy (px): over each \
         frame's top prediction, the root mean square of the error divided by σ on each axis (1 \
         when σ is right on average, above 1 when it is too small), the fraction of the per-axis \
         errors within 1 σ (0.683 for a Gaussian error of that σ), and Spearman's rank \
         correlation of σ with the distance to the truth (how well σ sorts precise from \
         imprecise localisations, as a filter on localisation precision does; docs/metric.md, \
         \"Calibration of the uncertainty\").\n"
    )?;
    writeln!(
        markdown,
        "| detector | dataset | localisations | RMS error/σ x | RMS error/σ y | within 1 σ | rank correlation |"
    )?;
    writeln!(markdown, "|---|---|---|---|---|---|---|")?;
    for (e, u) in reported {
        writeln!(
            markdown,
            "| {} | {} | {} | {:.3} | {:.3} | {:.3} | {} |",
            e.detector,
            e.dataset,
            u.localisations,
            u.rms_normalised_error_x,
            u.rms_normalised_error_y,
            u.within_one_sigma,
            or_dash(u.rank_correlation)
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::manifest::{ReferenceCell, ReferenceRow};
    use crate::metrics::Score;

    fn evaluation(detector: &str, kind: &str) -> Evaluation {
        Evaluation {
            detector: detector.to_string(),
            detector_kind: kind.parse().ok(),
            ranks_candidates: false,
            dataset: "test-1.00".to_string(),
            diffusion: Some(1.0),
            dataset_key: String::new(),
            predictions_key: String::new(),
            score: Score {
                per_eps: Vec::new(),
                rmse_top_px: None,
                frames: 1,
                frames_without_prediction: 0,
                fraction_without_prediction: 0.0,
                predictions: 0,
                ground_truths: 1,
                reading: None,
                empty_frames: None,
                reliability: None,
                reliability_by_rank: Vec::new(),
                uncertainty: None,
            },
        }
    }

    /// The paper manifest's evaluations (the run table's fixture, made-up
    /// figures in the paper run's shape), with a headroom per cell.
    fn paper_evaluations() -> Vec<Evaluation> {
        use crate::metrics::EpsScore;
        use crate::metrics::headroom::Headroom;
        use crate::run::table::tests::{SETS, paper_evaluations};
        let mut out = Vec::new();
        for (detector, first, ranked, auc, best) in paper_evaluations() {
            for (s, (set, d)) in SETS.iter().enumerate() {
                let mut e = evaluation(
                    detector,
                    if detector == "trackpy" {
                        "crocker_grier"
                    } else {
                        "cnn"
                    },
                );
                e.ranks_candidates = ranked;
                e.dataset = match first {
                    Some(n) => format!("{set}+first{n}"),
                    None => set.to_string(),
                };
                e.diffusion = Some(*d);
                e.score.per_eps = (0..3)
                    .map(|i| {
                        // Top guesses within ε: halfway from the best
                        // guesses' AUC to 1; the random order below both.
                        let within = best[s][i] + (1.0 - best[s][i]) / 2.0;
                        let random = within * best[s][i];
                        EpsScore {
                            eps_px: (i + 1) as f64,
                            auc: auc[s][i],
                            auc_best_per_frame: Some(best[s][i]),
                            true_positives: 0,
                            false_positives: 0,
                            curve: Vec::new(),
                            headroom: Some(Headroom {
                                top_predictions: 1000,
                                top_within_eps: (1000.0 * within) as usize,
                                fraction_top_within_eps: Some(within),
                                oracle_auc: within,
                                random_auc: random,
                                share_used: Some((auc[s][i] - random) / (within - random)),
                            }),
                            at_threshold: None,
                        }
                    })
                    .collect();
                out.push(e);
            }
        }
        out
    }

    #[test]
    fn the_paper_reports_auc_table_keeps_nine_cells_a_row_and_the_bound_subsets_apart() {
        let evaluations = paper_evaluations();
        let reference = crate::run::table::tests::paper_reference();
        let mut markdown = String::new();
        write_auc_table(&mut markdown, &evaluations, Some(&reference)).unwrap();
        for line in markdown.lines().filter(|l| l.starts_with('|')) {
            let columns = line.matches('|').count() - 1;
            assert!(columns <= 13, "{columns} columns: {line}");
        }
        insta::assert_snapshot!(markdown);
    }

    #[test]
    fn the_headroom_tables_share_is_that_of_the_best_guesses_for_ranked_lists_too() {
        let evaluations: Vec<Evaluation> = paper_evaluations()
            .into_iter()
            .filter(|e| !e.dataset.contains("+first"))
            .collect();
        let mut markdown = String::new();
        write_headroom_table(&mut markdown, &evaluations).unwrap();
        // Every share printed is a share: 0 to 100 %.
        for line in markdown
            .lines()
            .filter(|l| l.starts_with("| cnn") || l.starts_with("| trackpy"))
        {
            let share: f64 = line
                .split('|')
                .nth(8)
                .unwrap()
                .trim()
                .trim_end_matches(" %")
                .parse()
                .unwrap();
            assert!((0.0..=100.0).contains(&share), "{line}");
        }
        insta::assert_snapshot!(markdown);
    }

    fn row(detector: &str, label: &str) -> ReferenceRow {
        ReferenceRow {
            detector: detector.to_string(),
            label: label.to_string(),
            cells: vec![ReferenceCell {
                dataset: "test-1.00".to_string(),
                eps_px: 1.0,
                auc: 0.5,
            }],
        }
    }

    #[test]
    fn the_note_says_the_crocker_grier_row_was_fitted_and_the_cnn_row_is_out_of_sample() {
        let evaluations = [
            evaluation("trackpy", "crocker_grier"),
            evaluation("cnn", "cnn"),
        ];
        let reference = Reference {
            source: "Table 1".to_string(),
            rows: vec![row("trackpy", "TrackPy"), row("cnn", "FCNN")],
        };
        let mut markdown = String::new();
        write_reference_note(&mut markdown, &evaluations, &reference, &7.5.into()).unwrap();
        assert!(markdown.contains("N_qd (here 7.5)"), "{markdown}");
        assert!(
            markdown.contains("whose TrackPy (trackpy) row comes closest"),
            "{markdown}"
        );
        assert!(markdown.contains("That row was fitted"), "{markdown}");
        assert!(
            markdown.contains("Only the FCNN (cnn) row is an out-of-sample comparison"),
            "{markdown}"
        );

        // Without an untrained detector's row nothing was fitted: no note.
        let reference = Reference {
            source: "Table 1".to_string(),
            rows: vec![row("cnn", "FCNN")],
        };
        let mut markdown = String::new();
        write_reference_note(&mut markdown, &evaluations, &reference, &7.5.into()).unwrap();
        assert!(markdown.is_empty(), "{markdown}");
    }

    #[test]
    fn a_difference_is_ahead_or_behind_only_beyond_twice_its_combined_standard_error() {
        // Our standard error 0.01: the difference's √2 × 0.01 ≈ 0.0141, the
        // verdict's threshold ≈ 0.0283 for an exact reference.
        let verdict = |difference| LuckVerdict::of(difference, 0.01, 0.0).word;
        assert_eq!(verdict(0.03), "ahead");
        assert_eq!(verdict(-0.03), "behind");
        assert_eq!(verdict(0.027), "level");
        assert_eq!(verdict(-0.027), "level");
        // A reference printed as 0.99 may be 0.985 to 0.995: 0.005 more.
        assert_eq!(LuckVerdict::of(0.03, 0.01, 0.005).word, "level");
        assert_eq!(LuckVerdict::of(-0.034, 0.01, 0.005).word, "behind");
        let combined = LuckVerdict::of(0.0, 0.01, 0.0).standard_error;
        assert!((combined - 0.01 * 2f64.sqrt()).abs() < 1e-15);
        assert_eq!(LuckVerdict::of(0.5, f64::NAN, 0.005).word, "—");
    }

    #[test]
    fn a_published_figure_is_known_to_half_a_unit_of_its_last_decimal() {
        for (published, half_unit) in [(0.99, 0.005), (0.5, 0.05), (0.125, 0.0005), (1.0, 0.5)] {
            assert!(
                (rounding(published) - half_unit).abs() < 1e-15,
                "{published}"
            );
        }
    }
}
