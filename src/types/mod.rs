//! The data every layer shares: frame stacks, ground truth and predictions,
//! the kinds of detector, per-frame parameter distributions and seed
//! derivation.
//!
//! A leaf of the crate: it imports nothing of scanloc but [`crate::error`],
//! so the simulator, the detectors, the metric and the file formats can all
//! use these types without importing each other. Coordinates follow TrackPy:
//! `x` is the column, `y` the row, pixel centres at integers.

pub(crate) mod detector_kind;
pub(crate) mod distribution;
pub(crate) mod frames;
pub(crate) mod names;
pub(crate) mod prediction;
pub(crate) mod seed;
pub(crate) mod tracks;
pub(crate) mod truth;

pub use detector_kind::DetectorKind;
pub use distribution::{Distribution, RandomDistribution};
pub use frames::{FrameStack, Frames, RealFrameStack, Recording};
pub use prediction::{LocalisationSigma, Prediction};
pub use seed::derive_seed;
pub use tracks::{Track, TrackPoint};
pub use truth::{Dataset, RecordingTruthRow, TruthRow};
