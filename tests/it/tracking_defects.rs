//! The defects of issue 64 in the tracking commands, one test each (the
//! class of each, not only the example the issue gave).

use std::path::{Path, PathBuf};

use crate::common::cli_in_process;

/// A small localisation table (two particles over four frames).
const LOCS: &str = "frame,x,y,score\n0,5,5,0.9\n0,15,15,0.2\n1,5.5,5.2,0.9\n1,15.3,15.1,0.9\n\
                    2,5.9,5.1,0.1\n2,15.1,15.4,0.9\n3,6.1,5.3,0.9\n3,15.2,15.9,0.9\n";

fn text(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// The ways an output can name an input: the same path, the same path
/// spelled through `.`, a hard link and a symbolic link to it.
fn aliases(dir: &Path, input: &Path, tag: &str) -> Vec<PathBuf> {
    let dotted = dir.join(".").join(input.file_name().unwrap());
    let hard = dir.join(format!("hard-{tag}"));
    std::fs::hard_link(input, &hard).unwrap();
    let mut all = vec![input.to_path_buf(), dotted, hard];
    #[cfg(unix)]
    {
        let soft = dir.join(format!("soft-{tag}"));
        std::os::unix::fs::symlink(input, &soft).unwrap();
        all.push(soft);
    }
    all
}

/// Every command that writes a file, each with an output naming one of its
/// inputs (same path, `./`, hard link, symlink), is refused with exit 2 and
/// leaves the input byte for byte as it was.
#[test]
fn every_writing_command_refuses_an_output_that_is_or_links_to_an_input() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let locs = d.join("locs.csv");
    std::fs::write(&locs, LOCS).unwrap();
    let truth = d.join("truth.csv");
    std::fs::write(&truth, "frame,x,y\n0,5,5\n1,15,15\n").unwrap();
    let compare = d.join("compare.csv");
    std::fs::write(&compare, LOCS).unwrap();
    let frames = d.join("frames.npy");
    let (code, _, err) = cli_in_process(&[
        "simulate",
        "--frames",
        "2",
        "--seed",
        "1",
        "--out",
        text(&frames),
    ]);
    assert_eq!(code, 0, "{err}");
    let sim_out = d.join("sim.npy");
    let rec_out = d.join("rec.npy");
    std::fs::write(&sim_out, b"frames").unwrap();
    std::fs::write(&rec_out, b"frames").unwrap();

    // (command line with OUT for the output, the input it names)
    type Case = (Vec<String>, PathBuf);
    let owned = |args: &[&str]| args.iter().map(|a| a.to_string()).collect::<Vec<_>>();
    let mut cases: Vec<Case> = Vec::new();
    for extra in [
        &["--search-range", "3"][..],
        &["--search-range", "3", "--min-score", "0.5"],
        &["--linker", "lap", "--search-range", "3"],
    ] {
        let mut args = owned(&["link", "--locs", text(&locs), "--out", "OUT"]);
        args.extend(owned(extra));
        cases.push((args, locs.clone()));
    }
    cases.push((
        owned(&["locate", "--input", text(&frames), "--out", "OUT"]),
        frames.clone(),
    ));
    for input in [&truth, &locs, &compare] {
        cases.push((
            owned(&[
                "score",
                "--truth",
                text(&truth),
                "--locs",
                text(&locs),
                "--compare",
                text(&compare),
                "--curve",
                "OUT",
            ]),
            input.clone(),
        ));
    }
    // The simulators' two outputs, each the other.
    cases.push((
        owned(&[
            "simulate",
            "--frames",
            "1",
            "--out",
            text(&sim_out),
            "--truth",
            "OUT",
        ]),
        sim_out.clone(),
    ));
    cases.push((
        owned(&[
            "simulate-recording",
            "--frames",
            "2",
            "--out",
            text(&rec_out),
            "--truth",
            "OUT",
        ]),
        rec_out.clone(),
    ));

    for (index, (args, input)) in cases.iter().enumerate() {
        let before = std::fs::read(input).unwrap();
        for alias in aliases(d, input, &index.to_string()) {
            let args: Vec<&str> = args
                .iter()
                .map(|a| if a == "OUT" { text(&alias) } else { a.as_str() })
                .collect();
            let (code, out, err) = cli_in_process(&args);
            assert_eq!(code, 2, "{args:?} not refused: {out}{err}");
            assert_eq!(err.trim().lines().count(), 1, "{args:?}: one line: {err}");
            assert_eq!(
                std::fs::read(input).unwrap(),
                before,
                "{args:?} modified its input"
            );
        }
    }
}
