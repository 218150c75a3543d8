//! `scanloc cv`: k-fold cross-validation of a trained detector.
//!
//! The training set is split into k folds by a seeded permutation
//! (`derive_seed(master, "cv-permutation", detector)`, ChaCha8). Fold f's
//! model is trained on the other k − 1 folds (each fold's frame subset is an
//! artefact of its own, so an interrupted sweep resumes where it stopped),
//! scored on its held-out fold and on every test set the manifest evaluates
//! the detector on. The table reports mean ± standard deviation over folds.
//! Each fold's model is selected on its held-out fold (the epoch with the
//! best mean AUC there) and trains on all of the other k − 1 folds: the
//! detector's `validation_fraction` has nothing to hold out. At
//! `validation_fraction: 1` (the training set only selects; fresh frames
//! train) the fold models keep to that recipe and train on fresh frames
//! only, under keys of their own (`run::plan`).

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use serde_json::json;

use super::{RunOptions, RunOutcome, execute, plan::Plan};
use crate::error::input_error;
use crate::manifest::{CrossValidation, DatasetSpec, DetectorEntry, Manifest};
use crate::registry::{AucRow, CrossValidationPlan, Registry, RunKind};
use crate::types::derive_seed;

/// Mean and spread of one (dataset, ε) cell over the folds.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct CvCell {
    pub dataset: String,
    pub diffusion: Option<f64>,
    pub eps_px: f64,
    pub mean: f64,
    /// Sample standard deviation over folds (n − 1); none with a single
    /// fold (`scanloc cv --fold`).
    pub std: Option<f64>,
    pub per_fold: Vec<f64>,
    /// For a detector giving ranked lists: the same over folds of each
    /// frame's best guess alone (`None` without lists).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub best_guess: Option<BestGuessCell>,
}

/// Mean and spread over the folds of the best-guess-per-frame AUC.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct BestGuessCell {
    pub mean: f64,
    /// As [`CvCell::std`].
    pub std: Option<f64>,
    pub per_fold: Vec<f64>,
}

/// The mean and sample standard deviation (none for one value) of
/// `values`, which are not empty.
fn mean_and_std(values: &[f64]) -> (f64, Option<f64>) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let std = (values.len() > 1)
        .then(|| (values.iter().map(|a| (a - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt());
    (mean, std)
}

/// The outcome of a cross-validation run.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct CrossValidationOutcome {
    pub detector: String,
    pub folds: usize,
    pub run: RunOutcome,
    pub cells: Vec<CvCell>,
}

/// The frames of each fold: a seeded permutation of `0..frames` cut into
/// `folds` nearly equal parts (each sorted).
pub(crate) fn fold_frames(frames: usize, folds: usize, seed: u64) -> Vec<Vec<usize>> {
    let mut order: Vec<usize> = (0..frames).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(seed));
    (0..folds)
        .map(|f| {
            let mut part = order[f * frames / folds..(f + 1) * frames / folds].to_vec();
            part.sort_unstable();
            part
        })
        .collect()
}

// The names below are part of the fold artefacts' content keys: they are
// built here and never parsed (a run's plan is recorded with it).

/// Name of fold `fold`'s (1-based) model: `DETECTOR-cvKofN`.
fn fold_model_name(detector: &str, fold: usize, folds: usize) -> String {
    format!("{detector}-cv{fold}of{folds}")
}

/// Name of fold `fold`'s (1-based) subset `part` (`train` or `held-out`)
/// of the training set: `TRAINING-cvKofN-PART`.
fn fold_subset_name(training_set: &str, fold: usize, folds: usize, part: &str) -> String {
    format!("{training_set}-cv{fold}of{folds}-{part}")
}

/// The folds (1-based) `cv` runs: all, or its one fold.
fn folds_run(cv: &CrossValidationPlan) -> Vec<usize> {
    match cv.fold {
        Some(fold) => vec![fold],
        None => (1..=cv.folds).collect(),
    }
}

/// Runs the k-fold cross-validation `cv` (of a detector trained on a
/// manifest dataset) and records it, with its plan, as a run of kind `cv`.
/// With `cv.fold` just that fold's steps run: the same artefacts, under the
/// same keys, as in the whole sweep, so with `force` one fold of a recorded
/// sweep is recomputed and checked against the stored results.
pub(crate) fn cross_validate(
    registry: &mut Registry,
    manifest: &Manifest,
    cv: &CrossValidationPlan,
    force: bool,
) -> anyhow::Result<CrossValidationOutcome> {
    let plan = plan(manifest, cv)?;
    let run = execute(
        registry,
        manifest,
        &plan,
        &RunOptions {
            force,
            kind: RunKind::Cv,
            parent_run: None,
            cross_validation: Some(cv.clone()),
        },
    )?;

    let cells = summarise(&run.auc, cv, training_set(manifest, &cv.detector)?);
    Ok(CrossValidationOutcome {
        detector: cv.detector.clone(),
        folds: cv.folds,
        run,
        cells,
    })
}

