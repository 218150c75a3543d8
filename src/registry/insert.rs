//! Recording an artefact whose blobs are stored: its row, its blobs' rows
//! and the row of its kind's typed table.

use rusqlite::{Connection, OptionalExtension, params};

use super::{
    ArtefactDetails, ArtefactKind, BlobRef, BlobStore, EvaluationAuc, NewArtefact, Registry,
    utc_now,
};
use crate::error::input_error;

impl Registry {
    /// Records an artefact whose blobs are stored. If the key is already
    /// recorded with the same blobs, nothing changes. If it is recorded with
    /// other blobs, `replace` says the old ones were damaged and are to be
    /// superseded; otherwise that is an error (the step is not
    /// deterministic, or two builds disagree).
    pub fn record_artefact(&mut self, artefact: &NewArtefact, replace: bool) -> anyhow::Result<()> {
        if self.read_only {
            return Err(input_error(format!(
                "{}: the registry is read-only: {} ({}) cannot be stored",
                self.dir.display(),
                artefact.name,
                artefact.key
            )));
        }
        let tx = self.write_transaction()?;
        let now = utc_now();
        insert_blob_rows(&tx, &self.blobs, &artefact.blobs, &now)?;
        let existing: Option<String> = tx
            .query_row(
                "SELECT key FROM artefacts WHERE key = ?1",
                [&artefact.key],
                |row| row.get(0),
            )
            .optional()?;
        if existing.is_some() {
            supersede_blobs_if_changed(&tx, artefact, replace)?;
        } else {
            insert_artefact(&tx, artefact, &now)?;
        }
        tx.commit()?;
        Ok(())
    }
}

/// A per-frame simulator parameter as a registry column holds it: a REAL
/// when it is fixed, so existing queries and rows keep their numbers, and
/// the distribution's text form (`uniform:5,10`, as the flags take it)
/// when it is drawn per frame.
fn per_frame_column(value: &crate::types::Distribution) -> rusqlite::types::Value {
    match value.fixed() {
        Some(number) => rusqlite::types::Value::Real(number),
        None => rusqlite::types::Value::Text(value.to_string()),
    }
}

/// A `blobs` row for each of `blobs` not recorded yet (its size read from
/// the store), dated `now`.
fn insert_blob_rows(
    tx: &Connection,
    store: &BlobStore,
    blobs: &[BlobRef],
    now: &str,
) -> anyhow::Result<()> {
    for blob in blobs {
        let bytes = std::fs::metadata(store.path(&blob.sha256))
            .map(|m| m.len())
            .unwrap_or(0);
        tx.execute(
            "INSERT OR IGNORE INTO blobs (sha256, bytes, created_at) VALUES (?1, ?2, ?3)",
            params![blob.sha256, bytes as i64, now],
        )?;
    }
    Ok(())
}

/// For an artefact already recorded: nothing if its blobs are the same;
/// else, with `replace` (the old blobs were damaged), records the new ones
/// in their place, and without it refuses (the step is not deterministic).
fn supersede_blobs_if_changed(
    tx: &Connection,
    artefact: &NewArtefact,
    replace: bool,
) -> anyhow::Result<()> {
    let mut statement = tx
        .prepare("SELECT role, sha256 FROM artefact_blobs WHERE artefact_key = ?1 ORDER BY role")?;
    let stored: Vec<BlobRef> = statement
        .query_map([&artefact.key], |row| {
            Ok(BlobRef {
                role: row.get(0)?,
                sha256: row.get(1)?,
            })
        })?
        .collect::<Result<_, _>>()?;
    drop(statement);
    let mut ours = artefact.blobs.clone();
    ours.sort_by_key(|r| r.role);
    if stored == ours {
        return Ok(());
    }
    if !replace {
        anyhow::bail!(
            "artefact {} ({}) is already stored with different content: the step that makes it is not deterministic",
            artefact.name,
            artefact.key
        );
    }
    tx.execute(
        "DELETE FROM artefact_blobs WHERE artefact_key = ?1",
        [&artefact.key],
    )?;
    insert_artefact_blobs(tx, artefact)?;
    Ok(())
}

