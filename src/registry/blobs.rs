//! The blob store: immutable files named by the sha256 of their bytes,
//! `blobs/<first two hex digits>/<sha256>`, beside the database.
//!
//! Writing never leaves a partial blob that looks complete: bytes go to a
//! temporary file in `tmp/` (created read-only: mode 0444 minus the
//! umask, so whom the umask lets read a blob can), are synced to disk and
//! renamed into place (a rename within one file system is atomic), then the folder
//! is synced. A blob is re-hashed every time it is read; one whose bytes no
//! longer match its name is reported as damaged and never used.

use std::fs::{self, File};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;

use super::hashing::{sha256_hex, sha256_reader};

/// What a check of one blob found.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BlobState {
    /// Present, and its bytes hash to its name.
    Intact,
    /// No file.
    Missing,
    /// Present, but its bytes hash to `actual`.
    Damaged { actual: String },
}

/// A folder of content-addressed blobs.
#[derive(Debug, Clone)]
pub struct BlobStore {
    root: PathBuf,
}

impl BlobStore {
    /// The store under `registry_dir` (`blobs/` and `tmp/`), created if
    /// missing.
    pub fn open(registry_dir: &Path) -> anyhow::Result<Self> {
        for folder in ["blobs", "tmp"] {
            let path = registry_dir.join(folder);
            fs::create_dir_all(&path).with_context(|| format!("creating {}", path.display()))?;
        }
        Ok(Self {
            root: registry_dir.to_path_buf(),
        })
    }

    /// The store under `registry_dir` as it is, creating nothing: for
    /// reading another registry's blobs (a shard) without writing to it.
    pub fn read_only(registry_dir: &Path) -> Self {
        Self {
            root: registry_dir.to_path_buf(),
        }
    }

    /// Where the blob with hash `sha256` lives.
    pub fn path(&self, sha256: &str) -> PathBuf {
        let prefix = sha256.get(..2).unwrap_or("xx");
        self.root.join("blobs").join(prefix).join(sha256)
    }

    /// The folder of temporary files being written.
    pub fn tmp_dir(&self) -> PathBuf {
        self.root.join("tmp")
    }

    /// Stores `bytes` and returns their sha256. An intact blob with the same
    /// hash is kept as is; a damaged or missing one is (re)written.
    pub fn put(&self, bytes: &[u8]) -> anyhow::Result<String> {
        let sha256 = sha256_hex(bytes);
        if self.check(&sha256)? == BlobState::Intact {
            return Ok(sha256);
        }
        let mut temporary =
            temporary_blob(&self.tmp_dir(), &sha256).context("creating a temporary blob")?;
        temporary.write_all(bytes).context("writing a blob")?;
        temporary.as_file().sync_all().context("syncing a blob")?;
        self.install(temporary.into_temp_path(), &sha256)?;
        Ok(sha256)
    }

    /// Moves the complete, synced file `temporary` (on the store's file
    /// system; its bytes hash to `sha256`) into place as blob `sha256`:
    /// made read-only, renamed (atomic), the folder synced.
    pub fn install(&self, temporary: tempfile::TempPath, sha256: &str) -> anyhow::Result<()> {
        let path = self.path(sha256);
        let folder = path.parent().expect("blob paths have a folder");
        fs::create_dir_all(folder).with_context(|| format!("creating {}", folder.display()))?;
        let mut permissions = fs::metadata(&temporary)?.permissions();
        permissions.set_readonly(true);
        fs::set_permissions(&temporary, permissions)?;
        temporary
            .persist(&path)
            .map_err(|e| e.error)
            .with_context(|| format!("moving a blob into {}", path.display()))?;
        // Make the rename itself durable.
        if let Ok(dir) = File::open(folder) {
            let _ = dir.sync_all();
        }
        Ok(())
    }

    /// Re-hashes the blob `sha256` without keeping its bytes.
    pub fn check(&self, sha256: &str) -> anyhow::Result<BlobState> {
        let path = self.path(sha256);
        let file = match File::open(&path) {
            Ok(file) => file,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(BlobState::Missing),
            Err(e) => return Err(e).with_context(|| format!("opening {}", path.display())),
        };
        let actual = sha256_reader(std::io::BufReader::with_capacity(1 << 20, file))
            .with_context(|| format!("reading {}", path.display()))?;
        Ok(if actual == sha256 {
            BlobState::Intact
        } else {
            BlobState::Damaged { actual }
        })
    }

