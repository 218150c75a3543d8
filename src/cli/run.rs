//! `scanloc run`: run an experiment manifest over the registry.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::manifest;
use crate::registry::Registry;
use crate::run::{self, RunOptions, table};
use clap::Args;
use serde_json::json;

/// Run an experiment manifest: simulate its datasets, run its detectors,
/// score its evaluations, print the AUC table (and, for test sets with
/// empty frames, the false localisations per empty frame), run its
/// tracking pipelines on its recordings (tracking measures and D; see
/// docs/tracking.md) and record the run.
///
/// Every artefact is content-addressed: a step whose artefact is already in
/// the registry (and whose blobs re-hash correctly) is skipped and counted
/// as cached; a damaged blob is reported and rebuilt. Several runs may share
/// one registry at once.
///
/// With --json, one JSON object instead of the table:
/// {"run", "auc": [{"detector", "dataset", "diffusion", "eps_px", "auc", …}],
/// "empty_frames": [{"detector", "dataset", "threshold", "frames",
/// "localisations", "false_localisations_per_frame"}],
/// "tracking": [{"pipeline", "recording", "diffusion", "tracking": {"alpha",
/// …}, "estimators": [{"method", "ensemble", "per_track", …}]}],
/// "cached_steps", "computed_steps", …}.
///
/// Manifest format: docs/manifest.md; the registry: docs/registry.md.
#[derive(Debug, Args)]
pub(super) struct RunArgs {
    /// The manifest (YAML), e.g. experiments/smoke.yaml.
    manifest: PathBuf,
    #[command(flatten)]
    format: super::JsonFlag,
    /// Recompute every step, and fail (exit 1) unless every result is
    /// identical to the stored one.
    #[arg(long)]
    force: bool,
    #[command(flatten)]
    registry: super::RegistryDir,
}

pub(super) fn run(args: RunArgs, stdout: &mut dyn Write) -> anyhow::Result<ExitCode> {
    // Parse and validate before touching the registry: bad input leaves it
    // unchanged.
    let manifest = manifest::load(&args.manifest)?;
    // Its `sweep:` block as `sweep run` reads it: a grid that would be
    // refused there (two axes on one path) is refused here too.
    crate::sweep::grid::axes(&manifest.text, &args.manifest.display().to_string())?;
    let mut registry = Registry::open(&args.registry)?;
    let outcome = run::run_manifest(
        &mut registry,
        &manifest,
        &RunOptions {
            force: args.force,
            ..RunOptions::default()
        },
    )?;
    if args.format.json {
        let value = json!({
            "run": outcome.run,
            "manifest": outcome.manifest,
            "registry": args.registry.display().to_string(),
            "status": outcome.status,
            "auc": outcome.auc,
            "empty_frames": outcome.empty_frames,
            "tracking": outcome.tracking,
            "cached_steps": outcome.counts.cached,
            "computed_steps": outcome.counts.computed,
            "rebuilt_steps": outcome.counts.rebuilt,
            "damaged_blobs": outcome.damaged_blobs,
            "steps": outcome.steps,
            "seconds": outcome.seconds,
        });
        writeln!(stdout, "{value}")?;
    } else {
        // A run that scores only sets of empty frames, or only tracks, has
        // no AUC to show.
        if !outcome.auc.is_empty()
            || (outcome.empty_frames.is_empty() && outcome.tracking.is_empty())
        {
            write!(
                stdout,
                "{}",
                table::render(&outcome.auc, manifest.reference.as_ref())
            )?;
        }
        write!(
            stdout,
            "{}",
            table::render_empty_frames(&outcome.empty_frames)
        )?;
        write!(stdout, "{}", table::render_tracking(&outcome.tracking))?;
        writeln!(
            stdout,
            "run {}: {} steps cached, {} computed, {} rebuilt in {:.2} s (registry {})",
            outcome.run,
            outcome.counts.cached,
            outcome.counts.computed,
            outcome.counts.rebuilt,
            outcome.seconds,
            args.registry.display()
        )?;
    }
    Ok(ExitCode::SUCCESS)
}
