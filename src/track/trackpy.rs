//! TrackPy 0.7's `link` (Crocker–Grier linking with subnetworks), giving
//! the same trajectories as TrackPy on the same table (checked on fixtures
//! made by TrackPy itself, tests/fixtures/trackpy/make_link_fixtures.py).
//!
//! What TrackPy does, and so what this does:
//!
//! - Frames are taken in increasing order, every frame from the first to the
//!   last present (a frame without detections still counts for memory).
//!   The detections of the first frame each start a trajectory.
//! - At each frame the *sources* are the previous frame's detections plus
//!   the remembered ones (below); each detection of the frame (a
//!   *destination*) takes as candidates its up to 10 nearest sources within
//!   the search range (+ 1e-7, TrackPy's slack).
//! - Sources and destinations joined by candidates form subnetworks. A
//!   subnetwork of one source and one destination is a link; a destination
//!   alone starts a trajectory; otherwise the subnetwork is solved exactly
//!   for the least sum of squared displacements, an unlinked source costing
//!   the squared search range and an unlinked destination nothing (TrackPy
//!   searches exhaustively; this solves the same problem as a linear
//!   assignment, which gives the same minimum). TrackPy refuses a
//!   subnetwork of more than 30 sources (`SubnetOversizeException`,
//!   `adaptive_stop` being off by default); this solves it.
//! - Memory: a source left unlinked is remembered, at its last position,
//!   as a source of the next `memory` frames; a remembered source that is
//!   linked is forgotten, one not linked keeps its original expiry.
//! - Trajectory labels: the first frame's detections in order, then each
//!   new trajectory in the order TrackPy creates them (subnetworks in the
//!   order of their key, the index of a destination in its frame). Within
//!   one subnetwork TrackPy labels new trajectories in the order of a Python
//!   set; this uses destination order, so labels may differ there and the
//!   trajectories do not.

use rstar::RTree;
use rstar::primitives::GeomWithData;

use super::{Candidate, Detection, LinkStats, Linking, assign, frame_order};
use crate::error::input_error;

/// TrackPy's largest number of candidate sources per destination.
pub const MAX_NEIGHBORS: usize = 10;

/// TrackPy's slack on the search range (its k-d tree query's bound).
const RANGE_SLACK: f64 = 1e-7;

/// TrackPy `link`'s parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackpyParams {
    /// The largest displacement between frames, pixels (`search_range`).
    pub search_range: f64,
    /// Frames a particle may vanish for and still be linked (`memory`).
    pub memory: usize,
}

impl TrackpyParams {
    /// Refuses a search range that is not a finite number > 0.
    pub fn validate(&self) -> anyhow::Result<()> {
        if !(self.search_range.is_finite() && self.search_range > 0.0) {
            return Err(input_error(format!(
                "search range: must be a finite number > 0 px, got {}",
                self.search_range
            )));
        }
        Ok(())
    }
}

/// Links `detections` (any order) as TrackPy 0.7's `link` does.
pub fn link(detections: &[Detection], params: &TrackpyParams) -> anyhow::Result<Linking> {
    params.validate()?;
    let order = frame_order(detections);
    let mut state = State::new(detections, params);
    let mut at = 0;
    let Some(first) = order.first().map(|&i| detections[i].frame) else {
        return Ok(state.finish());
    };
    let last = detections[*order.last().unwrap_or(&0)].frame;
    for frame in first..=last {
        let start = at;
        while at < order.len() && detections[order[at]].frame == frame {
            at += 1;
        }
        let destinations = &order[start..at];
        if frame == first {
            state.start(destinations);
        } else {
            state.step(frame, destinations)?;
        }
    }
    Ok(state.finish())
}

/// A subnetwork: its key (TrackPy's: a destination's index in its frame),
/// sources and destinations (indices into the level's lists).
struct Subnet {
    key: usize,
    sources: Vec<usize>,
    destinations: Vec<usize>,
}

/// The linker between frames.
struct State<'a> {
    detections: &'a [Detection],
    search_range: f64,
    memory: usize,
    particle: Vec<usize>,
    next_label: usize,
    /// The previous frame's detections.
    previous: Vec<usize>,
    /// Remembered detections and the frame at which each was lost.
    remembered: Vec<(usize, usize)>,
    in_memory: Vec<bool>,
    stats: LinkStats,
}

impl<'a> State<'a> {
    fn new(detections: &'a [Detection], params: &TrackpyParams) -> Self {
        Self {
            detections,
            search_range: params.search_range,
            memory: params.memory,
            particle: vec![usize::MAX; detections.len()],
            next_label: 0,
            previous: Vec::new(),
            remembered: Vec::new(),
            in_memory: vec![false; detections.len()],
            stats: LinkStats::default(),
        }
    }

