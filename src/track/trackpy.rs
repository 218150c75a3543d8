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
//!
//! For speed (docs/linking.md, "Speed"): the detections are gathered in
//! frame order once, each frame's sources are bucketed in a uniform grid
//! (cells at least the search range wide) for the neighbour search, the
//! candidates among the previous frame's detections are found a block of
//! frames ahead, on a second thread, while the linking goes on,
//! subnetworks are grouped by a counting sort on their key, and the
//! per-frame buffers are kept from frame to frame.

use std::ops::Range;

use super::{Candidate, Detection, LinkStats, Linking, assign, frame_order};

/// TrackPy's largest number of candidate sources per destination.
pub(crate) const MAX_NEIGHBORS: usize = 10;

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
    /// Refuses a search range that is not a finite number > 0 and at most
    /// [`MAX_SEARCH_RANGE`](crate::limits::MAX_SEARCH_RANGE).
    pub fn validate(&self) -> anyhow::Result<()> {
        crate::limits::check_positive_at_most(
            "search range",
            self.search_range,
            crate::limits::MAX_SEARCH_RANGE,
        )?;
        Ok(())
    }
}

/// Detections per block of frames: the candidates of one block are found
/// (on a second thread where there is one) while an earlier block is
/// linked; at most four blocks' candidates are held at a time.
const BLOCK_DETECTIONS: usize = 4096;

/// Links `detections` (any order) as TrackPy 0.7's `link` does.
pub fn link(detections: &[Detection], params: &TrackpyParams) -> anyhow::Result<Linking> {
    let threaded = rayon::current_num_threads() > 1;
    link_in_blocks(detections, params, BLOCK_DETECTIONS, threaded)
}

/// [`link`] in blocks of about `block_detections`, searched ahead on a
/// second thread if `threaded`: the same result for any of them.
fn link_in_blocks(
    detections: &[Detection],
    params: &TrackpyParams,
    block_detections: usize,
    threaded: bool,
) -> anyhow::Result<Linking> {
    params.validate()?;
    // The linker works on the detections in frame order, gathered once
    // into contiguous arrays: a frame's detections are then a range, and
    // reading them does not jump around the input.
    let order = frame_order(detections);
    let frames: Vec<usize> = order.iter().map(|&i| detections[i].frame).collect();
    let positions: Vec<[f64; 2]> = order
        .iter()
        .map(|&i| [detections[i].x, detections[i].y])
        .collect();
    let runs = frame_runs(&frames);
    let mut state = State::new(&frames, &positions, params);
    let Some((_, first)) = runs.first() else {
        return Ok(state.finish(&order));
    };
    state.start(first.clone());
    // The candidates among the previous frame's detections need nothing
    // the linking decides (unlike those among remembered ones), so they
    // are found a block ahead: the two halves of the work overlap, and the
    // result is the same on any number of threads.
    let limit = params.search_range + RANGE_SLACK;
    let blocks = blocks_of(&runs, block_detections);
    let mut before = SourceGrid::default();
    before.build(&positions[first.clone()], limit);
    let search = |block: &Range<usize>, ahead: &mut Lookahead, before: &mut SourceGrid| {
        ahead.search(&runs, block.clone(), &positions, limit, before);
        if let Some(last) = ahead.last_grid() {
            before.clone_from(last);
        }
    };
    if blocks.len() < 2 || !threaded {
        let mut ahead = Lookahead::default();
        for block in &blocks {
            search(block, &mut ahead, &mut before);
            state.link_block(&runs, block.clone(), &ahead)?;
        }
    } else {
        // A second thread searches up to two blocks ahead; the buffers
        // go back to it once linked.
        std::thread::scope(|scope| -> anyhow::Result<()> {
            let (ready, searched) = std::sync::mpsc::sync_channel::<Lookahead>(1);
            let (done, spent) = std::sync::mpsc::channel::<Lookahead>();
            let blocks = &blocks;
            scope.spawn(move || {
                for block in blocks {
                    let mut ahead = spent.try_recv().unwrap_or_default();
                    search(block, &mut ahead, &mut before);
                    if ready.send(ahead).is_err() {
                        return; // The linking stopped (an error).
                    }
                }
            });
            for block in blocks {
                let ahead = searched
                    .recv()
                    .map_err(|_| anyhow::anyhow!("linking: the candidate search stopped"))?;
                state.link_block(&runs, block.clone(), &ahead)?;
                let _ = done.send(ahead);
            }
            Ok(())
        })?;
    }
    Ok(state.finish(&order))
}