/// The dataset `detector` of `manifest` is trained on; bad input if there
/// is no such detector or it is not trained.
pub fn training_set<'a>(manifest: &'a Manifest, detector: &str) -> anyhow::Result<&'a str> {
    let entry = manifest.detector(detector).ok_or_else(|| {
        input_error(format!(
            "{}: detectors.{detector}: no such detector",
            manifest.source
        ))
    })?;
    entry.spec.training_dataset().ok_or_else(|| {
        input_error(format!(
            "{}: detectors.{detector}: not a trained detector, nothing to cross-validate",
            manifest.source
        ))
    })
}

/// Refuses as bad input a fold count `cv.folds` outside its range or
/// larger than the `training` set's frames, and a fold `cv.fold` that is
/// not one of them.
fn check_fold_counts(training: &DatasetSpec, cv: &CrossValidationPlan) -> anyhow::Result<()> {
    let folds = cv.folds;
    CrossValidation::check_folds(folds)
        .map_err(|message| input_error(format!("folds: {message}")))?;
    if folds > training.frames {
        return Err(input_error(format!(
            "folds: must be at most the {} training frames, got {folds}",
            training.frames
        )));
    }
    if let Some(fold) = cv.fold
        && !(1..=folds).contains(&fold)
    {
        return Err(input_error(format!(
            "fold: must be between 1 and the {folds} folds, got {fold}"
        )));
    }
    Ok(())
}

/// The steps of the k-fold cross-validation `cv` (all folds, or only fold
/// `cv.fold`): the training and test datasets, each fold's training and
/// held-out subsets, its model, and its predictions and scores on the
/// held-out fold and on every test set.
pub fn plan(manifest: &Manifest, cv: &CrossValidationPlan) -> anyhow::Result<Plan> {
    let (detector, folds) = (cv.detector.as_str(), cv.folds);
    let entry = manifest.detector(detector).ok_or_else(|| {
        input_error(format!(
            "{}: detectors.{detector}: no such detector",
            manifest.source
        ))
    })?;
    let training_name = training_set(manifest, detector)?;
    let training: &DatasetSpec = manifest.dataset(training_name).ok_or_else(|| {
        input_error(format!(
            "{}: datasets.{training_name}: no such dataset",
            manifest.source
        ))
    })?;
    check_fold_counts(training, cv)?;
    let permutation_seed = derive_seed(manifest.seed, "cv-permutation", detector);
    let parts = fold_frames(training.frames, folds, permutation_seed);

    let mut plan = Plan::default();
    let training_step = plan.add_dataset(training)?;
    let test_sets: Vec<&DatasetSpec> = manifest
        .evaluations
        .iter()
        .filter(|e| e.detector == detector)
        .filter_map(|e| manifest.dataset(&e.dataset))
        .collect();
    let test_steps: Vec<(usize, &DatasetSpec)> = test_sets
        .iter()
        .map(|d| plan.add_dataset(d).map(|step| (step, *d)))
        .collect::<anyhow::Result<_>>()?;
    for fold in folds_run(cv) {
        let held_out = &parts[fold - 1];
        let train_frames: Vec<usize> = parts
            .iter()
            .enumerate()
            .filter(|(other, _)| *other + 1 != fold)
            .flat_map(|(_, p)| p.iter().copied())
            .collect();
        let mut train_frames = train_frames;
        train_frames.sort_unstable();
        let description = |part: &str| {
            json!({
                "fold": fold,
                "folds": folds,
                "part": part,
                "permutation_seed": permutation_seed.to_string(),
            })
        };
        let train_subset = plan.add_subset(
            training_step,
            &fold_subset_name(training_name, fold, folds, "train"),
            train_frames,
            description("train"),
        )?;
        let held_out_subset = plan.add_subset(
            training_step,
            &fold_subset_name(training_name, fold, folds, "held-out"),
            held_out.clone(),
            description("held-out"),
        )?;
        let name = fold_model_name(detector, fold, folds);
        let fold_entry = DetectorEntry {
            seed: derive_seed(manifest.seed, "detector", &name),
            name: name.clone(),
            spec: entry.spec.clone(),
        };
        let model = plan.add_training(&fold_entry, train_subset, Some(held_out_subset))?;
        for (dataset_step, diffusion) in std::iter::once((held_out_subset, None)).chain(
            test_steps
                .iter()
                .map(|(step, spec)| (*step, spec.fixed_diffusion())),
        ) {
            let predictions = plan.add_locate(&fold_entry, dataset_step, Some(model))?;
            plan.add_score(
                &name,
                dataset_step,
                diffusion,
                predictions,
                &manifest.metrics,
                // The fold models are read as the detector they train.
                manifest.metrics.score_reading(entry),
            )?;
        }
    }
    Ok(plan)
}