    fn finish(self) -> Linking {
        Linking {
            particle: self.particle,
            stats: self.stats,
        }
    }

    fn new_trajectory(&mut self, detection: usize) {
        self.particle[detection] = self.next_label;
        self.next_label += 1;
    }

    /// The first frame: every detection starts a trajectory.
    fn start(&mut self, destinations: &[usize]) {
        for &d in destinations {
            self.new_trajectory(d);
        }
        self.previous = destinations.to_vec();
    }

    /// One frame: candidates, subnetworks, their solutions, memory.
    fn step(&mut self, frame: usize, destinations: &[usize]) -> anyhow::Result<()> {
        let sources: Vec<usize> = self
            .previous
            .iter()
            .copied()
            .chain(self.remembered.iter().map(|&(d, _)| d))
            .collect();
        let candidates = self.candidates(&sources, destinations);
        let subnets = subnets(sources.len(), &candidates);
        let mut source_linked = vec![false; sources.len()];
        for subnet in &subnets {
            let links = self.solve(subnet, &candidates)?;
            for (&s, link) in subnet.sources.iter().zip(&links) {
                if let Some(d) = *link {
                    self.link(sources[s], destinations[d]);
                    source_linked[s] = true;
                }
            }
            let mut claimed: Vec<usize> = links.iter().flatten().copied().collect();
            claimed.sort_unstable();
            for &d in &subnet.destinations {
                if claimed.binary_search(&d).is_err() {
                    self.new_trajectory(destinations[d]);
                }
            }
        }
        let lost: Vec<usize> = sources
            .iter()
            .zip(&source_linked)
            .filter(|&(&s, &linked)| !linked && !self.in_memory[s])
            .map(|(&s, _)| s)
            .collect();
        self.remember(frame, lost);
        self.previous = destinations.to_vec();
        Ok(())
    }

    /// For each destination, its up to [`MAX_NEIGHBORS`] nearest sources
    /// within the search range: (source index, squared distance), nearest
    /// first.
    fn candidates(&self, sources: &[usize], destinations: &[usize]) -> Vec<Vec<(usize, f64)>> {
        if sources.is_empty() {
            return vec![Vec::new(); destinations.len()];
        }
        let points = sources
            .iter()
            .enumerate()
            .map(|(s, &d)| GeomWithData::new([self.detections[d].x, self.detections[d].y], s))
            .collect();
        let tree = RTree::bulk_load(points);
        let limit = self.search_range + RANGE_SLACK;
        destinations
            .iter()
            .map(|&d| {
                let p = &self.detections[d];
                tree.nearest_neighbor_iter_with_distance_2([p.x, p.y])
                    .take_while(|&(_, d2)| d2 < limit * limit)
                    .take(MAX_NEIGHBORS)
                    .map(|(source, d2)| (source.data, d2))
                    .collect()
            })
            .collect()
    }

    /// The links of one subnetwork: the destination (index in the frame) of
    /// each of its sources, or none.
    fn solve(
        &mut self,
        subnet: &Subnet,
        candidates: &[Vec<(usize, f64)>],
    ) -> anyhow::Result<Vec<Option<usize>>> {
        match (subnet.sources.len(), subnet.destinations.len()) {
            (0, _) => return Ok(Vec::new()),
            (1, 1) => return Ok(vec![Some(subnet.destinations[0])]),
            (s, d) => {
                self.stats.contested += 1;
                self.stats.largest = self.stats.largest.max(s + d);
            }
        }
        // Local indices: sources and destinations by position in the subnet.
        let local_source = |s: usize| subnet.sources.binary_search(&s).ok();
        let mut local = Vec::new();
        for (to, &d) in subnet.destinations.iter().enumerate() {
            for &(s, d2) in &candidates[d] {
                if let Some(from) = local_source(s) {
                    local.push(Candidate { from, to, cost: d2 });
                }
            }
        }
        let death = vec![self.search_range * self.search_range; subnet.sources.len()];
        let birth = vec![0.0; subnet.destinations.len()];
        let links = assign(
            subnet.sources.len(),
            subnet.destinations.len(),
            &local,
            &death,
            &birth,
        )?;
        Ok(links
            .into_iter()
            .map(|to| to.map(|t| subnet.destinations[t]))
            .collect())
    }

    fn link(&mut self, source: usize, destination: usize) {
        self.particle[destination] = self.particle[source];
        self.stats.links += 1;
        if self.detections[source].frame + 1 < self.detections[destination].frame {
            self.stats.gap_links += 1;
        }
        // Linked: no longer remembered (dropped from the list below).
        self.in_memory[source] = false;
    }

