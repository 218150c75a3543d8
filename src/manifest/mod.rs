//! Experiment manifests (`experiments/*.yaml`): what to simulate, which
//! detectors to run, how to score them. The format, every field and its
//! default are documented in `docs/manifest.md`.
//!
//! A manifest is parsed strictly: unknown fields are refused, every value is
//! validated, and every default is filled in, so the resolved [`Manifest`]
//! says everything a run will do. Errors are
//! [`InputError`](crate::error::InputError)s of the form
//! `experiments/x.yaml:14: datasets.test-1.00.frames: must be a positive integer`
//! (file, line, field path, what is wrong).
//!
//! ```yaml
//! name: smoke                 # free text, recorded with each run
//! seed: 1234                  # master seed: every artefact's seed derives from it
//! microscope:                 # simulator parameters shared by every dataset
//!   brightness: 7
//!   margin_px: 4
//! datasets:                   # name → frame count + overrides of `microscope`
//!   train: {frames: 200, diffusion_um2_s: {uniform: [0.75, 1.75]}}
//!   test-1.00: {frames: 100, diffusion_um2_s: 1.0}
//! detectors:                  # name → one of the detector kinds
//!   trackpy:
//!     crocker_grier: {diameter: 7, minmass: 0}   # TrackPy's parameter names
//!   cnn:
//!     cnn:
//!       training_set: train    # trained detectors name their training set
//!       architecture: {channels: 16}
//!       training: {epochs: 4}
//! metrics: {eps_px: [1, 2, 3], keep_curves: true}
//! evaluations:                # which detectors are scored on which datasets
//!   - {detector: trackpy, datasets: [test-1.00]}
//!   - {detector: cnn, datasets: [test-1.00]}
//! cross_validation: {folds: 5, detector: cnn}    # optional; run by `scanloc cv`
//! reference:                  # optional: published numbers printed beside ours
//!   source: Table 1
//!   rows:
//!     - {detector: trackpy, label: TrackPy, auc: {test-1.00: [0.04, 0.30, 0.61]}}
//! ```
//!
//! Seeds: each artefact's seed is [`derive_seed`]`(seed, kind, name)`, a
//! hash of the master seed and the artefact's name, so adding, removing or
//! reordering other entries never changes it and no global random state is
//! involved.

pub mod feasibility;
pub mod locate;

use std::fmt;
use std::path::Path;

use serde::de::{self, Deserializer, MapAccess, Visitor};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::error::input_error;
use crate::sim::SimParams;
pub use locate::{LineIndex, Segment, display_path};

/// Largest frame count a dataset may ask for.
pub const MAX_FRAMES: usize = 10_000_000;
/// Largest number of pixels (frames × height × width) one dataset may hold:
/// 2³¹ counts are 8 GiB in memory, more than the machines this runs on have.
pub const MAX_DATASET_PIXELS: usize = 1 << 31;
/// Longest artefact name.
pub const MAX_NAME_LEN: usize = 64;

/// A validated, fully resolved manifest.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Manifest {
    /// Where it was read from, as given by the user (for messages).
    pub source: String,
    /// sha256 of the manifest text, hex.
    pub manifest_sha256: String,
    pub name: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    /// The master seed.
    pub seed: u64,
    /// The shared microscope (defaults filled in).
    pub microscope: SimParams,
    /// Datasets in manifest order.
    pub datasets: Vec<DatasetSpec>,
    /// Detectors in manifest order.
    pub detectors: Vec<DetectorEntry>,
    pub metrics: MetricsSpec,
    /// Every (detector, dataset) pair to score, in manifest order.
    pub evaluations: Vec<EvaluationSpec>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cross_validation: Option<CrossValidation>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reference: Option<Reference>,
    /// The manifest text exactly as read (recorded with runs).
    #[serde(skip)]
    pub text: String,
}

/// One simulated dataset: the microscope with this dataset's overrides.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DatasetSpec {
    pub name: String,
    pub frames: usize,
    /// `derive_seed(master, "dataset", name)`.
    pub seed: u64,
    pub params: SimParams,
}

