//! The content keys of every manifest in `experiments/`, as the planner
//! resolves them without running anything, pinned by snapshots
//! (`tests/it/snapshots/`). A key may only change together with a
//! deliberate version bump or a manifest edit; then review the new
//! snapshot (`cargo insta review`, or `INSTA_UPDATE=always`) and commit it.

use std::path::Path;

fn planned_keys(manifest: &str) -> String {
    let path = Path::new("experiments").join(manifest);
    let manifest = scanloc::manifest::load(&path).unwrap();
    let plan = scanloc::run::Plan::from_manifest(&manifest).unwrap();
    let mut text = String::new();
    for step in &plan.steps {
        let seed = step.seed.map(|s| format!(" seed {s}")).unwrap_or_default();
        text.push_str(&format!("{} {}{seed}\n", step.id, step.key));
    }
    text
}

#[test]
fn the_paper_manifests_keys_are_pinned() {
    insta::assert_snapshot!(planned_keys("paper.yaml"));
}

#[test]
fn the_bound_manifests_keys_are_pinned() {
    insta::assert_snapshot!(planned_keys("bound.yaml"));
}

#[test]
fn the_scenes_manifests_keys_are_pinned() {
    insta::assert_snapshot!(planned_keys("scenes.yaml"));
}

#[test]
fn the_tracking_manifests_keys_are_pinned() {
    insta::assert_snapshot!(planned_keys("tracking.yaml"));
}

#[test]
fn the_smoke_manifests_keys_are_pinned() {
    insta::assert_snapshot!(planned_keys("smoke.yaml"));
}

/// Every manifest in `experiments/` has its snapshot test above.
#[test]
fn every_experiment_manifest_is_pinned() {
    let mut names: Vec<String> = std::fs::read_dir("experiments")
        .unwrap()
        .map(|entry| entry.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|name| name.ends_with(".yaml"))
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "bound.yaml",
            "paper.yaml",
            "scenes.yaml",
            "smoke.yaml",
            "tracking.yaml"
        ]
    );
}