/// Each frame with detections and their range, in frame order.
fn frame_runs(frames: &[usize]) -> Vec<(usize, Range<usize>)> {
    let mut runs: Vec<(usize, Range<usize>)> = Vec::new();
    for (at, &frame) in frames.iter().enumerate() {
        match runs.last_mut() {
            Some((last, range)) if *last == frame => range.end = at + 1,
            _ => runs.push((frame, at..at + 1)),
        }
    }
    runs
}

/// The runs after the first in blocks of about `block_detections`.
fn blocks_of(runs: &[(usize, Range<usize>)], block_detections: usize) -> Vec<Range<usize>> {
    let mut blocks = Vec::new();
    let (mut start, mut count) = (1, 0);
    for (i, (_, range)) in runs.iter().enumerate().skip(1) {
        count += range.len();
        if count >= block_detections {
            blocks.push(start..i + 1);
            (start, count) = (i + 1, 0);
        }
    }
    if start < runs.len() {
        blocks.push(start..runs.len());
    }
    blocks
}

/// The candidates of a block's destinations among the previous frame's
/// detections, and each of its frames' detections bucketed: the grid of
/// one frame finds the candidates of the next among its detections, and
/// the remembered sources' destinations in its own.
#[derive(Default)]
struct Lookahead {
    candidates: Candidates,
    /// `grids[k]`: the detections of the block's `k`-th frame (kept
    /// beyond the block's frames: their buffers are reused).
    grids: Vec<SourceGrid>,
    /// The frames of the block searched last.
    frames: usize,
}

impl Lookahead {
    /// For every destination of `runs[block]` in frame order, its
    /// candidates among the detections of the frame before (none where
    /// that frame has none), source indices counted from that frame's
    /// first detection; `before` holds the detections of the run before
    /// the block bucketed.
    fn search(
        &mut self,
        runs: &[(usize, Range<usize>)],
        block: Range<usize>,
        positions: &[[f64; 2]],
        limit: f64,
        before: &SourceGrid,
    ) {
        self.candidates.clear();
        self.frames = block.len();
        if self.grids.len() < block.len() {
            self.grids.resize_with(block.len(), SourceGrid::default);
        }
        for (k, i) in block.enumerate() {
            let (frame, destinations) = &runs[i];
            let (previous_frame, previous) = &runs[i - 1];
            let destinations = &positions[destinations.clone()];
            let (built, rest) = self.grids.split_at_mut(k);
            if previous_frame + 1 == *frame {
                let grid = built.last().unwrap_or(before);
                let sources = &positions[previous.clone()];
                search_sources(grid, sources, destinations, limit, &mut self.candidates);
            } else {
                self.candidates.push_empty(destinations.len());
            }
            rest[0].build(destinations, limit);
        }
    }

    /// The grid of the block's last frame.
    fn last_grid(&self) -> Option<&SourceGrid> {
        self.grids[..self.frames].last()
    }
}

/// Appends to `out` each destination's up to [`MAX_NEIGHBORS`] nearest
/// of `sources` (bucketed in `grid`) within `limit`, nearest first, ties
/// by source index.
fn search_sources(
    grid: &SourceGrid,
    sources: &[[f64; 2]],
    destinations: &[[f64; 2]],
    limit: f64,
    out: &mut Candidates,
) {
    for &[px, py] in destinations {
        let start = out.list.len();
        grid.near(px, py, limit, |s| {
            let [x, y] = sources[s];
            let d2 = (x - px) * (x - px) + (y - py) * (y - py);
            // TrackPy's bound is strict.
            if d2 < limit * limit {
                out.list.push((s, d2));
            }
        });
        let found = &mut out.list[start..];
        if found.len() > 1 {
            found.sort_unstable_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        }
        let kept = found.len().min(MAX_NEIGHBORS);
        out.list.truncate(start + kept);
        out.offsets.push(out.list.len());
    }
}

