//! `registry gc`: removes artefacts no run references and blob files no
//! remaining artefact references, sparing whatever a live run may be about
//! to record.

use std::collections::BTreeSet;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use rusqlite::params;
use serde::Serialize;

use super::dates::{format_utc, parse_utc};
use super::{Registry, RunStatus};

/// What `gc` removed (or would remove, with `dry_run`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GcReport {
    pub dry_run: bool,
    /// Artefacts no run step references.
    pub artefacts: Vec<String>,
    /// Blob files no remaining artefact references.
    pub blobs: Vec<String>,
    pub bytes: u64,
    pub temporaries: Vec<String>,
    /// What lies among the blobs or temporaries and is not a regular file
    /// (`PATH (a folder)`): named, and left alone.
    pub strays: Vec<String>,
}

impl Registry {
    /// Removes artefacts no run step references and blob files no remaining
    /// artefact references (`dry_run`: only says what it would remove).
    /// Anything newer than the start of the oldest run still in progress is
    /// kept, since that run may be about to record it.
    pub fn gc(&mut self, dry_run: bool) -> anyhow::Result<GcReport> {
        let mut cutoff = SystemTime::now();
        let mut some_run_live = false;
        {
            let mut statement = self
                .conn
                .prepare("SELECT started_at, host, pid FROM runs WHERE status = 'running'")?;
            let mut rows = statement.query([])?;
            while let Some(row) = rows.next()? {
                let (started, host, pid): (String, String, i64) =
                    (row.get("started_at")?, row.get("host")?, row.get("pid")?);
                if RunStatus::Running.in_effect(&host, pid) == RunStatus::Running
                    && let Some(started) = parse_utc(&started)
                {
                    cutoff = cutoff.min(started - Duration::from_secs(60));
                    some_run_live = true;
                }
            }
        }
        let live_cutoff_text = some_run_live.then(|| format_utc(cutoff));

        // (key, `kind name (key)`) of every artefact no step references.
        let artefacts: Vec<(String, String)> = {
            let mut statement = self.conn.prepare(
                "SELECT a.key AS key, a.kind AS kind, a.name AS name, a.created_at AS created_at
                 FROM artefacts a
                 WHERE NOT EXISTS (SELECT 1 FROM run_steps s WHERE s.artefact_key = a.key)
                 ORDER BY a.created_at",
            )?;
            let orphans: Vec<(String, String, String, String)> = statement
                .query_map([], |row| {
                    Ok((
                        row.get("key")?,
                        row.get("kind")?,
                        row.get("name")?,
                        row.get("created_at")?,
                    ))
                })?
                .collect::<Result<_, _>>()?;
            orphans
                .into_iter()
                .filter(|(_, _, _, created)| {
                    live_cutoff_text
                        .as_deref()
                        .is_none_or(|cutoff| created.as_str() < cutoff)
                })
                .map(|(key, kind, name, _)| {
                    let label = format!("{kind} {name} ({key})");
                    (key, label)
                })
                .collect()
        };
        let doomed: BTreeSet<&str> = artefacts.iter().map(|(k, _)| k.as_str()).collect();

        let still_used: BTreeSet<String> = {
            let mut statement = self
                .conn
                .prepare("SELECT artefact_key, sha256 FROM artefact_blobs")?;
            let pairs: Vec<(String, String)> = statement
                .query_map([], |row| Ok((row.get("artefact_key")?, row.get("sha256")?)))?
                .collect::<Result<_, _>>()?;
            pairs
                .into_iter()
                .filter(|(key, _)| !doomed.contains(key.as_str()))
                .map(|(_, sha)| sha)
                .collect()
        };
        let mut blobs = Vec::new();
        let mut bytes = 0;
        let mut blob_paths = Vec::new();
        for (sha, path, size) in self.blobs().list()? {
            if still_used.contains(&sha) {
                continue;
            }
            let modified = std::fs::metadata(&path)
                .and_then(|m| m.modified())
                .unwrap_or(UNIX_EPOCH);
            if modified >= cutoff {
                continue;
            }
            bytes += size;
            blobs.push(sha);
            blob_paths.push(path);
        }
        let mut temporaries = Vec::new();
        let day_ago = SystemTime::now() - Duration::from_secs(86_400);
        for path in self.blobs().leftovers()? {
            let modified = std::fs::metadata(&path)
                .and_then(|m| m.modified())
                .unwrap_or(UNIX_EPOCH);
            // A temporary is in use while its write lasts; only old ones
            // or ones from before every live run are certainly abandoned.
            if modified < cutoff.min(day_ago) || !some_run_live {
                temporaries.push(path);
            }
        }
        if !dry_run {
            let tx = self.write_transaction()?;
            for (key, _) in &artefacts {
                tx.execute("DELETE FROM auc WHERE evaluation_key = ?1", [key])?;
                for table in ["datasets", "models", "predictions", "evaluations"] {
                    tx.execute(&format!("DELETE FROM {table} WHERE key = ?1"), [key])?;
                }
                tx.execute("DELETE FROM artefact_blobs WHERE artefact_key = ?1", [key])?;
                tx.execute("DELETE FROM artefacts WHERE key = ?1", [key])?;
            }
            for sha in &blobs {
                tx.execute("DELETE FROM blobs WHERE sha256 = ?1", params![sha])?;
            }
            tx.commit()?;
            for path in blob_paths.iter().chain(&temporaries) {
                match std::fs::remove_file(path) {
                    Ok(()) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                    Err(e) => return Err(e.into()),
                }
            }
        }
        Ok(GcReport {
            dry_run,
            artefacts: artefacts.into_iter().map(|(_, label)| label).collect(),
            blobs,
            bytes,
            temporaries: temporaries
                .into_iter()
                .map(|p| p.display().to_string())
                .collect(),
            strays: stray_labels(self.blobs())?,
        })
    }
}

/// `PATH (what it is)` of every stray in the blob store (see
/// [`BlobStore::strays`](super::BlobStore::strays)).
pub(crate) fn stray_labels(store: &super::BlobStore) -> anyhow::Result<Vec<String>> {
    Ok(store
        .strays()?
        .into_iter()
        .map(|(path, kind)| format!("{} ({kind})", path.display()))
        .collect())
}
