//! Where one point of a sweep stands, as a kind: written as the text the
//! sweep's files and `sweep status` have always shown.

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::registry::RunStatus;

/// A point's status. Its run's end where the point ran (`done`: every
/// artefact is in the main registry; `failed`), or where it waits.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PointStatus {
    /// How the point's run stands: `done`, `failed` (a recorded run's
    /// status, the same words).
    Run(RunStatus),
    /// Finished in its shard, not yet imported (`in shard`).
    InShard,
    /// Never ran, or its results are lost (`missing`).
    Missing,
    /// Its Slurm task's state, lower-case, while queued or running or once
    /// Slurm ended it (`pending`, `timeout`, …): Slurm's vocabulary, kept as
    /// the text `sacct` gives.
    Slurm(String),
}

impl PointStatus {
    pub const DONE: PointStatus = PointStatus::Run(RunStatus::Done);
    pub const FAILED: PointStatus = PointStatus::Run(RunStatus::Failed);

    /// Whether every artefact of the point is in the main registry.
    pub fn is_done(&self) -> bool {
        *self == Self::DONE
    }
}

impl fmt::Display for PointStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PointStatus::Run(status) => f.pad(status.as_str()),
            PointStatus::InShard => f.pad("in shard"),
            PointStatus::Missing => f.pad("missing"),
            PointStatus::Slurm(state) => f.pad(state),
        }
    }
}

impl FromStr for PointStatus {
    type Err = std::convert::Infallible;

    /// Every text reads as a status: a run's status word, `in shard`,
    /// `missing`, else a Slurm state.
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        Ok(match text {
            "in shard" => PointStatus::InShard,
            "missing" => PointStatus::Missing,
            _ => match RunStatus::parse(text) {
                Some(status) => PointStatus::Run(status),
                None => PointStatus::Slurm(text.to_string()),
            },
        })
    }
}

impl Serialize for PointStatus {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for PointStatus {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let text = String::deserialize(deserializer)?;
        Ok(text.parse().unwrap_or_else(|never| match never {}))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statuses_print_as_they_parse() {
        for text in [
            "done", "failed", "in shard", "missing", "pending", "timeout",
        ] {
            let status: PointStatus = text.parse().unwrap();
            assert_eq!(status.to_string(), text);
            assert_eq!(serde_json::to_string(&status).unwrap(), format!("{text:?}"));
        }
        assert!("done".parse::<PointStatus>().unwrap().is_done());
        assert_eq!(
            "failed".parse::<PointStatus>().unwrap(),
            PointStatus::FAILED
        );
        assert_eq!(
            "timeout".parse::<PointStatus>().unwrap(),
            PointStatus::Slurm("timeout".into())
        );
        assert_eq!(format!("{:<8}|", PointStatus::Missing), "missing |");
    }
}