/// Records a new artefact: its row, its blobs, and the row of its kind's
/// table (`datasets`, `models`, `predictions`, `evaluations` with `auc`).
fn insert_artefact(tx: &Connection, artefact: &NewArtefact, now: &str) -> anyhow::Result<()> {
    tx.execute(
        "INSERT INTO artefacts (key, kind, name, spec, code_version, created_at, created_by_run, compute_seconds)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
        params![
            artefact.key,
            artefact.kind.as_str(),
            artefact.name,
            artefact.spec,
            artefact.code_version,
            now,
            artefact.run_id,
            artefact.compute_seconds
        ],
    )?;
    insert_artefact_blobs(tx, artefact)?;
    insert_details(tx, &artefact.key, &artefact.name, &artefact.details)
}

/// The AUC rows of evaluation `key`, one per matching radius.
fn insert_auc_rows(tx: &Connection, key: &str, auc: &[EvaluationAuc]) -> rusqlite::Result<()> {
    for row in auc {
        tx.execute(
            "INSERT INTO auc (evaluation_key, eps_px, auc, auc_best_per_frame, true_positives, false_positives)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
            params![
                key,
                row.eps_px,
                row.auc,
                row.auc_best_per_frame,
                row.true_positives as i64,
                row.false_positives as i64
            ],
        )?;
    }
    Ok(())
}

/// The row of artefact `key` (named `name`) in its kind's table.
fn insert_details(
    tx: &Connection,
    key: &str,
    name: &str,
    details: &ArtefactDetails,
) -> anyhow::Result<()> {
    match details {
        ArtefactDetails::Dataset {
            frames,
            height,
            width,
            seed,
            diffusion,
            brightness,
            params_json,
        } => insert_row(
            tx,
            ArtefactKind::Dataset,
            "key, name, frames, height, width, seed, diffusion, brightness, params",
            params![
                key,
                name,
                *frames as i64,
                *height as i64,
                *width as i64,
                seed.to_string(),
                diffusion,
                per_frame_column(brightness),
                params_json
            ],
        )?,
        ArtefactDetails::Model {
            detector,
            detector_kind,
            training_dataset_key,
            seed,
        } => insert_row(
            tx,
            ArtefactKind::Model,
            "key, detector, detector_kind, training_dataset_key, seed",
            params![
                key,
                detector,
                detector_kind.as_str(),
                training_dataset_key,
                seed.to_string()
            ],
        )?,
        ArtefactDetails::Predictions {
            detector,
            dataset_key,
            model_key,
            count,
        } => insert_row(
            tx,
            ArtefactKind::Predictions,
            "key, detector, dataset_key, model_key, count",
            params![key, detector, dataset_key, model_key, *count as i64],
        )?,
        ArtefactDetails::Evaluation {
            detector,
            dataset,
            dataset_key,
            predictions_key,
            rmse_top_px,
            fraction_without_prediction,
            auc,
        } => {
            insert_row(
                tx,
                ArtefactKind::Evaluation,
                "key, detector, dataset, dataset_key, predictions_key, rmse_top_px, fraction_without_prediction",
                params![
                    key,
                    detector,
                    dataset,
                    dataset_key,
                    predictions_key,
                    rmse_top_px,
                    fraction_without_prediction
                ],
            )?;
            insert_auc_rows(tx, key, auc)?;
        }
    }
    Ok(())
}

/// Inserts `values` as the `columns` (comma-separated) of a new row of
/// `kind`'s table.
fn insert_row(
    tx: &Connection,
    kind: ArtefactKind,
    columns: &str,
    values: &[&dyn rusqlite::ToSql],
) -> rusqlite::Result<()> {
    let placeholders = (1..=values.len())
        .map(|i| format!("?{i}"))
        .collect::<Vec<_>>()
        .join(", ");
    tx.execute(
        &format!(
            "INSERT INTO {} ({columns}) VALUES ({placeholders})",
            kind.table()
        ),
        values,
    )?;
    Ok(())
}

/// Records which blobs make `artefact` (one row per role).
fn insert_artefact_blobs(tx: &Connection, artefact: &NewArtefact) -> rusqlite::Result<()> {
    for blob in &artefact.blobs {
        tx.execute(
            "INSERT INTO artefact_blobs (artefact_key, role, sha256) VALUES (?1, ?2, ?3)",
            params![artefact.key, blob.role, blob.sha256],
        )?;
    }
    Ok(())
}
