//! Finds the line of a node in a manifest's YAML text from its path
//! (`datasets` → `test-1.00` → `frames`), so that errors found after parsing
//! (a value out of range, a reference to a missing dataset) can name the
//! line like parse errors do.
//!
//! It indexes block-style YAML, the style manifests are written in: mapping
//! keys and sequence items, by indentation. Anything inside a flow
//! collection (`{uniform: [0.75, 1.75]}`) is attributed to the line of the
//! key that holds it. A path not found falls back to its longest prefix
//! that is found.

use std::collections::HashMap;

use crate::error::Segment;

/// The line (1-based) of every key and sequence item of a document.
pub struct LineIndex {
    lines: HashMap<Vec<Segment>, usize>,
}

struct Open {
    indent: usize,
    segment: Segment,
    is_item: bool,
}

impl LineIndex {
    /// Indexes `text`. Never fails: lines it cannot read are skipped.
    pub fn new(text: &str) -> Self {
        let mut lines = HashMap::new();
        let mut stack: Vec<Open> = Vec::new();
        let mut item_counts: HashMap<Vec<Segment>, usize> = HashMap::new();
        for (number, raw) in text.lines().enumerate() {
            let line = number + 1;
            let trimmed = raw.trim_start_matches(' ');
            if trimmed.trim().is_empty() || trimmed.starts_with('#') || trimmed.starts_with("---") {
                continue;
            }
            let mut column = raw.len() - trimmed.len();
            let mut content = trimmed;
            // Sequence items, possibly several on one line (`- - a`).
            while content == "-" || content.starts_with("- ") {
                while stack
                    .last()
                    .is_some_and(|o| o.indent > column || (o.is_item && o.indent == column))
                {
                    stack.pop();
                }
                let parent: Vec<Segment> = stack.iter().map(|o| o.segment.clone()).collect();
                let count = item_counts.entry(parent.clone()).or_insert(0);
                let index = *count;
                *count += 1;
                let mut path = parent;
                path.push(Segment::Index(index));
                item_counts.remove(&path);
                lines.entry(path).or_insert(line);
                stack.push(Open {
                    indent: column,
                    segment: Segment::Index(index),
                    is_item: true,
                });
                let rest = content[1..].trim_start_matches(' ');
                column += content.len() - rest.len();
                content = rest;
            }
            let Some(key) = mapping_key(content) else {
                continue;
            };
            while stack.last().is_some_and(|o| o.indent >= column) {
                stack.pop();
            }
            let mut path: Vec<Segment> = stack.iter().map(|o| o.segment.clone()).collect();
            path.push(Segment::Key(key.clone()));
            item_counts.remove(&path);
            lines.entry(path).or_insert(line);
            stack.push(Open {
                indent: column,
                segment: Segment::Key(key),
                is_item: false,
            });
        }
        Self { lines }
    }

    /// The line of `path`, or of its longest prefix that the index knows.
    pub fn line_of(&self, path: &[Segment]) -> Option<usize> {
        (1..=path.len())
            .rev()
            .find_map(|len| self.lines.get(&path[..len]).copied())
    }
}

/// The key of a `key: value` or `key:` line, unquoted; `None` for other
/// lines (scalars, flow collections, block-scalar bodies).
fn mapping_key(content: &str) -> Option<String> {
    let content = content.trim_end();
    for quote in ['"', '\''] {
        if let Some(rest) = content.strip_prefix(quote) {
            let end = rest.find(quote)?;
            let after = rest[end + 1..].trim_start();
            return (after == ":" || after.starts_with(": ")).then(|| rest[..end].to_string());
        }
    }
    if content.starts_with(['{', '[', '|', '>', '&', '*', '!']) {
        return None;
    }
    let end = if let Some(position) = content.find(": ") {
        position
    } else if let Some(stripped) = content.strip_suffix(':') {
        stripped.len()
    } else {
        return None;
    };
    let key = content[..end].trim();
    (!key.is_empty() && !key.contains(" #")).then(|| key.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::display_path;

    fn key(k: &str) -> Segment {
        Segment::key(k)
    }

    #[test]
    fn finds_nested_keys_and_sequence_items() {
        let text = "\
name: x
# comment
datasets:
  test-1.00:
    frames: 10
    diffusion_um2_s: {uniform: [1, 2]}
  \"quoted name\":
    frames: 3
evaluations:
- detector: a
  datasets: [t]
- detector: b
metrics:
  eps_px:
    - 1
    - 2
";
        let index = LineIndex::new(text);
        assert_eq!(index.line_of(&[key("name")]), Some(1));
        assert_eq!(
            index.line_of(&[key("datasets"), key("test-1.00"), key("frames")]),
            Some(5)
        );
        assert_eq!(
            index.line_of(&[key("datasets"), key("test-1.00"), key("diffusion_um2_s")]),
            Some(6)
        );
        assert_eq!(
            index.line_of(&[key("datasets"), key("quoted name"), key("frames")]),
            Some(8)
        );
        assert_eq!(
            index.line_of(&[key("evaluations"), Segment::Index(1), key("detector")]),
            Some(12)
        );
        assert_eq!(
            index.line_of(&[key("evaluations"), Segment::Index(0), key("datasets")]),
            Some(11)
        );
        assert_eq!(
            index.line_of(&[key("metrics"), key("eps_px"), Segment::Index(1)]),
            Some(16)
        );
        // Unknown leaf: falls back to the parent.
        assert_eq!(
            index.line_of(&[key("datasets"), key("test-1.00"), key("nope")]),
            Some(4)
        );
        assert_eq!(
            display_path(&[key("evaluations"), Segment::Index(1), key("detector")]),
            "evaluations[1].detector"
        );
    }
}
