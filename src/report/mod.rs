//! Reports of runs: Markdown with the AUC table beside the paper's, and
//! figures (PNG and SVG).

pub mod figures;
pub mod recorded;
pub mod run_report;
pub mod summary;
