//! Tracking: from localisations to trajectories, and what they tell: the
//! diffusion coefficient of tracked particles ([`diffusion`],
//! `docs/tracking.md`).
//!
//! The linkers take [`Detection`]s in any order and label each with a
//! trajectory (`particle`, 0, 1, …). They look at frames in increasing
//! order; within a frame, detections keep their input order (the order
//! [`frame_order`] gives, a stable sort by frame, as TrackPy's `link`
//! sorts its table).
//!
//! - [`trackpy`]: TrackPy 0.7's `link` (search range, memory), the same
//!   trajectories on the same input.
//! - [`lap`]: a global linear assignment frame to frame followed by gap
//!   closing over blinks (Jaqaman et al. 2008), with costs from the
//!   localisations' uncertainty and the expected diffusion step.
//!
//! This layer sits on [`types`](crate::types) and [`io`](crate::io) (it
//! reads [`LocalisationTable`]s) and names nothing above them.

pub mod diffusion;
pub mod lap;
pub mod linker;
pub mod pipeline;
pub mod trackpy;

use crate::error::input_error;
use crate::io::localisation_table::LocalisationTable;
use crate::types::LocalisationSigma;

/// One localisation to link: its frame, position in pixels (`x` the
/// column, `y` the row) and, if known, its uncertainty (pixels, one
/// standard deviation per axis).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Detection {
    pub frame: usize,
    pub x: f64,
    pub y: f64,
    pub sigma: Option<LocalisationSigma>,
}

impl Detection {
    /// A detection without an uncertainty.
    pub fn new(frame: usize, x: f64, y: f64) -> Self {
        Self {
            frame,
            x,
            y,
            sigma: None,
        }
    }
}

/// The detections of a table's rows, in row order.
pub fn detections(table: &LocalisationTable) -> Vec<Detection> {
    (0..table.frames.len())
        .map(|row| Detection {
            frame: table.frames[row],
            x: table.xs[row],
            y: table.ys[row],
            sigma: table.sigmas[row],
        })
        .collect()
}

/// A linker's result.
#[derive(Debug, Clone, PartialEq)]
pub struct Linking {
    /// The trajectory of each detection, indexed like the input.
    pub particle: Vec<usize>,
    /// What the linker had to decide.
    pub stats: LinkStats,
    /// Per detection, the extent along x and y (px) of the gate that
    /// admitted the link from its predecessor in the trajectory (`None`
    /// for a trajectory's first detection): every displacement the gate
    /// admits is within it on each axis, and every displacement within
    /// 1/√2 of it on both axes is admitted. `None` from TrackPy's linker.
    pub gates: Option<Vec<Option<[f64; 2]>>>,
}

/// Counts that show what a linking had to resolve (and that a test's input
/// exercised it).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Links made (pairs of detections of one trajectory in consecutive
    /// observations, gaps included).
    pub links: usize,
    /// Links over one or more frames without the particle (memory or gap
    /// closing).
    pub gap_links: usize,
    /// Assignment problems with a choice: at least two sources or two
    /// destinations competing (TrackPy's subnetworks, the LAP's connected
    /// components).
    pub contested: usize,
    /// Sources + destinations of the largest such problem.
    pub largest: usize,
}

/// The indices of `detections` sorted by frame, ties in input order.
pub(crate) fn frame_order(detections: &[Detection]) -> Vec<usize> {
    // The frames gathered once: the passes below then read 8 bytes per
    // detection, not a whole detection.
    let frames: Vec<usize> = detections.iter().map(|d| d.frame).collect();
    let Some((first, last)) = frames.iter().fold(None, |range, &f| match range {
        None => Some((f, f)),
        Some((low, high)) => Some((f.min(low), f.max(high))),
    }) else {
        return Vec::new();
    };
    // Frames are usually dense: a counting sort then, in time linear in
    // the detections; a stable sort otherwise (no allocation in proportion
    // to the frame numbers).
    let span = last - first;
    if span >= 2 * frames.len() {
        let mut order: Vec<usize> = (0..frames.len()).collect();
        order.sort_by_key(|&i| frames[i]);
        return order;
    }
    let mut starts = vec![0; span + 2];
    for &frame in &frames {
        starts[frame - first + 1] += 1;
    }
    for f in 1..starts.len() {
        starts[f] += starts[f - 1];
    }
    let mut order = vec![0; frames.len()];
    for (i, &frame) in frames.iter().enumerate() {
        let at = &mut starts[frame - first];
        order[*at] = i;
        *at += 1;
    }
    order
}

/// Whether two labellings put the same items together (equal up to
/// renaming the labels).
pub fn same_partition(a: &[usize], b: &[usize]) -> bool {
    use std::collections::HashMap;
    if a.len() != b.len() {
        return false;
    }
    let mut forward: HashMap<usize, usize> = HashMap::new();
    let mut backward: HashMap<usize, usize> = HashMap::new();
    a.iter()
        .zip(b)
        .all(|(&x, &y)| *forward.entry(x).or_insert(y) == y && *backward.entry(y).or_insert(x) == x)
}

/// A possible link of an assignment problem: source `from`, destination
/// `to`, its cost (≥ 0).
#[derive(Debug, Clone, Copy)]
pub struct Candidate {
    pub from: usize,
    pub to: usize,
    pub cost: f64,
}

