//! The kinds of detector, as a type: manifests name them, the registry
//! records a model's kind, the report picks its figures by kind. Written
//! as the text manifests use (`crocker_grier`, `cnn`, `likelihood`) only
//! where JSON, SQL or text is written.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// A detector's kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DetectorKind {
    /// Crocker–Grier as in TrackPy (fitted to the frames, not trained).
    CrockerGrier,
    /// The fully convolutional network (trained).
    Cnn,
    /// The likelihood localiser, which knows the simulator's model (a bound).
    Likelihood,
}

impl DetectorKind {
    /// Every kind.
    pub const ALL: [DetectorKind; 3] = [
        DetectorKind::CrockerGrier,
        DetectorKind::Cnn,
        DetectorKind::Likelihood,
    ];

    /// The kind as manifests, the registry and JSON write it.
    pub fn as_str(self) -> &'static str {
        match self {
            DetectorKind::CrockerGrier => "crocker_grier",
            DetectorKind::Cnn => "cnn",
            DetectorKind::Likelihood => "likelihood",
        }
    }
}

impl fmt::Display for DetectorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(self.as_str())
    }
}

impl FromStr for DetectorKind {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        DetectorKind::ALL
            .into_iter()
            .find(|kind| kind.as_str() == text)
            .ok_or_else(|| format!("unknown detector kind {text:?}"))
    }
}

impl Serialize for DetectorKind {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for DetectorKind {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let text = String::deserialize(deserializer)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::DetectorKind;

    #[test]
    fn kinds_print_as_they_parse() {
        for kind in DetectorKind::ALL {
            assert_eq!(kind.to_string().parse::<DetectorKind>(), Ok(kind));
            assert_eq!(
                serde_json::to_string(&kind).unwrap(),
                format!("{:?}", kind.as_str())
            );
        }
        assert!("trackpy".parse::<DetectorKind>().is_err());
    }
}
