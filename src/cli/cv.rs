//! `scanloc cv`: k-fold cross-validation of a trained detector.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::input_error;
use crate::manifest;
use crate::registry::{CrossValidationPlan, Registry};
use crate::run::cross_validation;
use crate::sweep::{SweepKind, SweepSpec};
use clap::Args;

use super::sweep::{ExecutorArgs, run_sweep};

/// Cross-validate a trained detector: its training set split into k folds
/// by a recorded seeded permutation, k models each trained on k − 1 folds
/// (on fresh frames only, for a CNN with validation_fraction 1) and
/// selected on the remaining one, each scored on its held-out fold and on
/// every test set; the AUC table as mean ± standard deviation. Each fold's
/// data and model are artefacts of their own, so an interrupted sweep
/// resumes where it stopped and one fold can be rerun alone (--fold K
/// --force checks it against the stored one).
///
/// The cross_validation block: docs/manifest.md; how folds are stored:
/// docs/registry.md.
#[derive(Debug, Args)]
pub(super) struct CvArgs {
    /// The experiment manifest.
    manifest: PathBuf,
    /// Number of folds [default: the manifest's cross_validation.folds, else 5].
    #[arg(long)]
    folds: Option<usize>,
    /// The detector [default: the manifest's cross_validation.detector].
    #[arg(long)]
    detector: Option<String>,
    /// Only this fold (1 … folds): its subsets, model and scores, under the
    /// same keys as in the whole sweep. With --force, reproduces that one
    /// fold of a recorded sweep and checks it against the stored results.
    #[arg(long)]
    fold: Option<usize>,
    /// Recompute every step and check the results equal the stored ones.
    #[arg(long)]
    force: bool,
    #[command(flatten)]
    format: super::JsonFlag,
    #[command(flatten)]
    registry: super::RegistryDir,
    /// Where the folds run (each fold a recorded run, then the table).
    #[command(flatten)]
    executor: ExecutorArgs,
}

pub(super) fn run(args: CvArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    let manifest = manifest::load(&args.manifest)?;
    let block = manifest.cross_validation.clone();
    let detector = args
        .detector
        .or_else(|| block.as_ref().map(|b| b.detector.clone()))
        .ok_or_else(|| {
            input_error(format!(
                "{}: no cross_validation block: give --detector",
                manifest.source
            ))
        })?;
    let folds = args.folds.or(block.map(|b| b.folds)).unwrap_or(5);
    if args.fold.is_none() {
        // The whole sweep: a point per fold, through the sweep executors.
        let spec = SweepSpec {
            kind: SweepKind::Cv { detector, folds },
            manifest_path: manifest.source.clone(),
            manifest_text: manifest.text.clone(),
        };
        return run_sweep(
            &args.registry,
            spec,
            &args.executor,
            args.force,
            args.format.json,
            stdout,
        );
    }
    if args.executor.is_not_default() {
        return Err(input_error(
            "--fold: one fold runs here, in this process; --executor and --jobs are for the whole sweep",
        ));
    }
    let mut registry = Registry::open(&args.registry)?;
    let plan = CrossValidationPlan {
        detector,
        folds,
        fold: args.fold,
    };
    let outcome = cross_validation::cross_validate(&mut registry, &manifest, &plan, args.force)?;
    if args.format.json {
        writeln!(
            stdout,
            "{}",
            serde_json::json!({
                "run": outcome.run.run,
                "detector": outcome.detector,
                "folds": outcome.folds,
                "cells": outcome.cells,
                "cached_steps": outcome.run.counts.cached,
                "computed_steps": outcome.run.counts.computed,
            })
        )?;
    } else {
        write!(stdout, "{}", cross_validation::render(&outcome))?;
    }
    Ok(ExitCode::SUCCESS)
}
