-- scanloc registry schema, version 2 (see docs/registry.md): a
-- cross-validation run (kind cv) records its plan instead of leaving it to
-- be read off names. NULL for every other run.

ALTER TABLE runs ADD COLUMN cv_detector TEXT;    -- the detector cross-validated
ALTER TABLE runs ADD COLUMN cv_folds    INTEGER; -- k, 2 to 50
ALTER TABLE runs ADD COLUMN cv_fold     INTEGER; -- the one fold run (cv --fold K, 1-based); NULL: every fold
