//! `scanloc check`: validate a manifest and print it resolved.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::manifest;
use crate::run::Plan;
use clap::Args;
use serde_json::json;

/// Validate a manifest without running it, and print it resolved: every
/// default filled in, every seed derived, and the plan of steps with their
/// content keys.
///
/// Manifest format: docs/manifest.md.
#[derive(Debug, Args)]
pub(super) struct CheckArgs {
    /// The manifest (YAML).
    manifest: PathBuf,
    #[command(flatten)]
    format: super::JsonFlag,
}

pub(super) fn run(
    args: CheckArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let manifest = manifest::load(&args.manifest)?;
    // Its `sweep:` block as `sweep run` reads it: a grid that would be
    // refused there (two axes on one path) is refused here too.
    crate::sweep::grid::axes(&manifest.text, &args.manifest.display().to_string())?;
    let plan = Plan::from_manifest(&manifest)?;
    let steps: Vec<_> = plan
        .steps
        .iter()
        .map(|s| json!({"step": s.id, "key": s.key, "seed": s.seed.map(|v| v.to_string())}))
        .collect();
    if args.format.json {
        writeln!(stdout, "{}", json!({"manifest": manifest, "plan": steps}))?;
    } else {
        write!(stdout, "{}", manifest.to_resolved_yaml()?)?;
        writeln!(stdout, "plan:")?;
        for step in &plan.steps {
            writeln!(stdout, "- step: {}\n  key: {}", step.id, step.key)?;
        }
        writeln!(stderr, "{}: ok", args.manifest.display())?;
    }
    Ok(ExitCode::SUCCESS)
}
