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
//! detector's `validation_fraction` is not used.

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use serde_json::json;

use super::{RunOptions, RunOutcome, execute, plan::Plan};
use crate::error::input_error;
use crate::manifest::{DatasetSpec, DetectorEntry, Manifest, derive_seed};
use crate::registry::{AucRow, Registry};

/// Mean and spread of one (dataset, ε) cell over the folds.
#[derive(Debug, Clone, Serialize)]
pub struct CvCell {
    pub dataset: String,
    pub diffusion: Option<f64>,
    pub eps_px: f64,
    pub mean: f64,
    /// Sample standard deviation over folds (n − 1); none with a single
    /// fold (`scanloc cv --fold`).
    pub std: Option<f64>,
    pub per_fold: Vec<f64>,
}

/// The outcome of a cross-validation run.
#[derive(Debug, Clone, Serialize)]
pub struct CrossValidationOutcome {
    pub detector: String,
    pub folds: usize,
    pub run: RunOutcome,
    pub cells: Vec<CvCell>,
}

/// The frames of each fold: a seeded permutation of `0..frames` cut into
/// `folds` nearly equal parts (each sorted).
pub fn fold_frames(frames: usize, folds: usize, seed: u64) -> Vec<Vec<usize>> {
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

/// Name of fold `f`'s model.
fn fold_detector_name(detector: &str, fold: usize, folds: usize) -> String {
    format!("{detector}-cv{}of{folds}", fold + 1)
}

/// Runs k-fold cross-validation of `detector` (which must be trained on a
/// manifest dataset) and records it as a run of kind `cv`. With
/// `only_fold` (1-based) just that fold's steps run: the same artefacts,
/// under the same keys, as in the whole sweep, so with `force` one fold of a
/// recorded sweep is recomputed and checked against the stored results.
pub fn cross_validate(
    registry: &mut Registry,
    manifest: &Manifest,
    detector: &str,
    folds: usize,
    only_fold: Option<usize>,
    force: bool,
) -> anyhow::Result<CrossValidationOutcome> {
    let plan = plan(manifest, detector, folds, only_fold)?;
    let run = execute(
        registry,
        manifest,
        &plan,
        &RunOptions {
            force,
            kind: Some("cv".to_string()),
            parent_run: None,
        },
    )?;

    let cells = summarise(&run.auc, detector, folds);
    Ok(CrossValidationOutcome {
        detector: detector.to_string(),
        folds,
        run,
        cells,
    })
}

/// The steps of a k-fold cross-validation of `detector` (all folds, or
/// only fold `only_fold`, 1-based): the training and test datasets, each
/// fold's training and held-out subsets, its model, and its predictions and
/// scores on the held-out fold and on every test set.
pub fn plan(
    manifest: &Manifest,
    detector: &str,
    folds: usize,
    only_fold: Option<usize>,
) -> anyhow::Result<Plan> {
    let entry = manifest.detector(detector).ok_or_else(|| {
        input_error(format!(
            "{}: detectors.{detector}: no such detector",
            manifest.source
        ))
    })?;
    let training_name = entry.spec.training_dataset().ok_or_else(|| {
        input_error(format!(
            "{}: detectors.{detector}: not a trained detector, nothing to cross-validate",
            manifest.source
        ))
    })?;
    let training: &DatasetSpec = manifest.dataset(training_name).ok_or_else(|| {
        input_error(format!(
            "{}: datasets.{training_name}: no such dataset",
            manifest.source
        ))
    })?;
    if !(2..=50).contains(&folds) || folds > training.frames {
        return Err(input_error(format!(
            "folds: must be between 2 and 50 and at most the {} training frames, got {folds}",
            training.frames
        )));
    }
    if let Some(fold) = only_fold
        && !(1..=folds).contains(&fold)
    {
        return Err(input_error(format!(
            "fold: must be between 1 and the {folds} folds, got {fold}"
        )));
    }
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
    for (fold, held_out) in parts.iter().enumerate() {
        if only_fold.is_some_and(|only| only != fold + 1) {
            continue;
        }
        let train_frames: Vec<usize> = parts
            .iter()
            .enumerate()
            .filter(|(other, _)| *other != fold)
            .flat_map(|(_, p)| p.iter().copied())
            .collect();
        let mut train_frames = train_frames;
        train_frames.sort_unstable();
        let description = |part: &str| {
            json!({
                "fold": fold + 1,
                "folds": folds,
                "part": part,
                "permutation_seed": permutation_seed.to_string(),
            })
        };
        let train_subset = plan.add_subset(
            training_step,
            &format!("{training_name}-cv{}of{folds}-train", fold + 1),
            train_frames,
            description("train"),
        )?;
        let held_out_subset = plan.add_subset(
            training_step,
            &format!("{training_name}-cv{}of{folds}-held-out", fold + 1),
            held_out.clone(),
            description("held-out"),
        )?;
        let name = fold_detector_name(detector, fold, folds);
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
            )?;
        }
    }
    Ok(plan)
}

