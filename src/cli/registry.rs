//! `scanloc registry`: audit what has been run and stored.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use crate::error::{CheckFailed, input_error};
use crate::registry::{Found, Registry, Table, diff, shard, sql};
use crate::report::summary::{run_summary, run_summary_json};
use clap::{Args, Subcommand};

/// Query the registry: runs, datasets, models, evaluations, one run or
/// artefact in full, the differences between two runs, blob verification,
/// garbage collection, read-only SQL, and a trained model written out as a
/// model folder.
///
/// Tables, keys and blobs: docs/registry.md.
#[derive(Debug, Args)]
#[command(mut_arg("json", |arg| arg.global(true)))]
pub(super) struct RegistryArgs {
    #[command(subcommand)]
    command: RegistryCommand,
    #[command(flatten)]
    registry: super::RegistryDir,
    #[command(flatten)]
    format: super::JsonFlag,
}

#[derive(Debug, Subcommand)]
enum RegistryCommand {
    /// Every run, newest first (status running, done, failed or unfinished).
    Runs,
    /// Every stored dataset.
    Datasets,
    /// Every stored trained model.
    Models,
    /// Every stored evaluation, one row per ε.
    Evaluations,
    /// One run (status, manifest, code version, seeds, steps, AUC table,
    /// tracking tables; with --json the whole record and its `tracking`
    /// rows as `scanloc run --json` gives them) or artefact (spec, blobs,
    /// runs that used it) in full, by id or unique prefix.
    Show { id: String },
    /// What differs between two runs: code version, machine, manifest,
    /// parameters, seeds, artefact keys, AUC cells.
    Diff { a: String, b: String },
    /// Re-hash every blob and check the database; exit code 1 if a blob is
    /// missing or damaged.
    Verify,
    /// Remove artefacts no run references and blobs no artefact references.
    Gc {
        /// Only list what would be removed.
        #[arg(long)]
        dry_run: bool,
    },
    /// Write runs and every artefact they used (records and blobs) into a
    /// shard: a registry folder that `registry import` reads, to move runs
    /// between machines or labs.
    Export {
        /// Run ids (or unique prefixes).
        #[arg(required = true)]
        runs: Vec<String>,
        /// The shard folder to write (created; an existing one is added to).
        #[arg(long)]
        out: PathBuf,
    },
    /// Copy shards (registry folders: from `registry export`, or a sweep's
    /// tasks) into this registry: blobs re-hashed, artefact rows and run
    /// records. Importing twice changes nothing. A shard that is missing
    /// or damaged is reported and the others imported (exit 2); an artefact
    /// stored here with other blobs is refused (exit 1).
    Import {
        #[arg(required = true)]
        shards: Vec<PathBuf>,
    },
    /// Write a trained model out as a model folder that `scanloc locate
    /// --method cnn --model DIR` reads (docs/detectors.md). The model is
    /// named RUN:DETECTOR (a run id or unique prefix, and the detector's
    /// name in its manifest) or by its content key or a unique prefix.
    Model {
        /// RUN:DETECTOR, or a model's content key or unique prefix.
        model: String,
        /// The model folder to write, whole or not at all: a new path, or a
        /// model folder, which is replaced; a folder holding anything else
        /// (a link, a FIFO, another file) is refused and left as it is.
        #[arg(long)]
        out: PathBuf,
    },
    /// Run one read-only SQL statement, e.g.
    /// "SELECT detector, dataset, eps_px, auc FROM run_auc WHERE run_id = '…'".
    Sql { query: String },
}

fn print_table(table: &Table, json: bool, stdout: &mut dyn Write) -> anyhow::Result<()> {
    if json {
        writeln!(stdout, "{}", table.to_json())?;
    } else {
        write!(stdout, "{}", table.render())?;
    }
    Ok(())
}

fn print_value(
    value: &serde_json::Value,
    json: bool,
    stdout: &mut dyn Write,
) -> anyhow::Result<()> {
    if json {
        writeln!(stdout, "{value}")?;
    } else {
        write!(stdout, "{}", serde_yaml::to_string(value)?)?;
    }
    Ok(())
}

fn run_id(registry: &Registry, id: &str) -> anyhow::Result<String> {
    match registry.resolve_id(id)? {
        Found::Run(id) => Ok(id),
        Found::Artefact(key) => Err(input_error(format!(
            "{key} is an artefact, not a run; give a run id"
        ))),
    }
}

