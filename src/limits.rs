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

/// Checks a frame count (`name` names the field or flag): 1 to
/// [`MAX_FRAMES`].
pub fn check_frame_count(name: &str, frames: u64) -> Result<usize, FieldError> {
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
pub fn check_frame_side(name: &str, pixels: usize) -> Result<(), FieldError> {
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
pub fn check_dataset_pixels(
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
pub fn check_frame_not_empty(height: usize, width: usize) -> Result<(), FieldError> {
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
pub fn check_feature_px(name: &str, pixels: f64) -> Result<(), FieldError> {
    if pixels > MAX_FEATURE_PX as f64 {
        return Err(FieldError::new(
            name,
            format!("must be at most {MAX_FEATURE_PX} pixels, got {pixels}"),
        ));
    }
    Ok(())
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
}
