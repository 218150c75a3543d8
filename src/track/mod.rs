//! From localisations to trajectories and what they tell: the diffusion
//! coefficient of tracked particles ([`diffusion`], `docs/tracking.md`).

pub mod diffusion;