pub(super) fn run(
    args: RegistryArgs,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let json = args.format.json;
    if let RegistryCommand::Sql { query: sql } = &args.command {
        print_table(&sql::read_only_sql(&args.registry, sql)?, json, stdout)?;
        return Ok(ExitCode::SUCCESS);
    }
    if let RegistryCommand::Import { shards } = &args.command {
        return import(&args.registry, shards, json, stdout, stderr);
    }
    let mut registry = Registry::open_existing(&args.registry)?;
    match args.command {
        RegistryCommand::Runs => print_table(&registry.list_runs()?, json, stdout)?,
        RegistryCommand::Datasets => print_table(&registry.list_datasets()?, json, stdout)?,
        RegistryCommand::Models => print_table(&registry.list_models()?, json, stdout)?,
        RegistryCommand::Evaluations => print_table(&registry.list_evaluations()?, json, stdout)?,
        RegistryCommand::Show { id } => match registry.resolve_id(&id)? {
            Found::Run(id) => {
                let record = registry.run_record(&id)?;
                if json {
                    writeln!(stdout, "{}", run_summary_json(&registry, &record)?)?;
                } else {
                    write!(stdout, "{}", run_summary(&registry, &record))?;
                }
            }
            Found::Artefact(key) => print_value(&registry.artefact_record(&key)?, json, stdout)?,
        },
        RegistryCommand::Diff { a, b } => diff_runs(&registry, &a, &b, json, stdout)?,
        RegistryCommand::Verify => verify(&registry, json, stdout)?,
        RegistryCommand::Gc { dry_run } => gc(&mut registry, dry_run, json, stdout)?,
        RegistryCommand::Export { runs, out } => {
            let ids = runs
                .iter()
                .map(|id| run_id(&registry, id))
                .collect::<anyhow::Result<Vec<_>>>()?;
            drop(registry);
            let report = shard::export(&args.registry, &ids, &out)?;
            if json {
                writeln!(stdout, "{}", serde_json::to_string(&report)?)?;
            } else {
                writeln!(
                    stdout,
                    "exported to {}: {}",
                    out.display(),
                    report.summary()
                )?;
            }
        }
        RegistryCommand::Model { model, out } => {
            let (cnn, origin) = super::locate::registry_cnn(&registry, &model)?;
            cnn.save(&out)?;
            if json {
                writeln!(
                    stdout,
                    "{}",
                    serde_json::json!({"out": out.display().to_string(), "model": origin})
                )?;
            } else {
                writeln!(
                    stdout,
                    "wrote model {} ({}) to {}",
                    origin.model_key,
                    super::locate::describe_origin(&origin),
                    out.display()
                )?;
            }
        }
        RegistryCommand::Sql { .. } | RegistryCommand::Import { .. } => {
            unreachable!("handled above")
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `registry diff`: what differs between runs `a` and `b`.
fn diff_runs(
    registry: &Registry,
    a: &str,
    b: &str,
    json: bool,
    stdout: &mut dyn Write,
) -> anyhow::Result<()> {
    let (a, b) = (run_id(registry, a)?, run_id(registry, b)?);
    let differences = diff::diff_runs(&registry.run_record(&a)?, &registry.run_record(&b)?);
    if json {
        writeln!(
            stdout,
            "{}",
            serde_json::json!({"a": a, "b": b, "differences": differences})
        )?;
    } else if differences.is_empty() {
        writeln!(
            stdout,
            "runs {a} and {b}: no differences in code, parameters, seeds, artefacts or AUC"
        )?;
    } else {
        writeln!(stdout, "runs {a} (a) and {b} (b) differ in:")?;
        for d in &differences {
            writeln!(stdout, "  {:<10} {}: {} → {}", d.section, d.field, d.a, d.b)?;
        }
    }
    Ok(())
}

/// `registry verify`: the report, and a failed check if anything is wrong.
fn verify(registry: &Registry, json: bool, stdout: &mut dyn Write) -> anyhow::Result<()> {
    let report = registry.verify()?;
    if json {
        writeln!(stdout, "{}", serde_json::to_string(&report)?)?;
    } else {
        writeln!(
            stdout,
            "verified {} blobs ({} bytes); database integrity: {}",
            report.blobs_checked, report.bytes_checked, report.database_integrity
        )?;
        for bad in &report.bad {
            writeln!(
                stdout,
                "BAD {} {} ({}){}: used by {}",
                bad.problem,
                bad.sha256,
                bad.path,
                bad.actual_sha256
                    .as_ref()
                    .map(|a| format!(", bytes hash to {a}"))
                    .unwrap_or_default(),
                if bad.used_by.is_empty() {
                    "nothing".to_string()
                } else {
                    bad.used_by.join("; ")
                }
            )?;
        }
        for bad in &report.bad_specs {
            writeln!(
                stdout,
                "BAD spec of {}: it hashes to {}, not to its key",
                bad.artefact, bad.spec_sha256
            )?;
        }
        for file in &report.unrecorded_files {
            writeln!(
                stdout,
                "note: unrecorded blob file {file} (left by an interrupted run; gc removes it)"
            )?;
        }
        for file in &report.leftover_temporaries {
            writeln!(stdout, "note: leftover temporary {file} (gc removes it)")?;
        }
        for stray in &report.strays {
            writeln!(stdout, "note: {stray} is not a blob file; left alone")?;
        }
    }
    if !report.ok() {
        return Err(anyhow::Error::new(CheckFailed(format!(
            "{} blob(s) missing or damaged (the next run rebuilds them); {} artefact spec(s) not matching their key; database: {}",
            report.bad.len(),
            report.bad_specs.len(),
            report.database_integrity
        ))));
    }
    Ok(())
}

/// `registry gc`: what was (or would be) removed.
fn gc(
    registry: &mut Registry,
    dry_run: bool,
    json: bool,
    stdout: &mut dyn Write,
) -> anyhow::Result<()> {
    if !dry_run {
        registry.refuse_read_only("registry gc")?;
    }
    let report = registry.gc(dry_run)?;
    if json {
        writeln!(stdout, "{}", serde_json::to_string(&report)?)?;
    } else {
        let verb = if dry_run { "would remove" } else { "removed" };
        writeln!(
            stdout,
            "{verb} {} artefact(s), {} blob(s) ({} bytes), {} temporary file(s)",
            report.artefacts.len(),
            report.blobs.len(),
            report.bytes,
            report.temporaries.len()
        )?;
        for artefact in &report.artefacts {
            writeln!(stdout, "  artefact {artefact}")?;
        }
        for blob in &report.blobs {
            writeln!(stdout, "  blob {blob}")?;
        }
        for file in &report.temporaries {
            writeln!(stdout, "  temporary {file}")?;
        }
        for stray in &report.strays {
            writeln!(stdout, "skipped {stray}: not a blob file; left alone")?;
        }
    }
    Ok(())
}

/// `registry import`: every shard in turn; the exit code says the worst.
fn import(
    registry: &Path,
    shards: &[PathBuf],
    json: bool,
    stdout: &mut dyn Write,
    stderr: &mut dyn Write,
) -> anyhow::Result<ExitCode> {
    let mut registry = Registry::open_to_write(registry, "registry import")?;
    let shards: Vec<&Path> = shards.iter().map(PathBuf::as_path).collect();
    let results = shard::import_all(&mut registry, &shards);
    let (mut bad_shards, mut conflicts) = (Vec::new(), 0);
    let mut reports = Vec::new();
    for (shard, result) in results {
        match result {
            Ok(report) => {
                conflicts += report.conflicts.len();
                if !json {
                    writeln!(stdout, "imported {}", report.summary())?;
                }
                reports.push(serde_json::json!({"shard": shard, "report": report}));
            }
            Err(error) => {
                writeln!(stderr, "error: {error:#}")?;
                reports.push(serde_json::json!({"shard": shard, "error": format!("{error:#}")}));
                bad_shards.push(shard);
            }
        }
    }
    if json {
        writeln!(stdout, "{}", serde_json::Value::Array(reports))?;
    }
    if conflicts > 0 {
        return Err(anyhow::Error::new(CheckFailed(format!(
            "{conflicts} artefact(s) refused: stored here with other blobs (see above)"
        ))));
    }
    if !bad_shards.is_empty() {
        return Err(input_error(format!(
            "{} shard(s) not imported: {}",
            bad_shards.len(),
            bad_shards.join(", ")
        )));
    }
    Ok(ExitCode::SUCCESS)
}