/// Each destination's candidates merged from the previous frame's
/// (`ahead`) and the remembered sources' (`remembered`: (destination,
/// squared distance, source) sorted, source indices shifted by `shift`,
/// after the previous frame's): the nearest [`MAX_NEIGHBORS`], ties by
/// source index.
fn merge(
    ahead: CandidatesView<'_>,
    remembered: &[(usize, f64, usize)],
    shift: usize,
    out: &mut Candidates,
) {
    out.clear();
    let mut next = 0;
    for d in 0..ahead.destinations() {
        let a = ahead.of(d);
        let first = next;
        while next < remembered.len() && remembered[next].0 == d {
            next += 1;
        }
        let r = &remembered[first..next];
        let (mut i, mut j) = (0, 0);
        while i + j < MAX_NEIGHBORS && (i < a.len() || j < r.len()) {
            // Previous-frame sources have the smaller indices: first on ties.
            if j == r.len() || (i < a.len() && a[i].1.total_cmp(&r[j].1).is_le()) {
                out.list.push(a[i]);
                i += 1;
            } else {
                out.list.push((r[j].2 + shift, r[j].1));
                j += 1;
            }
        }
        out.offsets.push(out.list.len());
    }
}

/// Each destination's candidate sources, flat: those of destination `d`
/// are `list[offsets[d]..offsets[d + 1]]`, (source index, squared
/// distance), nearest first.
struct Candidates {
    list: Vec<(usize, f64)>,
    offsets: Vec<usize>,
}

impl Default for Candidates {
    fn default() -> Self {
        Self {
            list: Vec::new(),
            offsets: vec![0],
        }
    }
}

impl Candidates {
    fn clear(&mut self) {
        self.list.clear();
        self.offsets.clear();
        self.offsets.push(0);
    }

    /// Appends `count` destinations without candidates.
    fn push_empty(&mut self, count: usize) {
        let end = self.list.len();
        self.offsets.extend(std::iter::repeat_n(end, count));
    }

    fn view(&self) -> CandidatesView<'_> {
        self.slice(0, self.offsets.len() - 1)
    }

    /// Destinations `first..first + count`.
    fn slice(&self, first: usize, count: usize) -> CandidatesView<'_> {
        CandidatesView {
            list: &self.list,
            offsets: &self.offsets[first..=first + count],
        }
    }
}

/// Some destinations' candidates in a [`Candidates`]: destination `d`'s
/// are `list[offsets[d]..offsets[d + 1]]`.
#[derive(Clone, Copy)]
struct CandidatesView<'c> {
    list: &'c [(usize, f64)],
    offsets: &'c [usize],
}

impl<'c> CandidatesView<'c> {
    /// No destinations.
    const NONE: Self = Self {
        list: &[],
        offsets: &[0],
    };

    fn of(&self, destination: usize) -> &'c [(usize, f64)] {
        &self.list[self.offsets[destination]..self.offsets[destination + 1]]
    }

    fn destinations(&self) -> usize {
        self.offsets.len() - 1
    }
}

/// The subnetworks of a frame, keyed by TrackPy's key (a destination
/// index): the sources and the destinations of each key, ascending
/// (indices into the frame's lists).
#[derive(Default)]
struct Subnets {
    sources: KeyOrder,
    destinations: KeyOrder,
}

impl Subnets {
    /// (sources, destinations) of each subnetwork, in key order. Every
    /// subnetwork has a destination: the keys that have one.
    fn iter(&self) -> impl Iterator<Item = (&[usize], &[usize])> {
        (0..self.destinations.keys())
            .map(|key| (self.sources.of(key), self.destinations.of(key)))
            .filter(|(_, destinations)| !destinations.is_empty())
    }
}

/// What one frame needs, kept between frames so that a frame allocates
/// nothing once the buffers have grown to the largest frame.
#[derive(Default)]
struct FrameBuffers {
    /// The frame's sources (detections: the previous frame's, then the
    /// remembered ones).
    sources: Vec<usize>,
    /// The remembered sources in range of a destination: (destination,
    /// squared distance, remembered index).
    remembered_pairs: Vec<(usize, f64, usize)>,
    /// The candidates merged from the previous frame's and the
    /// remembered sources.
    candidates: Candidates,
    sets: KeyedSets,
    subnets: Subnets,
    source_linked: Vec<bool>,
    destination_linked: Vec<bool>,
    /// Sources lost at this frame (not linked, not remembered before).
    lost: Vec<usize>,
    /// One subnetwork's problem and solution.
    local: Vec<Candidate>,
    death: Vec<f64>,
    birth: Vec<f64>,
    links: Vec<Option<usize>>,
}

