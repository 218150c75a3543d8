//! `scanloc track`: a simulated recording of a microscope no manifest uses
//! in, tracks and a bias-corrected D out; and its refusals.

use std::path::Path;

use super::common::{scanloc, stderr, stdout};

const SCOPE: &str = "microscope:
  height: 32
  width: 32
  pixel_size_um: 0.1
  dwell_us: 4.0
  retrace_ms: 0.6
  sigma_xy_um: 0.21
  sigma_z_um: 1.36
  background: 8.4
  brightness: 7.5
";

fn simulate(dir: &Path, frames: &str, size: &str) -> String {
    let out = dir.join("rec.npy");
    let made = scanloc(&[
        "simulate-recording",
        "--height",
        size,
        "--width",
        size,
        "--pixel-size-um",
        "0.1",
        "--dwell-us",
        "4",
        "--retrace-ms",
        "0.6",
        "--brightness",
        "7.5",
        "--frames",
        frames,
        "--diffusion",
        "0.5",
        "--seed",
        "3",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(made.status.success(), "{}", stderr(&made));
    out.to_str().unwrap().to_string()
}

#[test]
fn track_reads_d_of_a_small_microscope_within_its_interval() {
    let dir = tempfile::tempdir().unwrap();
    let scope = dir.path().join("scope.yaml");
    std::fs::write(&scope, SCOPE).unwrap();
    let recording = simulate(dir.path(), "1500", "32");
    let out = dir.path().join("out");
    let run = scanloc(&[
        "track",
        &recording,
        "--microscope",
        scope.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(run.status.success(), "{}", stderr(&run));
    let json: serde_json::Value = serde_json::from_str(&stdout(&run)).unwrap();
    let ensemble = &json["ensemble"];
    let d = ensemble["d_um2_s"].as_f64().unwrap();
    let se = ensemble["standard_error"].as_f64().unwrap();
    assert!(json["bias_corrected"].as_bool().unwrap());
    // Tolerance: the corrected D within 3 of its standard errors (and
    // 25 %) of the true 0.5 µm²/s.
    assert!(
        (d - 0.5).abs() < (3.0 * se).min(0.125),
        "D {d} ± {se}: {json}"
    );
    assert!(ensemble["low_95"].as_f64().unwrap() < d);
    assert!(ensemble["high_95"].as_f64().unwrap() > d);
    let tracks = std::fs::read_to_string(out.join("tracks.csv")).unwrap();
    assert!(tracks.starts_with("frame,x,y,"), "{}", &tracks[..80]);
    assert!(tracks.lines().next().unwrap().ends_with(",particle"));
    let diffusion = std::fs::read_to_string(out.join("diffusion.csv")).unwrap();
    assert!(diffusion.contains("\nensemble-corrected,"), "{diffusion}");
    let settings: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("settings.json")).unwrap()).unwrap();
    assert_eq!(settings["detector"]["diameter"], 7);
}

#[test]
fn track_refuses_bad_input_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let scope = dir.path().join("scope.yaml");
    std::fs::write(&scope, SCOPE).unwrap();
    let recording = simulate(dir.path(), "20", "24");
    let out = dir.path().join("out");
    let refused = |args: &[&str], expected: &str| {
        let run = scanloc(args);
        assert_eq!(run.status.code(), Some(2), "{}", stderr(&run));
        let message = stderr(&run);
        assert_eq!(message.trim().lines().count(), 1, "{message}");
        assert!(message.contains(expected), "{message}");
        assert!(!out.exists());
    };
    // 24 × 24 frames, a 32 × 32 microscope.
    refused(
        &[
            "track",
            &recording,
            "--microscope",
            scope.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        "height/width",
    );
    // The output folder holds the recording.
    refused(
        &[
            "track",
            &recording,
            "--microscope",
            scope.to_str().unwrap(),
            "--out",
            dir.path().to_str().unwrap(),
            "--height",
            "24",
            "--width",
            "24",
        ],
        "holds the recording",
    );
    // A constant recording.
    let constant = dir.path().join("constant.npy");
    let mut file = std::fs::File::create(&constant).unwrap();
    use npyz::WriterBuilder;
    let mut writer = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&[5, 32, 32])
        .writer(&mut file)
        .begin_nd()
        .unwrap();
    for _ in 0..5 * 32 * 32 {
        writer.push(&7u32).unwrap();
    }
    writer.finish().unwrap();
    refused(
        &[
            "track",
            constant.to_str().unwrap(),
            "--microscope",
            scope.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        "nothing to track",
    );
    // A microscope without its timing.
    let bare = dir.path().join("bare.yaml");
    std::fs::write(&bare, "microscope:\n  height: 24\n  width: 24\n").unwrap();
    refused(
        &[
            "track",
            &recording,
            "--microscope",
            bare.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        "pixel_size_um",
    );
}
