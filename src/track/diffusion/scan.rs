//! What the raster scan does to a localisation's time and blur.
//!
//! A localisation is a weighted mean of the particle's path, `x̂ = ∫ X(t)
//! dS(t)`, `S` the cumulative weight (the "shutter") over the samples the
//! localisation averages. Two numbers of `S` are all the estimators need
//! (`docs/tracking.md` derives them):
//!
//! - the **time stamp** `t̄ = ∫ t dS`, the shutter's mean time;
//! - the **blur time** `τ = ∫ S(t)(1 − S(t)) dt`. For consecutive
//!   localisations `i`, `i+1` of Brownian motion with diffusion coefficient
//!   D and independent localisation errors of variance σᵢ²:
//!   `Var(Δᵢ) = 2D(t̄ᵢ₊₁ − t̄ᵢ − τᵢ − τᵢ₊₁) + σᵢ² + σᵢ₊₁²` and
//!   `Cov(Δᵢ, Δᵢ₊₁) = 2Dτᵢ₊₁ − σᵢ₊₁²` per axis. Vestergaard's blur
//!   coefficient is `R = τ / Δt`.
//!
//! Which shutter a localisation has depends on what the localiser
//! reports ([`Exposure`]).

/// The microscope's scan, in the units of the manifest's microscope
/// section.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanGeometry {
    /// Frame height (rows) and width (columns), px.
    pub height: usize,
    pub width: usize,
    /// Pixel size, µm.
    pub pixel_size_um: f64,
    /// Pixel dwell, µs.
    pub dwell_us: f64,
    /// Line retrace, ms.
    pub retrace_ms: f64,
    /// Time between the flyback after a frame and the next frame, ms.
    pub dead_time_ms: f64,
    /// Lateral PSF standard deviation, µm.
    pub sigma_xy_um: f64,
}

/// Which part of the frame's scan a localisation averages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Exposure {
    /// The trajectory centroid over every pixel of the frame (the
    /// simulator's truth, which detectors trained on it estimate): equal
    /// weights on all `H·W` samples. Time stamp: the frame's mid-time.
    WholeFrame,
    /// What the beam saw: the rows within the PSF of the particle, each
    /// weighted by the lateral PSF `exp(−(r − y)²a²/(2σxy²))`. Time stamp:
    /// when the beam passed the particle. For fields many PSFs tall.
    Rows,
    /// The frame index alone: `t = f · T`, no blur (`τ = 0`). The naive
    /// reading, for comparison.
    FrameIndex,
    /// The frame index with a camera's uniform full-frame exposure:
    /// `t = f · T`, `R = 1/6`. For comparison.
    UniformFrame,
}

/// Lateral PSF cut-off of the rows model, in σxy (the simulator's default).
const ROWS_CUTOFF_SIGMA: f64 = 6.0;

/// A field this many σxy tall or less is "small": [`ScanGeometry::auto_exposure`]
/// picks [`Exposure::WholeFrame`] for it.
pub(crate) const SMALL_FIELD_SIGMAS: f64 = 10.0;

impl ScanGeometry {
    /// The scan of `microscope` (the simulator's parameters, the
    /// manifest's `microscope` section), with `dead_time_ms` between
    /// frames: the one place its fields are taken from them.
    pub fn of(microscope: &crate::sim::SimParams, dead_time_ms: f64) -> Self {
        Self {
            height: microscope.height,
            width: microscope.width,
            pixel_size_um: microscope.pixel_size_um,
            dwell_us: microscope.dwell_us,
            retrace_ms: microscope.retrace_ms,
            dead_time_ms,
            sigma_xy_um: microscope.sigma_xy_um,
        }
    }

    /// Line time `L = W·δt + t_retrace`, s.
    pub fn line_time_s(&self) -> f64 {
        self.width as f64 * self.dwell_us * 1e-6 + self.retrace_ms * 1e-3
    }

    /// Frame period `T = H·L + dead time`, s.
    pub fn frame_period_s(&self) -> f64 {
        self.height as f64 * self.line_time_s() + self.dead_time_ms * 1e-3
    }

    /// [`Exposure::WholeFrame`] for a field at most
    /// [`SMALL_FIELD_SIGMAS`] σxy tall, else [`Exposure::Rows`].
    pub fn auto_exposure(&self) -> Exposure {
        if self.height as f64 * self.pixel_size_um <= SMALL_FIELD_SIGMAS * self.sigma_xy_um {
            Exposure::WholeFrame
        } else {
            Exposure::Rows
        }
    }

    /// `(t̄, τ)` in s of a localisation at `(x, y)` px in frame `frame`.
    pub fn stamp(&self, exposure: Exposure, frame: usize, x: f64, y: f64) -> (f64, f64) {
        let start = frame as f64 * self.frame_period_s();
        let period = self.frame_period_s();
        match exposure {
            Exposure::WholeFrame => {
                let (mid, blur) = self.whole_frame();
                (start + mid, blur)
            }
            Exposure::Rows => {
                let (mid, blur) = self.rows_around(y);
                let column = x.clamp(0.0, self.width.saturating_sub(1) as f64);
                (start + mid + column * self.dwell_us * 1e-6, blur)
            }
            Exposure::FrameIndex => (start, 0.0),
            Exposure::UniformFrame => (start, period / 6.0),
        }
    }

