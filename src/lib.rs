//! scanloc: simulate point-scanning two-photon microscopy frames of diffusing
//! quantum dots, localise the dots (Crocker–Grier as in TrackPy, or a CNN),
//! score localisations with the paper's precision–recall AUC, and run all of
//! it as reproducible, content-addressed experiments.
//!
//! The pipeline flows one way: [`sim`] → [`detect`] → [`metrics`], over
//! the data they share ([`types`]: frames, ground truth, predictions), at
//! the bottom. [`io`] holds every file format. Coordinates everywhere
//! follow TrackPy: `x` is the column, `y` the row, pixel centres at
//! integers.
//!
//! Visibility (docs/architecture.md, "Visibility"): a module is `pub` only
//! where something outside the library (the binary, `tests/`, `examples/`,
//! the Python bindings) names a path through it, else `pub(crate)`; an item
//! of a crate-private module is `pub(crate)` at most. `unreachable_pub`
//! holds that (and `make lint` denies its warnings), so the compiler's
//! dead-code analysis sees every item no one outside can reach.

#![warn(unreachable_pub)]

pub mod bench;
pub mod cli;
pub mod detect;
pub mod env_vars;
pub mod error;
pub mod fit;
pub mod io;
pub mod limits;
pub mod manifest;
pub mod metrics;
pub mod progress;
pub mod registry;
pub mod report;
pub mod run;
pub mod sim;
pub mod sweep;
pub mod track;
pub mod types;
