//! Error kinds that decide the process exit code.
//!
//! Library functions return [`anyhow::Result`]. An error whose root is an
//! [`InputError`] was caused by what the user gave us (a flag, a file, a
//! manifest) and makes the command exit with code 2; a [`CheckFailed`] means a
//! verification found a difference (exit 1). Anything else is an internal
//! failure (exit 1 too, but reported as such).
//!
//! Parameter checks (`validate` methods) return a [`FieldError`] instead:
//! which field is wrong and why, as data, so a manifest can place the field
//! under its own path and line. Passed on with `?` it becomes an
//! [`InputError`].

use std::fmt;

/// Long work stopped early because its caller asked it to (Ctrl-C in
/// Python, a monitor's stop request).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stopped;

impl fmt::Display for Stopped {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("stopped at the caller's request")
    }
}

impl std::error::Error for Stopped {}

/// Bad input from the user: a flag, a file or a manifest field. Exit code 2.
///
/// The message is one line and names the file and/or the parameter at fault.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InputError(pub String);

impl fmt::Display for InputError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for InputError {}

/// A check that ran to completion and found a difference (e.g. `reproduce`
/// saw a changed artefact, `verify` a damaged blob). Exit code 1.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CheckFailed(pub String);

impl fmt::Display for CheckFailed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CheckFailed {}

/// Builds an [`InputError`] wrapped in [`anyhow::Error`].
pub fn input_error(message: impl Into<String>) -> anyhow::Error {
    anyhow::Error::new(InputError(message.into()))
}

/// A number as messages and tables show it: the shortest text that reads
/// back as the same `f64`, in scientific notation outside 1e-4 ≤ |x| <
/// 1e15 (so 1e300 is `1e300`, not 301 digits; 0.1 is `0.1`).
pub fn readable(value: f64) -> String {
    let magnitude = value.abs();
    if value == 0.0 || !value.is_finite() || (1e-4..1e15).contains(&magnitude) {
        format!("{value}")
    } else {
        format!("{value:e}")
    }
}

/// Returns early with an [`InputError`] built from a format string.
#[macro_export]
macro_rules! bail_input {
    ($($arg:tt)*) => {
        return Err($crate::error::input_error(format!($($arg)*)))
    };
}

/// The exit code an error maps to: 2 for bad input anywhere in the chain,
/// 1 otherwise.
pub fn exit_code(error: &anyhow::Error) -> i32 {
    if error.chain().any(|cause| cause.is::<InputError>()) {
        2
    } else {
        1
    }
}

/// One step of the path to a field: a mapping key or a list index.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum Segment {
    /// A mapping key (a field name, or the name of a dataset or detector).
    Key(String),
    /// A list index (0-based).
    Index(usize),
}

impl Segment {
    /// The key `name`.
    pub fn key(name: &str) -> Self {
        Segment::Key(name.to_string())
    }
}

/// Formats a path the way errors print it: keys joined by `.`, indices as
/// `[i]` (`evaluations[0].detector`).
pub(crate) fn display_path(path: &[Segment]) -> String {
    let mut text = String::new();
    for segment in path {
        match segment {
            Segment::Key(key) => {
                if !text.is_empty() {
                    text.push('.');
                }
                text.push_str(key);
            }
            Segment::Index(index) => text.push_str(&format!("[{index}]")),
        }
    }
    text
}

/// A field that failed a check: where it is and what is wrong with it.
///
/// `path` is relative to the value that was checked (`training.epochs` for
/// the CNN's `TrainingSettings`); whoever holds
/// that value puts its own path in front with [`FieldError::under`]
/// (`detectors.cnn.cnn.training.epochs`). It prints as `path: message`, and
/// turned into an [`anyhow::Error`] (by `?`) it is an [`InputError`] with
/// that text.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FieldError {
    /// From the outermost field in; empty for the checked value itself.
    pub path: Vec<Segment>,
    /// What is wrong, e.g. `must be ≥ 1, got 0`.
    pub message: String,
}

