//! Content hashes and the canonical JSON that content keys are hashes of.

use std::io::Read;

use serde::Serialize;
use sha2::{Digest, Sha256};

/// sha256 of `bytes`, lower-case hex.
pub(crate) fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

/// sha256 of everything `reader` yields, lower-case hex, read in 1 MiB
/// chunks so large blobs are never held in memory for a check.
pub(crate) fn sha256_reader(mut reader: impl Read) -> std::io::Result<String> {
    let mut hasher = Sha256::new();
    let mut buffer = vec![0u8; 1 << 20];
    loop {
        let read = reader.read(&mut buffer)?;
        if read == 0 {
            break;
        }
        hasher.update(&buffer[..read]);
    }
    Ok(hex::encode(hasher.finalize()))
}

/// Canonical JSON of `value`: object keys sorted at every level, no
/// whitespace, numbers in serde_json's shortest round-trip form. Two values
/// that serialise to equal JSON trees give identical text.
pub(crate) fn canonical_json<T: Serialize + ?Sized>(value: &T) -> anyhow::Result<String> {
    let tree = serde_json::to_value(value)?;
    let mut text = String::new();
    write_canonical(&tree, &mut text);
    Ok(text)
}

fn write_canonical(value: &serde_json::Value, out: &mut String) {
    match value {
        serde_json::Value::Object(map) => {
            let mut keys: Vec<&String> = map.keys().collect();
            keys.sort();
            out.push('{');
            for (index, key) in keys.into_iter().enumerate() {
                if index > 0 {
                    out.push(',');
                }
                out.push_str(&serde_json::Value::String(key.clone()).to_string());
                out.push(':');
                write_canonical(&map[key], out);
            }
            out.push('}');
        }
        serde_json::Value::Array(items) => {
            out.push('[');
            for (index, item) in items.iter().enumerate() {
                if index > 0 {
                    out.push(',');
                }
                write_canonical(item, out);
            }
            out.push(']');
        }
        other => out.push_str(&other.to_string()),
    }
}

/// The content key of an artefact: sha256 of the canonical JSON of its
/// description (resolved spec, input keys, code version).
pub(crate) fn content_key<T: Serialize + ?Sized>(description: &T) -> anyhow::Result<String> {
    Ok(sha256_hex(canonical_json(description)?.as_bytes()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn canonical_json_sorts_keys_at_every_level() {
        let a = serde_json::json!({"b": 1, "a": {"d": [1.5, {"z": 0, "y": 1}], "c": null}});
        assert_eq!(
            canonical_json(&a).unwrap(),
            r#"{"a":{"c":null,"d":[1.5,{"y":1,"z":0}]},"b":1}"#
        );
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(sha256_reader(&b"abc"[..]).unwrap(), sha256_hex(b"abc"));
    }
}