/// The linker between frames. Detections are named by their place in
/// frame order.
struct State<'a> {
    frames: &'a [usize],
    positions: &'a [[f64; 2]],
    search_range: f64,
    memory: usize,
    particle: Vec<usize>,
    next_label: usize,
    /// The previous frame's detections.
    previous: Range<usize>,
    /// Remembered detections and the frame at which each was lost.
    remembered: Vec<(usize, usize)>,
    in_memory: Vec<bool>,
    stats: LinkStats,
    buffers: FrameBuffers,
}

impl<'a> State<'a> {
    fn new(frames: &'a [usize], positions: &'a [[f64; 2]], params: &TrackpyParams) -> Self {
        Self {
            frames,
            positions,
            search_range: params.search_range,
            memory: params.memory,
            particle: vec![usize::MAX; frames.len()],
            next_label: 0,
            previous: 0..0,
            remembered: Vec::new(),
            in_memory: vec![false; frames.len()],
            stats: LinkStats::default(),
            buffers: FrameBuffers::default(),
        }
    }

    /// The labels back in input order (`order`: the input index of each
    /// detection in frame order).
    fn finish(self, order: &[usize]) -> Linking {
        let mut particle = vec![usize::MAX; order.len()];
        for (&i, &label) in order.iter().zip(&self.particle) {
            particle[i] = label;
        }
        Linking {
            particle,
            stats: self.stats,
            gates: None,
        }
    }

    fn new_trajectory(&mut self, detection: usize) {
        self.particle[detection] = self.next_label;
        self.next_label += 1;
    }

    /// Forgets the remembered detections that the frames before `frame`
    /// (stepped or skipped) let expire.
    fn expire_before(&mut self, frame: usize) {
        self.remember(frame - 1, &[]);
    }

    /// The first frame: every detection starts a trajectory.
    fn start(&mut self, destinations: Range<usize>) {
        for d in destinations.clone() {
            self.new_trajectory(d);
        }
        self.previous = destinations;
    }

    /// The frames of `runs[block]` (each after the run before it), with
    /// `ahead` the candidates of their destinations among the previous
    /// frame's ([`Lookahead::search`]).
    fn link_block(
        &mut self,
        runs: &[(usize, Range<usize>)],
        block: Range<usize>,
        ahead: &Lookahead,
    ) -> anyhow::Result<()> {
        let mut first = 0;
        for (k, i) in block.enumerate() {
            let (frame, destinations) = runs[i].clone();
            let previous_frame = runs[i - 1].0;
            // Every frame counts for memory, but a run of frames without
            // detections only loses the previous frame's detections (at
            // its first frame) and lets remembered ones expire: step the
            // first empty frame, then expire what the rest would have
            // (frame numbers may be far apart, and `memory` may exceed
            // them).
            if frame != previous_frame + 1 {
                let none = destinations.start..destinations.start;
                self.step(previous_frame + 1, none, CandidatesView::NONE, None)?;
                if frame != previous_frame + 2 {
                    self.expire_before(frame);
                }
            }
            let count = destinations.len();
            let grid = ahead.grids.get(k);
            self.step(
                frame,
                destinations,
                ahead.candidates.slice(first, count),
                grid,
            )?;
            first += count;
        }
        Ok(())
    }

