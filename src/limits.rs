//! Size limits shared by every entry point: the manifest, the command line
//! and the file readers check the same constants through the same
//! functions, so a size the manifest refuses is refused on the command line
//! too (and the other way round).
//!
//! The limits are far beyond the paper's experiments (24 × 25 pixel frames,
//! thousands of frames) and low enough that no allocation sized by them can
//! exceed what a workstation holds.

use crate::error::{FieldError, input_error};

/// Largest frame count of a dataset (simulated or read) and the bound on
/// frame numbers in truth and localisation files.
pub const MAX_FRAMES: usize = 10_000_000;
/// Largest number of pixels (frames × height × width) one dataset may hold:
/// 2³¹ counts are 8 GiB in memory, more than the machines this runs on have.
pub const MAX_DATASET_PIXELS: usize = 1 << 31;
/// Largest frame side (height or width) in pixels.
pub const MAX_FRAME_SIDE: usize = 16_384;
/// Largest feature size in pixels (a Crocker–Grier diameter, smoothing
/// size or separation, a CNN peak window): TrackPy's features are a few
/// pixels across; this bound keeps the per-feature masks small.
pub const MAX_FEATURE_PX: usize = 1_001;

/// Longest cell, in characters, of a table printed for people (`registry
/// runs`, `registry sql`, the AUC table): longer text is cut with an
/// ellipsis by [`display_cell`], so a recorded name of any length prints as
/// one bounded line. `--json` prints cells whole.
pub(crate) const MAX_CELL_CHARS: usize = 200;
/// Longest record (row) of a CSV table, in bytes: a row of truth or
/// localisations is a few hundred bytes, so a longer one is a file that is
/// not such a table, refused before it is read into memory.
pub(crate) const MAX_CSV_RECORD_BYTES: usize = 1 << 20;
/// Largest manifest (YAML) read, in bytes: manifests are a few kilobytes,
/// so a larger file (or a device such as `/dev/zero`) is refused after
/// reading this much rather than read for ever.
pub(crate) const MAX_MANIFEST_BYTES: u64 = 4 << 20;
/// Most memory one command may plan to hold for a dataset it makes
/// (`simulate`'s frames and ground truth), checked before allocating;
/// [`check_memory`] also checks the machine's available memory.
pub(crate) const MAX_IN_MEMORY_BYTES: u64 = 16 << 30;
/// Most threads of the pool scanloc computes on (`RAYON_NUM_THREADS`):
/// far more than the CPUs of any machine this runs on, few enough to start
/// at once.
pub(crate) const MAX_THREADS: usize = 1024;

/// Largest matching radius ε of the metric, and gate of the tracking
/// measures, px: far beyond any frame.
pub(crate) const MAX_EPS_PX: f64 = 1e6;
/// Checks a matching radius ε: a positive number of pixels up to
/// [`MAX_EPS_PX`]; the error is the message alone, for the caller to name
/// the setting (a flag, or a manifest's `metrics.eps_px[i]`).
pub(crate) fn check_radius(eps: f64) -> Result<(), String> {
    if eps.is_finite() && eps > 0.0 && eps <= MAX_EPS_PX {
        return Ok(());
    }
    let shown = if eps.abs() > MAX_EPS_PX {
        format!("{eps:e}")
    } else {
        eps.to_string()
    };
    Err(format!(
        "must be a positive number of pixels (at most {MAX_EPS_PX:e}), got {shown}"
    ))
}

/// Most matching radii one score lists (columns of the AUC table per
/// dataset), in a manifest and on the command line.
pub(crate) const MAX_RADII: usize = 32;

/// Largest search range of a linker, in the localisation table's units
/// (pixels, or whatever a user's table is in): far beyond any field, and
/// small enough that a link's cost, which multiplies two variances of its
/// square, stays finite. The LAP's step variance is bounded by its square.
pub const MAX_SEARCH_RANGE: f64 = 1e9;
/// Largest diffusion coefficient a linker is told, µm²/s: a thousand times
/// a small molecule's in water.
pub const MAX_DIFFUSION_UM2_S: f64 = 1e6;
/// Largest LAP gate, in standard deviations of a link's displacement.
pub const MAX_GATE_SIGMAS: f64 = 1e3;

/// Checks a bounded setting (`name` names the field or flag): a finite
/// number > 0 and at most `max` (one of the bounds above).
pub fn check_positive_at_most(name: &str, value: f64, max: f64) -> Result<f64, FieldError> {
    if !(value.is_finite() && value > 0.0) {
        return Err(FieldError::new(
            name,
            format!(
                "must be a finite number > 0, got {}",
                crate::error::readable(value)
            ),
        ));
    }
    if value > max {
        return Err(FieldError::new(
            name,
            format!(
                "must be at most {max:e}, got {}",
                crate::error::readable(value)
            ),
        ));
    }
    Ok(value)
}

