//! Linking by global linear assignment with gap closing (Jaqaman et al.
//! 2008, "Robust single-particle tracking in live-cell time-lapse
//! sequences", Nat. Methods 5:695).
//!
//! Two steps, each one linear assignment problem (LAP) solved exactly:
//!
//! 1. **Frame to frame.** Detections of frame t (sources) against those of
//!    frame t + 1 (destinations): each pair within the gate may link; a
//!    source may end ("death"), a destination may start a segment
//!    ("birth"). The LAP minimises the total cost over the whole frame pair
//!    at once, not subnetwork by subnetwork greedily.
//! 2. **Gap closing.** The segments' ends against their starts 2 to
//!    `max_gap` + 1 frames later (the particle missing for 1 to `max_gap`
//!    frames, a blink): one LAP over the whole recording, so a
//!    reappearance is joined to the best end globally rather than to the
//!    first remembered source that happens to be near.
//!
//! Costs: a link over k frames between detections i and j has, per axis a,
//! the displacement variance v_a = k q + σ_a,i² + σ_a,j², with q the
//! variance of one frame's Brownian step per axis (2 D Δt / pixel², or
//! (R / 3)² from a search range R) and σ the localisations' uncertainty
//! (`sigma_x`, `sigma_y`; 0 when a table has none). The cost is minus twice
//! the log-likelihood of the displacement up to a constant,
//! c = dx²/v_x + dy²/v_y + ln(v_x v_y / q²) (≥ 0; the log term makes long
//! gaps and imprecise localisations cost more); the gate admits pairs with
//! dx²/v_x + dy²/v_y ≤ g², g = 3 by default (98.9 % of true steps in 2-D;
//! with σ = 0 and q = (R/3)², exactly the displacements within R·√k). Each
//! link records its gate's extent along x and y, g·√v_x and g·√v_y
//! ([`Linking::gates`](super::Linking::gates)), which the ML ensemble
//! narrows and conditions on (docs/tracking.md, "Wrong links"). Birth and death
//! cost, as in Jaqaman et al., 1.05 × the largest cost among the problem's
//! candidate links, so any gated link beats leaving both ends unlinked and
//! the choice is only among competing links.
//!
//! Each LAP is split into the connected components of its candidate graph
//! (a component's links do not interact with another's) and each is solved
//! by [`assign`](super::assign). Trajectory labels are given in order of
//! first appearance (by frame, then input order).

use rstar::primitives::GeomWithData;
use rstar::{AABB, RTree};

use super::{Candidate, Detection, LinkStats, Linking, assign, frame_order};
use crate::error::input_error;

/// The default gate on a link's Mahalanobis distance: 3 (2 degrees of
/// freedom: 1 − e^(−9/2) = 98.9 % of true links inside).
pub(crate) const GATE_SIGMAS: f64 = 3.0;

/// Birth and death cost as a multiple of the largest candidate link cost
/// (Jaqaman et al. 2008).
pub(crate) const ALTERNATIVE_COST_FACTOR: f64 = 1.05;

/// The most candidate links one LAP gathers (1.2 GB of them): a recording
/// of docs/tracking.md has about three per localisation.
pub(crate) const MAX_CANDIDATE_LINKS: usize = 50_000_000;

/// The smallest step variance q, px²: with it, and localisation σ at most
/// [`MAX_SEARCH_RANGE`](crate::limits::MAX_SEARCH_RANGE), every cost and
/// gate extent is a finite number (q² and `v_x v_y` stay within `f64`).
pub(crate) const MIN_STEP_VARIANCE: f64 = 1e-100;

/// The LAP linker's parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LapParams {
    /// q: variance per axis of one frame's displacement, px².
    pub step_variance: f64,
    /// The longest gap closed, in frames without the particle (0: no gap
    /// closing).
    pub max_gap: usize,
    /// The gate: the largest Mahalanobis distance of a link
    /// ([`GATE_SIGMAS`] by default).
    pub gate_sigmas: f64,
}

impl LapParams {
    /// q from a search range R (pixels) taken as 3 standard deviations of a
    /// frame's step: q = (R / 3)².
    pub fn from_search_range(search_range: f64, max_gap: usize) -> Self {
        Self {
            step_variance: (search_range / 3.0).powi(2),
            max_gap,
            gate_sigmas: GATE_SIGMAS,
        }
    }

