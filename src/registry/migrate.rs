//! The registry's schema migrations, applied once under the write lock.

use anyhow::Context;
use rusqlite::{Connection, params};

use super::{Registry, SCHEMA_VERSION};
use crate::error::input_error;

impl Registry {
    /// Applies missing schema migrations, once, under the write lock.
    pub(super) fn migrate(&mut self) -> anyhow::Result<()> {
        let version: i64 = self
            .conn
            .query_row("PRAGMA user_version", [], |row| row.get(0))?;
        if version == SCHEMA_VERSION {
            return Ok(());
        }
        let tx = self.write_transaction()?;
        // Read again under the lock: another process may have migrated.
        let version: i64 = tx.query_row("PRAGMA user_version", [], |row| row.get(0))?;
        if version > SCHEMA_VERSION {
            return Err(input_error(format!(
                "{}: registry schema version {version} is newer than this scanloc understands ({SCHEMA_VERSION})",
                self.dir.display()
            )));
        }
        if version < 1 {
            tx.execute_batch(SCHEMA_V1)
                .context("creating the registry schema")?;
        }
        if version < 2 {
            tx.execute_batch(SCHEMA_V2)
                .context("migrating the registry schema to version 2")?;
            backfill_cross_validation_plans(&tx)
                .context("recording the plans of earlier cross-validation runs")?;
        }
        if version < 3 {
            tx.execute_batch(SCHEMA_V3)
                .context("migrating the registry schema to version 3")?;
        }
        tx.execute_batch(&format!("PRAGMA user_version = {SCHEMA_VERSION}"))?;
        tx.commit()?;
        Ok(())
    }
}

pub(super) const SCHEMA_V1: &str = include_str!("schema.sql");

pub(super) const SCHEMA_V2: &str = include_str!("schema_v2.sql");

const SCHEMA_V3: &str = include_str!("schema_v3.sql");

/// Records the plan of every cross-validation run made before schema 2.
/// Such a run left its plan only in its fold models' names
/// (`DETECTOR-cvKofN`) in its AUC rows; they are read here, once, so that
/// nothing else ever parses names. A run that recorded no AUC rows (it
/// was interrupted) keeps no plan: it is still listed and shown, and
/// `reproduce` says it cannot re-plan it.
fn backfill_cross_validation_plans(tx: &Connection) -> anyhow::Result<()> {
    let runs: Vec<String> = {
        let mut statement =
            tx.prepare("SELECT id FROM runs WHERE kind = 'cv' AND cv_detector IS NULL")?;
        statement
            .query_map([], |row| row.get("id"))?
            .collect::<Result<_, _>>()?
    };
    for run in runs {
        let detectors: Vec<String> = {
            let mut statement =
                tx.prepare("SELECT DISTINCT detector FROM run_auc WHERE run_id = ?1")?;
            statement
                .query_map([&run], |row| row.get("detector"))?
                .collect::<Result<_, _>>()?
        };
        let parsed: Vec<(&str, usize, usize)> = detectors
            .iter()
            .filter_map(|name| {
                let (detector, fold) = name.rsplit_once("-cv")?;
                let (fold, folds) = fold.split_once("of")?;
                Some((detector, fold.parse().ok()?, folds.parse().ok()?))
            })
            .collect();
        let Some(&(detector, _, folds)) = parsed.first() else {
            continue;
        };
        if parsed.iter().any(|&(d, _, n)| d != detector || n != folds) {
            continue;
        }
        let mut scored: Vec<usize> = parsed.iter().map(|&(_, fold, _)| fold).collect();
        scored.sort_unstable();
        scored.dedup();
        // One fold scored out of several: a `cv --fold K` run.
        let only_fold = match scored.as_slice() {
            [fold] if folds > 1 => Some(*fold as i64),
            _ => None,
        };
        tx.execute(
            "UPDATE runs SET cv_detector = ?2, cv_folds = ?3, cv_fold = ?4 WHERE id = ?1",
            params![run, detector, folds as i64, only_fold],
        )?;
    }
    Ok(())
}
