//! The optional `reference` section: published AUC values printed beside
//! ours.

use crate::error::FieldError;
use crate::manifest::raw::{RawReference, RawReferenceRow};
use crate::manifest::{DatasetSpec, DetectorEntry, Reference, ReferenceCell, ReferenceRow};

/// The reference rows, each value paired with its dataset and radius.
pub(super) fn resolve_reference(
    section: RawReference,
    eps_px: &[f64],
    datasets: &[DatasetSpec],
    detectors: &[DetectorEntry],
) -> Result<Reference, FieldError> {
    let rows = section
        .rows
        .into_iter()
        .enumerate()
        .map(|(index, row)| resolve_row(index, row, eps_px, datasets, detectors))
        .collect::<Result<_, _>>()?;
    Ok(Reference {
        source: section.source,
        rows,
    })
}

/// Row `index`: its detector must exist, and each dataset it lists must
/// exist and get one AUC in [0, 1] per radius of `metrics.eps_px`.
fn resolve_row(
    index: usize,
    row: RawReferenceRow,
    eps_px: &[f64],
    datasets: &[DatasetSpec],
    detectors: &[DetectorEntry],
) -> Result<ReferenceRow, FieldError> {
    let path = super::item(&super::path_of(&["reference", "rows"]), index);
    super::require_detector(detectors, &super::field(&path, "detector"), &row.detector)?;
    let auc_path = super::field(&path, "auc");
    let mut cells = Vec::new();
    for (dataset, values) in row.auc.0 {
        let dataset_path = super::field(&auc_path, &dataset);
        super::require_dataset(datasets, &dataset_path, &dataset)?;
        if values.len() != eps_px.len() {
            return Err(FieldError::at(
                &dataset_path,
                format!(
                    "must list one AUC per radius of metrics.eps_px ({}), got {}",
                    eps_px.len(),
                    values.len()
                ),
            ));
        }
        for (&eps_px, &auc) in eps_px.iter().zip(&values) {
            if !(auc.is_finite() && (0.0..=1.0).contains(&auc)) {
                return Err(FieldError::at(
                    &dataset_path,
                    format!("AUC values must be between 0 and 1, got {auc}"),
                ));
            }
            cells.push(ReferenceCell {
                dataset: dataset.clone(),
                eps_px,
                auc,
            });
        }
    }
    Ok(ReferenceRow {
        label: row.label.unwrap_or_else(|| row.detector.clone()),
        detector: row.detector,
        cells,
    })
}