    /// q from Brownian motion: q = 2 D Δt / p², D in µm²/s, Δt the frame
    /// time in ms, p the pixel size in µm.
    pub fn from_diffusion(
        diffusion_um2_s: f64,
        frame_time_ms: f64,
        pixel_size_um: f64,
        max_gap: usize,
    ) -> Self {
        Self {
            step_variance: 2.0 * diffusion_um2_s * frame_time_ms * 1e-3
                / (pixel_size_um * pixel_size_um),
            max_gap,
            gate_sigmas: GATE_SIGMAS,
        }
    }

    /// Refuses a step variance that is not a finite number > 0, is below
    /// [`MIN_STEP_VARIANCE`] or exceeds the square of
    /// [`MAX_SEARCH_RANGE`](crate::limits::MAX_SEARCH_RANGE),
    /// a gate beyond [`MAX_GATE_SIGMAS`](crate::limits::MAX_GATE_SIGMAS)
    /// and gaps of more than [`MAX_FRAMES`](crate::limits::MAX_FRAMES).
    pub fn validate(&self) -> anyhow::Result<()> {
        use crate::limits::{MAX_GATE_SIGMAS, MAX_SEARCH_RANGE, check_positive_at_most};
        check_positive_at_most(
            "step variance (px²; from the search range, or the diffusion, frame time and \
             pixel size)",
            self.step_variance,
            MAX_SEARCH_RANGE * MAX_SEARCH_RANGE,
        )?;
        if self.step_variance < MIN_STEP_VARIANCE {
            return Err(input_error(format!(
                "step variance (px²; from the search range, or the diffusion, frame time and \
                 pixel size): must be at least {MIN_STEP_VARIANCE:e} (a search range of \
                 {:e} px), got {}",
                3.0 * MIN_STEP_VARIANCE.sqrt(),
                crate::error::readable(self.step_variance)
            )));
        }
        check_positive_at_most("gate", self.gate_sigmas, MAX_GATE_SIGMAS)?;
        if self.max_gap > crate::limits::MAX_FRAMES {
            return Err(input_error(format!(
                "max gap: must be at most {} frames, got {}",
                crate::limits::MAX_FRAMES,
                self.max_gap
            )));
        }
        Ok(())
    }
}

/// Links `detections` (any order): frame-to-frame LAPs, then one
/// gap-closing LAP.
pub fn link(detections: &[Detection], params: &LapParams) -> anyhow::Result<Linking> {
    params.validate()?;
    let most = crate::limits::MAX_SEARCH_RANGE;
    if let Some(sigma) = detections
        .iter()
        .filter_map(|d| d.sigma)
        .find(|s| !(s.x <= most && s.y <= most))
    {
        return Err(input_error(format!(
            "sigma_x, sigma_y: must be at most {most:e} px for the LAP's costs, got {}, {}",
            crate::error::readable(sigma.x),
            crate::error::readable(sigma.y)
        )));
    }
    let linker = Lap::new(detections, params);
    let order = frame_order(detections);
    let mut next: Vec<Option<usize>> = vec![None; detections.len()];
    let mut previous: Vec<Option<usize>> = vec![None; detections.len()];
    let mut stats = LinkStats::default();
    let frames: Vec<&[usize]> = order
        .chunk_by(|&a, &b| detections[a].frame == detections[b].frame)
        .collect();
    for pair in frames.windows(2) {
        let (sources, destinations) = (pair[0], pair[1]);
        if detections[sources[0]].frame + 1 != detections[destinations[0]].frame {
            continue;
        }
        let candidates = linker.candidates(sources, destinations, 1, 1)?;
        for (s, d) in solve(sources.len(), destinations.len(), &candidates, &mut stats)? {
            next[sources[s]] = Some(destinations[d]);
            previous[destinations[d]] = Some(sources[s]);
            stats.links += 1;
        }
    }
    if params.max_gap > 0 {
        let ends: Vec<usize> = order
            .iter()
            .copied()
            .filter(|&i| next[i].is_none())
            .collect();
        let starts: Vec<usize> = order
            .iter()
            .copied()
            .filter(|&i| previous[i].is_none())
            .collect();
        let candidates = linker.candidates(&ends, &starts, 2, params.max_gap + 1)?;
        for (e, s) in solve(ends.len(), starts.len(), &candidates, &mut stats)? {
            previous[starts[s]] = Some(ends[e]);
            stats.links += 1;
            stats.gap_links += 1;
        }
    }
    // The gate that admitted each link, for estimators that condition on it.
    let gates = previous
        .iter()
        .enumerate()
        .map(|(j, p)| {
            let (a, b) = (&detections[(*p)?], &detections[j]);
            linker.cost(a, b, b.frame - a.frame).map(|(_, gate)| gate)
        })
        .collect();
    let mut particle = vec![0; detections.len()];
    let mut labels = 0;
    for &i in &order {
        particle[i] = match previous[i] {
            Some(p) => particle[p],
            None => {
                labels += 1;
                labels - 1
            }
        };
    }
    Ok(Linking {
        particle,
        stats,
        gates: Some(gates),
    })
}