impl DatasetSpec {
    /// The dataset's diffusion coefficient if it is the same for every
    /// frame (the AUC table's column label), `None` for a distribution.
    pub fn fixed_diffusion(&self) -> Option<f64> {
        match self.params.diffusion_um2_s {
            crate::sim::Distribution::Fixed(d) => Some(d),
            crate::sim::Distribution::Random(_) => None,
        }
    }
}

/// The detector kinds a manifest can declare, as a YAML mapping with one
/// key naming the kind: `{crocker_grier: {...}}` or `{cnn: {...}}`.
///
/// Each kind's parameters are its module's own serde type (strict, with
/// defaults). Adding a kind means: a variant here, its validation in
/// [`DetectorSpec::validate`], its code version in
/// [`DetectorSpec::code_version`], and its execution in `run::execute`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum DetectorSpec {
    /// TrackPy's `locate` ([`crate::detect::crocker_grier`]); its parameters
    /// with TrackPy's names and defaults, e.g. `{diameter: 7, minmass: 0}`.
    CrockerGrier(crate::detect::crocker_grier::CrockerGrierParams),
    /// The CNN locator ([`crate::detect::cnn`]), trained on a dataset of
    /// the manifest.
    Cnn(CnnSpec),
}

/// A CNN detector: what it is trained on, its network, its training.
///
/// ```yaml
/// cnn:
///   training_set: train        # a dataset of this manifest
///   architecture: {channels: 32, dilations: [1, 1, 2, 4, 2, 1]}
///   training: {epochs: 20, batch_size: 64, validation_fraction: 0.1}
/// ```
///
/// Both `architecture` and `training` default to the CNN module's defaults.
/// The training seed is the detector's derived seed; with
/// `training.fresh_frames_per_epoch > 0`, fresh frames are simulated each
/// epoch with the training set's microscope.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CnnSpec {
    pub training_set: String,
    #[serde(default)]
    pub architecture: crate::detect::cnn::CnnArchitecture,
    #[serde(default)]
    pub training: crate::detect::cnn::TrainingSettings,
}

impl DetectorSpec {
    /// The name of the kind as written in manifests.
    pub fn kind(&self) -> &'static str {
        match self {
            DetectorSpec::CrockerGrier(_) => "crocker_grier",
            DetectorSpec::Cnn(_) => "cnn",
        }
    }

    /// The dataset this detector is trained on, if it is trained.
    pub fn training_dataset(&self) -> Option<&str> {
        match self {
            DetectorSpec::CrockerGrier(_) => None,
            DetectorSpec::Cnn(spec) => Some(&spec.training_set),
        }
    }

    /// Checks the parameters; errors start with the offending field's name.
    pub fn validate(&self) -> anyhow::Result<()> {
        match self {
            DetectorSpec::CrockerGrier(params) => params.validate(),
            DetectorSpec::Cnn(spec) => {
                spec.architecture.validate()?;
                spec.training.validate()
            }
        }
    }

    /// Version of the code that turns this detector's inputs into its
    /// outputs; part of the content key of everything it makes.
    pub fn code_version(&self) -> &'static str {
        match self {
            DetectorSpec::CrockerGrier(_) => crate::detect::crocker_grier::CODE_VERSION,
            DetectorSpec::Cnn(_) => crate::detect::cnn::CODE_VERSION,
        }
    }
}

/// A named detector.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DetectorEntry {
    pub name: String,
    /// `derive_seed(master, "detector", name)`: the seed of its training.
    pub seed: u64,
    pub spec: DetectorSpec,
}

/// How evaluations are scored (the metric: `docs/metric.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MetricsSpec {
    /// Matching radii in pixels, in the AUC table's column order.
    pub eps_px: Vec<f64>,
    /// Keep the precision–recall curves in the stored evaluations (for
    /// reports).
    pub keep_curves: bool,
}

impl Default for MetricsSpec {
    fn default() -> Self {
        Self {
            eps_px: crate::metrics::PAPER_EPS_PX.to_vec(),
            keep_curves: true,
        }
    }
}

/// One detector scored on one dataset.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct EvaluationSpec {
    pub detector: String,
    pub dataset: String,
}

/// Optional k-fold cross-validation of a trained detector over its
/// training set.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CrossValidation {
    /// Number of folds k (2 to 50).
    pub folds: usize,
    /// The detector to cross-validate (one with a training set).
    pub detector: String,
}

