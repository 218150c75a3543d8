//! `registry gc`: removes artefacts no run references and blob files no
//! remaining artefact references, sparing whatever a live run may be about
//! to record. It holds the registry's blob lock alone, so no import is
//! writing blobs meanwhile (`write_lock`).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use rusqlite::params;
use serde::Serialize;

use super::dates::{format_utc, parse_utc};
use super::write_lock::{BlobLock, BlobLockUse};
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

/// Whether a run is live, and the time before which anything unrecorded
/// is certainly not about to be recorded by one.
struct LiveRuns {
    /// Now, or a minute before the start of the oldest live run.
    cutoff: SystemTime,
    some_run_live: bool,
}

impl Registry {
    /// Removes artefacts no run step references and blob files no remaining
    /// artefact references (`dry_run`: only says what it would remove).
    /// Anything newer than the start of the oldest run still in progress is
    /// kept, since that run may be about to record it. Imports into the
    /// registry are waited for (they write blobs before their rows), and
    /// wait for it.
    pub fn gc(&mut self, dry_run: bool) -> anyhow::Result<GcReport> {
        let _alone = if dry_run {
            None
        } else {
            Some(BlobLock::take(
                &self.dir,
                BlobLockUse::Gc,
                super::BUSY_TIMEOUT,
            )?)
        };
        let live = self.live_runs()?;
        let artefacts = self.unreferenced_artefacts(&live)?;
        let (blobs, blob_paths, bytes) = self.unused_blobs(&artefacts, live.cutoff)?;
        let temporaries = self.abandoned_temporaries(&live)?;
        if !dry_run {
            self.delete(&artefacts, &blobs)?;
            for path in &blob_paths {
                remove(path, false)?;
            }
            for path in &temporaries {
                remove(path, true)?;
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

    /// The runs recorded as running whose process is alive.
    fn live_runs(&self) -> anyhow::Result<LiveRuns> {
        let mut live = LiveRuns {
            cutoff: SystemTime::now(),
            some_run_live: false,
        };
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
                live.cutoff = live.cutoff.min(started - Duration::from_secs(60));
                live.some_run_live = true;
            }
        }
        Ok(live)
    }

    /// (key, `kind name (key)`) of every artefact no step references,
    /// but those a live run may be about to reference.
    fn unreferenced_artefacts(&self, live: &LiveRuns) -> anyhow::Result<Vec<(String, String)>> {
        let live_cutoff_text = live.some_run_live.then(|| format_utc(live.cutoff));
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
        Ok(orphans
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
            .collect())
    }

    /// The blob files no artefact but `doomed` ones references and that
    /// are older than `cutoff`: (sha256s, paths, bytes).
    fn unused_blobs(
        &self,
        doomed: &[(String, String)],
        cutoff: SystemTime,
    ) -> anyhow::Result<(Vec<String>, Vec<PathBuf>, u64)> {
        let doomed: BTreeSet<&str> = doomed.iter().map(|(k, _)| k.as_str()).collect();
        let mut statement = self
            .conn
            .prepare("SELECT artefact_key, sha256 FROM artefact_blobs")?;
        let pairs: Vec<(String, String)> = statement
            .query_map([], |row| Ok((row.get("artefact_key")?, row.get("sha256")?)))?
            .collect::<Result<_, _>>()?;
        let still_used: BTreeSet<String> = pairs
            .into_iter()
            .filter(|(key, _)| !doomed.contains(key.as_str()))
            .map(|(_, sha)| sha)
            .collect();
        let mut blobs = Vec::new();
        let mut bytes = 0;
        let mut paths = Vec::new();
        for (sha, path, size) in self.blobs().list()? {
            if still_used.contains(&sha) || modified(&path) >= cutoff {
                continue;
            }
            bytes += size;
            blobs.push(sha);
            paths.push(path);
        }
        Ok((blobs, paths, bytes))
    }

    /// Temporary files (and import staging folders) certainly abandoned:
    /// a temporary is in use while its write lasts, so only old ones, or
    /// any when no run is live, are.
    fn abandoned_temporaries(&self, live: &LiveRuns) -> anyhow::Result<Vec<PathBuf>> {
        let day_ago = SystemTime::now() - Duration::from_secs(86_400);
        Ok(self
            .blobs()
            .leftovers()?
            .into_iter()
            .filter(|path| modified(path) < live.cutoff.min(day_ago) || !live.some_run_live)
            .collect())
    }

    /// Deletes the rows of `artefacts` and of `blobs`, in one transaction.
    fn delete(&self, artefacts: &[(String, String)], blobs: &[String]) -> anyhow::Result<()> {
        let tx = self.write_transaction()?;
        for (key, _) in artefacts {
            tx.execute("DELETE FROM auc WHERE evaluation_key = ?1", [key])?;
            for table in ["datasets", "models", "predictions", "evaluations"] {
                tx.execute(&format!("DELETE FROM {table} WHERE key = ?1"), [key])?;
            }
            tx.execute("DELETE FROM artefact_blobs WHERE artefact_key = ?1", [key])?;
            tx.execute("DELETE FROM artefacts WHERE key = ?1", [key])?;
        }
        for sha in blobs {
            tx.execute("DELETE FROM blobs WHERE sha256 = ?1", params![sha])?;
        }
        tx.commit()?;
        Ok(())
    }
}

/// When `path` was last modified (the epoch if that cannot be read).
fn modified(path: &Path) -> SystemTime {
    std::fs::metadata(path)
        .and_then(|m| m.modified())
        .unwrap_or(UNIX_EPOCH)
}

/// Removes the file, or with `folders` the folder (an interrupted
/// import's staging folder in `tmp/`).
fn remove(path: &Path, folders: bool) -> anyhow::Result<()> {
    let removed = match std::fs::symlink_metadata(path) {
        Ok(metadata) if folders && metadata.is_dir() => std::fs::remove_dir_all(path),
        _ => std::fs::remove_file(path),
    };
    match removed {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(anyhow::Error::new(e).context(format!("removing {}", path.display()))),
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
