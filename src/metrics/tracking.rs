//! How well trajectories follow the ground truth (`docs/tracking.md`,
//! "Tracking metrics"): the particle tracking challenge's measures
//! (Chenouard et al. 2014, Nat. Methods 11:281) and link precision and
//! recall.
//!
//! Tracks are sets of points, at most one per frame. Two points of one
//! frame are at distance `min(‖a − b‖, ε)` (`ε` the gate) and *match* when
//! closer than ε; a point with no partner in its frame is at distance ε.
//!
//! - **Track pairing.** The distance between a truth track θ and an
//!   estimated track ω is the sum of their points' distances over every
//!   frame either has a point in; a dummy (empty) track is at ε·|θ| from θ.
//!   Each truth track is paired with an estimated track or a dummy, each
//!   estimated track at most once, so that the sum of the pairs' distances
//!   `d(X, Y)` is least (an optimal assignment, solved exactly by `lapjv`).
//!   An estimated track left unpaired is spurious.
//! - **α** `= 1 − d(X, Y)/d(X, ∅)`, `d(X, ∅) = ε·Σ|θ|`: 1 when every truth
//!   point is matched at distance 0, 0 when nothing is matched.
//! - **β** `= (d(X, ∅) − d(X, Y))/(d(X, ∅) + ε·Σ_spurious|ω|)`: α
//!   penalised by the points of spurious tracks (β ≤ α).
//! - **Jaccard index of detections** `TP/(TP + FN + FP)` over the pairing:
//!   TP the matched points of paired tracks, FN the other truth points, FP
//!   the other estimated points (spurious tracks' included).
//! - **Jaccard index of tracks** `TPθ/(TPθ + FNθ + FPθ)`: paired truth
//!   tracks, truth tracks paired with a dummy, spurious tracks.
//! - **Links.** Independently of the pairing, each frame's points are
//!   matched one to one: the matching of points closer than ε with the
//!   least `Σ ‖a − b‖ + ε·(points left unmatched)`. A link is two
//!   consecutive points of an estimated track (over a gap too); it is true
//!   when both are matched to points of the same truth track. A truth link
//!   is two consecutive points of a truth track (over the gaps the truth
//!   has); it is recovered when its two points are matched to the two
//!   points of one estimated link. Precision: true links / estimated links;
//!   recall: recovered links / truth links.
//!
//! The layer names only the shared types and errors.

use std::collections::{BTreeMap, HashMap};

use serde::{Deserialize, Serialize};

use crate::error::input_error;
use crate::types::{RecordingTruthRow, Track, TrackPoint};

/// The default gate ε, px: the paper's first matching radius (70 nm at
/// 0.07 µm/px), as for localisations (`docs/metric.md`).
pub(crate) const DEFAULT_GATE_PX: f64 = 1.0;

/// Most pairs of a truth and an estimated point closer than the gate (in
/// one frame) that a scoring examines: more means a gate far wider than
/// the points' spacing or degenerate files, and a quadratic cost.
pub(crate) const MAX_NEAR_PAIRS: usize = 20_000_000;

/// Most tracks (truth + estimated) competing in one assignment problem
/// (its matrix has the square of that many entries).
pub(crate) const MAX_ASSIGNMENT_SIZE: usize = 4_000;

/// Which position of a recording truth row a track follows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TruthPosition {
    /// The trajectory centroid over the whole frame (`x, y`).
    #[default]
    Centroid,
    /// What the beam saw (`x_seen, y_seen`).
    Seen,
}

/// Which truth rows count, and where.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct TruthSelection {
    pub position: TruthPosition,
    /// Only rows with `|z_mean| ≤` this, µm.
    pub max_depth_um: Option<f64>,
    /// Only rows with `on_fraction ≥` this.
    pub min_on_fraction: Option<f64>,
    /// Split a QD's track where it is missing from the selected rows for
    /// more than this many frames (no split when `None`).
    pub split_gaps_over: Option<usize>,
}