/// Label of the held-out folds' column.
const HELD_OUT_LABEL: &str = "held-out fold";

/// The cells of the cross-validation table of `cv` (whose detector is
/// trained on `training_set`) from the AUC rows of its run: for each
/// (dataset, ε), the AUCs of the fold models with their mean and sample
/// standard deviation. Each fold's own held-out subset is one column,
/// "held-out fold"; every other dataset (whatever its name) is its own.
pub(crate) fn summarise(
    auc: &[AucRow],
    cv: &CrossValidationPlan,
    training_set: &str,
) -> Vec<CvCell> {
    let folds = folds_run(cv);
    // The fold whose model scored `row`, and the column the row belongs in.
    let place = |row: &AucRow| -> Option<(usize, String)> {
        let fold = folds
            .iter()
            .copied()
            .find(|&fold| row.detector == fold_model_name(&cv.detector, fold, cv.folds))?;
        let column = if row.dataset == fold_subset_name(training_set, fold, cv.folds, "held-out") {
            HELD_OUT_LABEL.to_string()
        } else {
            row.dataset.clone()
        };
        Some((fold, column))
    };
    let mut columns: Vec<(String, Option<f64>, f64)> = Vec::new();
    for row in auc {
        let Some((_, column)) = place(row) else {
            continue;
        };
        if !columns
            .iter()
            .any(|(d, _, e)| *d == column && *e == row.eps_px)
        {
            columns.push((column, row.diffusion, row.eps_px));
        }
    }
    let mut cells = Vec::new();
    for (dataset, diffusion, eps_px) in columns {
        let rows: Vec<&AucRow> = folds
            .iter()
            .filter_map(|&fold| {
                auc.iter()
                    .find(|row| row.eps_px == eps_px && place(row) == Some((fold, dataset.clone())))
            })
            .collect();
        if rows.is_empty() {
            continue;
        }
        let per_fold: Vec<f64> = rows.iter().map(|row| row.auc).collect();
        let (mean, std) = mean_and_std(&per_fold);
        // Every fold's model ranks its guesses, or none does: the table
        // gives the best guesses' row only when all folds have it.
        let best_guess = rows
            .iter()
            .map(|row| row.auc_best_per_frame)
            .collect::<Option<Vec<f64>>>()
            .map(|per_fold| {
                let (mean, std) = mean_and_std(&per_fold);
                BestGuessCell {
                    mean,
                    std,
                    per_fold,
                }
            });
        cells.push(CvCell {
            dataset,
            diffusion,
            eps_px,
            mean,
            std,
            per_fold,
            best_guess,
        });
    }
    cells
}

/// A standard deviation for a table: three decimals, `—` when there is
/// none (a single fold).
pub(crate) fn format_std(std: Option<f64>) -> String {
    std.map_or("—".to_string(), |std| format!("{std:.3}"))
}

