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
use rstar::primitives::{GeomWithData, Rectangle};

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

/// Each destination's candidate sources, flat: those of destination `d`
/// are `list[offsets[d]..offsets[d + 1]]`, (source index, squared
/// distance), nearest first.
struct Candidates {
    list: Vec<(usize, f64)>,
    offsets: Vec<usize>,
}

impl Candidates {
    fn of(&self, destination: usize) -> &[(usize, f64)] {
        &self.list[self.offsets[destination]..self.offsets[destination + 1]]
    }

    fn destinations(&self) -> usize {
        self.offsets.len() - 1
    }
}

/// The subnetworks of a frame in key order: subnetwork `i` has the sources
/// `sources[spans[i].0]` and destinations `destinations[spans[i].1]`
/// (indices into the frame's lists, ascending).
struct Subnets {
    sources: Vec<usize>,
    destinations: Vec<usize>,
    spans: Vec<(std::ops::Range<usize>, std::ops::Range<usize>)>,
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
        let mut claimed = Vec::new();
        for (source_span, destination_span) in &subnets.spans {
            let subnet_sources = &subnets.sources[source_span.clone()];
            let subnet_destinations = &subnets.destinations[destination_span.clone()];
            let links = self.solve(subnet_sources, subnet_destinations, &candidates)?;
            claimed.clear();
            for (&s, link) in subnet_sources.iter().zip(&links) {
                if let Some(d) = *link {
                    self.link(sources[s], destinations[d]);
                    source_linked[s] = true;
                    claimed.push(d);
                }
            }
            for &d in subnet_destinations {
                if !claimed.contains(&d) {
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
    /// within the search range.
    fn candidates(&self, sources: &[usize], destinations: &[usize]) -> Candidates {
        let mut candidates = Candidates {
            list: Vec::new(),
            offsets: Vec::with_capacity(destinations.len() + 1),
        };
        candidates.offsets.push(0);
        if sources.is_empty() {
            candidates.offsets.resize(destinations.len() + 1, 0);
            return candidates;
        }
        // One join of two R*-trees (sources as squares of the search range,
        // destinations as points) instead of a query per destination.
        let limit = self.search_range + RANGE_SLACK;
        let position = |d: usize| [self.detections[d].x, self.detections[d].y];
        let squares = sources
            .iter()
            .enumerate()
            .map(|(s, &d)| {
                let [x, y] = position(d);
                let square =
                    Rectangle::from_corners([x - limit, y - limit], [x + limit, y + limit]);
                GeomWithData::new(square, s)
            })
            .collect();
        let points = destinations
            .iter()
            .enumerate()
            .map(|(j, &d)| GeomWithData::new(position(d), j))
            .collect();
        let (squares, points): (RTree<_>, RTree<_>) =
            (RTree::bulk_load(squares), RTree::bulk_load(points));
        // (destination, squared distance, source), sorted: each
        // destination's candidates nearest first.
        let mut found: Vec<(usize, f64, usize)> = squares
            .intersection_candidates_with_other_tree(&points)
            .filter_map(|(square, point)| {
                let [x, y] = position(sources[square.data]);
                let [px, py] = *point.geom();
                let d2 = (x - px) * (x - px) + (y - py) * (y - py);
                // TrackPy's bound is strict.
                (d2 < limit * limit).then_some((point.data, d2, square.data))
            })
            .collect();
        found.sort_unstable_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)));
        let mut at = 0;
        for j in 0..destinations.len() {
            let mut kept = 0;
            while at < found.len() && found[at].0 == j {
                if kept < MAX_NEIGHBORS {
                    candidates.list.push((found[at].2, found[at].1));
                    kept += 1;
                }
                at += 1;
            }
            candidates.offsets.push(candidates.list.len());
        }
        candidates
    }

