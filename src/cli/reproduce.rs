//! `scanloc reproduce`: re-execute a recorded run and compare.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use crate::error::CheckFailed;
use crate::registry::{Found, Registry};
use crate::run::reproduce;
use clap::Args;

/// Re-execute a recorded run from scratch (ignoring every cached artefact,
/// into a scratch registry) and report, artefact by artefact and number by
/// number, whether everything came out identical. Exit code 1 if anything
/// differs, including a stored blob that was altered since.
///
/// What a run records and what is compared: docs/registry.md.
#[derive(Debug, Args)]
pub(super) struct ReproduceArgs {
    /// The run id (or a unique prefix of it), as `scanloc registry runs` lists.
    run: String,
    #[command(flatten)]
    format: super::JsonFlag,
    /// Scratch folder for the re-execution (default: a temporary folder,
    /// removed afterwards).
    #[arg(long)]
    scratch: Option<PathBuf>,
    #[command(flatten)]
    registry: super::RegistryDir,
}

pub(super) fn run(
    args: ReproduceArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let mut registry = Registry::open_existing(&args.registry)?;
    let run_id = match registry.resolve_id(&args.run)? {
        Found::Run(id) => id,
        Found::Artefact(key) => {
            return Err(crate::error::input_error(format!(
                "{key} is an artefact, not a run; give a run id"
            )));
        }
    };
    let (scratch, _guard) = reproduce::scratch_dir(args.scratch.as_deref())?;
    let report = reproduce::reproduce(&mut registry, &run_id, &scratch)?;
    if registry.is_read_only() {
        // It re-executed in the scratch folder; only its record is missing.
        writeln!(
            stderr,
            "warning: {} is read-only: reproduction run {} is not recorded there",
            args.registry.display(),
            report.reproduction_run
        )?;
    }
    if args.format.json {
        writeln!(stdout, "{}", serde_json::to_string(&report)?)?;
    } else {
        write!(stdout, "{}", report.render())?;
    }
    if report.identical {
        Ok(ExitCode::SUCCESS)
    } else {
        Err(anyhow::Error::new(CheckFailed(format!(
            "reproduction of run {run_id} differs from the record (see above)"
        ))))
    }
}