    /// The bytes of blob `sha256`, re-hashed: `Err` with the state if it is
    /// missing or damaged.
    pub fn get(&self, sha256: &str) -> anyhow::Result<Result<Vec<u8>, BlobState>> {
        let path = self.path(sha256);
        let mut file = match File::open(&path) {
            Ok(file) => file,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Ok(Err(BlobState::Missing));
            }
            Err(e) => return Err(e).with_context(|| format!("opening {}", path.display())),
        };
        let mut bytes = Vec::new();
        file.read_to_end(&mut bytes)
            .with_context(|| format!("reading {}", path.display()))?;
        let actual = sha256_hex(&bytes);
        Ok(if actual == sha256 {
            Ok(bytes)
        } else {
            Err(BlobState::Damaged { actual })
        })
    }

    /// Every blob file in the store: (sha256 named by the file, path, size).
    /// Only regular files: anything else found there is a stray (see
    /// [`BlobStore::strays`]).
    pub fn list(&self) -> anyhow::Result<Vec<(String, PathBuf, u64)>> {
        let mut blobs = Vec::new();
        for entry in self.entries()? {
            if let StoreEntry::File { path, size } = entry {
                let name = path
                    .file_name()
                    .map(|name| name.to_string_lossy().into_owned())
                    .unwrap_or_default();
                blobs.push((name, path, size));
            }
        }
        blobs.sort();
        Ok(blobs)
    }

    /// What lies in `blobs/<prefix>/` or `tmp/` and is not a regular file
    /// (a folder, a symbolic link, a FIFO, …): no write of scanloc's puts
    /// it there, so `gc` and `verify` name it and leave it alone. Each is
    /// (path, what it is).
    pub fn strays(&self) -> anyhow::Result<Vec<(PathBuf, &'static str)>> {
        let mut strays: Vec<(PathBuf, &'static str)> = self
            .entries()?
            .into_iter()
            .chain(self.tmp_entries()?)
            .filter_map(|entry| match entry {
                StoreEntry::Stray { path, kind } => Some((path, kind)),
                StoreEntry::File { .. } => None,
            })
            .collect();
        strays.sort();
        Ok(strays)
    }

    /// Temporary files left by interrupted writes (regular files only; see
    /// [`BlobStore::strays`]).
    pub fn leftovers(&self) -> anyhow::Result<Vec<PathBuf>> {
        let mut files: Vec<PathBuf> = self
            .tmp_entries()?
            .into_iter()
            .filter_map(|entry| match entry {
                StoreEntry::File { path, .. } => Some(path),
                StoreEntry::Stray { .. } => None,
            })
            .collect();
        files.sort();
        Ok(files)
    }

    /// Everything in the prefix folders of `blobs/`.
    fn entries(&self) -> anyhow::Result<Vec<StoreEntry>> {
        let mut entries = Vec::new();
        let top = self.root.join("blobs");
        for prefix in fs::read_dir(&top).with_context(|| format!("listing {}", top.display()))? {
            let prefix = prefix?;
            if !prefix.file_type()?.is_dir() {
                continue;
            }
            entries.extend(list_folder(&prefix.path())?);
        }
        Ok(entries)
    }

    /// Everything in `tmp/` (nothing if it is missing, as in a read-only
    /// registry's folder that never had one).
    fn tmp_entries(&self) -> anyhow::Result<Vec<StoreEntry>> {
        let tmp = self.tmp_dir();
        if !tmp.exists() {
            return Ok(Vec::new());
        }
        list_folder(&tmp)
    }
}

/// One entry of a store folder: a regular file, or anything else.
enum StoreEntry {
    File { path: PathBuf, size: u64 },
    Stray { path: PathBuf, kind: &'static str },
}

/// The entries of `folder`, typed without following symbolic links.
fn list_folder(folder: &Path) -> anyhow::Result<Vec<StoreEntry>> {
    let mut entries = Vec::new();
    for entry in fs::read_dir(folder).with_context(|| format!("listing {}", folder.display()))? {
        let entry = entry?;
        let path = entry.path();
        let metadata =
            fs::symlink_metadata(&path).with_context(|| format!("reading {}", path.display()))?;
        entries.push(if metadata.is_file() {
            StoreEntry::File {
                path,
                size: metadata.len(),
            }
        } else {
            StoreEntry::Stray {
                path,
                kind: crate::io::folders::kind_of(&metadata.file_type()),
            }
        });
    }
    Ok(entries)
}

/// A new temporary file in `dir` for the bytes of blob `sha256`, to be
/// [`install`](BlobStore::install)ed. On Unix it is created 0444, so the
/// kernel takes the umask off: the blob is read-only and readable by whom
/// the umask allows (the open file stays writable for this write).
pub(crate) fn temporary_blob(dir: &Path, sha256: &str) -> std::io::Result<tempfile::NamedTempFile> {
    let mut builder = tempfile::Builder::new();
    let prefix = format!("{sha256}.");
    builder.prefix(&prefix);
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(fs::Permissions::from_mode(0o444));
    }
    builder.tempfile_in(dir)
}
