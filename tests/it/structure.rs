//! The rooms of the source: no circle of imports among the files of one
//! module, and no function over [`MAX_FUNCTION_LINES`] lines outside tests
//! and SIMD kernels.
//!
//! A file's imports of its siblings are the `super::NAME` paths it names
//! outside comments and its `#[cfg(test)]` module (also inside `use
//! super::{a, b::c}` groups); a folder module is one node among its parent's
//! files, with the imports of its `mod.rs` (`super::`) and of its files
//! (`super::super::`). The module root (`mod.rs`) is not a node: it
//! declares and re-exports its files.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::common::root;

/// The longest a function may be, its signature and closing brace
/// included.
const MAX_FUNCTION_LINES: usize = 100;

/// Where long functions are exempt (paths starting so): SIMD kernels,
/// written out for the vectoriser.
const KERNELS: &[&str] = &[
    "src/detect/cnn/kernels/",
    "src/detect/likelihood/kernels.rs",
];

/// To be split: files other work is rewriting now, with the functions of
/// theirs that are over the limit (the list shrinks as they are split).
const TO_BE_SPLIT: &[(&str, &str)] = &[];

/// To be split: imports that close a circle among `run`'s files, which
/// other work removes now (module folder, importing file, imported file).
const CIRCLES_TO_BE_SPLIT: &[(&str, &str, &str)] = &[];

/// Where scanning resumes if `lines[i]` opens a `#[cfg(test)]` module (a
/// test module at column 0, ended by the first `}` at column 0): the line
/// after its end; `None` if it does not.
fn after_test_module(lines: &[&str], i: usize) -> Option<usize> {
    let opens = lines[i].starts_with("#[cfg(test)]")
        && lines
            .get(i + 1)
            .is_some_and(|next| next.starts_with("mod ") && next.trim_end().ends_with('{'));
    if !opens {
        return None;
    }
    let mut end = i + 2;
    while end < lines.len() && !lines[end].starts_with('}') {
        end += 1;
    }
    Some(end + 1)
}

/// `source` without its comments and its `#[cfg(test)]` module (a test
/// module at column 0, ended by the first `}` at column 0).
fn without_tests_and_comments(source: &str) -> String {
    let lines: Vec<&str> = source.lines().collect();
    let mut out = String::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        if let Some(after) = after_test_module(&lines, i) {
            i = after;
            continue;
        }
        let code = line.split("//").next().unwrap_or("");
        out.push_str(code);
        out.push('\n');
        i += 1;
    }
    out
}

/// The first segment of every path `source` names after `prefix`, groups
/// included: with prefix `super::`, `super::{a::X, b}` names `a` and `b`.
fn names_after(source: &str, prefix: &str) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    let mut from = 0;
    while let Some(found) = source[from..].find(prefix) {
        let at = from + found;
        from = at + prefix.len();
        // `super::super::x` is not `super::x`, nor `super::super`.
        if source[..at].ends_with("::") {
            continue;
        }
        let rest = &source[from..];
        if let Some(group) = rest.strip_prefix('{') {
            let mut depth = 1;
            let mut end = 0;
            for (index, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    _ => {}
                }
                if depth == 0 {
                    end = index;
                    break;
                }
            }
            let mut depth = 0;
            let mut part = String::new();
            for c in group[..end].chars().chain([',']) {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        let name = first_identifier(&part);
                        if !name.is_empty() {
                            names.insert(name);
                        }
                        part.clear();
                        continue;
                    }
                    _ => {}
                }
                part.push(c);
            }
        } else if !rest.starts_with(prefix) {
            let name = first_identifier(rest);
            if !name.is_empty() {
                names.insert(name);
            }
        }
    }
    names
}

fn first_identifier(text: &str) -> String {
    text.trim_start()
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect()
}

/// Every folder under `dir` (itself included).
fn folders(dir: &Path) -> Vec<PathBuf> {
    let mut all = vec![dir.to_path_buf()];
    for entry in std::fs::read_dir(dir).expect("read source folder") {
        let path = entry.expect("read source entry").path();
        if path.is_dir() {
            all.extend(folders(&path));
        }
    }
    all
}

/// The modules of `folder` that are nodes of its graph: its files but the
/// roots, and its sub-folders.
fn nodes(folder: &Path) -> BTreeSet<String> {
    let mut names = BTreeSet::new();
    for entry in std::fs::read_dir(folder).expect("read source folder") {
        let path = entry.expect("read source entry").path();
        let name = path.file_stem().unwrap().to_string_lossy().into_owned();
        let rust_file = path.extension().is_some_and(|e| e == "rs")
            && !["mod", "lib", "main"].contains(&name.as_str());
        if path.is_dir() || rust_file {
            names.insert(name);
        }
    }
    names
}

