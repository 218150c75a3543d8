//! Helpers shared by the test modules: run the binary, read its JSON,
//! snapshot a registry folder, size a fuzzing run.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use npyz::WriterBuilder;
use sha2::{Digest, Sha256};

/// The repository root (manifests are given relative to it).
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Runs `scanloc` with `args` from the repository root, without the
/// SCANLOC_REGISTRY of the environment.
pub fn scanloc(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_scanloc"))
        .args(args)
        .current_dir(root())
        .env_remove(scanloc::env_vars::SCANLOC_REGISTRY)
        .output()
        .expect("run scanloc")
}

pub fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

pub fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// Runs `scanloc run MANIFEST --json --registry DIR [extra]`, asserts
/// success, and returns the JSON object it printed.
pub fn run_json(manifest: &Path, registry: &Path, extra: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "run",
        manifest.to_str().unwrap(),
        "--json",
        "--registry",
        registry.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let output = scanloc(&args);
    assert!(
        output.status.success(),
        "scanloc {args:?} failed: {}",
        stderr(&output)
    );
    let text = stdout(&output);
    assert_eq!(text.trim().lines().count(), 1, "one JSON line: {text}");
    serde_json::from_str(&text).expect("run --json prints JSON")
}

/// Runs `scanloc run MANIFEST --registry DIR` (text), asserts success, and
/// returns what it printed and the run id from its last line.
pub fn run_text(manifest: &Path, registry: &Path) -> (String, String) {
    let output = scanloc(&[
        "run",
        manifest.to_str().unwrap(),
        "--registry",
        registry.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    let text = stdout(&output);
    let id = text
        .lines()
        .last()
        .and_then(|l| l.strip_prefix("run "))
        .and_then(|l| l.split(':').next())
        .unwrap_or_else(|| panic!("no run id in {text}"))
        .to_string();
    (text, id)
}

/// The tracking measures, as `scanloc score-tracks`, a tracking
/// evaluation's `score.json` and a run's `tracking` rows name them.
pub const TRACKING_MEASURES: [&str; 6] = [
    "alpha",
    "beta",
    "jaccard_detections",
    "jaccard_tracks",
    "link_precision",
    "link_recall",
];

/// Runs `scanloc report RUN --registry DIR --out OUT`, asserts success,
/// and returns the Markdown it wrote.
pub fn report_markdown(registry: &Path, run: &str, out: &Path) -> String {
    let output = scanloc(&[
        "report",
        run,
        "--registry",
        registry.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", stderr(&output));
    std::fs::read_to_string(out.join("report.md")).expect("report.md written")
}

/// The text of the report's section `## heading` up to the next section;
/// panics (with the report) if there is none.
pub fn report_section<'m>(markdown: &'m str, heading: &str) -> &'m str {
    markdown
        .split(&format!("## {heading}\n"))
        .nth(1)
        .and_then(|rest| rest.split("\n## ").next())
        .unwrap_or_else(|| panic!("no section {heading:?}: {markdown}"))
}

/// Every file under `dir` with the sha256 of its bytes.
pub fn snapshot(dir: &Path) -> BTreeMap<PathBuf, String> {
    let mut files = BTreeMap::new();
    if !dir.exists() {
        return files;
    }
    let mut stack = vec![dir.to_path_buf()];
    while let Some(folder) = stack.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let entry = entry.unwrap();
            let path = entry.path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let bytes = std::fs::read(&path).unwrap();
                files.insert(
                    path.strip_prefix(dir).unwrap().to_path_buf(),
                    hex::encode(Sha256::digest(&bytes)),
                );
            }
        }
    }
    files
}

/// Writes `text` to `dir/name` and returns the path.
pub fn write_manifest(dir: &Path, name: &str, text: &str) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// The smoke manifest shipped in experiments/.
pub fn smoke() -> PathBuf {
    root().join("experiments/smoke.yaml")
}

/// Flips one bit in the middle of a (read-only) blob file.
pub fn flip_a_byte(path: &Path) {
    let mut permissions = std::fs::metadata(path).unwrap().permissions();
    #[allow(clippy::permissions_set_readonly_false)]
    permissions.set_readonly(false);
    std::fs::set_permissions(path, permissions).unwrap();
    let mut bytes = std::fs::read(path).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x01;
    std::fs::write(path, bytes).unwrap();
}

/// The path of blob `sha256` in registry `dir`.
pub fn blob_path(dir: &Path, sha256: &str) -> PathBuf {
    dir.join("blobs").join(&sha256[..2]).join(sha256)
}

/// Cases per fuzzing property test: `default` in `make test`, or the
/// number in `SCANLOC_FUZZ_CASES` for a long run (`make fuzz`).
pub fn fuzz_cases(default: u32) -> u32 {
    match std::env::var(scanloc::env_vars::SCANLOC_FUZZ_CASES) {
        // A mistyped count must not quietly shrink a long fuzzing run to the
        // default.
        Ok(cases) => cases
            .parse()
            .unwrap_or_else(|_| panic!("SCANLOC_FUZZ_CASES: not a case count: {cases:?}")),
        Err(_) => default,
    }
}

/// A fresh folder for one fuzzing case: in memory (/dev/shm) where there
/// is one, since cases write (and the writers sync) files by the hundred
/// thousand; else in the system's temporary folder.
pub fn fuzz_case_dir() -> tempfile::TempDir {
    let in_memory = Path::new("/dev/shm");
    if in_memory.is_dir()
        && let Ok(dir) = tempfile::Builder::new()
            .prefix("scanloc-fuzz-")
            .tempdir_in(in_memory)
    {
        return dir;
    }
    tempfile::tempdir().unwrap()
}

/// Writes `values` as a C-order .npy array of `shape` in `T`'s dtype.
pub fn write_npy<T: npyz::AutoSerialize + Copy>(path: &Path, shape: &[u64], values: &[T]) {
    let mut bytes = Vec::new();
    {
        let mut writer = npyz::WriteOptions::new()
            .default_dtype()
            .shape(shape)
            .writer(&mut bytes)
            .begin_nd()
            .unwrap();
        writer.extend(values.iter().copied()).unwrap();
        writer.finish().unwrap();
    }
    std::fs::write(path, bytes).unwrap();
}

/// Runs the command line in-process (no child process, so a test can run
/// it many times cheaply): (exit code, stdout, stderr); an exit code other
/// than 0, 1 or 2 reads as 255.
pub fn cli_in_process(args: &[&str]) -> (u8, String, String) {
    let mut out = Vec::new();
    let mut err = Vec::new();
    let mut argv = vec!["scanloc"];
    argv.extend_from_slice(args);
    let exit = scanloc::cli::main_with(argv, &mut out, &mut err, false);
    let code = (0..=2u8)
        .find(|&c| exit == std::process::ExitCode::from(c))
        .unwrap_or(u8::MAX);
    (
        code,
        String::from_utf8_lossy(&out).into_owned(),
        String::from_utf8_lossy(&err).into_owned(),
    )
}
