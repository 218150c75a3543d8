//! An ensemble's members: the seed each trains from, and how its
//! messages name it.

use rand::RngExt;

use super::streams::{STREAM_MEMBER, stream};

/// The seed ensemble member `index` (0-based) trains from: the training
/// seed itself for member 0, so a single network trains exactly as it
/// would without ensembles; a seed drawn from a stream of its own for the
/// others.
pub(super) fn member_seed(seed: u64, index: usize) -> u64 {
    if index == 0 {
        seed
    } else {
        stream(seed, STREAM_MEMBER, index as u64).random::<u64>()
    }
}

/// Which member of how many a training run is (0-based `index`), in the
/// training the caller calls `task` (the progress bar's message when the
/// training began; may be empty).
#[derive(Clone, Copy)]
pub(super) struct Member<'a> {
    pub(super) task: &'a str,
    pub(super) index: usize,
    pub(super) count: usize,
}

impl Member<'_> {
    /// The task and, for an ensemble's member, "member 2/3": "train cnn ·
    /// member 2/3", "train cnn" for a single network; `None` when both are
    /// missing.
    pub(super) fn name(self) -> Option<String> {
        let member = (self.count > 1).then(|| format!("member {}/{}", self.index + 1, self.count));
        match (self.task.is_empty(), member) {
            (true, member) => member,
            (false, None) => Some(self.task.to_string()),
            (false, Some(member)) => Some(format!("{} · {member}", self.task)),
        }
    }

    /// [`name`](Self::name) and ": " to start the member's messages (empty
    /// when there is no name).
    pub(super) fn label(self) -> String {
        self.name().map(|name| name + ": ").unwrap_or_default()
    }
}
