//! Reports of runs: Markdown with the AUC table beside the paper's, and
//! figures (PNG and SVG).

pub mod figures;
pub(crate) mod recorded;
pub(crate) mod run_report;
pub(crate) mod summary;