    /// Mean time (from the frame's start) and blur time of equal weights
    /// on all `M = H·W` samples: within a row the samples are `δt` apart,
    /// between rows `δt + t_retrace`, and `S` after the `m`-th sample is
    /// `m/M`, so `τ = δt·(M² − 1)/(6M) + t_retrace·(H² − 1)/(6H)`.
    fn whole_frame(&self) -> (f64, f64) {
        let (h, w) = (self.height as f64, self.width as f64);
        let dwell = self.dwell_us * 1e-6;
        let retrace = self.retrace_ms * 1e-3;
        let m = h * w;
        let mid = (h - 1.0) / 2.0 * self.line_time_s() + (w - 1.0) / 2.0 * dwell;
        let blur = dwell * (m * m - 1.0) / (6.0 * m) + retrace * (h * h - 1.0) / (6.0 * h);
        (mid, blur)
    }

    /// Mean time (from the frame's start, column 0) and blur time of the
    /// rows model at row `y`: rows `r` weighted by `g_r = exp(−(r − y)²a²/(2σxy²))`
    /// within the cut-off, a line time `L` apart, so `t̄ = L·Σ g_r r / Σ g_r`
    /// and `τ = L·Σ_r S_r(1 − S_r)` with `S_r` the cumulative weight after
    /// row `r` (the within-row spread, microseconds, is left out).
    fn rows_around(&self, y: f64) -> (f64, f64) {
        let line = self.line_time_s();
        let last = self.height.saturating_sub(1) as f64;
        let spread = self.sigma_xy_um / self.pixel_size_um;
        let centre = y.clamp(0.0, last);
        let first = (centre - ROWS_CUTOFF_SIGMA * spread).ceil().max(0.0) as usize;
        let end = ((centre + ROWS_CUTOFF_SIGMA * spread).floor().min(last) as usize).max(first);
        let weights: Vec<f64> = (first..=end)
            .map(|r| (-((r as f64 - y).powi(2)) / (2.0 * spread * spread)).exp())
            .collect();
        let total: f64 = weights.iter().sum();
        if total.is_nan() || total <= 0.0 {
            return (centre * line, 0.0);
        }
        let mean_row = (first..=end)
            .zip(&weights)
            .map(|(r, g)| r as f64 * g)
            .sum::<f64>()
            / total;
        let mut cumulative = 0.0;
        let mut blur = 0.0;
        for g in &weights[..weights.len() - 1] {
            cumulative += g / total;
            blur += line * cumulative * (1.0 - cumulative);
        }
        (mean_row * line, blur)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn paper() -> ScanGeometry {
        ScanGeometry {
            height: 24,
            width: 25,
            pixel_size_um: 0.07,
            dwell_us: 2.0,
            retrace_ms: 1.1,
            dead_time_ms: 0.0,
            sigma_xy_um: 0.21,
        }
    }

    #[test]
    fn the_whole_frame_blur_is_a_sixth_of_the_period_less_the_comb_correction() {
        // Retrace only (dwell → 0): H equal point samples L apart over
        // T = H·L give R = (1 − 1/H²)/6; for H = 24, 0.16638…
        let geometry = ScanGeometry {
            dwell_us: 1e-9,
            ..paper()
        };
        let (_, blur) = geometry.stamp(Exposure::WholeFrame, 0, 0.0, 0.0);
        let r = blur / geometry.frame_period_s();
        assert!((r - (1.0 - 1.0 / 576.0) / 6.0).abs() < 1e-9, "{r}");
        // The paper's microscope: between the two.
        let (t, blur) = paper().stamp(Exposure::WholeFrame, 2, 0.0, 0.0);
        let period = paper().frame_period_s();
        assert!((period - 0.0276).abs() < 1e-12);
        let r = blur / period;
        assert!(r > 0.1663 && r < 1.0 / 6.0, "{r}");
        assert!((t - (2.0 * period + 11.5 * 1.15e-3 + 12.0 * 2e-6)).abs() < 1e-12);
    }

    #[test]
    fn the_rows_blur_of_a_tall_field_is_the_gaussian_shutters() {
        // A continuous Gaussian shutter of standard deviation s has
        // τ = s/√π; the comb of rows (s = 3 line times) is within 1 %.
        let geometry = ScanGeometry {
            height: 200,
            ..paper()
        };
        let (t, blur) = geometry.stamp(Exposure::Rows, 0, 10.0, 100.3);
        let line = geometry.line_time_s();
        let expected = 3.0 * line / std::f64::consts::PI.sqrt();
        assert!((blur / expected - 1.0).abs() < 0.01, "{blur} vs {expected}");
        assert!(
            (t - (100.3 * line + 10.0 * 2e-6)).abs() < 1e-3 * line,
            "{t}"
        );
    }
}
