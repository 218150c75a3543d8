//! Captures the code version a binary is built from, for run records:
//! the git commit, whether the work tree had uncommitted changes, and the
//! rustc that compiled it. Never fails: without git (e.g. a source tarball)
//! the commit is recorded as `unknown`.

use std::path::Path;
use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let output = Command::new("git").args(args).output().ok()?;
    if !output.status.success() {
        return None;
    }
    Some(String::from_utf8_lossy(&output.stdout).trim().to_string())
}

fn main() {
    // Rebuild the version stamp when the sources or git's idea of HEAD change.
    for path in ["src", "Cargo.toml", "Cargo.lock", "build.rs"] {
        println!("cargo:rerun-if-changed={path}");
    }
    let mut watched: Vec<String> = ["HEAD", "index"]
        .iter()
        .filter_map(|name| git(&["rev-parse", "--git-path", name]))
        .collect();
    if let Some(path) = git(&["symbolic-ref", "-q", "HEAD"])
        .and_then(|reference| git(&["rev-parse", "--git-path", &reference]))
    {
        watched.push(path);
    }
    for path in watched.iter().filter(|p| Path::new(p).exists()) {
        println!("cargo:rerun-if-changed={path}");
    }

    let commit = git(&["rev-parse", "HEAD"]).unwrap_or_else(|| "unknown".to_string());
    // Tracked files only: untracked scratch files (registries, reports) do
    // not change what is compiled. `--no-optional-locks` stops `git status`
    // from refreshing (rewriting) the index it is watched through above:
    // otherwise every build would leave the index newer than itself and the
    // next `make` would recompile the crate for nothing (35 s, measured).
    let dirty = match git(&[
        "--no-optional-locks",
        "status",
        "--porcelain",
        "--untracked-files=no",
    ]) {
        Some(status) => {
            if status.is_empty() {
                "false"
            } else {
                "true"
            }
        }
        None => "unknown",
    };
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".to_string());
    let rustc_version = Command::new(rustc)
        .arg("--version")
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .filter(|v| !v.is_empty())
        .unwrap_or_else(|| "unknown".to_string());

    println!("cargo:rustc-env=SCANLOC_GIT_COMMIT={commit}");
    println!("cargo:rustc-env=SCANLOC_GIT_DIRTY={dirty}");
    println!("cargo:rustc-env=SCANLOC_RUSTC_VERSION={rustc_version}");
}
