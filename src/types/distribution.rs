//! A per-frame parameter: a fixed value or a distribution drawn once per
//! frame. The simulator draws from it, the detectors read its bounds as
//! priors, and the registry records it as a column, so it sits with the
//! shared types rather than in the simulator.

use std::fmt;
use std::str::FromStr;

use rand::{Rng, RngExt};
use serde::{Deserialize, Serialize};

use crate::error::{FieldError, require_finite, require_non_negative};

/// A scalar parameter that is either fixed or drawn once per frame.
///
/// In YAML: a number (`1.0`) or a mapping (`{uniform: [0.75, 1.75]}`).
/// On the command line: `1.0` or `uniform:0.75,1.75`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(untagged, deny_unknown_fields)]
pub enum Distribution {
    /// The same value for every frame.
    Fixed(f64),
    /// Drawn per frame from a distribution.
    Random(RandomDistribution),
}

/// The distributions a per-frame parameter can follow.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum RandomDistribution {
    /// Uniform on `[low, high]`.
    Uniform([f64; 2]),
}

impl From<f64> for Distribution {
    fn from(value: f64) -> Self {
        Distribution::Fixed(value)
    }
}

impl Distribution {
    /// Draws one value. A fixed value consumes no randomness, so a fixed
    /// parameter never shifts the stream of later draws.
    pub fn sample<R: Rng + ?Sized>(&self, rng: &mut R) -> f64 {
        match *self {
            Distribution::Fixed(value) => value,
            Distribution::Random(RandomDistribution::Uniform([low, high])) => {
                if high > low {
                    low + (high - low) * rng.random::<f64>()
                } else {
                    low
                }
            }
        }
    }

    /// The value of every frame, if it is fixed.
    pub fn fixed(&self) -> Option<f64> {
        match *self {
            Distribution::Fixed(value) => Some(value),
            Distribution::Random(_) => None,
        }
    }

    /// The value of every frame, or an error naming the parameter `name`
    /// for a distribution, which `purpose` cannot use.
    pub fn require_fixed(&self, name: &str, purpose: &str) -> Result<f64, FieldError> {
        self.fixed().ok_or_else(|| {
            FieldError::new(
                name,
                format!("{purpose} needs one fixed number, got the distribution {self}"),
            )
        })
    }

    /// Smallest and largest value the distribution can produce.
    pub fn bounds(&self) -> (f64, f64) {
        match *self {
            Distribution::Fixed(value) => (value, value),
            Distribution::Random(RandomDistribution::Uniform([low, high])) => (low, high),
        }
    }

    /// Checks every value is finite (and ≥ 0 when `non_negative`), naming the
    /// parameter in the error.
    pub fn validate(&self, name: &str, non_negative: bool) -> Result<(), FieldError> {
        let (low, high) = self.bounds();
        for value in [low, high] {
            if non_negative {
                require_non_negative(name, value)?;
            } else {
                require_finite(name, value)?;
            }
        }
        if low > high {
            return Err(FieldError::new(
                name,
                format!("uniform bounds must be ordered (low ≤ high), got [{low}, {high}]"),
            ));
        }
        Ok(())
    }
}

impl fmt::Display for Distribution {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Distribution::Fixed(value) => write!(f, "{value}"),
            Distribution::Random(RandomDistribution::Uniform([low, high])) => {
                write!(f, "uniform:{low},{high}")
            }
        }
    }
}

impl FromStr for Distribution {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let text = text.trim();
        if let Some(rest) = text.strip_prefix("uniform:") {
            let parts: Vec<&str> = rest.split(',').collect();
            if parts.len() != 2 {
                return Err(format!("expected uniform:LOW,HIGH, got {text:?}"));
            }
            let low: f64 = parts[0]
                .trim()
                .parse()
                .map_err(|_| format!("not a number: {:?}", parts[0]))?;
            let high: f64 = parts[1]
                .trim()
                .parse()
                .map_err(|_| format!("not a number: {:?}", parts[1]))?;
            return Ok(Distribution::Random(RandomDistribution::Uniform([
                low, high,
            ])));
        }
        text.parse::<f64>()
            .map(Distribution::Fixed)
            .map_err(|_| format!("expected a number or uniform:LOW,HIGH, got {text:?}"))
    }
}