/// The cost model over one table.
struct Lap<'a> {
    detections: &'a [Detection],
    step_variance: f64,
    gate_sigmas: f64,
    /// The largest σ² of any detection on either axis (bounds the search).
    largest_sigma2: f64,
}

impl<'a> Lap<'a> {
    fn new(detections: &'a [Detection], params: &LapParams) -> Self {
        let largest_sigma2 = detections
            .iter()
            .filter_map(|d| d.sigma)
            .map(|s| s.x.max(s.y).powi(2))
            .fold(0.0, f64::max);
        Self {
            detections,
            step_variance: params.step_variance,
            gate_sigmas: params.gate_sigmas,
            largest_sigma2,
        }
    }

    /// The cost of linking `a` to `b` over `frames` frames and the gate's
    /// extent along x and y, if within the gate (see the module's
    /// formula).
    fn cost(&self, a: &Detection, b: &Detection, frames: usize) -> Option<(f64, [f64; 2])> {
        let q = self.step_variance;
        let sigma2 = |d: &Detection| d.sigma.map_or((0.0, 0.0), |s| (s.x * s.x, s.y * s.y));
        let ((ax, ay), (bx, by)) = (sigma2(a), sigma2(b));
        let steps = frames as f64 * q;
        let (vx, vy) = (steps + ax + bx, steps + ay + by);
        let (dx, dy) = (b.x - a.x, b.y - a.y);
        let mahalanobis2 = dx * dx / vx + dy * dy / vy;
        (mahalanobis2 <= self.gate_sigmas * self.gate_sigmas).then(|| {
            (
                mahalanobis2 + (vx * vy / (q * q)).ln(),
                [self.gate_sigmas * vx.sqrt(), self.gate_sigmas * vy.sqrt()],
            )
        })
    }

    /// Gated candidates from `sources` to `destinations` (detection
    /// indices) whose frames differ by `shortest..=longest`, with local
    /// indices.
    fn candidates(
        &self,
        sources: &[usize],
        destinations: &[usize],
        shortest: usize,
        longest: usize,
    ) -> anyhow::Result<Vec<Candidate>> {
        if sources.is_empty() || destinations.is_empty() {
            return Ok(Vec::new());
        }
        // Indexed by frame as well as position: gap closing looks for the
        // ends a few frames before each start, and an index by position
        // alone would visit every end of the recording near it (quadratic
        // in a long recording of a small field).
        let points = sources
            .iter()
            .enumerate()
            .map(|(s, &i)| {
                let a = &self.detections[i];
                GeomWithData::new([a.x, a.y, a.frame as f64], s)
            })
            .collect();
        let tree = RTree::bulk_load(points);
        // No gated pair is farther apart than this.
        let reach = (self.gate_sigmas
            * self.gate_sigmas
            * (longest as f64 * self.step_variance + 2.0 * self.largest_sigma2))
            .sqrt();
        let mut candidates = Vec::new();
        for (to, &j) in destinations.iter().enumerate() {
            let b = &self.detections[j];
            let frame = b.frame as f64;
            let window = AABB::from_corners(
                [b.x - reach, b.y - reach, frame - longest as f64],
                [b.x + reach, b.y + reach, frame - shortest as f64],
            );
            for found in tree.locate_in_envelope(window) {
                let from = found.data;
                let a = &self.detections[sources[from]];
                let Some(frames) = b.frame.checked_sub(a.frame) else {
                    continue;
                };
                if !(shortest..=longest).contains(&frames) {
                    continue;
                }
                if let Some((cost, _)) = self.cost(a, b, frames) {
                    if candidates.len() == MAX_CANDIDATE_LINKS {
                        return Err(input_error(format!(
                            "more than {MAX_CANDIDATE_LINKS} candidate links within the gates: \
                             lower the search range or the longest gap, or raise --min-score"
                        )));
                    }
                    candidates.push(Candidate { from, to, cost });
                }
            }
        }
        // The tree's order is not the input's: sorted, the result does not
        // depend on it.
        candidates.sort_by_key(|c| (c.from, c.to));
        Ok(candidates)
    }
}

