//! The one line a user reads when a manifest is refused:
//! `FILE:LINE: FIELD: what is wrong`, an [`InputError`](crate::error::InputError)
//! (exit code 2).
//!
//! Two sources: serde_yaml's errors while reading the document (they carry
//! their line; their field path is part of their text), and the
//! [`FieldError`]s of resolving it (they carry their path; the line is
//! found from it with the [`LineIndex`]).

use super::LineIndex;
use crate::error::{FieldError, input_error};

/// A resolution error, located: the line of its field (or of the nearest
/// enclosing one the index knows), then the field and the message.
pub(super) fn located_field_error(
    source: &str,
    lines: &LineIndex,
    error: &FieldError,
) -> anyhow::Error {
    let message = one_line(&error.to_string());
    match lines.line_of(&error.path) {
        Some(line) => input_error(format!("{source}:{line}: {message}")),
        None => input_error(format!("{source}: {message}")),
    }
}

/// A serde_yaml error, with its line in front where serde_yaml knows it.
pub(super) fn located_yaml_error(source: &str, error: serde_yaml::Error) -> anyhow::Error {
    let message = error.to_string();
    // serde_yaml appends " at line L column C"; the line goes in front.
    let message = match message.rfind(" at line ") {
        Some(cut) => message[..cut].to_string(),
        None => message,
    };
    let message = one_line(&explain_integer_overflow(message));
    match error.location() {
        Some(location) => input_error(format!("{source}:{}: {message}", location.line())),
        None => input_error(format!("{source}: {message}")),
    }
}

/// serde_yaml reads an integer beyond 64 bits as a 128-bit one and then
/// reports a type mismatch (`seed: invalid type: integer `…` as u128,
/// expected u64`); say what the user did wrong instead, keeping the field
/// path serde_yaml puts in front.
fn explain_integer_overflow(message: String) -> String {
    if !(message.contains("as u128") || message.contains("as i128")) {
        return message;
    }
    let field_prefix = message
        .find("invalid ")
        .map_or("", |start| &message[..start]);
    format!("{field_prefix}number too large: integers must fit in 64 bits")
}

/// `text` with line breaks escaped, so an error stays one line even when it
/// quotes a key or value that spans lines.
fn one_line(text: &str) -> String {
    text.replace('\r', "\\r").replace('\n', "\\n")
}