    /// One frame: candidates, subnetworks, their solutions, memory.
    /// `ahead` holds the destinations' candidates among the previous
    /// frame's detections, `grid` (with memory) the destinations bucketed.
    fn step(
        &mut self,
        frame: usize,
        destinations: Range<usize>,
        ahead: CandidatesView<'_>,
        grid: Option<&SourceGrid>,
    ) -> anyhow::Result<()> {
        // The buffers leave `self` for the frame so that linking (which
        // needs `self`) can read them.
        let mut b = std::mem::take(&mut self.buffers);
        b.sources.clear();
        b.sources.extend(self.previous.clone());
        b.sources.extend(self.remembered.iter().map(|&(d, _)| d));
        let candidates = match grid {
            Some(grid) if !self.remembered.is_empty() && !destinations.is_empty() => {
                self.add_remembered(destinations.clone(), grid, ahead, &mut b);
                b.candidates.view()
            }
            _ => ahead,
        };
        find_subnets(b.sources.len(), candidates, &mut b.sets, &mut b.subnets);
        b.source_linked.clear();
        b.source_linked.resize(b.sources.len(), false);
        b.destination_linked.clear();
        b.destination_linked.resize(destinations.len(), false);
        for (subnet_sources, subnet_destinations) in b.subnets.iter() {
            self.solve(
                subnet_sources,
                subnet_destinations,
                candidates,
                &mut b.local,
                &mut b.death,
                &mut b.birth,
                &mut b.links,
            )?;
            for (&s, link) in subnet_sources.iter().zip(&b.links) {
                if let Some(d) = *link {
                    self.link(b.sources[s], destinations.start + d);
                    b.source_linked[s] = true;
                    b.destination_linked[d] = true;
                }
            }
            for &d in subnet_destinations {
                if !b.destination_linked[d] {
                    self.new_trajectory(destinations.start + d);
                }
            }
        }
        b.lost.clear();
        b.lost.extend(
            b.sources
                .iter()
                .zip(&b.source_linked)
                .filter(|&(&s, &linked)| !linked && !self.in_memory[s])
                .map(|(&s, _)| s),
        );
        self.remember(frame, &b.lost);
        self.previous = destinations;
        self.buffers = b;
        Ok(())
    }

