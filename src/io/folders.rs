//! Output folders written whole or not at all, and the file names made
//! from recorded names (datasets, detectors, runs, roles).
//!
//! A recorded name is data: it may come from a shard another lab made, so
//! it may hold `/`, `..`, control characters or thousands of bytes.
//! [`safe_file_name`] is the one way such a name becomes a file name.
//!
//! A folder a command writes (`report --out`, `registry model --out`,
//! `train --out`) goes through [`PendingFolder`]: every destination is
//! checked before anything is written, the files go into a temporary
//! folder beside the destination, and that folder is renamed into place
//! when complete.

use std::ffi::OsStr;
use std::fs;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

use crate::error::input_error;

/// The longest part of a file name [`safe_file_name`] keeps from the name
/// it is given (its hash suffix comes on top): far below the 255 bytes
/// file systems allow, leaving room for what callers add (`pr_`, `.png`).
pub(crate) const MAX_NAME_BYTES: usize = 100;

/// Hex digits of the sha256 of the original name appended to a name that
/// had to be changed.
const HASH_SUFFIX_DIGITS: usize = 8;

/// A file name made from `name`, a recorded name that is data, never a
/// path. Characters other than `A-Z a-z 0-9 . _ -` become `_`, a leading
/// `.` becomes `_` (no hidden files, no `.` or `..`), an empty name is
/// `_`, and at most [`MAX_NAME_BYTES`] of it are kept. A name that had to
/// be changed gets `-` and the first 8 hex digits of its sha256 appended,
/// so two different names never share a file name; so does a name that
/// already ends like such a suffix, so a name cannot be chosen to meet
/// another's changed form. Every other name is kept as it is.
pub fn safe_file_name(name: &str) -> String {
    let mut safe: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '_'
            }
        })
        .take(MAX_NAME_BYTES)
        .collect();
    if safe.starts_with('.') {
        safe.replace_range(..1, "_");
    }
    if safe.is_empty() {
        safe.push('_');
    }
    if safe == name && !looks_hash_suffixed(name) {
        return safe;
    }
    let digest = hex::encode(Sha256::digest(name.as_bytes()));
    format!("{safe}-{}", &digest[..HASH_SUFFIX_DIGITS])
}

/// Whether `name` ends like a name [`safe_file_name`] changed (`-` and 8
/// lowercase hex digits).
fn looks_hash_suffixed(name: &str) -> bool {
    let bytes = name.as_bytes();
    bytes.len() > HASH_SUFFIX_DIGITS
        && bytes[bytes.len() - HASH_SUFFIX_DIGITS - 1] == b'-'
        && bytes[bytes.len() - HASH_SUFFIX_DIGITS..]
            .iter()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(b))
}

/// An output folder being written: files go into a hidden temporary folder
/// beside the destination, which [`PendingFolder::commit`] renames into
/// place, replacing the folder there whole. Dropped without commit, the
/// temporary folder vanishes and the destination is untouched.
///
/// The destination must be a new path or a folder holding nothing but
/// regular files that the command itself writes there (`owns` says which
/// names those are): a symbolic link, FIFO, device node, socket or
/// subfolder in it, or a file of another name, is refused (exit code 2,
/// naming the path) before anything is written, and left as it is. So a
/// command never deletes what it did not write, never writes through a
/// link, and never leaves a folder half old, half new.
pub struct PendingFolder {
    destination: PathBuf,
    temporary: tempfile::TempDir,
    owns: fn(&str) -> bool,
}

impl PendingFolder {
    /// Checks `destination` (see [`PendingFolder`]) and starts writing it;
    /// its parent folders are created if missing. `owns` says which file
    /// names the command writes into such a folder.
    pub fn create(destination: &Path, owns: fn(&str) -> bool) -> anyhow::Result<Self> {
        check_folder_destination(destination, owns)?;
        let parent = parent_folder(destination);
        fs::create_dir_all(parent)
            .map_err(|e| input_error(format!("{}: cannot create: {e}", parent.display())))?;
        let mut builder = tempfile::Builder::new();
        builder.prefix(".scanloc-partial-");
        #[cfg(unix)]
        {
            // tempfile's default is 0700; with 0777 the kernel applies the
            // umask, so the folder gets the permissions users expect.
            use std::os::unix::fs::PermissionsExt;
            builder.permissions(fs::Permissions::from_mode(0o777));
        }
        let temporary = builder.tempdir_in(parent).map_err(|e| {
            input_error(format!("{}: cannot write here: {e}", destination.display()))
        })?;
        Ok(Self {
            destination: destination.to_path_buf(),
            temporary,
            owns,
        })
    }

    /// Only the check of [`PendingFolder::create`], to refuse a bad
    /// destination before long work.
    pub fn check(destination: &Path, owns: fn(&str) -> bool) -> anyhow::Result<()> {
        check_folder_destination(destination, owns)
    }

    /// The temporary folder the files are written into, for writers that
    /// name their files themselves (names the command owns, made by
    /// [`safe_file_name`] when they come from recorded names).
    pub fn path(&self) -> &Path {
        self.temporary.path()
    }

    /// The destination folder.
    pub fn destination(&self) -> &Path {
        &self.destination
    }

    /// Where the file `name` (a plain file name the command owns, see
    /// [`PendingFolder::create`]) is written now: inside the temporary
    /// folder.
    pub fn file(&self, name: &str) -> PathBuf {
        debug_assert!(
            Path::new(name).file_name() == Some(OsStr::new(name)) && (self.owns)(name),
            "{name}: not a file name this folder's command writes"
        );
        self.temporary.path().join(name)
    }

