//! The `microscope` section, and the simulator parameters datasets
//! override on top of it.

use crate::error::{FieldError, Segment};
use crate::manifest::serde_adapters::as_tagged_enum;
use crate::sim::SimParams;

/// The `microscope` section: the simulator's defaults with the section's
/// fields on top, checked.
pub(super) fn resolve_microscope(section: &serde_yaml::Mapping) -> Result<SimParams, FieldError> {
    let path = super::path_of(&["microscope"]);
    let microscope = apply_sim_overrides(&path, &SimParams::default(), section, &[])?;
    microscope.validate().map_err(|e| e.under(&path))?;
    Ok(microscope)
}

/// Applies `overrides` (a YAML mapping of [`SimParams`] fields, found at
/// `path`) on top of `base`, reading each field on its own so an error
/// names the field. Keys in `skip` belong to the caller (a dataset's
/// `frames`) and are left alone. The result is not yet checked with
/// [`SimParams::validate`].
pub(super) fn apply_sim_overrides(
    path: &[Segment],
    base: &SimParams,
    overrides: &serde_yaml::Mapping,
    skip: &[&str],
) -> Result<SimParams, FieldError> {
    let fields = sim_field_names();
    let mut merged = as_mapping(base);
    for (field, value) in overrides {
        let Some(name) = field.as_str() else {
            return Err(FieldError::at(path, "field names must be strings"));
        };
        if skip.contains(&name) {
            continue;
        }
        let field_path = super::field(path, name);
        if !fields.iter().any(|f| f == name) {
            return Err(FieldError::at(
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
        let value = as_tagged_enum(value);
        let mut single = merged.clone();
        single.insert(field.clone(), value.clone());
        if let Err(error) = serde_yaml::from_value::<SimParams>(serde_yaml::Value::Mapping(single))
        {
            return Err(FieldError::at(
                &field_path,
                refusal(&merged, field).unwrap_or_else(|| error.to_string()),
            ));
        }
        merged.insert(field.clone(), value);
    }
    serde_yaml::from_value(serde_yaml::Value::Mapping(merged))
        .map_err(|e| FieldError::at(path, e.to_string()))
}

/// What field `field` accepts, said in the manifest's terms, when it is
/// one of the untagged enums, whose serde errors name neither the field
/// nor what it takes (`None` for other fields, whose serde error says it).
/// The field's type is told by what it accepts on top of `merged` (fields
/// that read): a distribution field takes `{uniform: [0, 1]}`, a count
/// `{choice: [1]}`.
fn refusal(merged: &serde_yaml::Mapping, field: &serde_yaml::Value) -> Option<String> {
    let accepts = |probe: &str| {
        let probe: serde_yaml::Value =
            serde_yaml::from_str(probe).expect("a probe value is valid YAML");
        let mut single = merged.clone();
        single.insert(field.clone(), as_tagged_enum(&probe));
        serde_yaml::from_value::<SimParams>(serde_yaml::Value::Mapping(single)).is_ok()
    };
    if accepts("{uniform: [0, 1]}") {
        Some("must be a number or {uniform: [LOW, HIGH]}".to_string())
    } else if accepts("{choice: [1]}") {
        Some(
            "must be a whole number or {choice: [N, ...]} with optional weights: [W, ...]"
                .to_string(),
        )
    } else {
        None
    }
}

/// `params` as a YAML mapping of its fields, each written as a manifest
/// writes it and [`apply_sim_overrides`] passes it on: through JSON, so a
/// distribution is the mapping `{uniform: [LOW, HIGH]}` its untagged enum
/// reads back (serde_yaml would write a `!uniform` tag, which it cannot),
/// then [`as_tagged_enum`] for the tagged enums (`{pmt: {...}}`).
fn as_mapping(params: &SimParams) -> serde_yaml::Mapping {
    let value = serde_json::to_value(params)
        .map_err(|e| e.to_string())
        .and_then(|json| serde_yaml::to_value(json).map_err(|e| e.to_string()));
    match value {
        Ok(serde_yaml::Value::Mapping(mapping)) => mapping
            .into_iter()
            .map(|(field, value)| {
                let value = as_tagged_enum(&value);
                (field, value)
            })
            .collect(),
        // A struct of numbers and enums always serialises to a mapping.
        other => unreachable!("SimParams serialised to {other:?}"),
    }
}

/// The field names of [`SimParams`], from its serialised default.
fn sim_field_names() -> Vec<String> {
    as_mapping(&SimParams::default())
        .keys()
        .filter_map(|k| k.as_str().map(str::to_string))
        .collect()
}
