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

/// A true value (see [`flag`]) opens every existing registry read-only, as if its folder could not
/// be written (a read-only mount): commands that only read work, commands
/// that write refuse with exit code 2, and the database is opened as an
/// immutable file. A new registry (`reproduce`'s scratch folder) is still
/// made. To guard registries against writes, or to test. Another value
/// than [`flag`]'s spellings is refused before any command runs.
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

/// The boolean variables scanloc reads, each checked by [`flag`] before
/// any command runs.
pub(crate) const BOOLEAN_FLAGS: [&str; 1] = [SCANLOC_REGISTRY_READ_ONLY];

/// The value of the boolean variable `name`: unset is false; `1`, `true`,
/// `yes`, `on` are true and `0`, `false`, `no`, `off` false (in any case,
/// blanks around ignored); anything else (an empty value too) is an error
/// naming the variable and the spellings, so a typo never leaves a guard
/// silently off.
pub fn flag(name: &str) -> Result<bool, String> {
    match std::env::var_os(name) {
        None => Ok(false),
        Some(value) => parse_flag(name, &value.to_string_lossy()),
    }
}

fn parse_flag(name: &str, text: &str) -> Result<bool, String> {
    match text.trim().to_ascii_lowercase().as_str() {
        "1" | "true" | "yes" | "on" => Ok(true),
        "0" | "false" | "no" | "off" => Ok(false),
        _ => Err(format!(
            "{name}={text:?}: not a boolean (1, true, yes, on or 0, false, no, off; any case)"
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::parse_flag;

    #[test]
    fn a_flag_takes_the_usual_spellings_and_refuses_others() {
        for text in ["1", "true", "TRUE", "Yes", "on", " On "] {
            assert_eq!(parse_flag("F", text), Ok(true), "{text}");
        }
        for text in ["0", "false", "False", "NO", "off"] {
            assert_eq!(parse_flag("F", text), Ok(false), "{text}");
        }
        for text in ["", "2", "y", "enable", "truee"] {
            let error = parse_flag("F", text).unwrap_err();
            assert!(error.starts_with("F="), "{error}");
        }
    }
}
