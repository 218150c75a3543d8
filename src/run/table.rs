//! The AUC table in the paper's layout: one row per detector, columns
//! grouped by test set (labelled by its D when fixed) and, within each, one
//! column per ε. Reference rows (e.g. the paper's) follow the detector they
//! compare with.

use crate::manifest::Reference;
use crate::registry::AucRow;

/// Renders `rows` as text; `reference` rows are printed under their
/// detector when given.
pub fn render(rows: &[AucRow], reference: Option<&Reference>) -> String {
    if rows.is_empty() {
        return "no evaluations: the manifest scores no detector on any dataset\n".to_string();
    }
    let mut detectors: Vec<&str> = Vec::new();
    let mut datasets: Vec<(&str, Option<f64>)> = Vec::new();
    let mut eps: Vec<f64> = Vec::new();
    for row in rows {
        if !detectors.contains(&row.detector.as_str()) {
            detectors.push(&row.detector);
        }
        if !datasets.iter().any(|(d, _)| *d == row.dataset) {
            datasets.push((&row.dataset, row.diffusion));
        }
        if !eps.contains(&row.eps_px) {
            eps.push(row.eps_px);
        }
    }
    let cell = 6;
    let group = eps.len() * (cell + 1) + 2;
    let mut label_width = detectors.iter().map(|d| d.len()).max().unwrap_or(0).max(10);
    if let Some(reference) = reference {
        for row in &reference.rows {
            label_width = label_width.max(row.label.len() + 9);
        }
    }
    let mut out = String::new();
    out.push_str(&format!("{:<label_width$}", "AUC"));
    for (name, diffusion) in &datasets {
        let title = match diffusion {
            // The paper's labels: 0.75, 1.00, 1.75.
            Some(d) if (d * 100.0).round() == d * 100.0 => format!("D = {d:.2} µm²/s"),
            Some(d) => format!("D = {d} µm²/s"),
            None => name.to_string(),
        };
        out.push_str(&format!("  {:<w$}", title, w = group - 2));
    }
    out.push('\n');
    out.push_str(&format!("{:<label_width$}", "ε (px)"));
    for _ in &datasets {
        out.push_str("  ");
        for e in &eps {
            out.push_str(&format!("{:<cell$} ", format!("{e}")));
        }
    }
    out.push('\n');
    let line = |label: &str, value: &dyn Fn(&str, f64) -> Option<f64>| -> String {
        let mut text = format!("{label:<label_width$}");
        for (name, _) in &datasets {
            text.push_str("  ");
            for &e in &eps {
                let shown = match value(name, e) {
                    Some(v) => format!("{v:.3}"),
                    None => "-".to_string(),
                };
                text.push_str(&format!("{shown:<cell$} "));
            }
        }
        text.trim_end().to_string() + "\n"
    };
    for detector in &detectors {
        out.push_str(&line(detector, &|dataset, e| {
            rows.iter()
                .find(|r| r.detector == *detector && r.dataset == dataset && r.eps_px == e)
                .map(|r| r.auc)
        }));
        if let Some(reference) = reference {
            for row in reference.rows.iter().filter(|r| r.detector == *detector) {
                out.push_str(&line(&format!("  paper: {}", row.label), &|dataset, e| {
                    row.auc(dataset, e)
                }));
            }
        }
    }
    if let Some(reference) = reference
        && !reference.source.is_empty()
    {
        out.push_str(&format!("(paper: {})\n", reference.source));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lays_out_detectors_by_dataset_and_eps() {
        let mut rows = Vec::new();
        for (detector, base) in [("trackpy", 0.1), ("cnn", 0.5)] {
            for (dataset, d) in [("t1", Some(0.75)), ("t2", None)] {
                for eps in [1.0, 2.0] {
                    rows.push(AucRow {
                        detector: detector.into(),
                        dataset: dataset.into(),
                        diffusion: d,
                        eps_px: eps,
                        auc: base + eps / 10.0,
                        evaluation_key: String::new(),
                    });
                }
            }
        }
        let text = render(&rows, None);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4, "{text}");
        assert!(lines[0].contains("D = 0.75 µm²/s") && lines[0].contains("t2"));
        assert!(
            lines[2].starts_with("trackpy") && lines[2].contains("0.200  0.300    0.200  0.300"),
            "{text}"
        );
        assert!(
            lines[3].starts_with("cnn") && lines[3].contains("0.600"),
            "{text}"
        );
    }
}
