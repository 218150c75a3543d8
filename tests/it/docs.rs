//! The documentation a reader follows: every relative link and `#anchor`
//! in README.md and docs/ resolves, every `docs/<page>.md#<anchor>` the source
//! and tests cite resolves, and no docs page is over 4,000 words (a page a
//! reader takes in; results and history go to docs/experiments-log/).
//!
//! Anchors are GitHub's: a heading lowercased, every character that is not
//! a letter, digit, space, `-` or `_` dropped, spaces turned into `-`, and a
//! repeated heading suffixed `-1`, `-2`, …

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::common::root;

/// The most words a docs page may hold.
const MAX_WORDS: usize = 4_000;

/// README.md and every Markdown file under docs/, sorted.
fn pages() -> Vec<PathBuf> {
    let root = root();
    let mut out = vec![root.join("README.md")];
    let mut stack = vec![root.join("docs")];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "md") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// The text outside fenced code blocks and inline code spans, where a
/// `](…)` is not a link.
fn prose(text: &str) -> String {
    let mut out = String::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Drop `code spans` (a line's backticks pair up).
        let mut in_code = false;
        for c in line.chars() {
            if c == '`' {
                in_code = !in_code;
            } else if !in_code {
                out.push(c);
            }
        }
        out.push('\n');
    }
    out
}

/// GitHub's anchor for a heading's text.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || matches!(c, ' ' | '-' | '_'))
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a Markdown file's headings (outside code blocks).
fn anchors(text: &str) -> BTreeSet<String> {
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let mut out = BTreeSet::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced || !line.starts_with('#') {
            continue;
        }
        let heading = line.trim_start_matches('#');
        if !heading.starts_with(' ') {
            continue;
        }
        let base = slug(heading);
        let n = seen.entry(base.clone()).or_insert(0);
        out.insert(if *n == 0 {
            base.clone()
        } else {
            format!("{base}-{n}")
        });
        *n += 1;
    }
    out
}

/// Every `](target)` of a page's prose.
fn links(text: &str) -> Vec<String> {
    let prose = prose(text);
    let mut out = Vec::new();
    let mut rest = prose.as_str();
    while let Some(i) = rest.find("](") {
        rest = &rest[i + 2..];
        if let Some(end) = rest.find(')') {
            out.push(rest[..end].to_string());
        }
    }
    out
}

/// Why `target`, linked from `from`, does not resolve (None if it does).
fn broken(
    from: &Path,
    target: &str,
    cache: &mut BTreeMap<PathBuf, BTreeSet<String>>,
) -> Option<String> {
    let (path, anchor) = match target.split_once('#') {
        Some((p, a)) => (p, Some(a)),
        None => (target, None),
    };
    let file = if path.is_empty() {
        from.to_path_buf()
    } else {
        from.parent().unwrap().join(path)
    };
    if !file.exists() {
        return Some(format!("no file {}", file.display()));
    }
    let anchor = anchor?;
    if file.extension().is_none_or(|e| e != "md") {
        return None;
    }
    let known = cache
        .entry(file.clone())
        .or_insert_with(|| anchors(&std::fs::read_to_string(&file).unwrap()));
    (!known.contains(anchor)).then(|| format!("no heading #{anchor} in {}", file.display()))
}

#[test]
fn every_relative_link_and_anchor_in_the_docs_resolves() {
    let mut cache = BTreeMap::new();
    let mut bad = Vec::new();
    let mut checked = 0;
    for page in pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        for target in links(&text) {
            let external = target.contains("://") || target.starts_with("mailto:");
            if external || target.contains(' ') {
                continue;
            }
            checked += 1;
            if let Some(why) = broken(&page, &target, &mut cache) {
                bad.push(format!("{}: ({target}): {why}", page.display()));
            }
        }
    }
    assert!(
        checked > 200,
        "only {checked} links found: the parser is broken"
    );
    assert!(bad.is_empty(), "broken links:\n{}", bad.join("\n"));
}

#[test]
fn the_docs_anchors_the_source_cites_resolve() {
    let root = root();
    let mut cache = BTreeMap::new();
    let mut bad = Vec::new();
    let mut checked = 0;
    let mut stack = vec![root.join("src"), root.join("tests/it")];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap();
            let mut rest = text.as_str();
            while let Some(i) = rest.find("docs/") {
                rest = &rest[i..];
                let end = rest
                    .find(|c: char| !(c.is_ascii_alphanumeric() || "/._-#".contains(c)))
                    .unwrap_or(rest.len());
                let cite = rest[..end].trim_end_matches('.');
                rest = &rest[end.max(5)..];
                let page = cite.split('#').next().unwrap();
                if !page.ends_with(".md") {
                    continue;
                }
                checked += 1;
                if let Some(why) = broken(&root.join("x"), cite, &mut cache) {
                    bad.push(format!("{}: {cite}: {why}", path.display()));
                }
            }
        }
    }
    assert!(
        checked > 20,
        "only {checked} citations found: the scan is broken"
    );
    assert!(
        bad.is_empty(),
        "citations of the docs that do not resolve:\n{}",
        bad.join("\n")
    );
}

#[test]
fn no_docs_page_is_over_4000_words() {
    let over: Vec<String> = pages()
        .into_iter()
        .filter(|p| p.starts_with(root().join("docs")))
        .filter_map(|p| {
            let words = std::fs::read_to_string(&p)
                .unwrap()
                .split_whitespace()
                .count();
            (words > MAX_WORDS).then(|| format!("{}: {words} words", p.display()))
        })
        .collect();
    assert!(
        over.is_empty(),
        "pages over {MAX_WORDS} words (move results and history to docs/experiments-log/):\n{}",
        over.join("\n")
    );
}

#[test]
fn anchors_follow_githubs_rules() {
    let text = "# A\n## `--linker trackpy` (default)\n## Near the field's edges\n## A\n```\n# not a heading\n```\n";
    let got = anchors(text);
    let want: BTreeSet<String> = [
        "a",
        "a-1",
        "--linker-trackpy-default",
        "near-the-fields-edges",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    assert_eq!(got, want);
    assert_eq!(
        links("see [x](a.md#b) and `[y](c.md)`\n```\n[z](d.md)\n```\n"),
        vec!["a.md#b"]
    );
}