impl FieldError {
    /// An error in field `field`, which may be a dotted path
    /// (`detector_noise.pmt.excess_noise_factor`).
    pub fn new(field: &str, message: impl Into<String>) -> Self {
        Self {
            path: field.split('.').map(Segment::key).collect(),
            message: message.into(),
        }
    }

    /// An error at `path` (segments from the outermost in).
    pub fn at(path: &[Segment], message: impl Into<String>) -> Self {
        Self {
            path: path.to_vec(),
            message: message.into(),
        }
    }

    /// The same error seen from the value that holds the checked one at
    /// `outer`: `outer` goes in front of the path.
    pub fn under(mut self, outer: &[Segment]) -> Self {
        self.path.splice(0..0, outer.iter().cloned());
        self
    }

    /// The path as errors print it (`datasets.a.brightness`).
    pub fn field(&self) -> String {
        display_path(&self.path)
    }
}

impl fmt::Display for FieldError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.path.is_empty() {
            f.write_str(&self.message)
        } else {
            write!(f, "{}: {}", self.field(), self.message)
        }
    }
}

/// Bad input: a failed field check ends the command with exit code 2 like
/// any other [`InputError`].
impl From<FieldError> for anyhow::Error {
    fn from(error: FieldError) -> Self {
        input_error(error.to_string())
    }
}

/// Checks that a parameter is a finite number, naming it in the error.
pub(crate) fn require_finite(name: &str, value: f64) -> Result<f64, FieldError> {
    if value.is_finite() {
        Ok(value)
    } else {
        Err(FieldError::new(
            name,
            format!("must be a finite number, got {}", readable(value)),
        ))
    }
}

/// Checks that a parameter is finite and ≥ 0, naming it in the error.
pub(crate) fn require_non_negative(name: &str, value: f64) -> Result<f64, FieldError> {
    require_finite(name, value)?;
    if value < 0.0 {
        return Err(FieldError::new(
            name,
            format!("must be ≥ 0, got {}", readable(value)),
        ));
    }
    Ok(value)
}

/// Checks that a parameter is finite and > 0, naming it in the error.
pub(crate) fn require_positive(name: &str, value: f64) -> Result<f64, FieldError> {
    require_finite(name, value)?;
    if value <= 0.0 {
        return Err(FieldError::new(
            name,
            format!("must be > 0, got {}", readable(value)),
        ));
    }
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readable_numbers_are_short_and_read_back_exactly() {
        for (value, text) in [
            (0.0, "0"),
            (0.1, "0.1"),
            (-2.5, "-2.5"),
            (1e300, "1e300"),
            (-1.5e-160, "-1.5e-160"),
            (123456789.0, "123456789"),
            (f64::INFINITY, "inf"),
        ] {
            assert_eq!(readable(value), text);
        }
        for value in [f64::MAX, f64::MIN_POSITIVE, 1.0 / 3.0, 7.1e-5, 2.0e15] {
            assert_eq!(readable(value).parse::<f64>().unwrap(), value);
            assert!(readable(value).len() < 25, "{}", readable(value));
        }
    }

    #[test]
    fn field_errors_take_the_path_of_the_value_that_holds_them() {
        let error = FieldError::new("training.epochs", "must be ≥ 1, got 0").under(&[
            Segment::key("detectors"),
            Segment::key("cnn.v2"),
            Segment::key("cnn"),
        ]);
        assert_eq!(error.field(), "detectors.cnn.v2.cnn.training.epochs");
        assert_eq!(error.path.len(), 5, "a dotted name stays one segment");
        assert_eq!(
            error.to_string(),
            "detectors.cnn.v2.cnn.training.epochs: must be ≥ 1, got 0"
        );
        let listed = FieldError::at(
            &[
                Segment::key("metrics"),
                Segment::key("eps_px"),
                Segment::Index(2),
            ],
            "duplicate radius 1",
        );
        assert_eq!(listed.to_string(), "metrics.eps_px[2]: duplicate radius 1");
        let converted: anyhow::Error = listed.into();
        assert_eq!(exit_code(&converted), 2);
        assert_eq!(
            converted.to_string(),
            "metrics.eps_px[2]: duplicate radius 1"
        );
    }
}
