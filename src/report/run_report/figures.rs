//! The report's figures: example frames, localisation panels,
//! precision–recall curves, reliability diagrams and error histograms
//! (drawn with [`crate::report::figures`]).

use std::path::Path;

use crate::progress::hidden;
use crate::registry::Registry;
use crate::report::figures::{Curve, FramePanel, MarkerKind, frame_panels, histograms, line_chart};
use crate::report::recorded::RecordedManifest;
use crate::run::load_artefact;
use crate::sim::{self, Distribution, SimParams};
use crate::types::{Dataset, DetectorKind, Prediction};

use super::Evaluation;
use super::tables::or_dash;

/// One reliability diagram per dataset with a probability-scored
/// evaluation: each detector's mean score against observed frequency per
/// non-empty bin, beside the diagonal of a calibrated score.
pub(super) fn reliability_diagrams(
    out: &Path,
    evaluations: &[Evaluation],
) -> anyhow::Result<Vec<String>> {
    let mut files = Vec::new();
    let mut datasets: Vec<&str> = Vec::new();
    for e in evaluations {
        if e.score.reliability.is_some() && !datasets.contains(&e.dataset.as_str()) {
            datasets.push(&e.dataset);
        }
    }
    for dataset in datasets {
        let mut curves = vec![Curve {
            label: "calibrated".to_string(),
            points: vec![(0.0, 0.0), (1.0, 1.0)],
        }];
        for e in evaluations.iter().filter(|e| e.dataset == dataset) {
            let Some(reliability) = &e.score.reliability else {
                continue;
            };
            curves.push(Curve {
                label: format!(
                    "{} (ECE {})",
                    e.detector,
                    or_dash(reliability.expected_calibration_error)
                ),
                points: reliability
                    .bins
                    .iter()
                    .filter_map(|b| Some((b.mean_score?, b.observed_frequency?)))
                    .collect(),
            });
        }
        let file = crate::io::safe_file_name(&format!("reliability_{dataset}"));
        line_chart(
            &out.join(&file),
            &format!("{dataset}: reliability of the score (within 1 px)"),
            (
                "score (predicted probability)",
                "observed frequency within 1 px",
            ),
            ((0.0, 1.0), (0.0, 1.05)),
            &curves,
        )?;
        files.push(file);
    }
    Ok(files)
}