    /// Each destination's candidates among the previous frame's (`ahead`)
    /// and the remembered sources, into `b.candidates`: the few remembered
    /// sources look for destinations in `grid` (the frame's bucketed).
    fn add_remembered(
        &self,
        destinations: Range<usize>,
        grid: &SourceGrid,
        ahead: CandidatesView<'_>,
        b: &mut FrameBuffers,
    ) {
        let limit = self.search_range + RANGE_SLACK;
        let frame_positions = &self.positions[destinations];
        b.remembered_pairs.clear();
        for (j, &(source, _)) in self.remembered.iter().enumerate() {
            let [x, y] = self.positions[source];
            grid.near(x, y, limit, |d| {
                let [px, py] = frame_positions[d];
                // As from the destination (the same bits): TrackPy's
                // strict bound.
                let d2 = (x - px) * (x - px) + (y - py) * (y - py);
                if d2 < limit * limit {
                    b.remembered_pairs.push((d, d2, j));
                }
            });
        }
        b.remembered_pairs
            .sort_unstable_by(|a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)).then(a.2.cmp(&b.2)));
        merge(
            ahead,
            &b.remembered_pairs,
            self.previous.len(),
            &mut b.candidates,
        );
    }

    /// The links of one subnetwork (sources and destinations as indices
    /// into the frame's lists, ascending) into `links`: the destination of
    /// each source, or none. `local`, `death` and `birth` are scratch.
    #[allow(clippy::too_many_arguments)]
    fn solve(
        &mut self,
        sources: &[usize],
        destinations: &[usize],
        candidates: CandidatesView<'_>,
        local: &mut Vec<Candidate>,
        death: &mut Vec<f64>,
        birth: &mut Vec<f64>,
        links: &mut Vec<Option<usize>>,
    ) -> anyhow::Result<()> {
        links.clear();
        match (sources.len(), destinations.len()) {
            (0, _) => return Ok(()),
            (1, 1) => {
                links.push(Some(destinations[0]));
                return Ok(());
            }
            (s, d) => {
                self.stats.contested += 1;
                self.stats.largest = self.stats.largest.max(s + d);
            }
        }
        local.clear();
        for (to, &d) in destinations.iter().enumerate() {
            for &(s, d2) in candidates.of(d) {
                if let Ok(from) = sources.binary_search(&s) {
                    local.push(Candidate { from, to, cost: d2 });
                }
            }
        }
        death.clear();
        death.resize(sources.len(), self.search_range * self.search_range);
        birth.clear();
        birth.resize(destinations.len(), 0.0);
        let solved = assign(sources.len(), destinations.len(), local, death, birth)?;
        links.extend(solved.into_iter().map(|to| to.map(|t| destinations[t])));
        Ok(())
    }

    fn link(&mut self, source: usize, destination: usize) {
        self.particle[destination] = self.particle[source];
        self.stats.links += 1;
        if self.frames[source] + 1 < self.frames[destination] {
            self.stats.gap_links += 1;
        }
        // Linked: no longer remembered (dropped from the list below).
        self.in_memory[source] = false;
    }

    /// Forgets what expired or was linked, then remembers the sources
    /// newly lost at `frame`.
    fn remember(&mut self, frame: usize, lost: &[usize]) {
        let memory = self.memory;
        let in_memory = &mut self.in_memory;
        self.remembered.retain(|&(d, lost_at)| {
            // `lost_at ≤ frame`; written as a difference so that a huge
            // `memory` cannot overflow.
            let keep = in_memory[d] && frame - lost_at < memory;
            in_memory[d] = keep;
            keep
        });
        if memory == 0 {
            return;
        }
        for &d in lost {
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
fn find_subnets(
    sources: usize,
    candidates: CandidatesView<'_>,
    sets: &mut KeyedSets,
    subnets: &mut Subnets,
) {
    let destinations = candidates.destinations();
    // Disjoint sets over destinations (0..) and sources (after); each root
    // holds its subnetwork's key.
    sets.reset(destinations, sources);
    for d in 0..destinations {
        for &(s, _) in candidates.of(d) {
            sets.join(d, destinations + s);
        }
    }
    // Keys are destination indices: bucketing by key beats sorting.
    subnets
        .destinations
        .order(destinations, (0..destinations).map(|d| sets.key(d)));
    subnets.sources.order(
        destinations,
        (0..sources).map(|s| sets.key(destinations + s)),
    );
}

/// A counting sort of items `0..` by a key in `0..keys` (items without
/// one, `usize::MAX`, left out), stable: each key's items ascending.
#[derive(Default)]
struct KeyOrder {
    /// The items of key `k` are `items[starts[k]..starts[k + 1]]`.
    items: Vec<usize>,
    starts: Vec<usize>,
    item_keys: Vec<usize>,
}

impl KeyOrder {
    fn keys(&self) -> usize {
        self.starts.len().saturating_sub(1)
    }

    fn of(&self, key: usize) -> &[usize] {
        &self.items[self.starts[key]..self.starts[key + 1]]
    }

    fn order(&mut self, keys: usize, item_keys: impl Iterator<Item = usize>) {
        self.item_keys.clear();
        self.item_keys.extend(item_keys);
        // Counts at starts[k + 2], then running sums: starts[k + 1] is
        // where key k's items begin, a cursor while filling that ends
        // where they end.
        self.starts.clear();
        self.starts.resize(keys + 2, 0);
        for &k in &self.item_keys {
            if k != usize::MAX {
                self.starts[k + 2] += 1;
            }
        }
        for k in 2..keys + 2 {
            self.starts[k] += self.starts[k - 1];
        }
        self.items.clear();
        self.items.resize(self.starts[keys + 1], 0);
        for (item, &k) in self.item_keys.iter().enumerate() {
            if k != usize::MAX {
                let at = &mut self.starts[k + 1];
                self.items[*at] = item;
                *at += 1;
            }
        }
        self.starts.truncate(keys + 1);
    }
}

/// Disjoint sets of destinations and sources whose roots carry TrackPy's
/// subnetwork key.
#[derive(Default)]
struct KeyedSets {
    parent: Vec<usize>,
    size: Vec<usize>,
    key: Vec<usize>,
}

impl KeyedSets {
    fn reset(&mut self, destinations: usize, sources: usize) {
        let n = destinations + sources;
        self.parent.clear();
        self.parent.extend(0..n);
        self.size.clear();
        self.size.resize(n, 1);
        // A source alone has no subnetwork (usize::MAX: not joined).
        self.key.clear();
        self.key.extend(0..destinations);
        self.key.resize(n, usize::MAX);
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

/// A frame's sources bucketed in a uniform grid of square cells, so that
/// a destination looks only at the cells its search square overlaps (two
/// or three per axis with cells as wide as the search range) instead of
/// a tree rebuilt every frame.
#[derive(Default, Clone)]
struct SourceGrid {
    origin: [f64; 2],
    cell: f64,
    /// `1 / cell`: a coordinate's cell by a product, not a division.
    scale: f64,
    columns: usize,
    rows: usize,
    /// The sources of cell `c` (row-major), ascending:
    /// `members[starts[c]..starts[c + 1]]`.
    starts: Vec<usize>,
    members: Vec<usize>,
    /// Each source's cell.
    cells: Vec<usize>,
}

impl SourceGrid {
    /// Buckets `positions` (source `s` at `positions[s]`) in cells at
    /// least `limit` wide.
    fn build(&mut self, positions: &[[f64; 2]], limit: f64) {
        let (mut low, mut high) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in positions {
            for axis in 0..2 {
                low[axis] = low[axis].min(p[axis]);
                high[axis] = high[axis].max(p[axis]);
            }
        }
        self.origin = low;
        // At most about four cells per source: a few sources spread over a
        // wide field get wider cells, not a grid as large as the field.
        let most = 4 * positions.len() + 16;
        let (width, height) = (high[0] - low[0], high[1] - low[1]);
        let count = |extent: f64, cell: f64| ((extent / cell) as usize).saturating_add(1);
        self.cell = limit;
        while count(width, self.cell).saturating_mul(count(height, self.cell)) > most {
            self.cell *= 2.0;
        }
        self.scale = 1.0 / self.cell;
        (self.columns, self.rows) = (count(width, self.cell), count(height, self.cell));
        if positions.is_empty() {
            (self.columns, self.rows) = (0, 0);
        }
        let cells = self.columns * self.rows;
        // A counting sort of the sources by cell: counts at starts[c + 2],
        // running sums, then starts[c + 1] is a cursor through cell c's
        // members that ends where cell c + 1's begin.
        let mut source_cells = std::mem::take(&mut self.cells);
        source_cells.clear();
        source_cells.extend(positions.iter().map(|p| {
            let column = self.index(p[0], 0).min(self.columns - 1);
            let row = self.index(p[1], 1).min(self.rows - 1);
            row * self.columns + column
        }));
        self.cells = source_cells;
        self.starts.clear();
        self.starts.resize(cells + 2, 0);
        for &c in &self.cells {
            self.starts[c + 2] += 1;
        }
        for c in 2..cells + 2 {
            self.starts[c] += self.starts[c - 1];
        }
        self.members.clear();
        self.members.resize(positions.len(), 0);
        for (s, &c) in self.cells.iter().enumerate() {
            let at = &mut self.starts[c + 1];
            self.members[*at] = s;
            *at += 1;
        }
        self.starts.truncate(cells + 1);
    }

    /// The cell index along `axis` of coordinate `v` (0 below the grid;
    /// not clamped above). Truncation is the floor here (≥ 0), and
    /// cheaper: `floor` is a library call on baseline x86-64.
    fn index(&self, v: f64, axis: usize) -> usize {
        ((v - self.origin[axis]) * self.scale).max(0.0) as usize
    }

    /// The cells along `axis` that hold coordinates in `[v - limit, v +
    /// limit]`. Rounding is monotone (the same product by `scale` as
    /// [`Self::index`]), so a source within the search
    /// range of `v` is always in one of them.
    fn span(&self, v: f64, limit: f64, axis: usize) -> std::ops::Range<usize> {
        let n = [self.columns, self.rows][axis];
        let from = (v - limit - self.origin[axis]) * self.scale;
        let to = (v + limit - self.origin[axis]) * self.scale;
        // Both ends in the grid once clamped (negated so that NaN gives an
        // empty span); then truncation is the floor.
        if !(to >= 0.0 && from < n as f64) {
            return 0..0;
        }
        (from.max(0.0) as usize)..(to as usize).min(n - 1) + 1
    }

    /// Calls `visit` with every source in the cells around `(x, y)` that
    /// may lie within `limit` of it.
    fn near(&self, x: f64, y: f64, limit: f64, mut visit: impl FnMut(usize)) {
        let columns = self.span(x, limit, 0);
        for row in self.span(y, limit, 1) {
            let first = row * self.columns;
            let members =
                &self.members[self.starts[first + columns.start]..self.starts[first + columns.end]];
            for &s in members {
                visit(s);
            }
        }
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
    fn a_memory_beyond_every_frame_number_remembers_for_ever() {
        let detections = [
            Detection::new(0, 5.0, 5.0),
            Detection::new(9_000, 5.5, 5.0),
            Detection::new(9_001, 9.0, 9.0),
            Detection::new(9_500, 5.0, 5.5),
        ];
        // `lost_at + memory` would wrap to a small number: the source
        // would expire at once and nothing over the gaps be linked.
        for memory in [9_000, usize::MAX] {
            let linked = link(&detections, &params(1.0, memory)).unwrap();
            assert_eq!(linked.particle, [0, 0, 1, 0], "memory {memory}");
            assert_eq!(linked.stats.gap_links, 2);
        }
        // The particle at 9,000 vanishes for frames 9,001 to 9,499.
        let linked = link(&detections, &params(1.0, 499)).unwrap();
        assert_eq!(linked.particle, [0, 1, 2, 1]);
        let linked = link(&detections, &params(1.0, 498)).unwrap();
        assert_eq!(linked.particle, [0, 1, 2, 3]);
    }

    #[test]
    fn frames_far_apart_are_not_walked_one_by_one() {
        let far = 1 << 50;
        let detections = [
            Detection::new(0, 1.0, 1.0),
            Detection::new(far, 1.0, 1.0),
            Detection::new(far + 2, 1.0, 1.0),
        ];
        // Returns at once; memory still bridges the gap after `far`.
        let linked = link(&detections, &params(1.0, 1)).unwrap();
        assert_eq!(linked.particle, [0, 1, 1]);
        assert_eq!(linked.stats.gap_links, 1);
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

    #[test]
    fn blocks_and_threads_do_not_change_the_trajectories() {
        use rand::{RngExt as _, SeedableRng as _};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        // Dense walks with blinks and runs of empty frames, so that memory,
        // remembered sources and gaps cross the blocks' edges.
        let mut detections = Vec::new();
        for _ in 0..60 {
            let (mut x, mut y) = (rng.random_range(0.0..30.0), rng.random_range(0.0..30.0));
            for frame in 0..80 {
                x += rng.random_range(-1.0..1.0);
                y += rng.random_range(-1.0..1.0);
                if rng.random::<f64>() > 0.2 && !(30..34).contains(&frame) {
                    detections.push(Detection::new(frame, x, y));
                }
            }
        }
        for memory in [0, 1, 3] {
            let params = params(1.5, memory);
            let whole = link_in_blocks(&detections, &params, usize::MAX, false).unwrap();
            assert!(whole.stats.contested > 10, "{:?}", whole.stats);
            if memory > 0 {
                assert!(whole.stats.gap_links > 10, "{:?}", whole.stats);
            }
            for block in [1, 7, 100, 1000] {
                for threaded in [false, true] {
                    let linked = link_in_blocks(&detections, &params, block, threaded).unwrap();
                    assert_eq!(
                        linked.particle, whole.particle,
                        "{memory} {block} {threaded}"
                    );
                    assert_eq!(linked.stats, whole.stats);
                }
            }
        }
    }

    #[test]
    fn the_grid_finds_exactly_the_sources_in_range() {
        use rand::{RngExt as _, SeedableRng as _};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(38);
        let limit = 2.0 + RANGE_SLACK;
        let mut grid = SourceGrid::default();
        // Dense and sparse fields (the sparse ones get cells wider than the
        // range), far from the origin, and sources exactly one range away
        // along an axis (out: the bound is strict).
        for (sources, side, offset) in [(300, 60.0, 0.0), (20, 1e4, -3e5), (1, 5.0, 7.0)] {
            let mut positions: Vec<[f64; 2]> = (0..sources)
                .map(|_| {
                    let x = offset + rng.random_range(0.0..side);
                    [x, offset + rng.random_range(0.0..side)]
                })
                .collect();
            let [x0, y0] = positions[0];
            positions.extend([[x0 + limit, y0], [x0, y0 - limit], [x0 + 1.0, y0 + 1.0]]);
            grid.build(&positions, limit);
            let mut queries: Vec<[f64; 2]> = (0..200)
                .map(|_| {
                    let x = offset + rng.random_range(-5.0..side + 5.0);
                    [x, offset + rng.random_range(-5.0..side + 5.0)]
                })
                .collect();
            queries.push([x0, y0]);
            let d2 = |p: [f64; 2], q: [f64; 2]| {
                (p[0] - q[0]) * (p[0] - q[0]) + (p[1] - q[1]) * (p[1] - q[1])
            };
            for q in queries {
                let mut found = Vec::new();
                grid.near(q[0], q[1], limit, |s| {
                    if d2(positions[s], q) < limit * limit {
                        found.push(s);
                    }
                });
                found.sort_unstable();
                let expected: Vec<usize> = (0..positions.len())
                    .filter(|&s| d2(positions[s], q) < limit * limit)
                    .collect();
                assert_eq!(found, expected, "query {q:?}");
            }
        }
    }
}