/// The cross-validation table as text: one line per dataset, `mean ± std`
/// per ε.
pub(crate) fn render(outcome: &CrossValidationOutcome) -> String {
    let mut out = format!(
        "{}-fold cross-validation of {} (run {}): AUC mean ± standard deviation over folds\n",
        outcome.folds, outcome.detector, outcome.run.run
    );
    let mut datasets: Vec<(&str, Option<f64>)> = Vec::new();
    for cell in &outcome.cells {
        if !datasets.iter().any(|(d, _)| *d == cell.dataset) {
            datasets.push((&cell.dataset, cell.diffusion));
        }
    }
    for (dataset, diffusion) in datasets {
        let label = match diffusion {
            Some(d) => format!("{dataset} (D = {d})"),
            None => dataset.to_string(),
        };
        let cells: Vec<&CvCell> = outcome
            .cells
            .iter()
            .filter(|c| c.dataset == dataset)
            .collect();
        out.push_str(&format!("{label:<28}"));
        for cell in &cells {
            out.push_str(&format!(
                "  ε={}: {:.3} ± {}",
                cell.eps_px,
                cell.mean,
                format_std(cell.std)
            ));
        }
        out.push('\n');
        // Ranked lists: the same cells for each frame's best guess alone.
        if cells.iter().all(|c| c.best_guess.is_some()) {
            out.push_str(&format!("{:<28}", "  best guess per frame"));
            for cell in cells
                .iter()
                .filter_map(|c| c.best_guess.as_ref().map(|b| (c, b)))
            {
                let (cell, best) = cell;
                out.push_str(&format!(
                    "  ε={}: {:.3} ± {}",
                    cell.eps_px,
                    best.mean,
                    format_std(best.std)
                ));
            }
            out.push('\n');
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn folds_partition_the_frames_and_depend_only_on_the_seed() {
        let parts = fold_frames(103, 5, 9);
        let mut all: Vec<usize> = parts.iter().flatten().copied().collect();
        all.sort_unstable();
        assert_eq!(all, (0..103).collect::<Vec<_>>());
        assert!(parts.iter().all(|p| p.len() == 20 || p.len() == 21));
        assert_eq!(parts, fold_frames(103, 5, 9));
        assert_ne!(parts, fold_frames(103, 5, 10));
    }

    fn row(detector: &str, dataset: &str, auc: f64) -> AucRow {
        AucRow {
            detector: detector.into(),
            dataset: dataset.into(),
            diffusion: None,
            eps_px: 1.0,
            auc,
            auc_best_per_frame: None,
            evaluation_key: String::new(),
        }
    }

    #[test]
    fn a_test_set_named_like_a_held_out_fold_keeps_its_own_column() {
        let cv = CrossValidationPlan {
            detector: "cnn".into(),
            folds: 2,
            fold: None,
        };
        let auc = [
            row("cnn-cv1of2", "train-cv1of2-held-out", 0.5),
            row("cnn-cv1of2", "x-held-out", 0.1),
            row("cnn-cv2of2", "train-cv2of2-held-out", 0.7),
            row("cnn-cv2of2", "x-held-out", 0.3),
        ];
        let cells = summarise(&auc, &cv, "train");
        let columns: Vec<(&str, &[f64])> = cells
            .iter()
            .map(|c| (c.dataset.as_str(), c.per_fold.as_slice()))
            .collect();
        assert_eq!(
            columns,
            [
                (HELD_OUT_LABEL, &[0.5, 0.7][..]),
                ("x-held-out", &[0.1, 0.3][..])
            ]
        );
        // One fold alone: that fold's values, no spread.
        let one = CrossValidationPlan {
            fold: Some(2),
            ..cv
        };
        let cells = summarise(&auc, &one, "train");
        assert_eq!(cells.len(), 2);
        assert_eq!(cells[1].per_fold, [0.3]);
        assert_eq!(cells[1].std, None);
    }

    #[test]
    fn ranked_lists_get_a_best_guess_line_with_its_own_mean_and_spread() {
        let cv = CrossValidationPlan {
            detector: "cnn".into(),
            folds: 2,
            fold: None,
        };
        let ranked = |detector: &str, auc: f64, best: f64| AucRow {
            auc_best_per_frame: Some(best),
            ..row(detector, "test", auc)
        };
        let auc = [
            ranked("cnn-cv1of2", 0.6, 0.4),
            ranked("cnn-cv2of2", 0.8, 0.5),
        ];
        let cells = summarise(&auc, &cv, "train");
        let best = cells[0].best_guess.as_ref().expect("both folds rank");
        assert!((best.mean - 0.45).abs() < 1e-12);
        assert!((best.std.unwrap() - 0.05f64.hypot(0.05)).abs() < 1e-12);
        let outcome = CrossValidationOutcome {
            detector: "cnn".into(),
            folds: 2,
            run: RunOutcome {
                run: "R".into(),
                manifest: "m".into(),
                status: crate::registry::RunStatus::Done,
                auc: Vec::new(),
                empty_frames: Vec::new(),
                tracking: Vec::new(),
                counts: Default::default(),
                steps: Vec::new(),
                damaged_blobs: Vec::new(),
                seconds: 0.0,
            },
            cells,
        };
        let text = render(&outcome);
        assert!(
            text.contains("test                          ε=1: 0.700 ± 0.141\n"),
            "{text}"
        );
        assert!(
            text.contains("  best guess per frame        ε=1: 0.450 ± 0.071\n"),
            "{text}"
        );
        // Without ranks (one fold's row lacks the value): no such line.
        let mixed = [
            ranked("cnn-cv1of2", 0.6, 0.4),
            row("cnn-cv2of2", "test", 0.8),
        ];
        let cells = summarise(&mixed, &cv, "train");
        assert!(cells[0].best_guess.is_none());
        let text = render(&CrossValidationOutcome { cells, ..outcome });
        assert!(!text.contains("best guess"), "{text}");
    }
}
