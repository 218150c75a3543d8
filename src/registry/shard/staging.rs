//! The staging folder of one copy, inside the destination's `tmp/`: the
//! private copy of a shard's database and the blobs read from the shard,
//! each hashed while copied. Blobs move into the store only once every row
//! has been written (just before the commit), so a refused copy leaves
//! nothing in the store; the folder goes when the copy ends, however it
//! ends.

use std::fs::File;
use std::io::{Read, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

use anyhow::Context;
use sha2::{Digest, Sha256};
use tempfile::{TempDir, TempPath};

use crate::registry::BlobStore;

/// A file opened only if it is a regular file: not a symlink (not
/// followed), not a FIFO (opened without blocking, then refused), not a
/// device. Returns the file and its size, as its own metadata says.
pub(super) fn open_regular(path: &Path) -> Result<(File, u64), String> {
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(path)
        .map_err(|e| match e.raw_os_error() {
            Some(libc::ELOOP) => "is a symbolic link, not a file".to_string(),
            _ => format!("cannot be opened: {e}"),
        })?;
    let metadata = file
        .metadata()
        .map_err(|e| format!("cannot be read: {e}"))?;
    if !metadata.file_type().is_file() {
        return Err(format!(
            "is not a regular file (a {})",
            kind_of(&metadata.file_type())
        ));
    }
    Ok((file, metadata.len()))
}

fn kind_of(file_type: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if file_type.is_dir() {
        "folder"
    } else if file_type.is_fifo() {
        "FIFO"
    } else if file_type.is_socket() {
        "socket"
    } else if file_type.is_block_device() || file_type.is_char_device() {
        "device"
    } else {
        "special file"
    }
}

/// Copies the `size` bytes of `from` (opened with [`open_regular`]) to
/// `to`, returning their sha256; fewer or more bytes than `size` (the file
/// changed while read) is an error.
fn copy_hashing(from: File, size: u64, to: &mut impl Write) -> Result<String, String> {
    let mut hasher = Sha256::new();
    let mut reader = from.take(size.saturating_add(1));
    let mut buffer = vec![0u8; 1 << 20];
    let mut copied: u64 = 0;
    loop {
        let read = reader
            .read(&mut buffer)
            .map_err(|e| format!("cannot be read: {e}"))?;
        if read == 0 {
            break;
        }
        hasher.update(&buffer[..read]);
        to.write_all(&buffer[..read])
            .map_err(|e| format!("cannot be copied: {e}"))?;
        copied += read as u64;
    }
    if copied != size {
        return Err(format!(
            "changed while read ({size} bytes by its metadata, {copied} read)"
        ));
    }
    Ok(hex::encode(hasher.finalize()))
}

/// One copy's staging folder.
pub(super) struct Staging {
    dir: TempDir,
    /// Blobs staged and not yet moved into the store: (sha256, file).
    blobs: Vec<(String, TempPath)>,
}

impl Staging {
    /// A new staging folder in the temporary folder of `store`.
    pub(super) fn new(store: &BlobStore) -> anyhow::Result<Self> {
        let dir = tempfile::Builder::new()
            .prefix("import-")
            .tempdir_in(store.tmp_dir())
            .with_context(|| format!("creating a folder in {}", store.tmp_dir().display()))?;
        Ok(Self {
            dir,
            blobs: Vec::new(),
        })
    }

    /// Copies the regular file `from` to `name` in the staging folder.
    pub(super) fn copy_file(&self, from: &Path, name: &str) -> Result<PathBuf, String> {
        let (file, size) = open_regular(from)?;
        let to = self.dir.path().join(name);
        let mut out = File::create(&to).map_err(|e| format!("cannot be copied: {e}"))?;
        copy_hashing(file, size, &mut out)?;
        Ok(to)
    }

    /// Copies blob `sha256` from the file `from`, which the shard records
    /// as `recorded_bytes` long, hashing it on the way: a file that is not
    /// a regular file, of another size or other bytes is refused.
    /// Returns the size.
    pub(super) fn stage_blob(
        &mut self,
        from: &Path,
        sha256: &str,
        recorded_bytes: i64,
    ) -> Result<u64, String> {
        let (file, size) = open_regular(from)?;
        if u64::try_from(recorded_bytes) != Ok(size) {
            return Err(format!(
                "is {size} bytes, the shard records {recorded_bytes}"
            ));
        }
        let mut temporary = super::super::blobs::temporary_blob(self.dir.path(), sha256)
            .map_err(|e| format!("cannot be copied: {e}"))?;
        let actual = copy_hashing(file, size, &mut temporary)?;
        if actual != sha256 {
            return Err(format!("is damaged: its bytes hash to {actual}"));
        }
        temporary
            .as_file()
            .sync_all()
            .map_err(|e| format!("cannot be copied: {e}"))?;
        self.blobs
            .push((sha256.to_string(), temporary.into_temp_path()));
        Ok(size)
    }

    /// Moves every staged blob into `store`.
    pub(super) fn install(&mut self, store: &BlobStore) -> anyhow::Result<()> {
        for (sha256, file) in self.blobs.drain(..) {
            store.install(file, &sha256)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_regular_files_are_opened() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("file");
        std::fs::write(&file, b"abc").unwrap();
        assert_eq!(open_regular(&file).unwrap().1, 3);
        let link = dir.path().join("link");
        std::os::unix::fs::symlink(&file, &link).unwrap();
        assert!(open_regular(&link).unwrap_err().contains("symbolic link"));
        let fifo = dir.path().join("fifo");
        let name = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(name.as_ptr(), 0o600) }, 0);
        assert!(open_regular(&fifo).unwrap_err().contains("FIFO"));
        assert!(
            open_regular(Path::new("/dev/zero"))
                .unwrap_err()
                .contains("device")
        );
        assert!(open_regular(dir.path()).unwrap_err().contains("folder"));
    }
}
