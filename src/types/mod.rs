//! The data every layer shares: frame stacks, ground truth and predictions.
//!
//! A leaf of the crate: it imports nothing of scanloc but [`crate::error`],
//! so the simulator, the detectors, the metric and the file formats can all
//! use these types without importing each other. Coordinates follow TrackPy:
//! `x` is the column, `y` the row, pixel centres at integers.

pub mod frames;
pub mod prediction;
pub mod tracks;
pub mod truth;

pub use frames::{FrameStack, Frames, RealFrameStack, Recording};
pub use prediction::{LocalisationSigma, Prediction};
pub use tracks::{Track, TrackPoint};
pub use truth::{Dataset, RecordingTruthRow, TruthRow};