    /// Forgets what expired or was linked, then remembers the sources
    /// newly lost at `frame`.
    fn remember(&mut self, frame: usize, lost: Vec<usize>) {
        let memory = self.memory;
        let in_memory = &mut self.in_memory;
        self.remembered.retain(|&(d, lost_at)| {
            let keep = in_memory[d] && lost_at + memory > frame;
            in_memory[d] = keep;
            keep
        });
        if memory == 0 {
            return;
        }
        for d in lost {
            self.in_memory[d] = true;
            self.remembered.push((d, frame));
        }
    }
}

/// TrackPy's subnetworks: every destination starts as its own subnetwork
/// keyed by its index; going through destinations in order and their
/// candidates nearest first, a source joins its destination's subnetwork,
/// or, if it is in another, that one merges into the destination's (which
/// keeps its key). Returned in key order, members sorted; sources without
/// candidates are in none.
fn subnets(sources: usize, candidates: &[Vec<(usize, f64)>]) -> Vec<Subnet> {
    let mut groups: Vec<Subnet> = (0..candidates.len())
        .map(|d| Subnet {
            key: d,
            sources: Vec::new(),
            destinations: vec![d],
        })
        .collect();
    let mut group_of_destination: Vec<usize> = (0..candidates.len()).collect();
    let mut group_of_source: Vec<Option<usize>> = vec![None; sources];
    for (d, list) in candidates.iter().enumerate() {
        for &(s, _) in list {
            let target = group_of_destination[d];
            match group_of_source[s] {
                None => {
                    groups[target].sources.push(s);
                    group_of_source[s] = Some(target);
                }
                Some(other) if other != target => {
                    // Move the smaller group's members; the key stays the
                    // destination's.
                    let key = groups[target].key;
                    let (from, into) = if groups[other].sources.len()
                        + groups[other].destinations.len()
                        > groups[target].sources.len() + groups[target].destinations.len()
                    {
                        (target, other)
                    } else {
                        (other, target)
                    };
                    let moved_sources = std::mem::take(&mut groups[from].sources);
                    let moved_destinations = std::mem::take(&mut groups[from].destinations);
                    for &m in &moved_sources {
                        group_of_source[m] = Some(into);
                    }
                    for &m in &moved_destinations {
                        group_of_destination[m] = into;
                    }
                    groups[into].sources.extend(moved_sources);
                    groups[into].destinations.extend(moved_destinations);
                    groups[into].key = key;
                }
                Some(_) => {}
            }
        }
    }
    let mut live: Vec<Subnet> = groups
        .into_iter()
        .filter(|g| !g.destinations.is_empty())
        .map(|mut g| {
            g.sources.sort_unstable();
            g.destinations.sort_unstable();
            g
        })
        .collect();
    live.sort_by_key(|g| g.key);
    live
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(search_range: f64, memory: usize) -> TrackpyParams {
        TrackpyParams {
            search_range,
            memory,
        }
    }

    #[test]
    fn a_subnet_is_solved_for_the_least_sum_of_squares() {
        // Sources A (x 0), B (x 2); destinations a (x 1), b (x 3.5): a is
        // 1 px from both, b only reaches B.
        let detections = [
            Detection::new(0, 0.0, 0.0),
            Detection::new(0, 2.0, 0.0),
            Detection::new(1, 1.0, 0.0),
            Detection::new(1, 3.5, 0.0),
        ];
        let linked = link(&detections, &params(2.0, 0)).unwrap();
        // A→a (1) + B→b (2.25) = 3.25 beats B→a (1) + A lost (4).
        assert_eq!(linked.particle, [0, 1, 0, 1]);
        assert_eq!(linked.stats.contested, 1);
    }

    #[test]
    fn memory_bridges_empty_frames_and_expires() {
        let detections = [
            Detection::new(0, 5.0, 5.0),
            Detection::new(3, 5.5, 5.0),
            Detection::new(7, 5.5, 5.0),
        ];
        // Gap of 2 missing frames (1, 2): memory 2 links it; the gap of 3
        // frames (4, 5, 6) is too long.
        let linked = link(&detections, &params(1.0, 2)).unwrap();
        assert_eq!(linked.particle, [0, 0, 1]);
        assert_eq!(linked.stats.gap_links, 1);
        let linked = link(&detections, &params(1.0, 1)).unwrap();
        assert_eq!(linked.particle, [0, 1, 2]);
    }

    #[test]
    fn input_order_does_not_change_the_trajectories() {
        let detections = [
            Detection::new(2, 1.2, 0.0),
            Detection::new(0, 0.0, 0.0),
            Detection::new(1, 0.5, 0.0),
            Detection::new(0, 10.0, 0.0),
            Detection::new(1, 10.4, 0.0),
        ];
        let linked = link(&detections, &params(1.0, 0)).unwrap();
        assert_eq!(linked.particle, [0, 0, 0, 1, 1]);
    }
}
