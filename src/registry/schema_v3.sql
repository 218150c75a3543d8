-- scanloc registry schema, version 3 (see docs/registry.md): an
-- evaluation of ranked lists of guesses (predictions with a `candidate`
-- rank) has two AUCs per ε, the whole list's (`auc`) and that of each
-- frame's best guess alone. NULL in rows recorded before version 3.

-- The evaluation's AUC of each frame's best prediction alone: its rank-1
-- candidate, or its top-scoring prediction when it has no ranks.
ALTER TABLE auc ADD COLUMN auc_best_per_frame REAL;
-- The same, in a run's AUC table, only where the run's table prints it:
-- the evaluated predictions are ranked lists. NULL otherwise.
ALTER TABLE run_auc ADD COLUMN auc_best_per_frame REAL;
