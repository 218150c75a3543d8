//! Every file format scanloc reads or writes, in one place.
//!
//! - Frames: `.npy` (`uint16`, or `uint32` when a count needs it; shape
//!   `(n, H, W)`, C order) and multi-page TIFF (one page per frame).
//! - Ground truth and localisations: CSV with a header ([`csv_tables`]).
//!
//! Writers never leave a partial file behind: they write to a temporary file
//! in the destination folder and rename it into place only when complete;
//! output folders are written whole or not at all, and a recorded name
//! becomes a file name only through [`safe_file_name`] ([`folders`]).
//! Readers report problems as [`InputError`](crate::error::InputError)s that
//! name the file.

pub(crate) mod acquisition;
pub mod csv_tables;
pub(crate) mod folders;
pub mod localisation_table;
pub mod npy;
pub(crate) mod tiff_stack;
pub mod tracks;

pub use acquisition::{AcquisitionMetadata, MetadataSource};
pub use folders::{PendingFolder, safe_file_name};
pub use tiff_stack::StackSelection;

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;

use crate::error::input_error;
use crate::types::{FrameStack, Recording};

/// The frame file formats, chosen by file extension.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FrameFormat {
    Npy,
    Tiff,
}

impl FrameFormat {
    /// The format a path's extension names (`.npy`, `.tif`, `.tiff`).
    pub(crate) fn from_path(path: &Path) -> anyhow::Result<Self> {
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

/// Reads a frame stack of photon counts from `.npy` or TIFF, by extension.
/// Refuses stacks no command can use (see
/// [`check_stack_shape`](crate::limits::check_stack_shape)): no frames,
/// frames without pixels, or more than the size limits; multi-channel
/// stacks (see [`read_frames_of_channel`]); and values that are not counts
/// (see [`Recording::into_counts`]).
pub fn read_frames(path: &Path) -> anyhow::Result<FrameStack> {
    read_frames_of_channel(path, None)
}

/// [`read_frames`] of one channel of a multi-channel stack (an ImageJ
/// hyperstack, see [`tiff_stack::read_channel`]); `None` for a stack with
/// one channel. A `.npy` stack has one channel (0).
pub fn read_frames_of_channel(path: &Path, channel: Option<usize>) -> anyhow::Result<FrameStack> {
    read_recording_of_channel(path, channel)?
        .into_counts()
        .map_err(|e| input_error(format!("{}: {e:#}", path.display())))
}

/// The frames of one channel of a `.npy` or TIFF stack as stored: photon
/// counts from integer data, real values from float data (see
/// [`Recording`]); otherwise as [`read_frames_of_channel`].
pub fn read_recording_of_channel(path: &Path, channel: Option<usize>) -> anyhow::Result<Recording> {
    let recording = match FrameFormat::from_path(path)? {
        FrameFormat::Npy => match channel {
            None | Some(0) => npy::read_recording(path),
            Some(channel) => Err(input_error(format!(
                "{}: --channel {channel} does not exist; a .npy stack (n, H, W) has one channel (0)",
                path.display()
            ))),
        },
        FrameFormat::Tiff => tiff_stack::read_channel(path, channel),
    }?;
    let (n, height, width) = recording.shape();
    crate::limits::check_stack_shape(&path.display().to_string(), n, height, width)?;
    Ok(recording)
}

/// A recording as a lab's software wrote it: its frames (one channel, one
/// plane) and what the file says about the acquisition.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingFile {
    pub frames: Recording,
    pub metadata: AcquisitionMetadata,
}

/// Reads a recording from `.npy` or TIFF (classic or BigTIFF, 8/16/32/64-bit
/// integer or float pages, ImageJ hyperstacks, ScanImage files) with its
/// acquisition metadata ([`AcquisitionMetadata`]; a `.npy` has none). A
/// multi-channel or multi-plane stack is read at the plane `selection`
/// names and refused without one ([`tiff_stack::read_selected`]); the
/// stack's shape is checked as [`read_frames`] checks it.
pub fn read_recording_file(
    path: &Path,
    selection: &StackSelection,
) -> anyhow::Result<RecordingFile> {
    let (frames, metadata) = match FrameFormat::from_path(path)? {
        FrameFormat::Npy => {
            for (flag, chosen) in [
                ("--channel", selection.channel),
                ("--slice", selection.slice),
            ] {
                if let Some(chosen) = chosen.filter(|&c| c > 0) {
                    return Err(input_error(format!(
                        "{}: {flag} {chosen} does not exist; a .npy stack (n, H, W) has one (0)",
                        path.display()
                    )));
                }
            }
            (npy::read_recording(path)?, AcquisitionMetadata::none())
        }
        FrameFormat::Tiff => tiff_stack::read_selected(path, selection)?,
    };
    let (n, height, width) = frames.shape();
    crate::limits::check_stack_shape(&path.display().to_string(), n, height, width)?;
    Ok(RecordingFile { frames, metadata })
}

/// Writes a frame stack to `.npy` or TIFF, by extension, atomically.
pub fn write_frames(path: &Path, frames: &FrameStack) -> anyhow::Result<()> {
    let mut pending = PendingFile::create(path)?;
    fill_frames(&mut pending, frames)?;
    pending.commit()
}

/// Fills a pending output with a frame stack in the format its extension
/// names.
pub(crate) fn fill_frames(pending: &mut PendingFile, frames: &FrameStack) -> anyhow::Result<()> {
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
///
/// This is the one way scanloc writes a user's output file. It refuses a
/// destination that exists and is not a regular file (a symlink, a FIFO, a
/// device node, a folder) instead of replacing it, and creates the file
/// with mode 0666 minus the umask, as any other program would.
pub(crate) struct PendingFile {
    path: PathBuf,
    temporary: tempfile::NamedTempFile,
}

impl PendingFile {
    /// Starts writing `path` (its folder must exist and be writable).
    pub(crate) fn create(path: &Path) -> anyhow::Result<Self> {
        refuse_special_destination(path)?;
        let folder = match path.parent() {
            Some(parent) if !parent.as_os_str().is_empty() => parent,
            _ => Path::new("."),
        };
        // The extension is kept so that writers which pick a format by file
        // name (the figure backends) see the destination's.
        let suffix = path
            .extension()
            .map(|extension| {
                let mut suffix = std::ffi::OsString::from(".");
                suffix.push(extension);
                suffix
            })
            .unwrap_or_default();
        let mut builder = tempfile::Builder::new();
        builder.prefix(".scanloc-partial-").suffix(&suffix);
        #[cfg(unix)]
        {
            // tempfile's own default is 0600; with 0666 the kernel applies
            // the umask, so outputs get the permissions users expect.
            use std::os::unix::fs::PermissionsExt;
            builder.permissions(std::fs::Permissions::from_mode(0o666));
        }
        let temporary = builder
            .tempfile_in(folder)
            .map_err(|e| input_error(format!("{}: cannot write here: {e}", path.display())))?;
        Ok(Self {
            path: path.to_path_buf(),
            temporary,
        })
    }

    /// The destination.
    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    /// The temporary file's path, for writers that can only write to a
    /// named file (it has the destination's extension).
    pub(crate) fn temporary_path(&self) -> &Path {
        self.temporary.path()
    }

    /// Fills the file through a buffered writer.
    pub(crate) fn fill(
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
    pub(crate) fn commit(self) -> anyhow::Result<()> {
        let path = self.path;
        // Checked again: the destination may have appeared since `create`.
        refuse_special_destination(&path)?;
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

/// Refuses an output path that exists and is not a regular file: renaming
/// over a symlink, FIFO, device node or folder would destroy it (or fail
/// late), and writing through it would write somewhere the user did not
/// name.
fn refuse_special_destination(path: &Path) -> anyhow::Result<()> {
    let Ok(metadata) = std::fs::symlink_metadata(path) else {
        return Ok(());
    };
    let file_type = metadata.file_type();
    if file_type.is_file() {
        return Ok(());
    }
    let kind = if file_type.is_symlink() {
        "a symbolic link"
    } else if file_type.is_dir() {
        "a folder"
    } else {
        special_file_kind(&file_type)
    };
    Err(input_error(format!(
        "{}: is {kind}; refusing to replace it (name a regular file or a new path)",
        path.display()
    )))
}

#[cfg(unix)]
fn special_file_kind(file_type: &std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if file_type.is_fifo() {
        "a FIFO"
    } else if file_type.is_block_device() || file_type.is_char_device() {
        "a device node"
    } else if file_type.is_socket() {
        "a socket"
    } else {
        "not a regular file"
    }
}

#[cfg(not(unix))]
fn special_file_kind(_file_type: &std::fs::FileType) -> &'static str {
    "not a regular file"
}

/// Refuses a command whose outputs name one of its inputs or each other
/// (after resolving `.`, `..` and symlinks, and comparing the files
/// themselves where they exist): writing one would silently destroy the
/// other. `inputs` and `outputs` pair a flag name with its path.
pub(crate) fn refuse_shared_paths(
    inputs: &[(&str, &Path)],
    outputs: &[(&str, &Path)],
) -> anyhow::Result<()> {
    let named: Vec<(&str, &Path, Option<FileIdentity>)> = inputs
        .iter()
        .chain(outputs)
        .map(|&(flag, path)| (flag, path, FileIdentity::of(path)))
        .collect();
    for (index, (output_flag, output, output_identity)) in
        named.iter().enumerate().skip(inputs.len())
    {
        for (other_flag, other, other_identity) in &named[..index] {
            if let (Some(output_identity), Some(other_identity)) = (output_identity, other_identity)
                && output_identity.same_file(other_identity)
            {
                return Err(input_error(format!(
                    "{output_flag} {} is the same file as {other_flag} {}; writing it would destroy the other",
                    output.display(),
                    other.display()
                )));
            }
        }
    }
    Ok(())
}

/// What makes two paths the same file: the canonical path, and for existing
/// files also the device and inode (hard links).
#[derive(Debug)]
struct FileIdentity {
    canonical: PathBuf,
    inode: Option<(u64, u64)>,
}

impl FileIdentity {
    fn of(path: &Path) -> Option<Self> {
        let canonical = canonical_destination(path)?;
        #[cfg(unix)]
        let inode = {
            use std::os::unix::fs::MetadataExt;
            std::fs::metadata(path)
                .ok()
                .map(|metadata| (metadata.dev(), metadata.ino()))
        };
        #[cfg(not(unix))]
        let inode = None;
        Some(Self { canonical, inode })
    }

    fn same_file(&self, other: &FileIdentity) -> bool {
        self.canonical == other.canonical || (self.inode.is_some() && self.inode == other.inode)
    }
}

/// The canonical form of `path`, which need not exist yet: its folder
/// canonicalised plus its file name (following a symlink at the end).
fn canonical_destination(path: &Path) -> Option<PathBuf> {
    if let Ok(canonical) = std::fs::canonicalize(path) {
        return Some(canonical);
    }
    let name = path.file_name()?;
    let folder = match path.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent,
        _ => Path::new("."),
    };
    Some(std::fs::canonicalize(folder).ok()?.join(name))
}

/// Writes `path` through `fill` atomically (see [`PendingFile`]).
pub(crate) fn write_atomically(
    path: &Path,
    fill: impl FnOnce(&mut BufWriter<&mut File>) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let mut pending = PendingFile::create(path)?;
    pending.fill(fill)?;
    pending.commit()
}

/// Writes `bytes` to `path` atomically (see [`write_atomically`]).
pub(crate) fn write_bytes_atomically(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    write_atomically(path, |writer| {
        writer.write_all(bytes)?;
        Ok(())
    })
}

/// Opens a file for reading, with an input error naming it on failure.
pub(crate) fn open_input(path: &Path) -> anyhow::Result<File> {
    File::open(path).map_err(|e| input_error(format!("{}: cannot read: {e}", path.display())))
}
