//! An in-memory stack of photon-count frames.
//!
//! Frames are stored row-major (C order) as `u32` counts, frame after frame,
//! exactly like the `(n, H, W)` `.npy` arrays scanloc writes. Pixel `(row r,
//! column c)` of frame `i` is `data[(i * height + r) * width + c]`. In TrackPy's
//! convention `x` is the column and `y` the row, with pixel centres at integer
//! coordinates.

use crate::error::input_error;

/// `n` frames of `height × width` photon counts.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct FrameStack {
    pub n: usize,
    pub height: usize,
    pub width: usize,
    pub data: Vec<u32>,
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

    /// Wraps existing data, checking that its length is `n · height · width`.
    pub fn from_vec(n: usize, height: usize, width: usize, data: Vec<u32>) -> anyhow::Result<Self> {
        if data.len() != n * height * width {
            return Err(input_error(format!(
                "frame data has {} values, expected {n} × {height} × {width}",
                data.len()
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

    /// The counts of frame `index`, row-major.
    pub fn frame(&self, index: usize) -> &[u32] {
        let len = self.frame_len();
        &self.data[index * len..(index + 1) * len]
    }

    /// Iterates over the frames in order.
    pub fn iter(&self) -> impl Iterator<Item = &[u32]> {
        // `max(1)` keeps `chunks_exact` valid for zero-sized frames.
        self.data.chunks_exact(self.frame_len().max(1)).take(self.n)
    }

    /// The largest count in the stack (0 when empty).
    pub fn max_count(&self) -> u32 {
        self.data.iter().copied().max().unwrap_or(0)
    }

    /// Appends the frames of `other`, which must have the same frame size.
    pub fn append(&mut self, other: FrameStack) -> anyhow::Result<()> {
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
