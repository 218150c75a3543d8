//! The library's layers point down only. From the top:
//!
//! | layer           | may import (besides the base)                            |
//! |-----------------|----------------------------------------------------------|
//! | `cli`           | everything below                                         |
//! | `bench`         | `report` and below                                       |
//! | `report`        | `sweep` and below                                        |
//! | `sweep`         | `run` and below                                          |
//! | `run`           | `manifest` and below                                     |
//! | `manifest`      | `registry` and below                                     |
//! | `registry`      | `io` (it stores the pipeline's results as plain values)  |
//! | `track`         | `detect` and below (linking and diffusion estimation)    |
//! | `detect`        | `sim`, `io`, `metrics`                                   |
//! | `sim`           | `io`, `metrics`                                          |
//! | `io`, `metrics` | the base only (neither names the other)                  |
//!
//! The base, which every layer may import: `types` (which imports only
//! `error`), `error`, `limits`, `progress` and `env_vars`. The check reads
//! every source file of a layer and lists each `crate::MODULE` it names, also
//! inside `use crate::{a, b::c}` groups (comments included: a doc link is an
//! import too).

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use crate::common::root;

/// The layers, top first: each may import the layers after it, except
/// what [`EXCEPTIONS`] refuses.
const LAYERS: &[&str] = &[
    "cli", "bench", "report", "sweep", "run", "manifest", "registry", "track", "detect", "fit",
    "sim", "io", "metrics",
];

/// Imports the order would allow but the design refuses: (layer, modules).
const EXCEPTIONS: &[(&str, &[&str])] = &[
    // The registry stores datasets, models and scores as plain values: it
    // never depends on how the pipeline makes them.
    ("registry", &["track", "detect", "fit", "sim", "metrics"]),
    // The metric and the file formats sit side by side.
    ("io", &["metrics"]),
];

/// Importable from every layer: the shared types and the crate-wide helpers
/// (`bail_input` is the error module's macro, named `crate::bail_input!`).
const BASE: &[&str] = &[
    "types",
    "error",
    "bail_input",
    "limits",
    "progress",
    "env_vars",
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
    modules_named(source, "crate::")
}

/// As [`crate_modules`], for paths starting with `prefix`.
fn modules_named(source: &str, prefix: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut rest = source;
    while let Some(at) = rest.find(prefix) {
        // `foo_crate::` is not the crate (`$crate::` in a macro is).
        let before = rest[..at].chars().next_back();
        rest = &rest[at + prefix.len()..];
        if before.is_some_and(|c| c.is_alphanumeric() || c == '_') {
            continue;
        }
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
    violations_of(path, "crate::", forbidden)
}

/// As [`violations`], for paths starting with `prefix` (`crate::`, `scanloc::`).
fn violations_of(
    path: &str,
    prefix: &str,
    forbidden: impl Fn(&str) -> bool,
) -> Vec<(String, String)> {
    let files = rust_files(&root().join("src").join(path));
    assert!(!files.is_empty(), "no source files under src/{path}");
    let mut found = Vec::new();
    for file in files {
        let source = std::fs::read_to_string(&file).expect("read source file");
        for module in modules_named(&source, prefix) {
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

/// Whether `layer` may import `module`.
fn allowed(layer: &str, module: &str) -> bool {
    if module == layer || BASE.contains(&module) {
        return true;
    }
    let rank = |m: &str| LAYERS.iter().position(|l| *l == m);
    let refused = EXCEPTIONS
        .iter()
        .any(|(l, modules)| *l == layer && modules.contains(&module));
    match (rank(layer), rank(module)) {
        (Some(layer), Some(module)) => module > layer && !refused,
        // A module that is neither a layer nor the base: the test must be told.
        _ => false,
    }
}

#[test]
fn every_layer_imports_only_the_layers_below_it() {
    for layer in LAYERS {
        assert_eq!(
            violations(layer, |m| !allowed(layer, m)),
            Vec::<(String, String)>::new(),
            "src/{layer} imports a layer above it (or one the design refuses)"
        );
    }
}

#[test]
fn the_layer_order_refuses_upward_imports() {
    assert!(allowed("sweep", "run") && !allowed("run", "sweep"));
    assert!(allowed("bench", "report") && !allowed("report", "bench"));
    assert!(allowed("detect", "sim") && !allowed("sim", "detect"));
    assert!(!allowed("registry", "sim") && allowed("manifest", "registry"));
    assert!(!allowed("io", "metrics") && !allowed("metrics", "io"));
    assert!(allowed("sim", "types") && !allowed("types", "sim"));
    assert!(!allowed("run", "no_such_module"));
}

#[test]
fn every_module_of_the_crate_is_a_layer_or_the_base() {
    let lib = std::fs::read_to_string(root().join("src/lib.rs")).expect("read src/lib.rs");
    for line in lib.lines() {
        if let Some(module) = line.strip_prefix("pub mod ") {
            let module = module.trim_end_matches(';');
            assert!(
                LAYERS.contains(&module) || BASE.contains(&module),
                "src/{module} is neither a layer nor the base: place it in tests/it/layers.rs"
            );
        }
    }
}

#[test]
fn the_base_imports_only_errors() {
    for (file, own) in [
        ("limits.rs", "limits"),
        ("progress.rs", "progress"),
        ("env_vars.rs", "env_vars"),
        ("error.rs", "error"),
    ] {
        assert_eq!(
            violations(file, |m| m != "error" && m != "bail_input" && m != own),
            Vec::<(String, String)>::new(),
            "src/{file} imports more than the errors"
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