type Graph = BTreeMap<String, BTreeSet<String>>;

/// The import graph of each folder of `src`, by the folder's path relative
/// to the repository (`src/run`).
fn import_graphs() -> BTreeMap<String, Graph> {
    let src = root().join("src");
    let relative = |p: &Path| {
        p.strip_prefix(root())
            .unwrap()
            .to_string_lossy()
            .replace('\\', "/")
    };
    let mut graphs: BTreeMap<String, Graph> = BTreeMap::new();
    for folder in folders(&src) {
        let siblings = nodes(&folder);
        let parent = folder.parent().map(|p| p.to_path_buf());
        let parent_siblings = parent.as_deref().map(nodes).unwrap_or_default();
        let folder_name = folder.file_name().unwrap().to_string_lossy().into_owned();
        for entry in std::fs::read_dir(&folder).expect("read source folder") {
            let path = entry.expect("read source entry").path();
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
            if stem == "lib" || stem == "main" {
                continue;
            }
            let source = std::fs::read_to_string(&path).expect("read source file");
            let code = without_tests_and_comments(&source);
            // (graph's folder, node, its siblings, the prefix naming them)
            let mut views = Vec::new();
            if stem == "mod" {
                if let Some(parent) = &parent {
                    views.push((
                        parent.clone(),
                        folder_name.clone(),
                        &parent_siblings,
                        "super::",
                    ));
                }
            } else {
                views.push((folder.clone(), stem.clone(), &siblings, "super::"));
                if let Some(parent) = &parent {
                    views.push((
                        parent.clone(),
                        folder_name.clone(),
                        &parent_siblings,
                        "super::super::",
                    ));
                }
            }
            for (graph_folder, node, candidates, prefix) in views {
                let graph = graphs.entry(relative(&graph_folder)).or_default();
                for name in names_after(&code, prefix) {
                    if name != node && candidates.contains(&name) {
                        graph.entry(node.clone()).or_default().insert(name);
                    }
                }
            }
        }
    }
    graphs
}

/// The circles of `graph`: its strongly connected components of more than
/// one node (Tarjan), each sorted.
fn circles(graph: &Graph) -> Vec<Vec<String>> {
    struct Search<'a> {
        graph: &'a Graph,
        index: BTreeMap<&'a str, usize>,
        low: BTreeMap<&'a str, usize>,
        stack: Vec<&'a str>,
        found: Vec<Vec<String>>,
    }
    impl<'a> Search<'a> {
        fn visit(&mut self, node: &'a str) {
            let at = self.index.len();
            self.index.insert(node, at);
            self.low.insert(node, at);
            self.stack.push(node);
            for next in self.graph.get(node).into_iter().flatten() {
                let next = next.as_str();
                if !self.index.contains_key(next) {
                    self.visit(next);
                    let low = self.low[node].min(self.low[next]);
                    self.low.insert(node, low);
                } else if self.stack.contains(&next) {
                    let low = self.low[node].min(self.index[next]);
                    self.low.insert(node, low);
                }
            }
            if self.low[node] == self.index[node] {
                let mut component = Vec::new();
                while let Some(top) = self.stack.pop() {
                    component.push(top.to_string());
                    if top == node {
                        break;
                    }
                }
                if component.len() > 1 {
                    component.sort();
                    self.found.push(component);
                }
            }
        }
    }
    let mut search = Search {
        graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        found: Vec::new(),
    };
    for node in graph.keys() {
        if !search.index.contains_key(node.as_str()) {
            search.visit(node);
        }
    }
    search.found
}

#[test]
fn the_import_scanner_sees_groups_and_skips_tests_and_comments() {
    let source = "use super::{a::X, b, c::{d, e}};\nuse super::f;\n// super::g\nfn h() { super::super::i::j(); }\n#[cfg(test)]\nmod tests {\n    use super::k;\n}\n";
    let code = without_tests_and_comments(source);
    let names: Vec<String> = names_after(&code, "super::").into_iter().collect();
    assert_eq!(names, ["a", "b", "c", "f"]);
    let names: Vec<String> = names_after(&code, "super::super::").into_iter().collect();
    assert_eq!(names, ["i"]);
}

#[test]
fn the_circle_search_finds_a_circle_and_only_it() {
    let graph: Graph = [("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")]
        .into_iter()
        .fold(Graph::new(), |mut graph, (from, to)| {
            graph
                .entry(from.to_string())
                .or_default()
                .insert(to.to_string());
            graph
        });
    assert_eq!(circles(&graph), [["a", "b", "c"]]);
}