impl CrossValidation {
    /// Checks a fold count k (2 to 50): the one place that range is
    /// enforced, for manifests and the command line alike.
    pub fn check_folds(folds: usize) -> Result<(), String> {
        if (2..=50).contains(&folds) {
            Ok(())
        } else {
            Err(format!("must be between 2 and 50, got {folds}"))
        }
    }
}

/// Published numbers to print beside ours (e.g. the paper's Table 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reference {
    pub source: String,
    pub rows: Vec<ReferenceRow>,
}

/// One published row: a detector's AUC per dataset and ε.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReferenceRow {
    /// The detector of this manifest the row compares with.
    pub detector: String,
    /// The row's name in the source (e.g. `TrackPy`).
    pub label: String,
    /// One value per (dataset, ε).
    pub cells: Vec<ReferenceCell>,
}

/// One published AUC value.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReferenceCell {
    pub dataset: String,
    pub eps_px: f64,
    pub auc: f64,
}

impl Reference {
    /// The published AUC of `detector` on `dataset` at `eps_px`, from the
    /// first row that compares with `detector`.
    pub fn auc(&self, detector: &str, dataset: &str, eps_px: f64) -> Option<f64> {
        self.rows
            .iter()
            .find(|row| row.detector == detector)
            .and_then(|row| row.auc(dataset, eps_px))
    }
}

impl ReferenceRow {
    /// This row's AUC on `dataset` at `eps_px`.
    pub fn auc(&self, dataset: &str, eps_px: f64) -> Option<f64> {
        self.cells
            .iter()
            .find(|c| c.dataset == dataset && c.eps_px == eps_px)
            .map(|c| c.auc)
    }
}

impl Manifest {
    /// The dataset named `name`.
    pub fn dataset(&self, name: &str) -> Option<&DatasetSpec> {
        self.datasets.iter().find(|d| d.name == name)
    }

    /// The detector named `name`.
    pub fn detector(&self, name: &str) -> Option<&DetectorEntry> {
        self.detectors.iter().find(|d| d.name == name)
    }

    /// The resolved manifest as YAML (what `scanloc check` prints).
    pub fn to_resolved_yaml(&self) -> anyhow::Result<String> {
        // Through JSON so enums print as `{variant: value}` maps, the way
        // manifests write them, rather than as YAML tags.
        Ok(serde_yaml::to_string(&serde_json::to_value(self)?)?)
    }
}

/// The seed of artefact `name` of kind `kind` (`dataset`, `detector`, …):
/// the first 8 bytes (little-endian) of
/// `sha256("scanloc-seed/1\0" ‖ master as 8 LE bytes ‖ kind ‖ "\0" ‖ name)`.
pub fn derive_seed(master: u64, kind: &str, name: &str) -> u64 {
    let mut hasher = Sha256::new();
    hasher.update(b"scanloc-seed/1\0");
    hasher.update(master.to_le_bytes());
    hasher.update(kind.as_bytes());
    hasher.update([0u8]);
    hasher.update(name.as_bytes());
    let digest = hasher.finalize();
    let mut bytes = [0u8; 8];
    bytes.copy_from_slice(&digest[..8]);
    u64::from_le_bytes(bytes)
}

/// Reads and resolves the manifest at `path`.
pub fn load(path: &Path) -> anyhow::Result<Manifest> {
    let source = path.display().to_string();
    let text = std::fs::read_to_string(path)
        .map_err(|e| input_error(format!("{source}: cannot read: {e}")))?;
    parse(&text, &source)
}