    /// The links of one subnetwork (sources and destinations as indices
    /// into the frame's lists, ascending): the destination of each source,
    /// or none.
    fn solve(
        &mut self,
        sources: &[usize],
        destinations: &[usize],
        candidates: &Candidates,
    ) -> anyhow::Result<Vec<Option<usize>>> {
        match (sources.len(), destinations.len()) {
            (0, _) => return Ok(Vec::new()),
            (1, 1) => return Ok(vec![Some(destinations[0])]),
            (s, d) => {
                self.stats.contested += 1;
                self.stats.largest = self.stats.largest.max(s + d);
            }
        }
        let mut local = Vec::new();
        for (to, &d) in destinations.iter().enumerate() {
            for &(s, d2) in candidates.of(d) {
                if let Ok(from) = sources.binary_search(&s) {
                    local.push(Candidate { from, to, cost: d2 });
                }
            }
        }
        let death = vec![self.search_range * self.search_range; sources.len()];
        let birth = vec![0.0; destinations.len()];
        let links = assign(sources.len(), destinations.len(), &local, &death, &birth)?;
        Ok(links
            .into_iter()
            .map(|to| to.map(|t| destinations[t]))
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
/// keeps its key). Sources without candidates are in none.
fn subnets(sources: usize, candidates: &Candidates) -> Subnets {
    let destinations = candidates.destinations();
    // Disjoint sets over destinations (0..) and sources (after); each root
    // holds its subnetwork's key and size.
    let mut sets = KeyedSets::new(destinations, sources);
    for d in 0..destinations {
        for &(s, _) in candidates.of(d) {
            sets.join(d, destinations + s);
        }
    }
    let mut keyed_destinations: Vec<(usize, usize)> =
        (0..destinations).map(|d| (sets.key(d), d)).collect();
    let mut keyed_sources: Vec<(usize, usize)> = (0..sources)
        .map(|s| (sets.key(destinations + s), s))
        .filter(|&(key, _)| key != usize::MAX)
        .collect();
    keyed_destinations.sort_unstable();
    keyed_sources.sort_unstable();
    let mut subnets = Subnets {
        sources: keyed_sources.iter().map(|&(_, s)| s).collect(),
        destinations: keyed_destinations.iter().map(|&(_, d)| d).collect(),
        spans: Vec::new(),
    };
    // Every subnetwork has a destination: sweep the keys of destinations.
    let (mut d, mut s) = (0, 0);
    while d < keyed_destinations.len() {
        let key = keyed_destinations[d].0;
        let (d_start, s_start) = (d, s);
        while d < keyed_destinations.len() && keyed_destinations[d].0 == key {
            d += 1;
        }
        while s < keyed_sources.len() && keyed_sources[s].0 == key {
            s += 1;
        }
        subnets.spans.push((s_start..s, d_start..d));
    }
    subnets
}

/// Disjoint sets of destinations and sources whose roots carry TrackPy's
/// subnetwork key.
struct KeyedSets {
    parent: Vec<usize>,
    size: Vec<usize>,
    key: Vec<usize>,
}

impl KeyedSets {
    fn new(destinations: usize, sources: usize) -> Self {
        let n = destinations + sources;
        Self {
            parent: (0..n).collect(),
            size: vec![1; n],
            // A source alone has no subnetwork (usize::MAX: not joined).
            key: (0..n)
                .map(|i| if i < destinations { i } else { usize::MAX })
                .collect(),
        }
    }

    fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }

    fn key(&mut self, x: usize) -> usize {
        let root = self.find(x);
        self.key[root]
    }

    /// Puts source `source` into destination `destination`'s subnetwork,
    /// merging its own into it; the result keeps the destination's key.
    fn join(&mut self, destination: usize, source: usize) {
        let (rd, rs) = (self.find(destination), self.find(source));
        if rd == rs {
            return;
        }
        let key = self.key[rd];
        let (small, large) = if self.size[rd] < self.size[rs] {
            (rd, rs)
        } else {
            (rs, rd)
        };
        self.parent[small] = large;
        self.size[large] += self.size[small];
        self.key[large] = key;
    }
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