/// The most sources plus destinations of one connected assignment problem
/// [`assign`] solves (a dense matrix of 800 MB). Linking the recordings of
/// docs/tracking.md gives problems of at most ten; only a search range or
/// gap far beyond the particles' steps, over localisations that crowd the
/// field, joins thousands into one.
pub(crate) const MAX_ASSIGNMENT_SIZE: usize = 10_000;

/// The least-cost links between `sources` sources and `destinations`
/// destinations: minimises the sum of the chosen candidates' costs plus
/// `death[s]` for each source left unlinked plus `birth[d]` for each
/// destination left unlinked, each source and destination linked at most
/// once. Returns the destination of each source. All costs ≥ 0 and finite.
///
/// Solved exactly as one square linear assignment of the sources and
/// destinations plus a "no link" partner for each (Jaqaman et al. 2008's
/// matrix: links top left, deaths and births on the diagonals of the
/// off-diagonal blocks, zeros bottom right) by `lapjv`.
pub(crate) fn assign(
    sources: usize,
    destinations: usize,
    candidates: &[Candidate],
    death: &[f64],
    birth: &[f64],
) -> anyhow::Result<Vec<Option<usize>>> {
    // The shapes without a matrix (most problems): one source links to the
    // destination that gains most, one destination to the source that
    // gains most, if linking beats leaving both unlinked.
    if sources == 1 || destinations == 1 {
        let gain = |c: &Candidate| death[c.from] + birth[c.to] - c.cost;
        let best = candidates
            .iter()
            .filter(|c| gain(c) > 0.0)
            .max_by(|a, b| gain(a).total_cmp(&gain(b)));
        let mut links = vec![None; sources];
        if let Some(c) = best {
            links[c.from] = Some(c.to);
        }
        return Ok(links);
    }
    let n = sources + destinations;
    if n > MAX_ASSIGNMENT_SIZE {
        // Its matrix alone would take 8·n² bytes (80 GB at n = 100,000),
        // and the solver's time grows as n³.
        return Err(input_error(format!(
            "{sources} sources and {destinations} destinations form one connected assignment \
             problem, more than the {MAX_ASSIGNMENT_SIZE} solved at once (its matrix would \
             take {:.1} GiB): lower the search range or the longest gap, or raise --min-score",
            (n as f64).powi(2) * 8.0 / (1u64 << 30) as f64
        )));
    }
    // More than any assignment without a forbidden entry can cost, so the
    // solver never takes one (linking nobody is always possible).
    let forbidden = 1.0
        + 2.0
            * (death.iter().sum::<f64>()
                + birth.iter().sum::<f64>()
                + candidates.iter().map(|c| c.cost).sum::<f64>());
    let mut costs = vec![forbidden; n * n];
    for c in candidates {
        costs[c.from * n + c.to] = c.cost;
    }
    for (s, &cost) in death.iter().enumerate() {
        costs[s * n + destinations + s] = cost;
    }
    for (d, &cost) in birth.iter().enumerate() {
        costs[(sources + d) * n + d] = cost;
    }
    for row in sources..n {
        for column in destinations..n {
            costs[row * n + column] = 0.0;
        }
    }
    let matrix = lapjv::Matrix::from_shape_vec((n, n), costs)
        .map_err(|e| anyhow::anyhow!("assignment matrix: {e}"))?;
    let (row_to_column, _) =
        lapjv::lapjv(&matrix).map_err(|e| anyhow::anyhow!("linear assignment: {e}"))?;
    Ok(row_to_column[..sources]
        .iter()
        .map(|&column| (column < destinations).then_some(column))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partitions_compare_up_to_relabelling() {
        assert!(same_partition(&[0, 0, 1, 2], &[5, 5, 3, 0]));
        assert!(!same_partition(&[0, 0, 1], &[1, 2, 2]));
        assert!(!same_partition(&[0, 1], &[3, 3]));
    }

    #[test]
    fn the_assignment_finds_the_global_optimum_not_the_greedy_one() {
        // Greedy would link 0→0 (cost 1) and leave source 1 unlinked;
        // 0→1 + 1→0 costs 2 + 2 < 1 + death 10.
        let candidates = [
            Candidate {
                from: 0,
                to: 0,
                cost: 1.0,
            },
            Candidate {
                from: 0,
                to: 1,
                cost: 2.0,
            },
            Candidate {
                from: 1,
                to: 0,
                cost: 2.0,
            },
        ];
        let links = assign(2, 2, &candidates, &[10.0, 10.0], &[0.0, 0.0]).unwrap();
        assert_eq!(links, [Some(1), Some(0)]);
        // With cheaper deaths, one link (1 + 1.5) beats two (4) and none (3).
        let links = assign(2, 2, &candidates, &[1.5, 1.5], &[0.0, 0.0]).unwrap();
        assert_eq!(links, [Some(0), None]);
    }

    #[test]
    fn frame_order_is_a_stable_sort_by_frame() {
        // Dense frames (the counting sort) and sparse ones (the sort).
        for frames in [
            vec![3, 1, 3, 2, 1, 1, 4],
            vec![9_000_000, 5, 9_000_000, 5, 0],
        ] {
            let detections: Vec<Detection> = frames
                .iter()
                .map(|&f| Detection::new(f, 0.0, 0.0))
                .collect();
            let mut expected: Vec<usize> = (0..frames.len()).collect();
            expected.sort_by_key(|&i| frames[i]);
            assert_eq!(frame_order(&detections), expected);
        }
        assert!(frame_order(&[]).is_empty());
    }
}
