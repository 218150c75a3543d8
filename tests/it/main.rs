//! The integration tests, as one test binary with a module per feature:
//! one link of the library and its dependencies (burn, rusqlite,
//! plotters) instead of one per file. `common` holds the helpers the
//! modules share.

mod common;

/// Counts live heap bytes, so the in-process CLI fuzz cases can be refused
/// allocations no small case needs (`hostile_fuzz_guard`).
#[global_allocator]
static ALLOCATOR: hostile_fuzz_guard::CountingAllocator = hostile_fuzz_guard::CountingAllocator;

mod bench_tradeoffs;
mod calibrate_cv;
mod cli_locate;
mod cli_microscope;
mod cli_simulate;
mod cnn;
mod content_keys;
mod crocker_grier;
mod diffusion;
mod docs;
mod empty_frames;
mod figures;
mod fit_microscope;
mod hostile_bounds;
mod hostile_cli_fuzz;
mod hostile_files;
mod hostile_fuzz_guard;
mod hostile_manifest;
mod hostile_outputs;
mod hostile_real_frames;
mod hostile_registry;
mod hostile_shard_fuzz;
mod hostile_shards;
mod layers;
mod likelihood;
mod link;
mod manifest_errors;
mod manifest_fuzz;
mod metric;
mod registry_crash;
mod registry_models;
mod registry_runs;
mod report;
mod score_tracks;
mod simulator;
mod stress;
mod structure;
mod sweep_cluster;
mod track;
mod tracking_defects;
mod tracking_runs;