/// Checks a frame count (`name` names the field or flag): 1 to
/// [`MAX_FRAMES`].
pub(crate) fn check_frame_count(name: &str, frames: u64) -> Result<usize, FieldError> {
    if frames == 0 {
        return Err(FieldError::new(name, "must be a positive integer"));
    }
    if frames > MAX_FRAMES as u64 {
        return Err(FieldError::new(
            name,
            format!("must be at most {MAX_FRAMES}, got {frames}"),
        ));
    }
    Ok(frames as usize)
}

/// Checks a frame side (`name` names the field or flag): 1 to
/// [`MAX_FRAME_SIDE`] pixels.
pub(crate) fn check_frame_side(name: &str, pixels: usize) -> Result<(), FieldError> {
    if pixels == 0 || pixels > MAX_FRAME_SIDE {
        return Err(FieldError::new(
            name,
            format!("must be between 1 and {MAX_FRAME_SIDE} pixels, got {pixels}"),
        ));
    }
    Ok(())
}

/// Checks that `frames` frames of `height × width` pixels stay within
/// [`MAX_DATASET_PIXELS`]; the error is about `name` (the frame count's
/// field or flag).
pub(crate) fn check_dataset_pixels(
    name: &str,
    frames: usize,
    height: usize,
    width: usize,
) -> Result<(), FieldError> {
    let pixels = frames
        .checked_mul(height)
        .and_then(|p| p.checked_mul(width));
    if pixels.is_none_or(|p| p > MAX_DATASET_PIXELS) {
        return Err(FieldError::new(
            name,
            format!(
                "{frames} frames of {height}×{width} pixels exceed the limit of {MAX_DATASET_PIXELS} pixels per dataset"
            ),
        ));
    }
    Ok(())
}

/// Checks a dataset of `frames` frames of `height × width` pixels asked for
/// by flag or field `name`: [`check_frame_count`] and
/// [`check_dataset_pixels`], the checks a manifest's datasets pass.
pub fn check_dataset_size(
    name: &str,
    frames: usize,
    height: usize,
    width: usize,
) -> Result<(), FieldError> {
    check_frame_count(name, frames as u64)?;
    check_dataset_pixels(name, frames, height, width)
}

/// Checks a frame stack's shape as read from a file: at least one frame,
/// no side of zero or above [`MAX_FRAME_SIDE`], at most [`MAX_FRAMES`]
/// frames and [`MAX_DATASET_PIXELS`] pixels. `source` names the file.
pub fn check_stack_shape(
    source: &str,
    frames: usize,
    height: usize,
    width: usize,
) -> anyhow::Result<()> {
    let located = |e: FieldError| input_error(format!("{source}: {e}"));
    check_frame_not_empty(height, width).map_err(located)?;
    if frames == 0 {
        return Err(input_error(format!("{source}: contains no frames")));
    }
    check_frame_side("frame height", height).map_err(located)?;
    check_frame_side("frame width", width).map_err(located)?;
    check_dataset_size("frame count", frames, height, width).map_err(located)
}

/// Refuses frames without pixels (`height` or `width` 0): no detector can
/// look for anything in them, and saying so beats an empty result.
pub(crate) fn check_frame_not_empty(height: usize, width: usize) -> Result<(), FieldError> {
    if height == 0 || width == 0 {
        return Err(FieldError::at(
            &[],
            format!(
                "frames of {height}×{width} pixels are empty; every frame needs at least one row and one column"
            ),
        ));
    }
    Ok(())
}

/// Checks a size-like parameter in pixels: at most [`MAX_FEATURE_PX`].
pub(crate) fn check_feature_px(name: &str, pixels: f64) -> Result<(), FieldError> {
    if pixels > MAX_FEATURE_PX as f64 {
        return Err(FieldError::new(
            name,
            format!("must be at most {MAX_FEATURE_PX} pixels, got {pixels}"),
        ));
    }
    Ok(())
}

/// `text` as a table cell shows it: whole up to [`MAX_CELL_CHARS`]
/// characters, else its first `MAX_CELL_CHARS − 1` and `…`.
pub(crate) fn display_cell(text: &str) -> std::borrow::Cow<'_, str> {
    match text.char_indices().nth(MAX_CELL_CHARS - 1) {
        Some((cut, _)) if text[cut..].chars().nth(1).is_some() => {
            std::borrow::Cow::Owned(format!("{}…", &text[..cut]))
        }
        _ => std::borrow::Cow::Borrowed(text),
    }
}

/// The memory the kernel says can be allocated without swapping
/// (`MemAvailable` of `/proc/meminfo`, in bytes); `None` where there is no
/// such file or line.
pub fn available_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kib.checked_mul(1024)
}

