//! Every file format scanloc reads or writes, in one place.
//!
//! - Frames: `.npy` (`uint16`, or `uint32` when a count needs it; shape
//!   `(n, H, W)`, C order) and multi-page TIFF (one page per frame).
//! - Ground truth and localisations: CSV with a header ([`csv_tables`]).
//!
//! Writers never leave a partial file behind: they write to a temporary file
//! in the destination folder and rename it into place only when complete.
//! Readers report problems as [`InputError`](crate::error::InputError)s that
//! name the file.

pub mod csv_tables;
pub mod npy;
pub mod tiff_stack;

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::error::input_error;
use crate::types::FrameStack;

/// The frame file formats, chosen by file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FrameFormat {
    Npy,
    Tiff,
}

impl FrameFormat {
    /// The format a path's extension names (`.npy`, `.tif`, `.tiff`).
    pub fn from_path(path: &Path) -> anyhow::Result<Self> {
        let extension = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        match extension.as_deref() {
            Some("npy") => Ok(FrameFormat::Npy),
            Some("tif") | Some("tiff") => Ok(FrameFormat::Tiff),
            _ => Err(input_error(format!(
                "{}: unknown frame format (use .npy, .tif or .tiff)",
                path.display()
            ))),
        }
    }
}

/// Reads a frame stack from `.npy` or TIFF, by extension.
pub fn read_frames(path: &Path) -> anyhow::Result<FrameStack> {
    match FrameFormat::from_path(path)? {
        FrameFormat::Npy => npy::read_frames(path),
        FrameFormat::Tiff => tiff_stack::read_frames(path),
    }
}

/// Writes a frame stack to `.npy` or TIFF, by extension, atomically.
pub fn write_frames(path: &Path, frames: &FrameStack) -> anyhow::Result<()> {
    let mut pending = PendingFile::create(path)?;
    fill_frames(&mut pending, frames)?;
    pending.commit()
}

/// Fills a pending output with a frame stack in the format its extension
/// names.
pub fn fill_frames(pending: &mut PendingFile, frames: &FrameStack) -> anyhow::Result<()> {
    let format = FrameFormat::from_path(&pending.path)?;
    pending.fill(|writer| match format {
        FrameFormat::Npy => npy::write_frames(writer, frames),
        FrameFormat::Tiff => tiff_stack::write_frames(writer, frames),
    })
}

/// An output file being written: data goes to a hidden temporary file in the
/// destination folder, which [`PendingFile::commit`] syncs and renames into
/// place. Dropped without commit, it vanishes and the destination is
/// untouched. Creating every pending output of a command before computing
/// anything makes an unwritable destination fail fast, and committing them
/// only at the end leaves no partial output behind.
pub struct PendingFile {
    path: PathBuf,
    temporary: tempfile::NamedTempFile,
}

impl PendingFile {
    /// Starts writing `path` (its folder must exist and be writable).
    pub fn create(path: &Path) -> anyhow::Result<Self> {
        let folder = match path.parent() {
            Some(parent) if !parent.as_os_str().is_empty() => parent,
            _ => Path::new("."),
        };
        let temporary = tempfile::Builder::new()
            .prefix(".scanloc-partial-")
            .tempfile_in(folder)
            .map_err(|e| input_error(format!("{}: cannot write here: {e}", path.display())))?;
        Ok(Self {
            path: path.to_path_buf(),
            temporary,
        })
    }

    /// Fills the file through a buffered writer.
    pub fn fill(
        &mut self,
        fill: impl FnOnce(&mut BufWriter<&mut File>) -> anyhow::Result<()>,
    ) -> anyhow::Result<()> {
        let path = self.path.display().to_string();
        let mut writer = BufWriter::new(self.temporary.as_file_mut());
        fill(&mut writer).with_context(|| format!("writing {path}"))?;
        writer
            .flush()
            .map_err(|e| input_error(format!("{path}: write failed: {e}")))?;
        Ok(())
    }

    /// Syncs the data to disk and renames the file into place.
    pub fn commit(self) -> anyhow::Result<()> {
        let path = self.path;
        self.temporary
            .as_file()
            .sync_all()
            .map_err(|e| input_error(format!("{}: write failed: {e}", path.display())))?;
        self.temporary
            .persist(&path)
            .map_err(|e| input_error(format!("{}: cannot write: {}", path.display(), e.error)))?;
        Ok(())
    }
}

/// Writes `path` through `fill` atomically (see [`PendingFile`]).
pub fn write_atomically(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<&mut File>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let mut pending = PendingFile::create(path)?;
    pending.fill(fill)?;
    pending.commit()
}

/// Writes `bytes` to `path` atomically (see [`write_atomically`]).
pub fn write_bytes_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    write_atomically(path, |writer| {
        writer.write_all(bytes)?;
        Ok(())
    })
}

/// Opens a file for reading, with an input error naming it on failure.
pub fn open_input(path: &Path) -> anyhow::Result<File> {
    File::open(path).map_err(|e| input_error(format!("{}: cannot read: {e}", path.display())))
}
