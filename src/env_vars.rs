//! The environment variables scanloc reads, named once.
//!
//! Code refers to these constants instead of writing the names as string
//! literals, so a name is spelt in one place and this list is complete.
//!
//! Not listed: `SCANLOC_GIT_COMMIT`, `SCANLOC_GIT_DIRTY` and
//! `SCANLOC_RUSTC_VERSION`, which `build.rs` sets at compile time for
//! `env!` (a macro that needs the name as a literal); setting them when
//! running scanloc has no effect.

/// The registry folder, when `--registry` is not given (default
/// `registry`).
pub const SCANLOC_REGISTRY: &str = "SCANLOC_REGISTRY";

/// `1` opens every existing registry read-only, as if its folder could not
/// be written (a read-only mount): commands that only read work, commands
/// that write refuse with exit code 2, and the database is opened as an
/// immutable file. A new registry (`reproduce`'s scratch folder) is still
/// made. To guard registries against writes, or to test.
pub const SCANLOC_REGISTRY_READ_ONLY: &str = "SCANLOC_REGISTRY_READ_ONLY";

/// What the log on standard error shows, as a `tracing` filter
/// (`warn` by default; e.g. `info` or `scanloc=debug`).
pub const SCANLOC_LOG: &str = "SCANLOC_LOG";

/// A TrueType font file for the text of figures, tried before the font
/// embedded in scanloc: a regular file of at most 64 MiB
/// (`report::figures::MAX_FONT_BYTES`); anything else is not read, with a
/// one-line warning.
pub const SCANLOC_FONT: &str = "SCANLOC_FONT";

/// Cases per property of the fuzzing tests (`make fuzz` sets it; without
/// it `make test` runs a short default). Read by the test suite only.
pub const SCANLOC_FUZZ_CASES: &str = "SCANLOC_FUZZ_CASES";

/// A folder in which the figures test keeps the figures it draws, for a
/// person to look at. Read by the test suite only.
pub const SCANLOC_KEEP_FIGURES: &str = "SCANLOC_KEEP_FIGURES";

/// `1` makes the Slurm tests fail, instead of skipping, when no Slurm
/// answers (`.ci/run` sets it after starting its test cluster). Read by the
/// test suite only.
pub const SCANLOC_REQUIRE_SLURM: &str = "SCANLOC_REQUIRE_SLURM";

/// The number of threads of the pool scanloc computes on (rayon's own
/// variable; default: every CPU). A sweep sets it for each of its local
/// processes, and its Slurm batch script to the task's CPUs. A number
/// above `limits::MAX_THREADS` (1,024) is refused before any command runs
/// (exit code 2).
pub const RAYON_NUM_THREADS: &str = "RAYON_NUM_THREADS";
