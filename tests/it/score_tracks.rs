//! `scanloc score-tracks` (docs/tracking.md#tracking-metrics) end to end:
//! a tiny simulated recording, its truth positions linked by `scanloc link`
//! and scored through the command, the link figures checked against a count
//! made here from the QD ids the link carries through, and bad input.

use std::collections::BTreeMap;
use std::path::Path;

/// `scanloc score-tracks --tracks TRACKS --truth TRUTH EXTRA…`, in
/// process: (exit code, stdout, stderr).
fn score_tracks(tracks: &Path, truth: &Path, extra: &[&str]) -> (u8, String, String) {
    let mut args = vec![
        "score-tracks",
        "--tracks",
        tracks.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    crate::common::cli_in_process(&args)
}

fn score_json(tracks: &Path, truth: &Path, extra: &[&str]) -> serde_json::Value {
    let mut with_json = vec!["--json"];
    with_json.extend_from_slice(extra);
    let (code, out, err) = score_tracks(tracks, truth, &with_json);
    assert_eq!(code, 0, "{err}");
    serde_json::from_str(&out).expect("score-tracks --json prints JSON")
}

/// The truth file's rows as `frame,x,y,qd` text (the positions' text as
/// written, so linked tracks sit exactly on the truth), and a tracks table
/// with `particle` = the QD id.
fn truth_as_tables(truth: &Path) -> (String, String) {
    let mut reader = csv::Reader::from_path(truth).unwrap();
    let header = reader.headers().unwrap().clone();
    let at = |name: &str| header.iter().position(|h| h == name).unwrap();
    let (frame, qd, x, y) = (at("frame"), at("qd"), at("x"), at("y"));
    let mut locs = String::from("frame,x,y,qd\n");
    let mut tracks = String::from("frame,x,y,particle\n");
    for record in reader.records() {
        let r = record.unwrap();
        locs.push_str(&format!("{},{},{},{}\n", &r[frame], &r[x], &r[y], &r[qd]));
        tracks.push_str(&format!("{},{},{},{}\n", &r[frame], &r[x], &r[y], &r[qd]));
    }
    (locs, tracks)
}

#[test]
fn linked_truth_positions_score_as_their_links_say() {
    let dir = tempfile::tempdir().unwrap();
    let truth = dir.path().join("truth.csv");
    let frames = dir.path().join("rec.npy");
    // 60 frames of the paper's 24 × 25 field at D = 1, dense enough that
    // QDs meet and leave.
    let (code, _, err) = crate::common::cli_in_process(&[
        "simulate-recording",
        "--frames",
        "60",
        "--seed",
        "3",
        "--qd-density",
        "0.15",
        "--out",
        frames.to_str().unwrap(),
        "--truth",
        truth.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let (locs_text, truth_tracks_text) = truth_as_tables(&truth);
    let locs = dir.path().join("locs.csv");
    std::fs::write(&locs, &locs_text).unwrap();

    // The truth as tracks scores 1 everywhere.
    let perfect = dir.path().join("perfect.csv");
    std::fs::write(&perfect, &truth_tracks_text).unwrap();
    let s = score_json(&perfect, &truth, &[]);
    for measure in crate::common::TRACKING_MEASURES {
        assert_eq!(s[measure], 1.0, "{measure}: {s}");
    }

    // Linked by TrackPy's rules with a search range shorter than many of
    // the steps (σ ≈ 3.4 px per axis): some links are wrong or missing.
    let tracks = dir.path().join("tracks.csv");
    let (code, _, err) = crate::common::cli_in_process(&[
        "link",
        "--locs",
        locs.to_str().unwrap(),
        "--out",
        tracks.to_str().unwrap(),
        "--search-range",
        "5",
    ]);
    assert_eq!(code, 0, "{err}");
    let s = score_json(&tracks, &truth, &[]);

    // The links counted here from the QD id each row carries: a link is
    // true when its two rows are one QD; a truth link (consecutive rows of
    // a QD) is recovered when its rows are consecutive in one track.
    let mut reader = csv::Reader::from_path(&tracks).unwrap();
    let mut by_particle: BTreeMap<u64, Vec<(usize, u64)>> = BTreeMap::new();
    let mut by_qd: BTreeMap<u64, Vec<(usize, u64)>> = BTreeMap::new();
    for record in reader.records() {
        let r = record.unwrap();
        let (frame, qd, particle): (usize, u64, u64) = (
            r[0].parse().unwrap(),
            r[3].parse().unwrap(),
            r[4].parse().unwrap(),
        );
        by_particle.entry(particle).or_default().push((frame, qd));
        by_qd.entry(qd).or_default().push((frame, particle));
    }
    let mut links = 0;
    let mut true_links = 0;
    let mut next_in_track = std::collections::HashSet::new();
    for rows in by_particle.values_mut() {
        rows.sort();
        for w in rows.windows(2) {
            links += 1;
            true_links += usize::from(w[0].1 == w[1].1);
            next_in_track.insert((w[0], w[1]));
        }
    }
    let mut truth_links = 0;
    let mut recovered = 0;
    for (&qd, rows) in by_qd.iter_mut() {
        rows.sort();
        for w in rows.windows(2) {
            truth_links += 1;
            recovered += usize::from(
                w[0].1 == w[1].1 && next_in_track.contains(&((w[0].0, qd), (w[1].0, qd))),
            );
        }
    }
    assert_eq!(s["estimated_links"], links, "{s}");
    assert_eq!(s["true_links"], true_links, "{s}");
    assert_eq!(s["truth_links"], truth_links, "{s}");
    assert_eq!(s["recovered_links"], recovered, "{s}");
    // The case exercises what it is for: wrong links, missed links.
    assert!(true_links < links && recovered < truth_links, "{s}");
    let (alpha, beta) = (s["alpha"].as_f64().unwrap(), s["beta"].as_f64().unwrap());
    assert!(0.0 < beta && beta < alpha && alpha < 1.0, "{s}");
    // Every point sits on the truth: each is matched unless its track's
    // pairing leaves it out.
    assert_eq!(s["truth_points"], s["estimated_points"], "{s}");

    // The table names every measure.
    let (code, out, err) = score_tracks(&tracks, &truth, &[]);
    assert_eq!(code, 0, "{err}");
    for measure in ["alpha", "beta", "jaccard_tracks", "link_recall"] {
        assert!(out.contains(measure), "{out}");
    }
}

#[test]
fn bad_input_is_one_line_naming_the_file_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    let header = "frame,qd,x,y,z_mean,on_fraction,x_seen,y_seen,t_mid,t_beam,t_seen,diffusion\n";
    let truth = write(
        "truth.csv",
        &format!("{header}0,1,2,3,2.5,1,2,3,0,0,0,1\n1,1,2.5,3,2.5,1,2,3,0,0,0,1\n"),
    );
    let tracks = write("tracks.csv", "frame,x,y,particle\n0,2,3,0\n1,2.5,3,0\n");
    let cases: Vec<(Vec<&str>, String)> = vec![
        (
            vec![],
            String::new(), // the good case
        ),
        (vec!["--gate-px", "0"], "--gate-px".into()),
        (
            vec!["--gate-px", "1e300"],
            "--gate-px: must be at most 1e6".into(),
        ),
        (vec!["--min-on-fraction", "1.5"], "--min-on-fraction".into()),
        (
            vec!["--max-depth-um", "1"],
            "truth.csv: no truth rows left".into(),
        ),
    ];
    for (extra, needle) in cases {
        let (code, out, err) = score_tracks(&tracks, &truth, &extra);
        if needle.is_empty() {
            assert_eq!(code, 0, "{err}");
            assert!(out.contains("alpha"), "{out}");
            continue;
        }
        assert_eq!(code, 2, "{extra:?}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "{err}");
        assert!(err.contains(&needle), "{extra:?}: {err}");
    }
    let files = [
        (
            "tracks",
            "nan.csv",
            "frame,x,y,particle\n0,NaN,3,0\n",
            "nan.csv: row 1: column x",
        ),
        (
            "tracks",
            "twice.csv",
            "frame,x,y,particle\n0,1,3,0\n0,2,3,0\n",
            "twice in frame 0",
        ),
        (
            "tracks",
            "notable.csv",
            "\u{93}NUMPY\u{1}\0v\0\n\0",
            "notable.csv",
        ),
        (
            "truth",
            "nodepth.csv",
            "frame,qd,x,y\n0,1,2,3\n",
            "nodepth.csv: missing column(s) z_mean",
        ),
        (
            "truth",
            "badqd.csv",
            &format!("{header}0,1.5,2,3,0,1,2,3,0,0,0,1\n"),
            "badqd.csv: row 1: column qd",
        ),
    ];
    for (which, name, text, needle) in files {
        let path = write(name, text);
        let (tracks_arg, truth_arg) = match which {
            "tracks" => (path.as_path(), truth.as_path()),
            _ => (tracks.as_path(), path.as_path()),
        };
        let (code, _, err) = score_tracks(tracks_arg, truth_arg, &[]);
        assert_eq!(code, 2, "{name}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "{name}: {err}");
        assert!(err.contains(needle), "{name}: {err}");
    }
}