/// Solves one LAP (birth and death at the alternative cost) component by
/// component; returns the (source, destination) links.
fn solve(
    sources: usize,
    destinations: usize,
    candidates: &[Candidate],
    stats: &mut LinkStats,
) -> anyhow::Result<Vec<(usize, usize)>> {
    let Some(largest) = candidates.iter().map(|c| c.cost).reduce(f64::max) else {
        return Ok(Vec::new());
    };
    let alternative = if largest > 0.0 {
        ALTERNATIVE_COST_FACTOR * largest
    } else {
        1.0
    };
    // Components of the candidate graph: sources 0.., destinations after.
    let mut components = UnionFind::new(sources + destinations);
    for c in candidates {
        components.union(c.from, sources + c.to);
    }
    let mut by_root: std::collections::BTreeMap<usize, Vec<Candidate>> = Default::default();
    for c in candidates {
        by_root.entry(components.find(c.from)).or_default().push(*c);
    }
    let mut links = Vec::new();
    for group in by_root.values() {
        let mut local_sources: Vec<usize> = group.iter().map(|c| c.from).collect();
        let mut local_destinations: Vec<usize> = group.iter().map(|c| c.to).collect();
        local_sources.sort_unstable();
        local_sources.dedup();
        local_destinations.sort_unstable();
        local_destinations.dedup();
        let (s, d) = (local_sources.len(), local_destinations.len());
        if s > 1 || d > 1 {
            stats.contested += 1;
            stats.largest = stats.largest.max(s + d);
        }
        let local: Vec<Candidate> = group
            .iter()
            .map(|c| Candidate {
                from: local_sources.binary_search(&c.from).unwrap_or_default(),
                to: local_destinations.binary_search(&c.to).unwrap_or_default(),
                cost: c.cost,
            })
            .collect();
        let assigned = assign(s, d, &local, &vec![alternative; s], &vec![alternative; d])?;
        for (from, to) in assigned.into_iter().enumerate() {
            if let Some(to) = to {
                links.push((local_sources[from], local_destinations[to]));
            }
        }
    }
    Ok(links)
}

/// Disjoint sets with path halving.
struct UnionFind {
    parent: Vec<usize>,
}

impl UnionFind {
    fn new(n: usize) -> Self {
        Self {
            parent: (0..n).collect(),
        }
    }

    fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }

    fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.parent[ra.max(rb)] = ra.min(rb);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn costs_grow_with_the_gap_and_the_uncertainty() {
        let detections = [Detection::new(0, 0.0, 0.0), Detection::new(2, 1.0, 0.0)];
        let params = LapParams::from_search_range(3.0, 2);
        let lap = Lap::new(&detections, &params);
        let one = lap.cost(&detections[0], &detections[1], 1).unwrap().0;
        let two = lap.cost(&detections[0], &detections[1], 2).unwrap().0;
        assert_eq!(one, 1.0);
        assert!((two - (0.5 + 4f64.ln())).abs() < 1e-12, "{two}");
        // Beyond R·√k with σ = 0: outside the gate.
        let far = Detection::new(1, 3.01, 0.0);
        assert_eq!(lap.cost(&detections[0], &far, 1), None);
    }

    #[test]
    fn q_from_diffusion_is_two_d_dt_over_pixel_squared() {
        let params = LapParams::from_diffusion(1.0, 27.6, 0.068, 0);
        let expected = 2.0 * 1.0 * 0.0276 / (0.068 * 0.068);
        assert!((params.step_variance - expected).abs() < 1e-12);
    }
}
