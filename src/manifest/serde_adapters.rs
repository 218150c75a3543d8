//! Adapters between the way manifests write things and what serde_yaml
//! 0.9 reads: name → entry mappings that keep their order, and enums
//! written as one-entry mappings `{variant: value}`.

use std::fmt;

use serde::Deserialize;
use serde::de::{self, Deserializer, MapAccess, Visitor};

/// An enum written as a one-entry YAML mapping `{variant: value}` (serde_yaml
/// 0.9 otherwise expects a `!variant` tag).
pub(super) struct SingletonMap<T>(pub T);

impl<'de, T: Deserialize<'de>> Deserialize<'de> for SingletonMap<T> {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        serde_yaml::with::singleton_map::deserialize(deserializer).map(SingletonMap)
    }
}

/// A YAML mapping from names to values that keeps the manifest's order and
/// refuses duplicate names.
pub(super) struct Named<V>(pub Vec<(String, V)>);

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

/// A one-entry mapping `{variant: value}` whose key is a plain name, as
/// the tagged value `!variant value` serde_yaml 0.9 expects for an enum;
/// anything else unchanged. (Distributions, being untagged, accept both;
/// a count's `{choice: [...]}` is a struct, not an enum.)
pub(super) fn as_tagged_enum(value: &serde_yaml::Value) -> serde_yaml::Value {
    if let serde_yaml::Value::Mapping(mapping) = value
        && mapping.len() == 1
        && let Some((serde_yaml::Value::String(variant), inner)) = mapping.iter().next()
        && variant != "uniform"
        && variant != "choice"
        && variant.chars().all(|c| c.is_ascii_lowercase() || c == '_')
    {
        return serde_yaml::Value::Tagged(Box::new(serde_yaml::value::TaggedValue {
            tag: serde_yaml::value::Tag::new(variant.clone()),
            value: inner.clone(),
        }));
    }
    value.clone()
}
