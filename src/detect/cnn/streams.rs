//! The random streams a training draws from, each derived from the
//! training seed and a purpose of its own.

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// Purposes of the random streams derived from the training seed.
pub(super) const STREAM_INIT: u64 = 1;
pub(super) const STREAM_SPLIT: u64 = 2;
pub(super) const STREAM_SHUFFLE: u64 = 3;
pub(super) const STREAM_FRESH: u64 = 4;
/// The seeds of an ensemble's members 2, 3, … (index = 0-based member).
pub(super) const STREAM_MEMBER: u64 = 5;
pub(super) const STREAM_TEACHER: u64 = 6;

/// A ChaCha8 stream for `purpose` (and `index`, e.g. the epoch) of `seed`.
pub(super) fn stream(seed: u64, purpose: u64, index: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(purpose);
    rng.set_word_pos(u128::from(index) << 32);
    rng
}