pub(super) fn example_frames(out: &Path, microscope: &SimParams, seed: u64) -> anyhow::Result<()> {
    let panels = [0.0, 0.75, 1.0, 1.75]
        .iter()
        .enumerate()
        .map(|(i, &d)| {
            let params = SimParams {
                diffusion_um2_s: Distribution::Fixed(d),
                emitters: 1.into(),
                ..microscope.clone()
            };
            let dataset = sim::simulate(&params, seed, i..i + 1, &hidden())?;
            let truth = dataset.truth[0];
            Ok(FramePanel {
                title: format!("D = {d} µm²/s"),
                height: params.height,
                width: params.width,
                counts: dataset.frames.frame(0).to_vec(),
                trajectory: sim::trajectories(&params, seed, i).remove(0),
                markers: vec![
                    (MarkerKind::Start, truth.x_start, truth.y_start),
                    (MarkerKind::End, truth.x_end, truth.y_end),
                    (MarkerKind::Truth, truth.x, truth.y),
                ],
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    frame_panels(&out.join("example_frames"), &panels)
}

fn top_per_frame(predictions: &[Prediction], frames: usize) -> Vec<Option<Prediction>> {
    let mut top: Vec<Option<Prediction>> = vec![None; frames];
    for p in predictions {
        if p.frame < frames && top[p.frame].is_none_or(|best| p.score > best.score) {
            top[p.frame] = Some(*p);
        }
    }
    top
}

pub(super) fn localisation_panels(
    registry: &Registry,
    out: &Path,
    resolved: &RecordedManifest,
    evaluations: &[Evaluation],
) -> anyhow::Result<bool> {
    // The first dataset with a fixed D that every detector scored.
    let Some(first) = evaluations.iter().find(|e| e.diffusion.is_some()) else {
        return Ok(false);
    };
    let Some(dataset_entry) = resolved.dataset(&first.dataset) else {
        return Ok(false);
    };
    let (params, seed) = (&dataset_entry.params, dataset_entry.seed);
    let dataset: Dataset = load_artefact(registry, &first.dataset_key)?
        .dataset()?
        .as_ref()
        .clone();
    let mut tops = Vec::new();
    for e in evaluations.iter().filter(|e| e.dataset == first.dataset) {
        let predictions = load_artefact(registry, &e.predictions_key)?
            .predictions()?
            .as_ref()
            .clone();
        let kind = if e.detector_kind == Some(DetectorKind::Cnn) {
            MarkerKind::Cnn
        } else {
            MarkerKind::CrockerGrier
        };
        tops.push((kind, top_per_frame(&predictions, dataset.frames.n)));
    }
    let panels: Vec<FramePanel> = (0..dataset.frames.n.min(4))
        .map(|i| {
            let truth = dataset.truth.iter().find(|t| t.frame == i).copied();
            let mut markers = Vec::new();
            if let Some(t) = truth {
                markers.push((MarkerKind::Truth, t.x, t.y));
            }
            for (kind, top) in &tops {
                if let Some(p) = top[i] {
                    markers.push((*kind, p.x, p.y));
                }
            }
            FramePanel {
                title: format!("{} frame {i}", first.dataset),
                height: dataset.frames.height,
                width: dataset.frames.width,
                counts: dataset.frames.frame(i).to_vec(),
                trajectory: sim::trajectories(params, seed, i)
                    .into_iter()
                    .next()
                    .unwrap_or_default(),
                markers,
            }
        })
        .collect();
    frame_panels(&out.join("localisations"), &panels)?;
    Ok(true)
}

pub(super) fn precision_recall_curves(
    out: &Path,
    evaluations: &[Evaluation],
) -> anyhow::Result<Vec<String>> {
    let mut files = Vec::new();
    let mut datasets: Vec<&str> = Vec::new();
    for e in evaluations {
        if !datasets.contains(&e.dataset.as_str()) {
            datasets.push(&e.dataset);
        }
    }
    for dataset in datasets {
        let of_dataset: Vec<&Evaluation> = evaluations
            .iter()
            .filter(|e| e.dataset == dataset)
            .collect();
        let eps: Vec<f64> = of_dataset[0]
            .score
            .per_eps
            .iter()
            .map(|s| s.eps_px)
            .collect();
        for e in eps {
            let curves: Vec<Curve> = of_dataset
                .iter()
                .filter_map(|ev| {
                    let per_eps = ev.score.per_eps.iter().find(|s| s.eps_px == e)?;
                    if per_eps.curve.is_empty() {
                        return None;
                    }
                    // Thin long curves: every point is not needed to draw them.
                    let step = (per_eps.curve.len() / 2000).max(1);
                    Some(Curve {
                        label: format!("{} (AUC {:.2})", ev.detector, per_eps.auc),
                        points: per_eps
                            .curve
                            .iter()
                            .step_by(step)
                            .map(|p| (p.recall, p.precision))
                            .collect(),
                    })
                })
                .collect();
            if curves.is_empty() {
                continue;
            }
            let file = crate::io::safe_file_name(&format!("pr_{dataset}_eps{e}"));
            line_chart(
                &out.join(&file),
                &format!("{dataset}, ε = {e} px"),
                ("recall", "precision"),
                ((0.0, 1.0), (0.0, 1.05)),
                &curves,
            )?;
            files.push(file);
        }
    }
    Ok(files)
}

pub(super) fn error_histograms(
    registry: &Registry,
    out: &Path,
    evaluations: &[Evaluation],
) -> anyhow::Result<Vec<String>> {
    let mut files = Vec::new();
    let mut datasets: Vec<(&str, &str)> = Vec::new();
    for e in evaluations {
        if !datasets.iter().any(|(d, _)| *d == e.dataset) {
            datasets.push((&e.dataset, &e.dataset_key));
        }
    }
    for (dataset, key) in datasets {
        let data = load_artefact(registry, key)?.dataset()?.as_ref().clone();
        if data.truth.is_empty() {
            // A set of empty frames: no distance to a QD to draw.
            continue;
        }
        let mut series = Vec::new();
        for e in evaluations.iter().filter(|e| e.dataset == dataset) {
            let predictions = load_artefact(registry, &e.predictions_key)?
                .predictions()?
                .as_ref()
                .clone();
            let top = top_per_frame(&predictions, data.frames.n);
            let errors: Vec<f64> = data
                .truth
                .iter()
                .filter_map(|t| {
                    top[t.frame].map(|p| ((p.x - t.x).powi(2) + (p.y - t.y).powi(2)).sqrt())
                })
                .collect();
            series.push((e.detector.clone(), errors));
        }
        let file = crate::io::safe_file_name(&format!("errors_{dataset}"));
        histograms(
            &out.join(&file),
            &format!("{dataset}: distance of the top prediction to the trajectory centroid"),
            "distance (px); the last bin holds all beyond",
            6.0,
            24,
            &series,
        )?;
        files.push(file);
    }
    Ok(files)
}
