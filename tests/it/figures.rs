//! Figures are drawn as PNG and SVG with the paper's elements.

use scanloc::progress::hidden;
use scanloc::report::figures::{
    Curve, FramePanel, MarkerKind, frame_panels, histograms, line_chart,
};
use scanloc::sim::{self, Distribution, SimParams};

fn example_panels() -> Vec<FramePanel> {
    [0.0, 0.75, 1.0, 1.75]
        .iter()
        .map(|&d| {
            let params = SimParams {
                diffusion_um2_s: Distribution::Fixed(d),
                margin_px: 4.0,
                brightness: 30.0.into(),
                ..SimParams::default()
            };
            let dataset = sim::simulate(&params, 1, 0..1, &hidden()).unwrap();
            let truth = dataset.truth[0];
            FramePanel {
                title: format!("D = {d} µm²/s"),
                height: params.height,
                width: params.width,
                counts: dataset.frames.frame(0).to_vec(),
                trajectory: sim::trajectories(&params, 1, 0).remove(0),
                markers: vec![
                    (MarkerKind::Start, truth.x_start, truth.y_start),
                    (MarkerKind::End, truth.x_end, truth.y_end),
                    (MarkerKind::Truth, truth.x, truth.y),
                ],
            }
        })
        .collect()
}

fn png_size(path: &std::path::Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[1..4], b"PNG", "{} is not a PNG", path.display());
    let width = u32::from_be_bytes(bytes[16..20].try_into().unwrap());
    let height = u32::from_be_bytes(bytes[20..24].try_into().unwrap());
    (width, height)
}

#[test]
fn example_frames_curves_and_histograms_are_written_in_both_formats() {
    let temporary = tempfile::tempdir().unwrap();
    // SCANLOC_KEEP_FIGURES=DIR keeps the figures for a person to look at.
    let kept =
        std::env::var_os(scanloc::env_vars::SCANLOC_KEEP_FIGURES).map(std::path::PathBuf::from);
    let dir = kept.as_deref().unwrap_or(temporary.path());
    let frames = dir.join("example_frames");
    frame_panels(&frames, &example_panels()).unwrap();
    assert_eq!(png_size(&frames.with_extension("png")), (1200, 340));
    let svg = std::fs::read_to_string(frames.with_extension("svg")).unwrap();
    assert!(svg.contains("<svg") && svg.contains("D = 1.75"));
    // The trajectory is a polyline in the SVG.
    assert!(svg.contains("polyline") || svg.contains("<path"));

    let curve = dir.join("pr");
    let curves = vec![Curve {
        label: "ε = 1 px".into(),
        points: vec![(0.0, 1.0), (0.5, 0.8), (1.0, 0.5)],
    }];
    line_chart(
        &curve,
        "PR",
        ("recall", "precision"),
        ((0.0, 1.0), (0.0, 1.0)),
        &curves,
    )
    .unwrap();
    assert_eq!(png_size(&curve.with_extension("png")), (640, 480));
    assert!(
        std::fs::read_to_string(curve.with_extension("svg"))
            .unwrap()
            .contains("ε = 1 px")
    );

    let hist = dir.join("errors");
    histograms(
        &hist,
        "errors",
        "px",
        5.0,
        20,
        &[("CNN".into(), vec![0.1, 0.5, 0.7, 9.0])],
    )
    .unwrap();
    assert!(hist.with_extension("png").exists() && hist.with_extension("svg").exists());
}
