//! The `metrics` section: the matching radii of the AUC table and the
//! detectors' score thresholds.

use crate::error::{FieldError, Segment};
use crate::limits::MAX_RADII;
use crate::manifest::{DetectorEntry, MetricsSpec};

/// Checks the radii (1 to [`MAX_RADII`] distinct positive numbers of
/// pixels) and the score thresholds (finite, of detectors of the manifest).
pub(super) fn check_metrics(
    metrics: &MetricsSpec,
    detectors: &[DetectorEntry],
) -> Result<(), FieldError> {
    for (name, &threshold) in &metrics.score_thresholds {
        let path = super::path_of(&["metrics", "score_thresholds", name]);
        super::require_detector(detectors, &path, name)?;
        if !threshold.is_finite() {
            return Err(FieldError::at(
                &path,
                format!("must be a finite score, got {threshold}"),
            ));
        }
    }
    let path = super::path_of(&["metrics", "eps_px"]);
    if metrics.eps_px.is_empty() {
        return Err(FieldError::at(&path, "must list at least one radius"));
    }
    if metrics.eps_px.len() > MAX_RADII {
        return Err(FieldError::at(
            &path,
            format!("must list at most {MAX_RADII} radii"),
        ));
    }
    for (index, &eps) in metrics.eps_px.iter().enumerate() {
        let radius_path: Vec<Segment> = super::item(&path, index);
        crate::limits::check_radius(eps).map_err(|e| FieldError::at(&radius_path, e))?;
        if metrics.eps_px[..index].contains(&eps) {
            return Err(FieldError::at(
                &radius_path,
                format!("duplicate radius {eps}"),
            ));
        }
    }
    Ok(())
}