/// Checks that `bytes`, the memory a command estimates it will hold for
/// what flag or field `name` asks, stays within [`MAX_IN_MEMORY_BYTES`] and
/// within `available` (the machine's available memory, when known), so
/// that an oversized request is refused before anything is allocated.
pub fn check_memory(name: &str, bytes: u64, available: Option<u64>) -> Result<(), FieldError> {
    let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
    if bytes > MAX_IN_MEMORY_BYTES {
        return Err(FieldError::new(
            name,
            format!(
                "needs about {:.1} GiB of memory, more than the limit of {:.0} GiB",
                gib(bytes),
                gib(MAX_IN_MEMORY_BYTES)
            ),
        ));
    }
    if let Some(available) = available
        && bytes > available
    {
        return Err(FieldError::new(
            name,
            format!(
                "needs about {:.1} GiB of memory, more than the {:.1} GiB this machine has available (MemAvailable)",
                gib(bytes),
                gib(available)
            ),
        ));
    }
    Ok(())
}

/// Checks the value of the thread-count variable `name`
/// (`RAYON_NUM_THREADS`, the size of the pool built at the first parallel
/// step): a number above [`MAX_THREADS`] is refused rather than a billion
/// threads started. Empty, 0 or not a number leave rayon's default (one
/// thread per CPU), as rayon itself does.
pub(crate) fn check_thread_count(name: &str, value: &std::ffi::OsStr) -> anyhow::Result<()> {
    let text = value.to_string_lossy();
    match text.parse::<u128>() {
        Ok(threads) if threads > MAX_THREADS as u128 => Err(input_error(format!(
            "{name}={text}: at most {MAX_THREADS} threads (0 or unset: one per CPU)"
        ))),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_refuse_sizes_beyond_them_and_accept_those_at_them() {
        assert!(check_frame_count("f", MAX_FRAMES as u64).is_ok());
        assert!(check_frame_count("f", MAX_FRAMES as u64 + 1).is_err());
        assert!(check_frame_count("f", u64::MAX).is_err());
        assert!(check_frame_count("f", 0).is_err());
        assert!(check_dataset_pixels("f", 1 << 11, 1 << 10, 1 << 10).is_ok());
        assert!(check_dataset_pixels("f", (1 << 11) + 1, 1 << 10, 1 << 10).is_err());
        assert!(check_dataset_pixels("f", usize::MAX, 2, 2).is_err());
        assert!(check_stack_shape("x", 3, 5, 0).is_err());
        assert!(check_stack_shape("x", 3, 0, 5).is_err());
        assert!(check_stack_shape("x", 0, 5, 5).is_err());
        assert!(check_stack_shape("x", 3, 5, 5).is_ok());
        assert!(check_feature_px("d", MAX_FEATURE_PX as f64).is_ok());
        assert!(check_feature_px("d", 4_000_000_001.0).is_err());
    }

    #[test]
    fn cells_are_cut_to_their_bound_with_an_ellipsis() {
        let at_bound = "é".repeat(MAX_CELL_CHARS);
        assert_eq!(display_cell(&at_bound), at_bound.as_str());
        for length in [MAX_CELL_CHARS + 1, 70_000] {
            let shown = display_cell(&"x".repeat(length)).into_owned();
            assert_eq!(shown.chars().count(), MAX_CELL_CHARS);
            assert!(shown.ends_with('…'));
        }
        assert_eq!(display_cell(""), "");
    }

    #[test]
    fn memory_beyond_the_limit_or_the_machine_is_refused_naming_the_flag() {
        assert!(check_memory("--frames", 1 << 20, None).is_ok());
        assert!(check_memory("--frames", 1 << 20, Some(2 << 20)).is_ok());
        let error = check_memory("--frames", 3 << 20, Some(2 << 20)).unwrap_err();
        assert!(error.to_string().contains("--frames"), "{error}");
        assert!(error.to_string().contains("available"), "{error}");
        let error = check_memory("--frames", MAX_IN_MEMORY_BYTES + 1, None).unwrap_err();
        assert!(error.to_string().contains("limit"), "{error}");
        assert!(check_memory("--frames", u64::MAX, Some(u64::MAX)).is_err());
    }

    #[test]
    fn thread_counts_above_the_bound_are_refused_and_others_left_to_rayon() {
        let check = |text: &str| check_thread_count("T", std::ffi::OsStr::new(text));
        for refused in [
            "1025",
            "1000000000",
            "340282366920938463463374607431768211455",
        ] {
            let error = check(refused).unwrap_err();
            assert!(error.to_string().starts_with("T="), "{error}");
            assert_eq!(crate::error::exit_code(&error), 2);
        }
        for left in ["", "0", "1", "1024", "1e9", "-3", "many"] {
            assert!(check(left).is_ok(), "{left}");
        }
    }
}
