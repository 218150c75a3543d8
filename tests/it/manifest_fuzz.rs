//! The manifest loader on arbitrary and mutated text: it never panics, and
//! every refusal is bad input (exit code 2) naming the file. A fuzzing test:
//! `make fuzz` runs it with `SCANLOC_FUZZ_CASES` cases per property.

use crate::common;

use proptest::prelude::*;
use scanloc::error::exit_code;
use scanloc::manifest;

const SMOKE: &str = include_str!("../../experiments/smoke.yaml");

fn check(text: &str) {
    match manifest::parse(text, "fuzz.yaml") {
        Ok(manifest) => {
            // Whatever parses must resolve to a usable plan.
            assert!(!manifest.datasets.is_empty());
            scanloc::run::Plan::from_manifest(&manifest).unwrap();
        }
        Err(error) => {
            assert_eq!(exit_code(&error), 2, "{error:#}");
            let message = format!("{error:#}");
            assert!(message.starts_with("fuzz.yaml"), "{message}");
            assert_eq!(message.lines().count(), 1, "{message}");
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::fuzz_cases(1500), ..ProptestConfig::default() })]

    #[test]
    fn arbitrary_text_never_panics(text in "\\PC{0,300}") {
        check(&text);
    }

    #[test]
    fn yaml_like_text_never_panics(
        text in "(name: x\n|seed: [0-9-]{1,25}\n|datasets:\n|  [a-z.-]{1,6}:\n|    frames: [-0-9.e]{1,12}\n|    [a-z_]{1,15}: [-0-9.a-z{}\\[\\],: ]{0,20}\n|- [a-z]{1,5}\n|  - [a-z:]{1,8}\n|\t\n|#.{0,5}\n){0,14}"
    ) {
        check(&text);
    }

    #[test]
    fn mutated_smoke_manifests_never_panic(
        edits in proptest::collection::vec((any::<prop::sample::Index>(), 0u8..3, "[ -~\n\t]{0,4}"), 1..6)
    ) {
        let mut text = SMOKE.to_string();
        for (at, kind, insert) in edits {
            let boundaries: Vec<usize> = text.char_indices().map(|(i, _)| i).chain([text.len()]).collect();
            let start = boundaries[at.index(boundaries.len())];
            match kind {
                0 => text.insert_str(start, &insert),
                1 => {
                    let end = boundaries.iter().copied().find(|&b| b > start).unwrap_or(start);
                    text.replace_range(start..end, "");
                }
                _ => {
                    let end = boundaries.iter().copied().filter(|&b| b > start).nth(insert.len()).unwrap_or(text.len());
                    text.replace_range(start..end, &insert);
                }
            }
        }
        check(&text);
    }
}