/// Label of the held-out folds' column.
const HELD_OUT_LABEL: &str = "held-out fold";

/// The cells of a cross-validation table from the AUC rows of its run: for
/// each (dataset, ε), the AUCs of `detector`'s `folds` fold models (named
/// `DETECTOR-cvKofN`) with their mean and sample standard deviation. Each
/// fold's own held-out subset is one column, "held-out fold".
pub fn summarise(auc: &[AucRow], detector: &str, folds: usize) -> Vec<CvCell> {
    let is_held_out = |row: &AucRow| row.dataset.contains("-held-out");
    let mut columns: Vec<(String, Option<f64>, f64)> = Vec::new();
    for row in auc {
        let dataset = if is_held_out(row) {
            HELD_OUT_LABEL.to_string()
        } else {
            row.dataset.clone()
        };
        if !columns
            .iter()
            .any(|(d, _, e)| *d == dataset && *e == row.eps_px)
        {
            columns.push((dataset, row.diffusion, row.eps_px));
        }
    }
    let mut cells = Vec::new();
    for (dataset, diffusion, eps_px) in columns {
        let per_fold: Vec<f64> = (0..folds)
            .filter_map(|fold| {
                let name = fold_detector_name(detector, fold, folds);
                auc.iter().find(|r| {
                    r.detector == name
                        && r.eps_px == eps_px
                        && (r.dataset == dataset || (dataset == HELD_OUT_LABEL && is_held_out(r)))
                })
            })
            .map(|r| r.auc)
            .collect();
        if per_fold.is_empty() {
            continue;
        }
        let n = per_fold.len() as f64;
        let mean = per_fold.iter().sum::<f64>() / n;
        let std = (per_fold.len() > 1)
            .then(|| (per_fold.iter().map(|a| (a - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt());
        cells.push(CvCell {
            dataset,
            diffusion,
            eps_px,
            mean,
            std,
            per_fold,
        });
    }
    cells
}

/// The detector, fold (1-based) and fold count a fold model's name
/// (`DETECTOR-cvKofN`, see [`fold_detector_name`]) stands for.
fn parse_fold_detector_name(name: &str) -> Option<(&str, usize, usize)> {
    let (detector, fold) = name.rsplit_once("-cv")?;
    let (fold, folds) = fold.split_once("of")?;
    Some((detector, fold.parse().ok()?, folds.parse().ok()?))
}

/// The detector and fold count of a cross-validation run, read off its fold
/// models' names (`DETECTOR-cvKofN`).
pub fn detector_and_folds(auc: &[AucRow]) -> Option<(String, usize)> {
    auc.iter().find_map(|row| {
        let (detector, _, folds) = parse_fold_detector_name(&row.detector)?;
        Some((detector.to_string(), folds))
    })
}

/// The folds (1-based, ascending) that have scores among `auc`: all of
/// them for a whole sweep, one for `scanloc cv --fold K`.
pub fn scored_folds(auc: &[AucRow]) -> Vec<usize> {
    let mut folds: Vec<usize> = auc
        .iter()
        .filter_map(|row| parse_fold_detector_name(&row.detector).map(|(_, fold, _)| fold))
        .collect();
    folds.sort_unstable();
    folds.dedup();
    folds
}

/// A standard deviation for a table: three decimals, `—` when there is
/// none (a single fold).
pub fn format_std(std: Option<f64>) -> String {
    std.map_or("—".to_string(), |std| format!("{std:.3}"))
}

/// The cross-validation table as text: one line per dataset, `mean ± std`
/// per ε.
pub fn render(outcome: &CrossValidationOutcome) -> String {
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
        out.push_str(&format!("{label:<28}"));
        for cell in outcome.cells.iter().filter(|c| c.dataset == dataset) {
            out.push_str(&format!(
                "  ε={}: {:.3} ± {}",
                cell.eps_px,
                cell.mean,
                format_std(cell.std)
            ));
        }
        out.push('\n');
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
}