/// The truth tracks of a recording's truth rows: one per QD id, its
/// selected rows in frame order (a QD that leaves the selection and comes
/// back keeps one track, with a gap, unless the gap is longer than
/// `split_gaps_over` frames: then a new track starts, with the same label).
pub(crate) fn truth_tracks(rows: &[RecordingTruthRow], selection: &TruthSelection) -> Vec<Track> {
    let mut by_qd: BTreeMap<u64, Vec<TrackPoint>> = BTreeMap::new();
    let kept = rows.iter().filter(|row| {
        selection
            .max_depth_um
            .is_none_or(|depth| row.z_mean.abs() <= depth)
            && selection
                .min_on_fraction
                .is_none_or(|share| row.on_fraction >= share)
    });
    for row in kept {
        let (x, y) = match selection.position {
            TruthPosition::Centroid => (row.x, row.y),
            TruthPosition::Seen => (row.x_seen, row.y_seen),
        };
        by_qd.entry(row.qd).or_default().push(TrackPoint {
            frame: row.frame,
            x,
            y,
            sigma: None,
            time_s: Some(row.t_mid),
            gate: None,
        });
    }
    let mut tracks = Vec::new();
    for (qd, mut points) in by_qd {
        points.sort_by_key(|p| p.frame);
        let particle = i64::try_from(qd).unwrap_or(i64::MAX);
        let mut start = 0;
        for end in 1..=points.len() {
            let split = end == points.len()
                || selection
                    .split_gaps_over
                    .is_some_and(|most| points[end].frame - points[end - 1].frame - 1 > most);
            if split {
                tracks.push(Track {
                    particle,
                    points: points[start..end].to_vec(),
                });
                start = end;
            }
        }
    }
    tracks
}

/// The tracking measures of a set of estimated tracks against the truth.
/// A ratio with nothing to count (no truth point, no link) is `None`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackingScore {
    /// The gate ε, px.
    pub gate_px: f64,
    /// α: 1 − d(X, Y)/d(X, ∅).
    pub alpha: Option<f64>,
    /// β: α penalised by spurious tracks.
    pub beta: Option<f64>,
    /// TP/(TP + FN + FP) over the points of the pairing.
    pub jaccard_detections: Option<f64>,
    /// TPθ/(TPθ + FNθ + FPθ) over the tracks.
    pub jaccard_tracks: Option<f64>,
    /// True links / estimated links.
    pub link_precision: Option<f64>,
    /// Recovered truth links / truth links.
    pub link_recall: Option<f64>,
    pub truth_tracks: usize,
    pub estimated_tracks: usize,
    /// Truth tracks paired with an estimated track (TPθ).
    pub paired_tracks: usize,
    /// Truth tracks paired with a dummy (FNθ).
    pub missed_tracks: usize,
    /// Estimated tracks left unpaired (FPθ).
    pub spurious_tracks: usize,
    pub truth_points: usize,
    pub estimated_points: usize,
    /// Matched points of paired tracks (TP).
    pub matched_points: usize,
    /// Truth points not matched in the pairing (FN).
    pub missed_points: usize,
    /// Estimated points not matched in the pairing (FP).
    pub false_points: usize,
    /// Points of spurious tracks (part of FP; β's penalty, in units of ε).
    pub spurious_track_points: usize,
    /// d(X, Y), px.
    pub distance_px: f64,
    /// d(X, ∅) = ε·(truth points), px.
    pub distance_to_nothing_px: f64,
    pub estimated_links: usize,
    /// Estimated links joining points matched to one truth track.
    pub true_links: usize,
    pub truth_links: usize,
    /// Truth links whose two points are matched to one estimated link.
    pub recovered_links: usize,
}

/// A point of a track: the track's index and the point's index in it.
type PointRef = (usize, usize);

/// A truth point and an estimated point of one frame closer than the gate.
#[derive(Debug, Clone, Copy)]
struct NearPair {
    truth: PointRef,
    estimated: PointRef,
    distance: f64,
}

/// The pairs of a truth and an estimated point closer than `gate` in the
/// same frame, frame by frame (at most [`MAX_NEAR_PAIRS`]).
fn near_pairs(truth: &[Track], estimated: &[Track], gate: f64) -> anyhow::Result<Vec<NearPair>> {
    let mut frames: BTreeMap<usize, (Vec<PointRef>, Vec<PointRef>)> = BTreeMap::new();
    for (t, track) in truth.iter().enumerate() {
        for (p, point) in track.points.iter().enumerate() {
            frames.entry(point.frame).or_default().0.push((t, p));
        }
    }
    for (e, track) in estimated.iter().enumerate() {
        for (p, point) in track.points.iter().enumerate() {
            frames.entry(point.frame).or_default().1.push((e, p));
        }
    }
    let at = |tracks: &[Track], (t, p): PointRef| tracks[t].points[p];
    let mut pairs = Vec::new();
    for (truth_points, mut estimated_points) in frames.into_values() {
        if truth_points.is_empty() || estimated_points.is_empty() {
            continue;
        }
        estimated_points.sort_by(|&a, &b| at(estimated, a).x.total_cmp(&at(estimated, b).x));
        for &tp in &truth_points {
            let a = at(truth, tp);
            let first = estimated_points.partition_point(|&e| at(estimated, e).x <= a.x - gate);
            for &ep in &estimated_points[first..] {
                let b = at(estimated, ep);
                if b.x >= a.x + gate {
                    break;
                }
                let distance = (a.x - b.x).hypot(a.y - b.y);
                if distance < gate {
                    if pairs.len() == MAX_NEAR_PAIRS {
                        return Err(input_error(format!(
                            "more than {MAX_NEAR_PAIRS} pairs of a truth and an estimated point \
                             closer than the gate of {gate} px: the gate is far wider than the \
                             points' spacing"
                        )));
                    }
                    pairs.push(NearPair {
                        truth: tp,
                        estimated: ep,
                        distance,
                    });
                }
            }
        }
    }
    Ok(pairs)
}

