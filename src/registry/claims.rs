//! Which run is computing which step now (`step_claims`): a second run
//! that needs the same artefact waits for it instead of computing it too.

use rusqlite::{OptionalExtension, params};

use super::{Registry, RunStatus, host_name, utc_now};

impl Registry {
    /// Claims the computation of the artefact `key` for run `run_id` (this
    /// process), or returns the live claim of another run on this host to
    /// wait for. A claim by a process that is gone (the pid/host rule of
    /// unfinished runs) is taken over; one from another host is not waited
    /// for (its liveness cannot be known): both compute, as before claims.
    pub fn claim_step(&mut self, key: &str, run_id: &str) -> anyhow::Result<Option<StepClaim>> {
        if self.read_only {
            return Ok(None);
        }
        let tx = self.write_transaction()?;
        let holder: Option<StepClaim> = tx
            .query_row(
                "SELECT run_id, host, pid FROM step_claims WHERE key = ?1",
                [key],
                |row| {
                    Ok(StepClaim {
                        run_id: row.get(0)?,
                        host: row.get(1)?,
                        pid: row.get(2)?,
                    })
                },
            )
            .optional()?;
        if let Some(holder) = holder
            && holder.run_id != run_id
            && holder.host == host_name()
            && RunStatus::Running.in_effect(&holder.host, holder.pid) == RunStatus::Running
        {
            return Ok(Some(holder));
        }
        tx.execute(
            "INSERT OR REPLACE INTO step_claims (key, run_id, host, pid, claimed_at)
             VALUES (?1, ?2, ?3, ?4, ?5)",
            params![key, run_id, host_name(), std::process::id(), utc_now()],
        )?;
        tx.commit()?;
        Ok(None)
    }

    /// Releases run `run_id`'s claim on `key` (all its claims with `None`).
    pub fn release_claims(&mut self, run_id: &str, key: Option<&str>) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let tx = self.write_transaction()?;
        tx.execute(
            "DELETE FROM step_claims WHERE run_id = ?1 AND (?2 IS NULL OR key = ?2)",
            params![run_id, key],
        )?;
        tx.commit()?;
        Ok(())
    }
}

pub(super) const STEP_CLAIMS: &str = "CREATE TABLE IF NOT EXISTS step_claims (
    key TEXT PRIMARY KEY,
    run_id TEXT NOT NULL,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    claimed_at TEXT NOT NULL
)";

/// A run computing a step another run needs.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StepClaim {
    pub run_id: String,
    pub host: String,
    pub pid: i64,
}