/// Parses and resolves manifest `text`; `source` names it in errors.
pub fn parse(text: &str, source: &str) -> anyhow::Result<Manifest> {
    // Editors on Windows save UTF-8 with a byte-order mark; YAML allows it
    // but serde_yaml takes it for the start of a second document.
    let text = text.strip_prefix('\u{feff}').unwrap_or(text);
    let lines = LineIndex::new(text);
    let located = |error: serde_yaml::Error| -> anyhow::Error {
        let message = error.to_string();
        // serde_yaml appends " at line L column C"; we put the line first.
        let message = match message.rfind(" at line ") {
            Some(cut) => message[..cut].to_string(),
            None => message,
        };
        let message = if message.contains("as u128") || message.contains("as i128") {
            let field = message.split_once(": ").map_or("", |(f, _)| f);
            format!(
                "{field}{}number too large: integers must fit in 64 bits",
                if field.is_empty() { "" } else { ": " }
            )
        } else {
            message
        };
        let message = one_line(&message);
        match error.location() {
            Some(location) => input_error(format!("{source}:{}: {message}", location.line())),
            None => input_error(format!("{source}: {message}")),
        }
    };
    // First as plain YAML: syntax errors and duplicate keys, with lines.
    let document: serde_yaml::Value = serde_yaml::from_str(text).map_err(located)?;
    if !document.is_mapping() {
        return Err(input_error(format!(
            "{source}:1: a manifest must be a YAML mapping with name, seed, datasets, …"
        )));
    }
    let raw: RawManifest = serde_yaml::from_str(text).map_err(located)?;
    let context = Context {
        source,
        lines: &lines,
    };
    resolve(raw, text, &context)
}

/// `text` with line breaks escaped, so an error stays one line even when it
/// quotes a key or value that spans lines.
fn one_line(text: &str) -> String {
    text.replace('\r', "\\r").replace('\n', "\\n")
}

/// Where a manifest came from, for located errors.
struct Context<'a> {
    source: &'a str,
    lines: &'a LineIndex,
}

impl Context<'_> {
    fn error(&self, path: &[Segment], message: impl fmt::Display) -> anyhow::Error {
        let field = one_line(&display_path(path));
        let message = one_line(&message.to_string());
        match self.lines.line_of(path) {
            Some(line) => input_error(format!("{}:{line}: {field}: {message}", self.source)),
            None => input_error(format!("{}: {field}: {message}", self.source)),
        }
    }
}

fn key(k: &str) -> Segment {
    Segment::Key(k.to_string())
}

fn path_of(parts: &[&str]) -> Vec<Segment> {
    parts.iter().map(|p| key(p)).collect()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawManifest {
    name: String,
    #[serde(default)]
    description: Option<String>,
    seed: u64,
    #[serde(default)]
    microscope: serde_yaml::Mapping,
    datasets: Named<serde_yaml::Mapping>,
    #[serde(default)]
    detectors: Named<SingletonMap<DetectorSpec>>,
    #[serde(default)]
    metrics: MetricsSpec,
    #[serde(default)]
    evaluations: Vec<RawEvaluation>,
    #[serde(default)]
    cross_validation: Option<CrossValidation>,
    #[serde(default)]
    reference: Option<RawReference>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEvaluation {
    detector: String,
    datasets: Vec<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawReference {
    #[serde(default)]
    source: String,
    rows: Vec<RawReferenceRow>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawReferenceRow {
    detector: String,
    #[serde(default)]
    label: Option<String>,
    /// dataset name → one AUC per ε of `metrics.eps_px`.
    auc: Named<Vec<f64>>,
}

/// An enum written as a one-entry YAML mapping `{variant: value}` (serde_yaml
/// 0.9 otherwise expects a `!variant` tag).
struct SingletonMap<T>(T);

impl<'de, T: Deserialize<'de>> Deserialize<'de> for SingletonMap<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        serde_yaml::with::singleton_map::deserialize(deserializer).map(SingletonMap)
    }
}

/// A YAML mapping from names to values that keeps the manifest's order and
/// refuses duplicate names.
struct Named<V>(Vec<(String, V)>);

impl<V> Default for Named<V> {
    fn default() -> Self {
        Named(Vec::new())
    }
}

impl<'de, V: Deserialize<'de>> Deserialize<'de> for Named<V> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct NamedVisitor<V>(std::marker::PhantomData<V>);
        impl<'de, V: Deserialize<'de>> Visitor<'de> for NamedVisitor<V> {
            type Value = Named<V>;
            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a mapping from names to entries")
            }
            fn visit_unit<E: de::Error>(self) -> Result<Self::Value, E> {
                Ok(Named(Vec::new()))
            }
            fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
                let mut entries: Vec<(String, V)> = Vec::new();
                while let Some(name) = map.next_key::<String>()? {
                    if entries.iter().any(|(n, _)| *n == name) {
                        return Err(de::Error::custom(format!("duplicate name `{name}`")));
                    }
                    let value = map.next_value::<V>()?;
                    entries.push((name, value));
                }
                Ok(Named(entries))
            }
        }
        deserializer.deserialize_map(NamedVisitor(std::marker::PhantomData))
    }
}

