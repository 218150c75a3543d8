//! The record of runs: begun, each step as it finishes, ended, and those a
//! dead process left `running` marked unfinished.

use rusqlite::params;

use super::{
    AucRow, CodeVersion, Registry, RunStart, RunStatus, StepCounts, StepRecord, host_name, utc_now,
};

impl Registry {
    /// Records as `unfinished` every run whose status in effect is
    /// (see [`RunStatus::in_effect`]).
    pub fn mark_abandoned_runs(&mut self) -> anyhow::Result<usize> {
        if self.read_only {
            return Ok(0);
        }
        let candidates: Vec<(String, String, i64)> = {
            let mut statement = self
                .conn
                .prepare("SELECT id, host, pid FROM runs WHERE status = 'running'")?;
            statement
                .query_map([], |row| {
                    Ok((row.get("id")?, row.get("host")?, row.get("pid")?))
                })?
                .collect::<Result<_, _>>()?
        };
        let mut marked = 0;
        for (id, host, pid) in candidates {
            if RunStatus::Running.in_effect(&host, pid) == RunStatus::Unfinished {
                let tx = self.write_transaction()?;
                marked += tx.execute(
                    "UPDATE runs SET status = 'unfinished',
                       error = 'the process (pid ' || pid || ') ended without finishing the run'
                     WHERE id = ?1 AND status = 'running'",
                    [&id],
                )?;
                tx.commit()?;
            }
        }
        Ok(marked)
    }

    /// Records the start of a run (status `running`).
    pub fn begin_run(&mut self, start: &RunStart) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let code = CodeVersion::current();
        let cv = start.cross_validation.as_ref();
        self.writer_run = Some(start.id.clone());
        let tx = self.write_transaction()?;
        tx.execute(
            "INSERT INTO runs (id, kind, parent_run, manifest_name, manifest_path, manifest_text,
                 manifest_sha256, resolved, seeds, crate_version, git_commit, git_dirty, rustc, host,
                 pid, threads, forced, started_at, status, cv_detector, cv_folds, cv_fold)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18,
                 'running', ?19, ?20, ?21)",
            params![
                start.id,
                start.kind.as_str(),
                start.parent_run,
                start.manifest_name,
                start.manifest_path,
                start.manifest_text,
                start.manifest_sha256,
                start.resolved_json,
                start.seeds_json,
                code.crate_version,
                code.git_commit,
                code.git_dirty,
                code.rustc,
                host_name(),
                std::process::id() as i64,
                rayon::current_num_threads() as i64,
                start.forced,
                utc_now(),
                cv.map(|cv| cv.detector.as_str()),
                cv.map(|cv| cv.folds as i64),
                cv.and_then(|cv| cv.fold).map(|fold| fold as i64),
            ],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// Records one finished step of a running run.
    pub fn record_step(&mut self, run_id: &str, step: &StepRecord) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let blobs: serde_json::Map<String, serde_json::Value> = step
            .blobs
            .iter()
            .map(|b| {
                (
                    b.role.to_string(),
                    serde_json::Value::String(b.sha256.clone()),
                )
            })
            .collect();
        let tx = self.write_transaction()?;
        tx.execute(
            "INSERT INTO run_steps (run_id, ordinal, step, kind, artefact_key, outcome, seconds, blobs, detail)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)",
            params![
                run_id,
                step.ordinal as i64,
                step.step.to_string(),
                step.kind.as_str(),
                step.artefact_key,
                step.outcome.as_str(),
                step.seconds,
                serde_json::Value::Object(blobs).to_string(),
                step.detail
            ],
        )?;
        tx.commit()?;
        Ok(())
    }

    /// Records the end of a run: its status, error, step counts and AUC table.
    pub fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        error: Option<&str>,
        counts: StepCounts,
        auc: &[AucRow],
    ) -> anyhow::Result<()> {
        if self.read_only {
            return Ok(());
        }
        let tx = self.write_transaction()?;
        tx.execute(
            "UPDATE runs SET status = ?2, error = ?3, ended_at = ?4,
                 cached_steps = ?5, computed_steps = ?6, rebuilt_steps = ?7
             WHERE id = ?1",
            params![
                run_id,
                status.as_str(),
                error,
                utc_now(),
                counts.cached as i64,
                counts.computed as i64,
                counts.rebuilt as i64
            ],
        )?;
        for row in auc {
            tx.execute(
                "INSERT INTO run_auc (run_id, detector, dataset, diffusion, eps_px, auc, auc_best_per_frame, evaluation_key)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)",
                params![
                    run_id,
                    row.detector,
                    row.dataset,
                    row.diffusion,
                    row.eps_px,
                    row.auc,
                    row.auc_best_per_frame,
                    row.evaluation_key
                ],
            )?;
        }
        tx.commit()?;
        self.writer_run = None;
        Ok(())
    }
}
