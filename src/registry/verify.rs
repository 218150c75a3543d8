//! `registry verify`: every blob re-hashed (in parallel) and SQLite's own
//! integrity check.

use std::collections::BTreeSet;

use rayon::prelude::*;
use serde::Serialize;

use super::{BlobState, Registry};

/// One blob that failed verification.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BadBlob {
    pub sha256: String,
    pub path: String,
    /// `missing` or `damaged`.
    pub problem: String,
    /// The hash the bytes have now (damaged blobs).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub actual_sha256: Option<String>,
    /// The artefacts that use it: `kind name (key)`.
    pub used_by: Vec<String>,
}

/// What `verify` found.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct VerifyReport {
    pub blobs_checked: usize,
    pub bytes_checked: u64,
    pub bad: Vec<BadBlob>,
    /// Blob files no artefact records (left by an interrupted write; `gc`
    /// removes them).
    pub unrecorded_files: Vec<String>,
    /// Temporary files left by interrupted writes.
    pub leftover_temporaries: Vec<String>,
    /// What lies among the blobs or temporaries and is not a regular file
    /// (`PATH (a folder)`): named, and left alone.
    pub strays: Vec<String>,
    /// SQLite's own `PRAGMA integrity_check` result.
    pub database_integrity: String,
    /// Artefacts whose stored spec no longer hashes to their key (edited
    /// or damaged records: the key no longer says what the artefact is).
    pub bad_specs: Vec<BadSpec>,
}

/// An artefact whose recorded spec does not hash to its content key.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BadSpec {
    /// `kind name (key)`.
    pub artefact: String,
    /// The sha256 of the spec as stored now.
    pub spec_sha256: String,
}

impl VerifyReport {
    pub fn ok(&self) -> bool {
        self.bad.is_empty() && self.bad_specs.is_empty() && self.database_integrity == "ok"
    }
}

impl Registry {
    /// Re-hashes every blob file, in parallel, and checks the database.
    pub fn verify(&self) -> anyhow::Result<VerifyReport> {
        let integrity: String =
            self.connection()
                .query_row("PRAGMA integrity_check", [], |row| row.get(0))?;
        // Each recorded blob with the artefacts that use it.
        let entries: Vec<(String, Vec<String>)> = {
            let mut statement = self.connection().prepare(
                "SELECT b.sha256 AS sha256,
                        group_concat(a.kind || ' ' || a.name || ' (' || a.key || ')', '; ') AS used_by
                 FROM blobs b LEFT JOIN artefact_blobs ab ON ab.sha256 = b.sha256
                 LEFT JOIN artefacts a ON a.key = ab.artefact_key
                 GROUP BY b.sha256 ORDER BY b.sha256",
            )?;
            statement
                .query_map([], |row| {
                    let users: Option<String> = row.get("used_by")?;
                    Ok((
                        row.get("sha256")?,
                        users
                            .map(|u| u.split("; ").map(str::to_string).collect())
                            .unwrap_or_default(),
                    ))
                })?
                .collect::<Result<_, _>>()?
        };
        // Every key is the sha256 of its spec, by construction.
        let mut bad_specs = Vec::new();
        {
            let mut statement = self
                .connection()
                .prepare("SELECT key, kind, name, spec FROM artefacts ORDER BY key")?;
            let mut rows = statement.query([])?;
            while let Some(row) = rows.next()? {
                let (key, kind, name, spec): (String, String, String, String) =
                    (row.get(0)?, row.get(1)?, row.get(2)?, row.get(3)?);
                let spec_sha256 = super::hashing::sha256_hex(spec.as_bytes());
                if spec_sha256 != key {
                    bad_specs.push(BadSpec {
                        artefact: format!("{kind} {name} ({key})"),
                        spec_sha256,
                    });
                }
            }
        }
        let store = self.blobs();
        let results: Vec<anyhow::Result<(BlobState, u64)>> = entries
            .par_iter()
            .map(|(sha, _)| {
                let state = store.check(sha)?;
                let bytes = std::fs::metadata(store.path(sha))
                    .map(|m| m.len())
                    .unwrap_or(0);
                Ok((state, bytes))
            })
            .collect();
        let mut bad = Vec::new();
        let mut bytes_checked = 0;
        for ((sha, users), result) in entries.iter().zip(results) {
            let (state, bytes) = result?;
            bytes_checked += bytes;
            let (problem, actual) = match state {
                BlobState::Intact => continue,
                BlobState::Missing => ("missing", None),
                BlobState::Damaged { actual } => ("damaged", Some(actual)),
            };
            bad.push(BadBlob {
                sha256: sha.clone(),
                path: store.path(sha).display().to_string(),
                problem: problem.to_string(),
                actual_sha256: actual,
                used_by: users.clone(),
            });
        }
        let known: BTreeSet<&str> = entries.iter().map(|(sha, _)| sha.as_str()).collect();
        let unrecorded_files = store
            .list()?
            .into_iter()
            .filter(|(name, _, _)| !known.contains(name.as_str()))
            .map(|(_, path, _)| path.display().to_string())
            .collect();
        Ok(VerifyReport {
            blobs_checked: entries.len(),
            bytes_checked,
            bad,
            unrecorded_files,
            leftover_temporaries: store
                .leftovers()?
                .into_iter()
                .map(|p| p.display().to_string())
                .collect(),
            database_integrity: integrity,
            bad_specs,
            strays: super::gc::stray_labels(store)?,
        })
    }
}
