//! The names the registry records as text, as types: a run step's id
//! ([`StepId`], the `run_steps.step` column) and a blob's role within its
//! artefact ([`BlobRole`], the `artefact_blobs.role` column). Each parses
//! from and prints as exactly the text stored, so rows and JSON stay as they
//! were; in between, code compares kinds, never words.

use std::fmt;
use std::str::FromStr;

use rusqlite::types::{FromSql, FromSqlError, FromSqlResult, ToSql, ToSqlOutput, ValueRef};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use super::ArtefactKind;

/// A step of a run plan: `dataset/NAME` (simulate, or a subset of frames),
/// `model/DETECTOR` (train), `predictions/DETECTOR@DATASET` (locate),
/// `evaluation/DETECTOR@DATASET` (score). Detector names hold no `@`, so
/// the first `@` splits a pair.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum StepId {
    Dataset(String),
    Model(String),
    Predictions { detector: String, dataset: String },
    Evaluation { detector: String, dataset: String },
}

impl StepId {
    /// The kind of artefact the step makes.
    pub fn kind(&self) -> ArtefactKind {
        match self {
            StepId::Dataset(_) => ArtefactKind::Dataset,
            StepId::Model(_) => ArtefactKind::Model,
            StepId::Predictions { .. } => ArtefactKind::Predictions,
            StepId::Evaluation { .. } => ArtefactKind::Evaluation,
        }
    }

    /// The artefact's name: `train`, `cnn`, `trackpy@test-1.00`.
    pub fn name(&self) -> String {
        match self {
            StepId::Dataset(name) | StepId::Model(name) => name.clone(),
            StepId::Predictions { detector, dataset }
            | StepId::Evaluation { detector, dataset } => {
                format!("{detector}@{dataset}")
            }
        }
    }

    /// The detector the step trains, runs or scores (none for a dataset).
    pub fn detector(&self) -> Option<&str> {
        match self {
            StepId::Dataset(_) => None,
            StepId::Model(detector)
            | StepId::Predictions { detector, .. }
            | StepId::Evaluation { detector, .. } => Some(detector),
        }
    }
}

impl fmt::Display for StepId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Through `pad`, so width and alignment apply as to the text.
        f.pad(&format!("{}/{}", self.kind().as_str(), self.name()))
    }
}

impl FromStr for StepId {
    type Err = anyhow::Error;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = || anyhow::anyhow!("{text:?} is not a step id (KIND/NAME)");
        let (kind, name) = text.split_once('/').ok_or_else(bad)?;
        let pair = || {
            name.split_once('@')
                .map(|(detector, dataset)| (detector.to_string(), dataset.to_string()))
                .ok_or_else(bad)
        };
        Ok(match ArtefactKind::parse(kind)? {
            ArtefactKind::Dataset => StepId::Dataset(name.to_string()),
            ArtefactKind::Model => StepId::Model(name.to_string()),
            ArtefactKind::Predictions => {
                let (detector, dataset) = pair()?;
                StepId::Predictions { detector, dataset }
            }
            ArtefactKind::Evaluation => {
                let (detector, dataset) = pair()?;
                StepId::Evaluation { detector, dataset }
            }
        })
    }
}

impl Serialize for StepId {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for StepId {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let text = String::deserialize(deserializer)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

/// What a blob is within its artefact; the text is its file name in an
/// exported artefact and its `role` in the registry. Ordered as the text
/// sorts (the registry lists blobs `ORDER BY role`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum BlobRole {
    /// A dataset's frames (`.npy`).
    Frames,
    /// A model's bytes, the detector's own serialisation.
    Model,
    /// Predictions (`frame,x,y,score` CSV).
    Predictions,
    /// An evaluation's score (JSON).
    Score,
    /// A dataset's ground truth (CSV).
    Truth,
}

impl BlobRole {
    /// Every role, in text order.
    pub const ALL: [BlobRole; 5] = [
        BlobRole::Frames,
        BlobRole::Model,
        BlobRole::Predictions,
        BlobRole::Score,
        BlobRole::Truth,
    ];

    /// The role as stored: `frames.npy`, `model.bin`, `predictions.csv`,
    /// `score.json`, `truth.csv`.
    pub fn as_str(self) -> &'static str {
        match self {
            BlobRole::Frames => "frames.npy",
            BlobRole::Model => "model.bin",
            BlobRole::Predictions => "predictions.csv",
            BlobRole::Score => "score.json",
            BlobRole::Truth => "truth.csv",
        }
    }
}

impl fmt::Display for BlobRole {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.pad(self.as_str())
    }
}

impl FromStr for BlobRole {
    type Err = anyhow::Error;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        BlobRole::ALL
            .into_iter()
            .find(|role| role.as_str() == text)
            .ok_or_else(|| anyhow::anyhow!("{text:?} is not a blob role"))
    }
}

impl Serialize for BlobRole {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_str(self.as_str())
    }
}

impl<'de> Deserialize<'de> for BlobRole {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let text = String::deserialize(deserializer)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

impl ToSql for BlobRole {
    fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
        Ok(ToSqlOutput::from(self.as_str()))
    }
}

impl FromSql for BlobRole {
    fn column_result(value: ValueRef<'_>) -> FromSqlResult<Self> {
        value
            .as_str()?
            .parse()
            .map_err(|e: anyhow::Error| FromSqlError::Other(e.into()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn step_ids_print_as_they_parse() {
        for text in [
            "dataset/train",
            "model/cnn",
            "predictions/trackpy@test-1.00",
            "evaluation/cnn@cv-fold-2",
        ] {
            let id: StepId = text.parse().unwrap();
            assert_eq!(id.to_string(), text);
            assert_eq!(serde_json::to_string(&id).unwrap(), format!("{text:?}"));
        }
        let id: StepId = "predictions/trackpy@test@x".parse().unwrap();
        assert_eq!(id.detector(), Some("trackpy"));
        assert_eq!(id.name(), "trackpy@test@x");
        for bad in ["dataset", "subset/x", "evaluation/cnn", ""] {
            assert!(bad.parse::<StepId>().is_err(), "{bad}");
        }
        assert_eq!(
            format!("{:<14}|", StepId::Model("cnn".into())),
            "model/cnn     |"
        );
    }

    #[test]
    fn roles_sort_and_print_as_their_text() {
        let mut texts: Vec<&str> = BlobRole::ALL.iter().map(|r| r.as_str()).collect();
        texts.sort();
        assert_eq!(
            texts,
            BlobRole::ALL.iter().map(|r| r.as_str()).collect::<Vec<_>>()
        );
        for role in BlobRole::ALL {
            assert_eq!(role.to_string().parse::<BlobRole>().unwrap(), role);
        }
        assert!("notes.txt".parse::<BlobRole>().is_err());
    }
}