#[test]
fn no_module_has_a_circle_of_imports_among_its_files() {
    let mut graphs = import_graphs();
    for (folder, from, to) in CIRCLES_TO_BE_SPLIT {
        let removed = graphs
            .get_mut(*folder)
            .and_then(|graph| graph.get_mut(*from))
            .is_some_and(|imports| imports.remove(*to));
        assert!(
            removed,
            "{folder}: {from} no longer imports {to}: take it off CIRCLES_TO_BE_SPLIT"
        );
    }
    let found: Vec<String> = graphs
        .iter()
        .flat_map(|(folder, graph)| {
            circles(graph)
                .into_iter()
                .map(move |circle| format!("{folder}: {}", circle.join(" ↔ ")))
        })
        .collect();
    assert!(found.is_empty(), "circles of imports: {found:#?}");
}

/// A function's first line: `fn NAME`, after any of `pub`, `pub(…)`,
/// `const`, `async`, `unsafe`, `extern "…"`; its name.
fn function_name(line: &str) -> Option<String> {
    let mut rest = line.trim_start();
    loop {
        let before = rest;
        for keyword in ["const ", "async ", "unsafe ", "pub "] {
            rest = rest.strip_prefix(keyword).unwrap_or(rest);
        }
        if rest.starts_with("pub(") {
            rest = rest.split_once(") ").map_or(rest, |(_, after)| after);
        }
        if rest.starts_with("extern \"") {
            rest = rest.splitn(3, '"').nth(2).unwrap_or("").trim_start();
        }
        if rest == before {
            break;
        }
    }
    let name = rest.strip_prefix("fn ")?;
    Some(first_identifier(name))
}

/// Every function of `source` (outside its test module) longer than
/// [`MAX_FUNCTION_LINES`], as (name, first line, lines). A function ends at
/// the first line that is its indentation and `}`, as rustfmt writes it.
fn long_functions(source: &str) -> Vec<(String, usize, usize)> {
    let lines: Vec<&str> = source.lines().collect();
    let mut found = Vec::new();
    let mut i = 0;
    while i < lines.len() {
        let line = lines[i];
        if let Some(after) = after_test_module(&lines, i) {
            i = after;
            continue;
        }
        if let Some(name) = function_name(line) {
            let indent = &line[..line.len() - line.trim_start().len()];
            let mut end = i;
            while end < lines.len() && !lines[end].trim_end().ends_with(['{', ';', '}']) {
                end += 1;
            }
            let body = lines.get(end).is_some_and(|l| l.trim_end().ends_with('{'));
            if body && !lines[end].trim_end().ends_with('}') {
                let close = format!("{indent}}}");
                while end < lines.len() && lines[end] != close {
                    end += 1;
                }
                let length = end + 1 - i;
                if length > MAX_FUNCTION_LINES {
                    found.push((name, i + 1, length));
                }
            }
        }
        i += 1;
    }
    found
}

#[test]
fn the_length_scanner_counts_a_function_to_its_closing_brace() {
    // 102 lines, then 100 (at the limit), then a long test helper.
    let body = "    let x = 1;\n".repeat(98);
    let source = format!(
        "pub(crate) fn long(\n    a: u8,\n) -> u8 {{\n{body}}}\n\nfn short() {{}}\n\nimpl A {{\n    fn fits() {{\n{body}    }}\n}}\n#[cfg(test)]\nmod tests {{\n    fn test_helper() {{\n{body}{body}    }}\n}}\n"
    );
    assert_eq!(long_functions(&source), [("long".to_string(), 1, 102)]);
}

#[test]
fn no_function_outside_tests_and_kernels_is_over_100_lines() {
    let src = root().join("src");
    let mut found = Vec::new();
    let mut exempt_seen = BTreeSet::new();
    for folder in folders(&src) {
        for entry in std::fs::read_dir(&folder).expect("read source folder") {
            let path = entry.expect("read source entry").path();
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let relative = path
                .strip_prefix(root())
                .unwrap()
                .to_string_lossy()
                .replace('\\', "/");
            if KERNELS.iter().any(|k| relative.starts_with(k)) {
                continue;
            }
            let source = std::fs::read_to_string(&path).expect("read source file");
            for (name, line, length) in long_functions(&source) {
                if TO_BE_SPLIT.contains(&(relative.as_str(), name.as_str())) {
                    exempt_seen.insert((relative.clone(), name));
                    continue;
                }
                found.push(format!("{relative}:{line} {name}: {length} lines"));
            }
        }
    }
    assert!(
        found.is_empty(),
        "functions over {MAX_FUNCTION_LINES} lines: {found:#?}"
    );
    for (file, name) in TO_BE_SPLIT {
        assert!(
            exempt_seen.contains(&(file.to_string(), name.to_string())),
            "{file} {name} is no longer over {MAX_FUNCTION_LINES} lines: take it off TO_BE_SPLIT"
        );
    }
}
