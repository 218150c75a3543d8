//! `scanloc locate` and `scanloc score` as a user runs them.

use crate::common::scanloc;

#[test]
fn simulate_locate_score_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_string_lossy().into_owned();
    let (frames, truth, locs, curve) = (path("f.tif"), path("t.csv"), path("l.csv"), path("c.csv"));
    let out = scanloc(&[
        "simulate",
        "--frames",
        "300",
        "--brightness",
        "40",
        "--margin-px",
        "4",
        "--out",
        &frames,
        "--truth",
        &truth,
    ]);
    assert!(out.status.success());
    let out = scanloc(&[
        "locate",
        "--method",
        "crocker-grier",
        "--diameter",
        "7",
        "--minmass",
        "0",
        "--input",
        &frames,
        "--out",
        &locs,
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = std::fs::read_to_string(&locs).unwrap();
    assert!(text.starts_with("frame,x,y,mass,size,ecc,signal,raw_mass,ep,score\n"));
    let out = scanloc(&[
        "score", "--truth", &truth, "--locs", &locs, "--json", "--curve", &curve,
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let score: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    // A bright QD (N_qd 40) is found near its path by the intensity method:
    // at ε = 3 px the AUC is far above what random guesses would give.
    let auc3 = score["per_eps"][2]["auc"].as_f64().unwrap();
    assert!(auc3 > 0.5, "AUC at 3 px: {auc3}");
    assert!(
        std::fs::read_to_string(&curve)
            .unwrap()
            .starts_with("eps_px,k,score,precision,recall\n")
    );
}

#[test]
fn bad_input_is_refused_with_exit_code_2() {
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_string_lossy().into_owned();
    let frames = path("f.npy");
    assert!(
        scanloc(&[
            "simulate",
            "--frames",
            "3",
            "--out",
            &frames,
            "--truth",
            &path("t.csv")
        ])
        .status
        .success()
    );
    std::fs::write(path("bad.npy"), b"\x93NUMPY garbage").unwrap();
    std::fs::write(path("notruth.csv"), "frame,x\n0,1\n").unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                "locate".into(),
                "--diameter".into(),
                "6".into(),
                "--input".into(),
                frames.clone(),
                "--out".into(),
                path("o.csv"),
            ],
            "diameter",
        ),
        (
            vec![
                "locate".into(),
                "--diameter".into(),
                "-7".into(),
                "--input".into(),
                frames.clone(),
                "--out".into(),
                path("o.csv"),
            ],
            "diameter",
        ),
        (
            vec![
                "locate".into(),
                "--input".into(),
                path("missing.npy"),
                "--out".into(),
                path("o.csv"),
            ],
            "missing.npy",
        ),
        (
            vec![
                "locate".into(),
                "--input".into(),
                path("bad.npy"),
                "--out".into(),
                path("o.csv"),
            ],
            "bad.npy",
        ),
        (
            vec![
                "locate".into(),
                "--percentile".into(),
                "nan".into(),
                "--input".into(),
                frames.clone(),
                "--out".into(),
                path("o.csv"),
            ],
            "percentile",
        ),
        (
            vec![
                "score".into(),
                "--truth".into(),
                path("notruth.csv"),
                "--locs".into(),
                path("t.csv"),
            ],
            "missing column",
        ),
    ];
    for (args, needle) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let out = scanloc(&args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains(needle), "{args:?}: {stderr}");
    }
    assert!(!dir.path().join("o.csv").exists());
}
