//! Trained models read back from the registry, to localise with them
//! outside a run (`scanloc locate --model`, `scanloc registry model`).
//!
//! A model is named either by the run that trained it and its detector,
//! `RUN:DETECTOR` (a run id or a unique prefix of one, and the detector's
//! name in that run's manifest), or by its content key or a unique prefix
//! of it. The bytes are the model artefact's `model.bin` blob, re-hashed
//! when read; decoding them is the detector's business.

use anyhow::Context;
use rusqlite::OptionalExtension;
use serde::Serialize;

use super::{ArtefactKind, BlobRole, BlobState, Registry, StepId};
use crate::error::input_error;
use crate::types::DetectorKind;

/// The blob role that holds a model's bytes.
pub(crate) const MODEL_BLOB: BlobRole = BlobRole::Model;

/// Shortest prefix accepted for a run id or a content key.
const MIN_PREFIX: usize = 4;

/// Where a stored model came from: what `locate` reports beside its
/// predictions, and what an exported model folder keeps.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct ModelOrigin {
    /// The model artefact's content key.
    pub model_key: String,
    /// The detector's name in the manifest that trained it.
    pub detector: String,
    /// The detector's kind (`cnn`).
    pub detector_kind: DetectorKind,
    /// The run named in the reference (`RUN:DETECTOR`), else the run that
    /// first computed the model, if recorded.
    pub run: Option<String>,
}

/// A model read from the registry: its origin and its bytes.
#[derive(Debug, Clone)]
pub struct StoredModel {
    pub origin: ModelOrigin,
    pub bytes: Vec<u8>,
}

impl Registry {
    /// The model named by `reference` (`RUN:DETECTOR`, or a content key or
    /// unique prefix of one), which must be of `detector_kind`. Every
    /// failure is an input error of one line: no such run or model, an
    /// ambiguous prefix, a run without that detector, a detector of
    /// another kind or without a trained model, a missing or damaged blob.
    pub fn stored_model(
        &self,
        reference: &str,
        detector_kind: DetectorKind,
    ) -> anyhow::Result<StoredModel> {
        super::sql::check_id_length(reference)?;
        let (key, run) = match reference.split_once(':') {
            Some((run, detector)) => {
                let run = self.unique_run(run)?;
                (self.model_of_run(&run, detector)?, Some(run))
            }
            None => (self.unique_model_key(reference)?, None),
        };
        let (detector, kind, created_by) = self
            .connection()
            .query_row(
                "SELECT m.detector, m.detector_kind, a.created_by_run
                 FROM models m JOIN artefacts a ON a.key = m.key WHERE m.key = ?1",
                [&key],
                |row| {
                    Ok((
                        row.get::<_, String>(0)?,
                        row.get::<_, String>(1)?,
                        row.get(2)?,
                    ))
                },
            )
            .optional()?
            .ok_or_else(|| input_error(format!("{reference}: model {key} has no models row")))?;
        if kind.parse::<DetectorKind>() != Ok(detector_kind) {
            crate::bail_input!(
                "{reference}: detector `{detector}` is a {kind} model, not a {detector_kind}"
            );
        }
        let artefact = self
            .artefact(&key)?
            .filter(|a| a.kind == ArtefactKind::Model)
            .ok_or_else(|| input_error(format!("{reference}: {key} is not a stored model")))?;
        let Some(blob) = artefact.blobs.iter().find(|b| b.role == MODEL_BLOB) else {
            crate::bail_input!("{reference}: model {key} has no {MODEL_BLOB} blob");
        };
        let bytes = match self.blobs().get(&blob.sha256)? {
            Ok(bytes) => bytes,
            Err(BlobState::Missing) => crate::bail_input!(
                "{reference}: the blob of model {key} is missing from {} (`scanloc run` rebuilds it)",
                self.dir().display()
            ),
            Err(state) => crate::bail_input!(
                "{reference}: the blob of model {key} is damaged ({state:?}; `scanloc run` rebuilds it)"
            ),
        };
        Ok(StoredModel {
            origin: ModelOrigin {
                model_key: key,
                detector,
                detector_kind,
                run: run.or(created_by),
            },
            bytes,
        })
    }