fn check_name(context: &Context, path: &[Segment], name: &str) -> anyhow::Result<()> {
    let valid = !name.is_empty()
        && name.len() <= MAX_NAME_LEN
        && name
            .chars()
            .next()
            .is_some_and(|c| c.is_ascii_alphanumeric())
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
    if valid {
        Ok(())
    } else {
        Err(context.error(
            path,
            format!(
                "invalid name {name:?}: use 1 to {MAX_NAME_LEN} letters, digits, '.', '_' or '-', starting with a letter or digit"
            ),
        ))
    }
}

/// The field names of [`SimParams`], from its serialised default.
fn sim_field_names() -> Vec<String> {
    match serde_yaml::to_value(SimParams::default()) {
        Ok(serde_yaml::Value::Mapping(mapping)) => mapping
            .keys()
            .filter_map(|k| k.as_str().map(str::to_string))
            .collect(),
        _ => Vec::new(),
    }
}

/// Applies `overrides` (a YAML mapping of [`SimParams`] fields, found at
/// `path`) on top of `base`, checking each field on its own so an error
/// names the field.
fn apply_sim_overrides(
    context: &Context,
    path: &[Segment],
    base: &SimParams,
    overrides: &serde_yaml::Mapping,
    skip: &[&str],
) -> anyhow::Result<SimParams> {
    let fields = sim_field_names();
    let serde_yaml::Value::Mapping(mut merged) = serde_yaml::to_value(base)? else {
        anyhow::bail!("simulator parameters do not serialise to a mapping");
    };
    for (field, value) in overrides {
        let Some(name) = field.as_str() else {
            return Err(context.error(path, "field names must be strings"));
        };
        if skip.contains(&name) {
            continue;
        }
        let mut field_path = path.to_vec();
        field_path.push(key(name));
        if !fields.iter().any(|f| f == name) {
            return Err(context.error(
                &field_path,
                format!(
                    "unknown field `{name}`, expected one of: {}",
                    skip.iter()
                        .map(|s| s.to_string())
                        .chain(fields.iter().cloned())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            ));
        }
        let value = &as_tagged_enum(value);
        let mut single = merged.clone();
        single.insert(field.clone(), value.clone());
        if let Err(error) = serde_yaml::from_value::<SimParams>(serde_yaml::Value::Mapping(single))
        {
            let message = error.to_string();
            let message = if message.contains("untagged enum Distribution") {
                "must be a number or {uniform: [LOW, HIGH]}".to_string()
            } else {
                message
            };
            return Err(context.error(&field_path, message));
        }
        merged.insert(field.clone(), value.clone());
    }
    serde_yaml::from_value(serde_yaml::Value::Mapping(merged))
        .map_err(|e| context.error(path, e.to_string()))
}

/// A one-entry mapping `{variant: value}` whose key is a plain name, as
/// the tagged value `!variant value` serde_yaml 0.9 expects for an enum;
/// anything else unchanged. (Distributions, being untagged, accept both.)
fn as_tagged_enum(value: &serde_yaml::Value) -> serde_yaml::Value {
    if let serde_yaml::Value::Mapping(mapping) = value
        && mapping.len() == 1
        && let Some((serde_yaml::Value::String(variant), inner)) = mapping.iter().next()
        && variant != "uniform"
        && variant.chars().all(|c| c.is_ascii_lowercase() || c == '_')
    {
        return serde_yaml::Value::Tagged(Box::new(serde_yaml::value::TaggedValue {
            tag: serde_yaml::value::Tag::new(variant.clone()),
            value: inner.clone(),
        }));
    }
    value.clone()
}

/// Turns a validation error `field: message` from a parameter type into a
/// located error, attributing the field to `own` if that mapping sets it
/// and to `inherited` otherwise.
fn locate_validation_error(
    context: &Context,
    error: anyhow::Error,
    own: (&[Segment], Option<&serde_yaml::Mapping>),
    inherited: &[Segment],
) -> anyhow::Error {
    let message = error.to_string();
    let Some((field, rest)) = message.split_once(": ") else {
        return context.error(own.0, message);
    };
    if field.contains(' ') {
        return context.error(own.0, message);
    }
    let top = field.split('.').next().unwrap_or(field);
    let overridden = own
        .1
        .is_some_and(|m| m.contains_key(serde_yaml::Value::String(top.to_string())));
    let mut path = if overridden || own.1.is_none() {
        own.0.to_vec()
    } else {
        inherited.to_vec()
    };
    path.extend(field.split('.').map(key));
    context.error(&path, rest)
}

fn parse_frames(
    context: &Context,
    path: &[Segment],
    value: Option<&serde_yaml::Value>,
) -> anyhow::Result<usize> {
    let Some(value) = value else {
        return Err(context.error(path, "missing field `frames` (the number of frames)"));
    };
    let mut frames_path = path.to_vec();
    frames_path.push(key("frames"));
    match value.as_u64() {
        Some(0) | None => Err(context.error(&frames_path, "must be a positive integer")),
        Some(n) if n > MAX_FRAMES as u64 => Err(context.error(
            &frames_path,
            format!("must be at most {MAX_FRAMES}, got {n}"),
        )),
        Some(n) => Ok(n as usize),
    }
}

fn resolve(raw: RawManifest, text: &str, context: &Context) -> anyhow::Result<Manifest> {
    let RawManifest {
        name,
        description,
        seed,
        microscope: raw_microscope,
        datasets: raw_datasets,
        detectors: raw_detectors,
        metrics,
        evaluations: raw_evaluations,
        cross_validation,
        reference: raw_reference,
    } = raw;
    if name.trim().is_empty() {
        return Err(context.error(&[key("name")], "must not be empty"));
    }

    let microscope_path = [key("microscope")];
    let microscope = apply_sim_overrides(
        context,
        &microscope_path,
        &SimParams::default(),
        &raw_microscope,
        &[],
    )?;
    microscope
        .validate()
        .map_err(|e| locate_validation_error(context, e, (&microscope_path, None), &[]))?;

    if raw_datasets.0.is_empty() {
        return Err(context.error(&[key("datasets")], "must declare at least one dataset"));
    }
    let mut datasets = Vec::new();
    for (dataset_name, entry) in &raw_datasets.0 {
        let path = path_of(&["datasets", dataset_name]);
        check_name(context, &path, dataset_name)?;
        let frames = parse_frames(context, &path, entry.get("frames"))?;
        let params = apply_sim_overrides(context, &path, &microscope, entry, &["frames"])?;
        params.validate().map_err(|e| {
            locate_validation_error(context, e, (&path, Some(entry)), &microscope_path)
        })?;
        let pixels = frames
            .checked_mul(params.height)
            .and_then(|p| p.checked_mul(params.width));
        if pixels.is_none_or(|p| p > MAX_DATASET_PIXELS) {
            let mut frames_path = path.clone();
            frames_path.push(key("frames"));
            return Err(context.error(
                &frames_path,
                format!(
                    "{frames} frames of {}×{} pixels exceed the limit of {MAX_DATASET_PIXELS} pixels per dataset",
                    params.height, params.width
                ),
            ));
        }
        datasets.push(DatasetSpec {
            name: dataset_name.clone(),
            frames,
            seed: derive_seed(seed, "dataset", dataset_name),
            params,
        });
    }
    let has_dataset = |n: &str| datasets.iter().any(|d| d.name == n);

    let mut detectors = Vec::new();
    for (detector_name, SingletonMap(spec)) in raw_detectors.0 {
        let path = path_of(&["detectors", &detector_name]);
        check_name(context, &path, &detector_name)?;
        {
            let kind_path = {
                let mut p = path.clone();
                p.push(key(spec.kind()));
                p
            };
            spec.validate()
                .map_err(|e| locate_validation_error(context, e, (&kind_path, None), &[]))?;
            if let Some(training) = spec.training_dataset()
                && !has_dataset(training)
            {
                let mut path = kind_path.clone();
                path.push(key("training_set"));
                return Err(context.error(
                    &path,
                    format!("`{training}` is not a dataset of this manifest"),
                ));
            }
            detectors.push(DetectorEntry {
                seed: derive_seed(seed, "detector", &detector_name),
                name: detector_name,
                spec,
            });
        }
    }
    let has_detector = |n: &str| detectors.iter().any(|d| d.name == n);

    let metrics_path = path_of(&["metrics", "eps_px"]);
    if metrics.eps_px.is_empty() {
        return Err(context.error(&metrics_path, "must list at least one radius"));
    }
    if metrics.eps_px.len() > 32 {
        return Err(context.error(&metrics_path, "must list at most 32 radii"));
    }
    for (index, &eps) in metrics.eps_px.iter().enumerate() {
        let mut path = metrics_path.clone();
        path.push(Segment::Index(index));
        if !(eps.is_finite() && eps > 0.0 && eps <= 1e6) {
            return Err(context.error(
                &path,
                format!("must be a positive number of pixels (at most 1e6), got {eps}"),
            ));
        }
        if metrics.eps_px[..index].contains(&eps) {
            return Err(context.error(&path, format!("duplicate radius {eps}")));
        }
    }

    let mut evaluations: Vec<EvaluationSpec> = Vec::new();
    for (index, evaluation) in raw_evaluations.iter().enumerate() {
        let path = vec![key("evaluations"), Segment::Index(index)];
        let mut detector_path = path.clone();
        detector_path.push(key("detector"));
        if !has_detector(&evaluation.detector) {
            return Err(context.error(
                &detector_path,
                format!(
                    "`{}` is not a detector of this manifest",
                    evaluation.detector
                ),
            ));
        }
        if evaluation.datasets.is_empty() {
            let mut datasets_path = path.clone();
            datasets_path.push(key("datasets"));
            return Err(context.error(&datasets_path, "must list at least one dataset"));
        }
        for (position, dataset) in evaluation.datasets.iter().enumerate() {
            let mut dataset_path = path.clone();
            dataset_path.push(key("datasets"));
            dataset_path.push(Segment::Index(position));
            if !has_dataset(dataset) {
                return Err(context.error(
                    &dataset_path,
                    format!("`{dataset}` is not a dataset of this manifest"),
                ));
            }
            let spec = EvaluationSpec {
                detector: evaluation.detector.clone(),
                dataset: dataset.clone(),
            };
            if evaluations.contains(&spec) {
                return Err(context.error(
                    &dataset_path,
                    format!(
                        "`{}` is already evaluated on `{dataset}`",
                        evaluation.detector
                    ),
                ));
            }
            evaluations.push(spec);
        }
    }

    if let Some(cv) = &cross_validation {
        if let Err(message) = CrossValidation::check_folds(cv.folds) {
            return Err(context.error(&path_of(&["cross_validation", "folds"]), message));
        }
        let detector_path = path_of(&["cross_validation", "detector"]);
        match detectors.iter().find(|d| d.name == cv.detector) {
            None => {
                return Err(context.error(
                    &detector_path,
                    format!("`{}` is not a detector of this manifest", cv.detector),
                ));
            }
            Some(entry) => {
                if entry.spec.training_dataset().is_none() {
                    return Err(context.error(
                        &detector_path,
                        format!(
                            "`{}` is not trained, so there is nothing to cross-validate",
                            cv.detector
                        ),
                    ));
                }
            }
        }
    }

    let reference = match raw_reference {
        None => None,
        Some(raw) => {
            let mut rows = Vec::new();
            for (index, row) in raw.rows.into_iter().enumerate() {
                let path = vec![key("reference"), key("rows"), Segment::Index(index)];
                if !has_detector(&row.detector) {
                    let mut p = path.clone();
                    p.push(key("detector"));
                    return Err(context.error(
                        &p,
                        format!("`{}` is not a detector of this manifest", row.detector),
                    ));
                }
                let mut cells = Vec::new();
                for (dataset, values) in row.auc.0 {
                    let mut p = path.clone();
                    p.push(key("auc"));
                    p.push(key(&dataset));
                    if !has_dataset(&dataset) {
                        return Err(context
                            .error(&p, format!("`{dataset}` is not a dataset of this manifest")));
                    }
                    if values.len() != metrics.eps_px.len() {
                        return Err(context.error(
                            &p,
                            format!(
                                "must list one AUC per radius of metrics.eps_px ({}), got {}",
                                metrics.eps_px.len(),
                                values.len()
                            ),
                        ));
                    }
                    for (&eps_px, &auc) in metrics.eps_px.iter().zip(&values) {
                        if !(auc.is_finite() && (0.0..=1.0).contains(&auc)) {
                            return Err(context.error(
                                &p,
                                format!("AUC values must be between 0 and 1, got {auc}"),
                            ));
                        }
                        cells.push(ReferenceCell {
                            dataset: dataset.clone(),
                            eps_px,
                            auc,
                        });
                    }
                }
                rows.push(ReferenceRow {
                    label: row.label.unwrap_or_else(|| row.detector.clone()),
                    detector: row.detector,
                    cells,
                });
            }
            Some(Reference {
                source: raw.source,
                rows,
            })
        }
    };

    let manifest = Manifest {
        source: context.source.to_string(),
        manifest_sha256: hex::encode(Sha256::digest(text.as_bytes())),
        name,
        description,
        seed,
        microscope,
        datasets,
        detectors,
        metrics,
        evaluations,
        cross_validation,
        reference,
        text: text.to_string(),
    };
    feasibility::check(&manifest).map_err(|p| context.error(&p.path, p.message))?;
    Ok(manifest)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_depend_on_master_kind_and_name_only() {
        let a = derive_seed(1, "dataset", "train");
        assert_eq!(a, derive_seed(1, "dataset", "train"));
        assert_ne!(a, derive_seed(2, "dataset", "train"));
        assert_ne!(a, derive_seed(1, "detector", "train"));
        assert_ne!(a, derive_seed(1, "dataset", "train2"));
    }

    #[test]
    fn datasets_inherit_the_microscope_and_override_it() {
        let text = "name: t\nseed: 3\nmicroscope:\n  brightness: 9\n  margin_px: 4\ndatasets:\n  a:\n    frames: 5\n  b:\n    frames: 6\n    brightness: 11\n    diffusion_um2_s: {uniform: [0.75, 1.75]}\n";
        let manifest = parse(text, "t.yaml").unwrap();
        assert_eq!(manifest.datasets[0].params.brightness, 9.0);
        assert_eq!(manifest.datasets[0].params.margin_px, 4.0);
        assert_eq!(manifest.datasets[1].params.brightness, 11.0);
        assert_eq!(manifest.datasets[1].frames, 6);
        assert_eq!(manifest.datasets[1].fixed_diffusion(), None);
        assert_eq!(manifest.datasets[0].seed, derive_seed(3, "dataset", "a"));
    }

    #[test]
    fn errors_name_file_line_and_path() {
        let text = "name: t\nseed: 3\ndatasets:\n  test-1.00:\n    frames: 0\n";
        let error = parse(text, "x.yaml").unwrap_err().to_string();
        assert_eq!(
            error,
            "x.yaml:5: datasets.test-1.00.frames: must be a positive integer"
        );
        let text =
            "name: t\nseed: 3\nmicroscope:\n  brightness: -1\ndatasets:\n  a:\n    frames: 2\n";
        let error = parse(text, "x.yaml").unwrap_err().to_string();
        assert!(
            error.starts_with("x.yaml:4: microscope.brightness: must be ≥ 0"),
            "{error}"
        );
        let text = "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 2\n    detector_noise: {pmt: {excess_noise_factor: 2}}\n";
        let manifest = parse(text, "x.yaml").unwrap();
        assert_eq!(
            manifest.datasets[0].params.detector_noise,
            crate::sim::DetectorNoise::Pmt {
                excess_noise_factor: 2.0
            }
        );
        assert!(manifest.to_resolved_yaml().unwrap().contains("pmt:"));
        let text = "name: t\nseed: 3\ndatasets:\n  a:\n    frames: 2\n    brightnes: 3\n";
        let error = parse(text, "x.yaml").unwrap_err().to_string();
        assert!(
            error.starts_with("x.yaml:6: datasets.a.brightnes: unknown field"),
            "{error}"
        );
    }
}