/// A possible pairing of row `row` with column `column` at `cost` (≥ 0).
#[derive(Debug, Clone, Copy)]
struct Edge {
    row: usize,
    column: usize,
    cost: f64,
}

/// The least-cost one-to-one pairing of `row_alone.len()` rows with
/// `column_alone.len()` columns over `edges`: minimises the chosen edges'
/// costs plus `row_alone[r]` for each row and `column_alone[c]` for each
/// column left unpaired. Returns each row's column. Each connected
/// component of the edges is solved exactly by `lapjv` on the square
/// matrix of its rows and columns plus an "alone" partner for each.
fn assign(
    edges: &[Edge],
    row_alone: &[f64],
    column_alone: &[f64],
) -> anyhow::Result<Vec<Option<usize>>> {
    let rows = row_alone.len();
    // Union-find over rows (0..rows) and columns (rows..).
    let mut parent: Vec<usize> = (0..rows + column_alone.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    for edge in edges {
        let (a, b) = (
            root(&mut parent, edge.row),
            root(&mut parent, rows + edge.column),
        );
        if a != b {
            parent[a] = b;
        }
    }
    let mut components: HashMap<usize, Vec<usize>> = HashMap::new();
    for (index, edge) in edges.iter().enumerate() {
        let component = root(&mut parent, edge.row);
        components.entry(component).or_default().push(index);
    }
    let mut assigned = vec![None; rows];
    for indices in components.into_values() {
        solve_component(
            &indices.iter().map(|&i| edges[i]).collect::<Vec<_>>(),
            row_alone,
            column_alone,
            &mut assigned,
        )?;
    }
    Ok(assigned)
}

/// [`assign`] on one connected component's edges, writing its rows'
/// columns into `assigned`.
fn solve_component(
    edges: &[Edge],
    row_alone: &[f64],
    column_alone: &[f64],
    assigned: &mut [Option<usize>],
) -> anyhow::Result<()> {
    let gain = |e: &Edge| row_alone[e.row] + column_alone[e.column] - e.cost;
    let mut rows: Vec<usize> = edges.iter().map(|e| e.row).collect();
    let mut columns: Vec<usize> = edges.iter().map(|e| e.column).collect();
    rows.sort_unstable();
    rows.dedup();
    columns.sort_unstable();
    columns.dedup();
    // One row or one column (most components): the edge that gains most,
    // if any gains.
    if rows.len() == 1 || columns.len() == 1 {
        let best = edges
            .iter()
            .filter(|e| gain(e) > 0.0)
            .max_by(|a, b| gain(a).total_cmp(&gain(b)));
        if let Some(edge) = best {
            assigned[edge.row] = Some(edge.column);
        }
        return Ok(());
    }
    let (r, c) = (rows.len(), columns.len());
    let n = r + c;
    if n > MAX_ASSIGNMENT_SIZE {
        return Err(input_error(format!(
            "{r} truth and {c} estimated tracks (or points) compete within the gate, more than \
             the {MAX_ASSIGNMENT_SIZE} one assignment may hold: the gate is far wider than the \
             points' spacing"
        )));
    }
    let row_at: HashMap<usize, usize> = rows.iter().enumerate().map(|(i, &v)| (v, i)).collect();
    let column_at: HashMap<usize, usize> =
        columns.iter().enumerate().map(|(i, &v)| (v, i)).collect();
    let total: f64 = edges.iter().map(|e| e.cost).sum::<f64>()
        + rows.iter().map(|&i| row_alone[i]).sum::<f64>()
        + columns.iter().map(|&i| column_alone[i]).sum::<f64>();
    // More than any assignment without it can cost (pairing nothing is
    // always possible), so the solver never takes it.
    let forbidden = 1.0 + 2.0 * total;
    let mut costs = vec![forbidden; n * n];
    for e in edges {
        // An edge that gains nothing is never taken.
        if gain(e) > 0.0 {
            costs[row_at[&e.row] * n + column_at[&e.column]] = e.cost;
        }
    }
    // Rows alone: any of the last r columns; columns alone: any of the
    // last c rows; alone with alone costs nothing.
    for (i, &row) in rows.iter().enumerate() {
        for j in c..n {
            costs[i * n + j] = row_alone[row];
        }
    }
    for (j, &column) in columns.iter().enumerate() {
        for i in r..n {
            costs[i * n + j] = column_alone[column];
        }
    }
    for i in r..n {
        for j in c..n {
            costs[i * n + j] = 0.0;
        }
    }
    let matrix = lapjv::Matrix::from_shape_vec((n, n), costs)
        .map_err(|e| anyhow::anyhow!("assignment matrix: {e}"))?;
    let (row_to_column, _) =
        lapjv::lapjv(&matrix).map_err(|e| anyhow::anyhow!("linear assignment: {e}"))?;
    for (i, &j) in row_to_column[..r].iter().enumerate() {
        if j < c {
            assigned[rows[i]] = Some(columns[j]);
        }
    }
    Ok(())
}

/// A ratio, `None` when there is nothing to count.
fn ratio(numerator: f64, denominator: f64) -> Option<f64> {
    (denominator > 0.0).then(|| numerator / denominator)
}

/// Scores `estimated` tracks against `truth` tracks with the gate
/// `gate_px` (finite, > 0, at most
/// [`MAX_EPS_PX`](crate::limits::MAX_EPS_PX)); see the module's
/// documentation. Each track's points must be in increasing frame order,
/// one per frame (as the tracks reader and [`truth_tracks`] give them).
pub(crate) fn score_tracks(
    truth: &[Track],
    estimated: &[Track],
    gate_px: f64,
) -> anyhow::Result<TrackingScore> {
    let gate =
        crate::limits::check_positive_at_most("the gate (px)", gate_px, crate::limits::MAX_EPS_PX)?;
    let pairs = near_pairs(truth, estimated, gate)?;
    let truth_points: usize = truth.iter().map(|t| t.points.len()).sum();
    let estimated_points: usize = estimated.iter().map(|t| t.points.len()).sum();
    let tracks = pair_tracks(truth, estimated, &pairs, gate)?;
    let links = count_links(truth, estimated, &pairs, gate)?;

    let TrackPairing {
        distance,
        matched_points,
        paired_tracks,
        spurious_track_points,
    } = tracks;
    let nothing = gate * truth_points as f64;
    let missed_tracks = truth.len() - paired_tracks;
    let spurious_tracks = estimated.len() - paired_tracks;
    Ok(TrackingScore {
        gate_px,
        alpha: ratio(nothing - distance, nothing),
        beta: ratio(
            nothing - distance,
            nothing + gate * spurious_track_points as f64,
        ),
        jaccard_detections: ratio(
            matched_points as f64,
            (truth_points + estimated_points - matched_points) as f64,
        ),
        jaccard_tracks: ratio(
            paired_tracks as f64,
            (paired_tracks + missed_tracks + spurious_tracks) as f64,
        ),
        link_precision: ratio(links.true_links as f64, links.estimated_links as f64),
        link_recall: ratio(links.recovered_links as f64, links.truth_links as f64),
        truth_tracks: truth.len(),
        estimated_tracks: estimated.len(),
        paired_tracks,
        missed_tracks,
        spurious_tracks,
        truth_points,
        estimated_points,
        matched_points,
        missed_points: truth_points - matched_points,
        false_points: estimated_points - matched_points,
        spurious_track_points,
        distance_px: distance,
        distance_to_nothing_px: nothing,
        estimated_links: links.estimated_links,
        true_links: links.true_links,
        truth_links: links.truth_links,
        recovered_links: links.recovered_links,
    })
}

/// The one-to-one pairing of whole tracks and what it costs (see the
/// module's documentation).
struct TrackPairing {
    /// The pairing's distance (px): each paired track's matched distances
    /// plus the gate for each frame only one of the pair has, and the gate
    /// for each point of an unpaired truth track.
    distance: f64,
    /// Points matched within the paired tracks.
    matched_points: usize,
    paired_tracks: usize,
    /// Points of the estimated tracks left unpaired.
    spurious_track_points: usize,
}

/// Pairs truth with estimated tracks one to one at the least distance:
/// a pair costs its matched points' distances and the gate for every
/// frame in which only one of the two has a point; a truth track left
/// alone costs the gate per point, an estimated one nothing (α ignores
/// spurious tracks; β charges them afterwards).
fn pair_tracks(
    truth: &[Track],
    estimated: &[Track],
    pairs: &[NearPair],
    gate: f64,
) -> anyhow::Result<TrackPairing> {
    // Per (truth, estimated) track pair with a match, the matched points
    // and their summed distance.
    let mut matched: HashMap<(usize, usize), (usize, f64)> = HashMap::new();
    for pair in pairs {
        let entry = matched
            .entry((pair.truth.0, pair.estimated.0))
            .or_insert((0, 0.0));
        entry.0 += 1;
        entry.1 += pair.distance;
    }
    let mut track_edges: Vec<(Edge, usize)> = matched
        .into_iter()
        .map(|((t, e), (count, sum))| {
            let union = union_of_frames(&truth[t], &estimated[e]);
            let edge = Edge {
                row: t,
                column: e,
                cost: sum + gate * (union - count) as f64,
            };
            (edge, count)
        })
        .collect();
    // Sorted, so the pairing's edges are found by binary search below
    // (and the solver sees them in an order independent of hashing).
    track_edges.sort_by_key(|(e, _)| (e.row, e.column));
    let edges: Vec<Edge> = track_edges.iter().map(|(e, _)| *e).collect();
    let dummy: Vec<f64> = truth.iter().map(|t| gate * t.points.len() as f64).collect();
    let pairing = assign(&edges, &dummy, &vec![0.0; estimated.len()])?;
    let mut distance = 0.0;
    let mut matched_points = 0;
    let mut paired_estimated = vec![false; estimated.len()];
    for (t, partner) in pairing.iter().enumerate() {
        match partner {
            Some(e) => {
                let at = track_edges.partition_point(|(edge, _)| (edge.row, edge.column) < (t, *e));
                let (edge, count) = track_edges[at];
                distance += edge.cost;
                matched_points += count;
                paired_estimated[*e] = true;
            }
            None => distance += dummy[t],
        }
    }
    let spurious_track_points = estimated
        .iter()
        .zip(&paired_estimated)
        .filter(|(_, paired)| !**paired)
        .map(|(t, _)| t.points.len())
        .sum();
    Ok(TrackPairing {
        distance,
        matched_points,
        paired_tracks: pairing.iter().flatten().count(),
        spurious_track_points,
    })
}

/// Links (consecutive points of one track) counted against the
/// frame-by-frame matching of points.
struct LinkCounts {
    estimated_links: usize,
    /// Estimated links whose two points match points of one truth track.
    true_links: usize,
    truth_links: usize,
    /// Truth links whose two points match consecutive points of one
    /// estimated track.
    recovered_links: usize,
}

/// Counts the links of both sides and those the other side has too, with
/// each frame's points matched one to one (independently of the track
/// pairing, so a link is judged by itself).
fn count_links(
    truth: &[Track],
    estimated: &[Track],
    pairs: &[NearPair],
    gate: f64,
) -> anyhow::Result<LinkCounts> {
    let (estimated_match, truth_match) = match_points(pairs, gate)?;
    let mut counts = LinkCounts {
        estimated_links: 0,
        true_links: 0,
        truth_links: 0,
        recovered_links: 0,
    };
    for (e, track) in estimated.iter().enumerate() {
        for p in 1..track.points.len() {
            counts.estimated_links += 1;
            if let (Some(a), Some(b)) = (
                estimated_match.get(&(e, p - 1)),
                estimated_match.get(&(e, p)),
            ) && a.0 == b.0
            {
                counts.true_links += 1;
            }
        }
    }
    for (t, track) in truth.iter().enumerate() {
        for p in 1..track.points.len() {
            counts.truth_links += 1;
            if let (Some(a), Some(b)) = (truth_match.get(&(t, p - 1)), truth_match.get(&(t, p)))
                && a.0 == b.0
                && a.1 + 1 == b.1
            {
                counts.recovered_links += 1;
            }
        }
    }
    Ok(counts)
}

/// The number of frames with a point of `a` or of `b` (both in increasing
/// frame order).
fn union_of_frames(a: &Track, b: &Track) -> usize {
    let (short, long) = if a.points.len() <= b.points.len() {
        (a, b)
    } else {
        (b, a)
    };
    let shared = short
        .points
        .iter()
        .filter(|p| {
            long.points
                .binary_search_by_key(&p.frame, |q| q.frame)
                .is_ok()
        })
        .count();
    a.points.len() + b.points.len() - shared
}

/// The one-to-one matching of each frame's points (see the module's
/// documentation), as maps both ways: estimated point → truth point and
/// truth point → estimated point.
#[allow(clippy::type_complexity)]
fn match_points(
    pairs: &[NearPair],
    gate: f64,
) -> anyhow::Result<(HashMap<PointRef, PointRef>, HashMap<PointRef, PointRef>)> {
    // Number the points that have a near pair, rows for truth and columns
    // for estimated ones.
    let mut truth_index: HashMap<PointRef, usize> = HashMap::new();
    let mut estimated_index: HashMap<PointRef, usize> = HashMap::new();
    let mut truth_refs = Vec::new();
    let mut estimated_refs = Vec::new();
    let edges: Vec<Edge> = pairs
        .iter()
        .map(|pair| {
            let row = *truth_index.entry(pair.truth).or_insert_with(|| {
                truth_refs.push(pair.truth);
                truth_refs.len() - 1
            });
            let column = *estimated_index.entry(pair.estimated).or_insert_with(|| {
                estimated_refs.push(pair.estimated);
                estimated_refs.len() - 1
            });
            Edge {
                row,
                column,
                cost: pair.distance,
            }
        })
        .collect();
    let assigned = assign(
        &edges,
        &vec![gate; truth_refs.len()],
        &vec![gate; estimated_refs.len()],
    )?;
    let mut estimated_match = HashMap::new();
    let mut truth_match = HashMap::new();
    for (row, column) in assigned.into_iter().enumerate() {
        if let Some(column) = column {
            estimated_match.insert(estimated_refs[column], truth_refs[row]);
            truth_match.insert(truth_refs[row], estimated_refs[column]);
        }
    }
    Ok((estimated_match, truth_match))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A track of points `(frame, x, y)`.
    fn track(particle: i64, points: &[(usize, f64, f64)]) -> Track {
        Track {
            particle,
            points: points
                .iter()
                .map(|&(frame, x, y)| TrackPoint {
                    frame,
                    x,
                    y,
                    sigma: None,
                    time_s: None,
                    gate: None,
                })
                .collect(),
        }
    }

    /// A walk along x: frames `frames`, starting at `(x, y)`, 0.7 px a frame.
    fn walk(particle: i64, frames: std::ops::Range<usize>, x: f64, y: f64) -> Track {
        let points: Vec<(usize, f64, f64)> = frames.map(|f| (f, x + 0.7 * f as f64, y)).collect();
        track(particle, &points)
    }

    fn close(value: Option<f64>, expected: f64) -> bool {
        value.is_some_and(|v| (v - expected).abs() < 1e-12)
    }

    #[test]
    fn perfect_tracks_score_one_everywhere() {
        let truth = [walk(0, 0..10, 10.0, 10.0), walk(1, 2..8, 10.0, 30.0)];
        // Other labels, other order: the measures do not look at labels.
        let estimated = [
            Track {
                particle: 7,
                ..truth[1].clone()
            },
            Track {
                particle: 3,
                ..truth[0].clone()
            },
        ];
        let s = score_tracks(&truth, &estimated, 1.0).unwrap();
        for value in [
            s.alpha,
            s.beta,
            s.jaccard_detections,
            s.jaccard_tracks,
            s.link_precision,
            s.link_recall,
        ] {
            assert!(close(value, 1.0), "{s:?}");
        }
        assert_eq!(
            (s.paired_tracks, s.matched_points, s.true_links),
            (2, 16, 14)
        );
    }

    #[test]
    fn a_track_split_in_two_scores_its_known_values() {
        // θ: 10 points. ω1: its first 6, 0.25 px off in x; ω2: its last 4,
        // exact. Pairing θ with ω1 costs 6 × 0.25 + 4 × ε = 5.5 px, with ω2
        // 6 × ε = 6 px: ω1 is paired and ω2 is spurious (4 points).
        let truth = [walk(0, 0..10, 10.0, 10.0)];
        let shifted: Vec<(usize, f64, f64)> = truth[0].points[..6]
            .iter()
            .map(|p| (p.frame, p.x + 0.25, p.y))
            .collect();
        let estimated = [
            track(1, &shifted),
            Track {
                particle: 2,
                points: truth[0].points[6..].to_vec(),
            },
        ];
        let s = score_tracks(&truth, &estimated, 1.0).unwrap();
        // α = 1 − 5.5/10; β = (10 − 5.5)/(10 + 4).
        assert!(close(s.alpha, 0.45), "{s:?}");
        assert!(close(s.beta, 4.5 / 14.0), "{s:?}");
        // TP 6, FN 4, FP 4; tracks: 1 paired, 0 missed, 1 spurious.
        assert!(close(s.jaccard_detections, 6.0 / 14.0), "{s:?}");
        assert!(close(s.jaccard_tracks, 0.5), "{s:?}");
        // Every estimated link is true (5 + 3); 8 of the 9 truth links are
        // recovered (not the one between the halves).
        assert!(close(s.link_precision, 1.0), "{s:?}");
        assert!(close(s.link_recall, 8.0 / 9.0), "{s:?}");
        assert_eq!((s.spurious_tracks, s.spurious_track_points), (1, 4));
        assert_eq!((s.missed_points, s.false_points), (4, 4));
    }

    #[test]
    fn a_spurious_track_lowers_beta_not_alpha() {
        let truth = [walk(0, 0..10, 10.0, 10.0)];
        let spurious = walk(9, 0..5, 10.0, 40.0);
        let alone = score_tracks(&truth, &truth, 1.0).unwrap();
        let s = score_tracks(&truth, &[truth[0].clone(), spurious], 1.0).unwrap();
        assert_eq!(s.alpha, alone.alpha);
        assert!(close(s.alpha, 1.0));
        // β = 10/(10 + 5); detections 10/15; tracks 1/2; the spurious
        // track's 4 links are false: precision 9/13; recall unchanged.
        assert!(close(s.beta, 10.0 / 15.0), "{s:?}");
        assert!(close(s.jaccard_detections, 10.0 / 15.0), "{s:?}");
        assert!(close(s.jaccard_tracks, 0.5), "{s:?}");
        assert!(close(s.link_precision, 9.0 / 13.0), "{s:?}");
        assert!(close(s.link_recall, 1.0), "{s:?}");
    }

    #[test]
    fn a_swapped_link_lowers_link_precision_by_its_share() {
        // A and B, 10 frames each, 20 px apart; each estimated track follows
        // one for frames 0–4 and the other for frames 5–9.
        let a = walk(0, 0..10, 10.0, 10.0);
        let b = walk(1, 0..10, 10.0, 30.0);
        let swap = |first: &Track, second: &Track, particle| Track {
            particle,
            points: [&first.points[..5], &second.points[5..]].concat(),
        };
        let estimated = [swap(&a, &b, 0), swap(&b, &a, 1)];
        let s = score_tracks(&[a, b], &estimated, 1.0).unwrap();
        // One false link of 9 in each track: 16/18 true; the same 16 of
        // the 18 truth links are recovered.
        assert!(close(s.link_precision, 16.0 / 18.0), "{s:?}");
        assert!(close(s.link_recall, 16.0 / 18.0), "{s:?}");
        // Each truth track pairs with a track matching half of it: d = 5ε
        // each, α = β = 1 − 10/20; TP 10, FN 10, FP 10; both tracks paired.
        assert!(close(s.alpha, 0.5) && close(s.beta, 0.5), "{s:?}");
        assert!(close(s.jaccard_detections, 1.0 / 3.0), "{s:?}");
        assert!(close(s.jaccard_tracks, 1.0), "{s:?}");
    }

    #[test]
    fn a_track_that_wanders_off_is_not_paired() {
        // ω matches θ's first point, then has 6 points elsewhere: pairing
        // costs ε·(3 + 7 − 1 − 1) = 8ε > the dummy's 3ε.
        let truth = [walk(0, 0..3, 10.0, 10.0)];
        let mut points = vec![(0, 10.0, 10.0)];
        points.extend((10..16).map(|f| (f, 50.0, 50.0)));
        let s = score_tracks(&truth, &[track(1, &points)], 1.0).unwrap();
        assert_eq!(
            (s.paired_tracks, s.missed_tracks, s.spurious_tracks),
            (0, 1, 1)
        );
        assert!(close(s.alpha, 0.0) && close(s.beta, 0.0), "{s:?}");
        assert!(close(s.jaccard_detections, 0.0), "{s:?}");
        // Its first link starts on θ's point but ends on nothing.
        assert!(
            close(s.link_precision, 0.0) && close(s.link_recall, 0.0),
            "{s:?}"
        );
    }

    #[test]
    fn a_missed_detection_keeps_the_link_over_it_true() {
        // θ in frames 0–4; the estimate misses frame 2 and links 1 to 3.
        let truth = [walk(0, 0..5, 10.0, 10.0)];
        let mut points = truth[0].points.clone();
        points.remove(2);
        let estimated = [Track {
            particle: 0,
            points,
        }];
        let s = score_tracks(&truth, &estimated, 1.0).unwrap();
        // 3 links, all true; 2 of the 4 truth links recovered (0–1, 3–4).
        assert_eq!((s.estimated_links, s.true_links), (3, 3));
        assert!(close(s.link_recall, 0.5), "{s:?}");
        // α = 1 − ε/5ε.
        assert!(close(s.alpha, 0.8) && close(s.beta, 0.8), "{s:?}");
    }

    #[test]
    fn the_gate_decides_what_matches() {
        // 1.5 px off everywhere: no match at ε = 1, all matched at ε = 2
        // with α = 1 − 1.5/2.
        let truth = [walk(0, 0..4, 10.0, 10.0)];
        let off: Vec<(usize, f64, f64)> = truth[0]
            .points
            .iter()
            .map(|p| (p.frame, p.x, p.y + 1.5))
            .collect();
        let estimated = [track(0, &off)];
        let narrow = score_tracks(&truth, &estimated, 1.0).unwrap();
        assert!(close(narrow.alpha, 0.0), "{narrow:?}");
        assert_eq!(narrow.matched_points, 0);
        let wide = score_tracks(&truth, &estimated, 2.0).unwrap();
        assert!(
            close(wide.alpha, 0.25) && close(wide.link_precision, 1.0),
            "{wide:?}"
        );
        for gate in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let error = score_tracks(&truth, &estimated, gate).unwrap_err();
            assert_eq!(crate::error::exit_code(&error), 2);
        }
    }

    #[test]
    fn the_pairing_is_the_optimal_one_not_the_greedy_one() {
        // θ0, θ1: frames 0–9, 20 px apart. ω0 is on θ0 (exact) for frames
        // 0–4 and on θ1 (0.2 px off) for 5–9; ω1 is on θ0 (0.1 px off) for
        // frames 5–9. Gains over the dummy (Σ ε − d over matched points):
        // θ0–ω0 5, θ1–ω0 4, θ0–ω1 4.5. Greedy takes θ0–ω0 and leaves θ1
        // alone (gain 5); the optimum pairs θ0–ω1 and θ1–ω0 (gain 8.5).
        let theta0 = walk(0, 0..10, 10.0, 10.0);
        let theta1 = walk(1, 0..10, 10.0, 30.0);
        let on = |t: &Track, frames: std::ops::Range<usize>, dy: f64| -> Vec<(usize, f64, f64)> {
            t.points[frames]
                .iter()
                .map(|p| (p.frame, p.x, p.y + dy))
                .collect()
        };
        let w0 = [on(&theta0, 0..5, 0.0), on(&theta1, 5..10, 0.2)].concat();
        let w1 = on(&theta0, 5..10, 0.1);
        let s = score_tracks(&[theta0, theta1], &[track(0, &w0), track(1, &w1)], 1.0).unwrap();
        assert_eq!((s.paired_tracks, s.spurious_tracks), (2, 0), "{s:?}");
        // d(X, Y) = 20 − 8.5; α = β = 8.5/20; TP 10 of 20 + 15 points.
        assert!((s.distance_px - 11.5).abs() < 1e-9, "{s:?}");
        assert!(close(s.alpha, 0.425) && close(s.beta, 0.425), "{s:?}");
        assert!(close(s.jaccard_detections, 10.0 / 25.0), "{s:?}");
    }

    #[test]
    fn truth_tracks_follow_the_selection() {
        let row = |frame: usize, qd: u64, z_mean: f64, on_fraction: f64| RecordingTruthRow {
            frame,
            qd,
            x: frame as f64,
            y: 1.0,
            z_mean,
            on_fraction,
            x_seen: frame as f64 + 0.5,
            y_seen: 2.0,
            t_mid: 0.0,
            t_beam: 0.0,
            t_seen: 0.0,
            diffusion: 1.0,
        };
        // QD 4 goes out of focus in frame 1; QD 2 is dark in frame 2.
        let rows = [
            row(2, 4, 0.1, 1.0),
            row(0, 4, 0.2, 1.0),
            row(1, 4, -2.0, 1.0),
            row(0, 2, 0.0, 1.0),
            row(2, 2, 0.0, 0.1),
        ];
        let all = truth_tracks(&rows, &TruthSelection::default());
        assert_eq!(all.len(), 2);
        assert_eq!((all[0].particle, all[0].points.len()), (2, 2));
        let frames: Vec<usize> = all[1].points.iter().map(|p| p.frame).collect();
        assert_eq!(frames, [0, 1, 2]);
        let selected = truth_tracks(
            &rows,
            &TruthSelection {
                position: TruthPosition::Seen,
                max_depth_um: Some(1.0),
                min_on_fraction: Some(0.5),
                split_gaps_over: None,
            },
        );
        let points =
            |t: &Track| -> Vec<(usize, f64)> { t.points.iter().map(|p| (p.frame, p.x)).collect() };
        assert_eq!(points(&selected[0]), [(0, 0.5)]);
        // One track with a gap where the QD was out of focus.
        assert_eq!(points(&selected[1]), [(0, 0.5), (2, 2.5)]);
        // Split where a gap is longer than allowed (1 frame missing > 0):
        // both QDs miss frame 1.
        let split = truth_tracks(
            &rows,
            &TruthSelection {
                max_depth_um: Some(1.0),
                split_gaps_over: Some(0),
                ..TruthSelection::default()
            },
        );
        let lengths: Vec<(i64, usize)> =
            split.iter().map(|t| (t.particle, t.points.len())).collect();
        assert_eq!(lengths, [(2, 1), (2, 1), (4, 1), (4, 1)]);
        let kept = truth_tracks(
            &rows,
            &TruthSelection {
                max_depth_um: Some(1.0),
                split_gaps_over: Some(1),
                ..TruthSelection::default()
            },
        );
        assert_eq!(kept.len(), 2);
    }
}