    /// The run whose id is `id` or starts with it.
    fn unique_run(&self, id: &str) -> anyhow::Result<String> {
        if self.run_exists(id)? {
            return Ok(id.to_string());
        }
        self.unique_prefix(
            "SELECT id FROM runs WHERE id LIKE ?1 ESCAPE '\\' LIMIT 2",
            id,
            "run with this id",
            "",
        )
    }

    /// The model whose content key is `key` or starts with it.
    fn unique_model_key(&self, key: &str) -> anyhow::Result<String> {
        self.unique_prefix(
            "SELECT key FROM models WHERE key LIKE ?1 ESCAPE '\\' LIMIT 2",
            key,
            "model with this key",
            " (name a model by RUN:DETECTOR or its key)",
        )
    }

    /// The one row of `sql` (see [`Self::matching_prefix`]) starting with
    /// `prefix`; an error naming `what` (`run with this id`) if there is
    /// none, with `hint` appended, or if there are several.
    fn unique_prefix(
        &self,
        sql: &str,
        prefix: &str,
        what: &str,
        hint: &str,
    ) -> anyhow::Result<String> {
        let found = self.matching_prefix(sql, prefix)?;
        match found.as_slice() {
            [one] => Ok(one.clone()),
            [] => Err(input_error(format!(
                "{prefix}: no {what} or prefix in {}{hint}",
                self.dir().display()
            ))),
            _ => Err(input_error(format!(
                "{prefix}: ambiguous, the prefix of several; give more characters"
            ))),
        }
    }

    /// The model that run `run` used for `detector` (its step
    /// `model/DETECTOR`).
    fn model_of_run(&self, run: &str, detector: &str) -> anyhow::Result<String> {
        let steps = self.steps_of_run(run)?;
        if let Some((_, key)) = steps
            .iter()
            .find(|(step, _)| *step == StepId::Model(detector.to_string()))
        {
            return Ok(key.clone());
        }
        let predicts = steps.iter().any(
            |(step, _)| matches!(step, StepId::Predictions { detector: d, .. } if d == detector),
        );
        if predicts {
            crate::bail_input!(
                "{run}:{detector}: detector `{detector}` of run {run} has no trained model (it is not a CNN)"
            );
        }
        let models: Vec<String> = steps
            .iter()
            .filter_map(|(step, _)| match step {
                StepId::Model(name) => Some(name.clone()),
                _ => None,
            })
            .collect();
        crate::bail_input!(
            "{run}:{detector}: run {run} has no detector `{detector}` (its trained models: {})",
            if models.is_empty() {
                "none".to_string()
            } else {
                models.join(", ")
            }
        )
    }

    /// Every step of run `run` with its artefact's key, in run order.
    fn steps_of_run(&self, run: &str) -> anyhow::Result<Vec<(StepId, String)>> {
        let mut statement = self.connection().prepare(
            "SELECT step, artefact_key FROM run_steps WHERE run_id = ?1 ORDER BY ordinal",
        )?;
        let rows = statement
            .query_map([run], |row| {
                Ok((row.get::<_, String>(0)?, row.get::<_, String>(1)?))
            })?
            .collect::<Result<Vec<_>, _>>()?;
        rows.into_iter()
            .map(|(step, key)| {
                let step = step
                    .parse()
                    .with_context(|| format!("run {run}: column run_steps.step"))?;
                Ok((step, key))
            })
            .collect()
    }

    /// The first column of `sql` (one `LIKE ?1 ESCAPE '\'` parameter) for rows
    /// starting with `prefix` (at least [`MIN_PREFIX`] characters, taken
    /// literally).
    fn matching_prefix(&self, sql: &str, prefix: &str) -> anyhow::Result<Vec<String>> {
        if prefix.chars().count() < MIN_PREFIX {
            crate::bail_input!(
                "{prefix:?}: give a full id or key, or a prefix of at least {MIN_PREFIX} characters"
            );
        }
        let mut statement = self.connection().prepare(sql)?;
        let found = statement
            .query_map([super::sql::like_prefix(prefix)], |row| {
                row.get::<_, String>(0)
            })?
            .collect::<Result<_, _>>()?;
        Ok(found)
    }
}
