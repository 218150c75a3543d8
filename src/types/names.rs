//! The rule for the names a manifest declares and the registry records:
//! plain file names and plain labels, nothing to escape. Shared by the
//! manifest's checks and the registry's import of shards.

/// Longest artefact name.
pub const MAX_NAME_LEN: usize = 64;

/// Whether `name` obeys the rule for the names a manifest declares
/// (datasets, detectors): 1 to `max_len` ASCII letters, digits, '.', '_'
/// or '-', starting with a letter or digit. Such a name is a plain file
/// name and a plain label: no separators, no `..`, nothing to escape. The
/// manifest takes `max_len` = [`MAX_NAME_LEN`]; names a run derives from
/// them (fold names, `DETECTOR@DATASET`) are checked part by part with
/// the same characters (`registry import`).
pub fn is_plain_name(name: &str, max_len: usize) -> bool {
    !name.is_empty()
        && name.len() <= max_len
        && name.starts_with(|c: char| c.is_ascii_alphanumeric())
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
}