    /// Renames the written folder into place. An existing destination is
    /// checked again (it may have changed since `create`), moved aside,
    /// and its files removed once the new folder is in place.
    pub fn commit(self) -> anyhow::Result<()> {
        let Self {
            destination,
            temporary,
            owns,
        } = self;
        check_folder_destination(&destination, owns)?;
        let cannot = |e: std::io::Error| {
            input_error(format!("{}: cannot write: {e}", destination.display()))
        };
        if fs::symlink_metadata(&destination).is_err() {
            fs::rename(temporary.path(), &destination).map_err(cannot)?;
            // The folder is in place: nothing is left to clean up.
            let _ = temporary.keep();
            return Ok(());
        }
        // Renaming a folder onto an empty one replaces it: the old folder
        // goes to a fresh empty name beside it, the new one into place.
        // Kept at once: once it holds the old folder, nothing may remove
        // it wholesale.
        let aside = tempfile::Builder::new()
            .prefix(".scanloc-replaced-")
            .tempdir_in(parent_folder(&destination))
            .map_err(cannot)?
            .keep();
        if let Err(e) = fs::rename(&destination, &aside) {
            let _ = fs::remove_dir(&aside);
            return Err(cannot(e));
        }
        if let Err(e) = fs::rename(temporary.path(), &destination) {
            // Put the old folder back; the new one vanishes with `temporary`.
            if fs::rename(&aside, &destination).is_err() {
                crate::bail_input!(
                    "{}: cannot write: {e}; the folder that was there is now {}",
                    destination.display(),
                    aside.display()
                );
            }
            return Err(cannot(e));
        }
        let _ = temporary.keep();
        remove_replaced_folder(&aside, owns)
    }
}

/// The folder a path lies in (`.` for a bare name).
fn parent_folder(path: &Path) -> &Path {
    match path.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent,
        _ => Path::new("."),
    }
}

/// Refuses a folder destination that is not a new path or a real folder
/// holding only regular files whose names `owns` accepts.
fn check_folder_destination(destination: &Path, owns: fn(&str) -> bool) -> anyhow::Result<()> {
    let metadata = match fs::symlink_metadata(destination) {
        Ok(metadata) => metadata,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => crate::bail_input!("{}: cannot read: {e}", destination.display()),
    };
    if !metadata.is_dir() {
        crate::bail_input!(
            "{}: is {}, not a folder; an output folder goes here (give a folder or a new path)",
            destination.display(),
            kind_of(&metadata.file_type())
        );
    }
    let entries = fs::read_dir(destination)
        .map_err(|e| input_error(format!("{}: cannot read: {e}", destination.display())))?;
    for entry in entries {
        let entry = entry
            .map_err(|e| input_error(format!("{}: cannot read: {e}", destination.display())))?;
        let path = entry.path();
        let file_type = entry
            .file_type()
            .map_err(|e| input_error(format!("{}: cannot read: {e}", path.display())))?;
        if !file_type.is_file() {
            crate::bail_input!(
                "{}: is {}; refusing to replace it (nothing was written; move it away or give a new folder)",
                path.display(),
                kind_of(&file_type)
            );
        }
        let name = entry.file_name();
        if !name.to_str().is_some_and(owns) {
            crate::bail_input!(
                "{}: not a file this command writes; refusing to replace the folder holding it (nothing was written; move it away or give a new folder)",
                path.display()
            );
        }
    }
    Ok(())
}

/// Removes the old folder moved aside by [`PendingFolder::commit`]: its
/// regular files the command owns, then the folder; anything else found
/// there (put in since the check) is left, and named.
fn remove_replaced_folder(aside: &Path, owns: fn(&str) -> bool) -> anyhow::Result<()> {
    let entries = fs::read_dir(aside)
        .map_err(|e| input_error(format!("{}: cannot read: {e}", aside.display())))?;
    for entry in entries.flatten() {
        let owned = entry.file_type().is_ok_and(|t| t.is_file())
            && entry.file_name().to_str().is_some_and(owns);
        if owned {
            let _ = fs::remove_file(entry.path());
        }
    }
    fs::remove_dir(aside).map_err(|e| {
        input_error(format!(
            "{}: the replaced folder was kept, it holds files this command did not write: {e}",
            aside.display()
        ))
    })
}

/// What a file type is, in words, for refusals.
pub(crate) fn kind_of(file_type: &fs::FileType) -> &'static str {
    if file_type.is_symlink() {
        "a symbolic link"
    } else if file_type.is_dir() {
        "a folder"
    } else if file_type.is_file() {
        "a regular file"
    } else {
        super::special_file_kind(file_type)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ordinary_names_are_kept_and_others_made_safe_and_distinct() {
        for name in ["test", "test-0.75", "D_1.5", "cnn"] {
            assert_eq!(safe_file_name(name), name);
        }
        for name in [
            "/../../../../elsewhere/X",
            "..",
            ".",
            "",
            ".hidden",
            "a/b",
            "a\\b",
            "é",
            "a\0b",
        ] {
            let safe = safe_file_name(name);
            assert!(
                safe.bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"._-".contains(&b)),
                "{name:?} -> {safe:?}"
            );
            assert!(!safe.starts_with('.'), "{name:?} -> {safe:?}");
            assert_ne!(safe, name);
        }
        assert_ne!(safe_file_name("a/b"), safe_file_name("a:b"));
        assert!(safe_file_name(&"x".repeat(100_000)).len() <= MAX_NAME_BYTES + 9);
        // A name chosen to look like another's changed form is changed too.
        let changed = safe_file_name("a/b");
        assert_ne!(safe_file_name(&changed), changed);
    }
}
