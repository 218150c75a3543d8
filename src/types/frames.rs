//! In-memory frame stacks: photon counts ([`FrameStack`]), and real-valued
//! frames ([`RealFrameStack`]: background-subtracted or normalised
//! recordings, fractional or negative) for the detectors that can use them;
//! [`Recording`] is either, as read from a file.
//!
//! Frames are stored row-major (C order), counts as `u32`, frame after
//! frame, exactly like the `(n, H, W)` `.npy` arrays scanloc writes. Pixel `(row r,
//! column c)` of frame `i` is `data[(i * height + r) * width + c]`. In TrackPy's
//! convention `x` is the column and `y` the row, with pixel centres at integer
//! coordinates.

use crate::error::input_error;

/// `n` frames of `height × width` values of type `T`, row-major, frame
/// after frame: [`FrameStack`] (photon counts) or [`RealFrameStack`].
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Frames<T> {
    pub n: usize,
    pub height: usize,
    pub width: usize,
    pub data: Vec<T>,
}

/// `n` frames of `height × width` photon counts.
pub type FrameStack = Frames<u32>;

/// `n` frames of `height × width` real values (finite, of any sign): a
/// recording that is not photon counts, such as a background-subtracted or
/// normalised one.
pub type RealFrameStack = Frames<f64>;

/// A value a frame holds.
pub trait Sample: Copy {
    /// Why `self` cannot be in a frame, if it cannot.
    fn refusal(self) -> Option<String>;
}

impl Sample for u32 {
    fn refusal(self) -> Option<String> {
        None
    }
}

impl Sample for f64 {
    fn refusal(self) -> Option<String> {
        (!self.is_finite()).then(|| format!("{self}; frames must hold finite numbers"))
    }
}

impl FrameStack {
    /// A stack of `n` zero frames.
    pub fn zeros(n: usize, height: usize, width: usize) -> Self {
        Self {
            n,
            height,
            width,
            data: vec![0; n * height * width],
        }
    }

    /// The largest count in the stack (0 when empty).
    pub fn max_count(&self) -> u32 {
        self.data.iter().copied().max().unwrap_or(0)
    }
}

impl<T: Sample> Frames<T> {
    /// Wraps existing data, checking that its length is `n · height · width`
    /// and that every value can be in a frame (real values must be finite;
    /// the first that is not is named by its flat index).
    pub fn from_vec(n: usize, height: usize, width: usize, data: Vec<T>) -> anyhow::Result<Self> {
        if data.len() != n * height * width {
            return Err(input_error(format!(
                "frame data has {} values, expected {n} × {height} × {width}",
                data.len()
            )));
        }
        if let Some((index, refusal)) = data
            .iter()
            .enumerate()
            .find_map(|(index, value)| value.refusal().map(|refusal| (index, refusal)))
        {
            return Err(input_error(format!(
                "value at flat index {index} is {refusal}"
            )));
        }
        Ok(Self {
            n,
            height,
            width,
            data,
        })
    }

    /// Number of pixels in one frame.
    pub fn frame_len(&self) -> usize {
        self.height * self.width
    }

    /// The values of frame `index`, row-major.
    pub fn frame(&self, index: usize) -> &[T] {
        let len = self.frame_len();
        &self.data[index * len..(index + 1) * len]
    }

    /// Iterates over the frames in order.
    pub fn iter(&self) -> impl Iterator<Item = &[T]> {
        // `max(1)` keeps `chunks_exact` valid for zero-sized frames.
        self.data.chunks_exact(self.frame_len().max(1)).take(self.n)
    }

    /// Appends the frames of `other`, which must have the same frame size.
    pub fn append(&mut self, other: Frames<T>) -> anyhow::Result<()> {
        if self.n == 0 && self.data.is_empty() {
            *self = other;
            return Ok(());
        }
        if (other.height, other.width) != (self.height, self.width) {
            return Err(input_error(format!(
                "cannot append {}×{} frames to {}×{} frames",
                other.height, other.width, self.height, self.width
            )));
        }
        self.n += other.n;
        self.data.extend(other.data);
        Ok(())
    }
}

impl From<FrameStack> for RealFrameStack {
    /// The same frames as real values (exact: every `u32` is an `f64`).
    fn from(counts: FrameStack) -> Self {
        Self {
            n: counts.n,
            height: counts.height,
            width: counts.width,
            data: counts.data.into_iter().map(f64::from).collect(),
        }
    }
}

/// Frames as read from a file: photon counts when the file holds integers,
/// real values when it holds floating-point numbers (whatever the values:
/// like TrackPy, the element type decides how a detector treats them).
#[derive(Debug, Clone, PartialEq)]
pub enum Recording {
    Counts(FrameStack),
    Real(RealFrameStack),
}

impl Recording {
    /// `(n, height, width)`.
    pub fn shape(&self) -> (usize, usize, usize) {
        match self {
            Recording::Counts(f) => (f.n, f.height, f.width),
            Recording::Real(f) => (f.n, f.height, f.width),
        }
    }

    /// Appends the frames of `other` (same frame size); counts appended to
    /// real frames, or real frames to counts, make real frames.
    pub fn append(&mut self, other: Recording) -> anyhow::Result<()> {
        match (&mut *self, other) {
            (Recording::Counts(stack), Recording::Counts(more)) => stack.append(more),
            (Recording::Real(stack), Recording::Real(more)) => stack.append(more),
            (Recording::Real(stack), Recording::Counts(more)) => stack.append(more.into()),
            (Recording::Counts(stack), Recording::Real(more)) => {
                let mut real = RealFrameStack::from(std::mem::take(stack));
                real.append(more)?;
                *self = Recording::Real(real);
                Ok(())
            }
        }
    }

    /// The frames as photon counts: integer frames as they are, real
    /// frames if every value is a whole number from 0 to `u32::MAX`. The
    /// error names the first value that is not (by flat index) and says
    /// that these frames need a detector that takes real values.
    pub fn into_counts(self) -> anyhow::Result<FrameStack> {
        match self {
            Recording::Counts(counts) => Ok(counts),
            Recording::Real(real) => {
                let mut data = Vec::with_capacity(real.data.len());
                for (index, &value) in real.data.iter().enumerate() {
                    match whole_count(value) {
                        Some(count) => data.push(count),
                        None => {
                            return Err(input_error(format!(
                                "value at flat index {index} ({value}) is not a photon count (a whole number from 0 to {}); real-valued frames are taken by the crocker-grier detector only (docs/detectors.md, \"Input frames\")",
                                u32::MAX
                            )));
                        }
                    }
                }
                FrameStack::from_vec(real.n, real.height, real.width, data)
            }
        }
    }
}

/// `Some(count)` if `value` is a whole number representable as `u32`.
pub(crate) fn whole_count(value: f64) -> Option<u32> {
    if value.is_finite() && value >= 0.0 && value <= u32::MAX as f64 && value.fract() == 0.0 {
        Some(value as u32)
    } else {
        None
    }
}
