//! The library's layers point down only: the pipeline (`types`, `sim`,
//! `detect`, `metrics`) and the file formats (`io`) never name the
//! orchestration above them, and `metrics`/`io` never name a detector (nor
//! the simulator or `track`, which sits above `io`). The
//! check reads every source file of a lower module and lists each
//! `crate::MODULE` it names, also inside `use crate::{a, b::c}` groups.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use crate::common::root;

/// Modules above the pipeline: nothing in the pipeline or in `io` may name them.
const ORCHESTRATION: &[&str] = &[
    "run", "sweep", "registry", "report", "bench", "cli", "manifest",
];

/// Every `.rs` file of `path` (a file, or a folder searched recursively).
fn rust_files(path: &Path) -> Vec<PathBuf> {
    if path.is_file() {
        return vec![path.to_path_buf()];
    }
    let mut files = Vec::new();
    for entry in std::fs::read_dir(path).expect("read source folder") {
        let entry = entry.expect("read source entry").path();
        if entry.is_dir() {
            files.extend(rust_files(&entry));
        } else if entry.extension().is_some_and(|e| e == "rs") {
            files.push(entry);
        }
    }
    files
}

/// The first segment of every `crate::` path in `source`, groups included:
/// `use crate::{sim::X, io}` names `sim` and `io`.
fn crate_modules(source: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut rest = source;
    while let Some(at) = rest.find("crate::") {
        rest = &rest[at + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            // Top-level items of the group: split at commas outside nested braces.
            let mut depth = 0usize;
            let mut item = String::new();
            for c in group.chars() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        names.insert(first_segment(&item));
                        item.clear();
                        continue;
                    }
                    _ => {}
                }
                if depth == 0 {
                    item.push(c);
                }
            }
            names.insert(first_segment(&item));
        } else {
            names.insert(first_segment(rest));
        }
    }
    names.remove("");
    names
}

fn first_segment(path: &str) -> String {
    path.trim_start()
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect()
}

/// `(file, module)` for every module named below `path` that `forbidden` rejects.
fn violations(path: &str, forbidden: impl Fn(&str) -> bool) -> Vec<(String, String)> {
    let files = rust_files(&root().join("src").join(path));
    assert!(!files.is_empty(), "no source files under src/{path}");
    let mut found = Vec::new();
    for file in files {
        let source = std::fs::read_to_string(&file).expect("read source file");
        for module in crate_modules(&source) {
            if forbidden(&module) {
                found.push((file.display().to_string(), module));
            }
        }
    }
    found
}

#[test]
fn the_scanner_sees_plain_paths_and_groups() {
    let source = "use crate::error::x;\nuse crate::{sim::{a, b}, io,\n run::Plan};\nlet p = crate::registry::open();";
    let names: Vec<String> = crate_modules(source).into_iter().collect();
    assert_eq!(names, ["error", "io", "registry", "run", "sim"]);
}

#[test]
fn the_pipeline_and_io_never_import_the_orchestration() {
    for layer in ["types", "sim", "detect", "metrics", "io", "track"] {
        assert_eq!(
            violations(layer, |m| ORCHESTRATION.contains(&m)),
            Vec::<(String, String)>::new(),
            "src/{layer} imports a higher layer"
        );
    }
}

#[test]
fn metrics_and_io_never_import_a_detector_or_the_simulator() {
    for layer in ["metrics", "io"] {
        assert_eq!(
            violations(layer, |m| ["detect", "sim", "track"].contains(&m)),
            Vec::<(String, String)>::new(),
            "src/{layer} imports detect or sim"
        );
    }
}

#[test]
fn the_shared_types_import_nothing_but_errors() {
    // Any module but `error` (and the module itself) is refused, so a module
    // added later is covered without being listed here.
    assert_eq!(
        violations("types", |m| m != "error" && m != "types"),
        Vec::<(String, String)>::new()
    );
    // The size limits every layer checks against sit as low as the types.
    assert_eq!(
        violations("limits.rs", |m| m != "error" && m != "limits"),
        Vec::<(String, String)>::new()
    );
}
