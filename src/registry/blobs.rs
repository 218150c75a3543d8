//! The blob store: immutable files named by the sha256 of their bytes,
//! `blobs/<first two hex digits>/<sha256>`, beside the database.
//!
//! Writing never leaves a partial blob that looks complete: bytes go to a
//! temporary file in `tmp/`, are synced to disk, made read-only and renamed
//! into place (a rename within one file system is atomic), then the folder
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
        let mut temporary = tempfile::Builder::new()
            .prefix(&format!("{sha256}."))
            .tempfile_in(self.tmp_dir())
            .context("creating a temporary blob")?;
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
    pub fn list(&self) -> anyhow::Result<Vec<(String, PathBuf, u64)>> {
        let mut blobs = Vec::new();
        let top = self.root.join("blobs");
        for prefix in fs::read_dir(&top).with_context(|| format!("listing {}", top.display()))? {
            let prefix = prefix?;
            if !prefix.file_type()?.is_dir() {
                continue;
            }
            for entry in fs::read_dir(prefix.path())? {
                let entry = entry?;
                let name = entry.file_name().to_string_lossy().into_owned();
                blobs.push((name, entry.path(), entry.metadata()?.len()));
            }
        }
        blobs.sort();
        Ok(blobs)
    }

    /// Temporary files left by interrupted writes.
    pub fn leftovers(&self) -> anyhow::Result<Vec<PathBuf>> {
        let mut files = Vec::new();
        for entry in fs::read_dir(self.tmp_dir())? {
            files.push(entry?.path());
        }
        files.sort();
        Ok(files)
    }
}
