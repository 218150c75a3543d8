//! Seed derivation: every random stream of a run, a bench or `train` is
//! ChaCha seeded from a seed derived here from one master seed and the
//! drawing artefact's kind and name, so adding an artefact never shifts
//! another's stream. Low in the stack because the manifest, `train` and the
//! benches all derive seeds the same way.

use sha2::{Digest, Sha256};

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

#[cfg(test)]
mod tests {
    use super::derive_seed;

    #[test]
    fn a_seed_depends_on_master_kind_and_name() {
        let a = derive_seed(1, "dataset", "train");
        assert_eq!(a, derive_seed(1, "dataset", "train"));
        assert_ne!(a, derive_seed(2, "dataset", "train"));
        assert_ne!(a, derive_seed(1, "detector", "train"));
        assert_ne!(a, derive_seed(1, "dataset", "train2"));
    }
}
