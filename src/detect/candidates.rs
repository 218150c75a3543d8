//! A ranked list of guesses from a weighted posterior: the greedy disc cover
//! (`docs/metric.md`, "Why a list scores higher").
//!
//! Input: weighted points in pixels (a particle filter's centroids with
//! their weights; a per-pixel probability map's pixel centres plus their
//! sub-pixel offsets, with the probabilities as weights). Output: up to
//! `max_candidates` disc centres of radius `radius_px`, in order; each
//! centre maximises the posterior mass not yet covered by the discs before
//! it, and is scored by the mass it newly covers (a fraction of the total
//! weight). At ε = the radius, that mass is the probability that the guess
//! is a true positive given that the ones before it missed, which is what
//! the metric's pooled ranking rewards.
//!
//! The search for each centre: every point is bucketed into a grid of cells
//! of side `radius_px` (a disc meets at most the 3×3 cells around its
//! centre's), and into a finer grid of side `radius_px / 4`; the weighted
//! mean of each occupied fine cell's points is a candidate centre (so the
//! search costs the number of occupied fine cells, not the number of
//! points, times the points near each), and the best few are then moved by
//! mean shift (to the mean of the uncovered points within the radius, or
//! within twice it) while that covers more. The points themselves as centres, exhaustively, is the
//! reference it is tested against ([`CentreSearch::Points`]).
//!
//! Deterministic: no random draw; points are visited in input order.

use std::collections::HashMap;

/// Most guesses per frame a detector may be asked for: beyond a handful a
/// guess holds almost no mass.
pub const MAX_CANDIDATES: usize = 100;

/// The default guess count of a detector's settings: one, a position per
/// frame (serde default).
pub(crate) fn one_candidate() -> usize {
    1
}

/// Whether a guess count is the default, left out of serialised settings
/// so that content keys made before lists existed stand.
pub(crate) fn is_one_candidate(count: &usize) -> bool {
    *count == 1
}

/// The default radius of the cover's discs, px (serde default).
pub(crate) fn unit_radius() -> f64 {
    1.0
}

/// Whether a disc radius is the default, left out of serialised settings.
pub(crate) fn is_unit_radius(radius: &f64) -> bool {
    *radius == 1.0
}

/// A guess: a disc centre (px) and the posterior mass it newly covers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Candidate {
    pub x: f64,
    pub y: f64,
    /// The mass within the radius of the centre not covered by the
    /// candidates before it, as a fraction of the total weight (in [0, 1]).
    pub mass: f64,
}

/// Where the cover looks for each disc's centre.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CentreSearch {
    /// The weighted means of the points in cells of side radius / 4, the
    /// best [`REFINED_STARTS`] of them then moved by mean shift (the
    /// default: fast whatever the number of points).
    CellsWithMeanShift,
    /// Every point as a centre, exhaustively (time grows as the square of
    /// the points within a disc: the reference the default is checked
    /// against).
    Points,
}

/// How many of the best cell centres mean shift refines per disc.
pub(crate) const REFINED_STARTS: usize = 8;

/// Mean-shift steps at most per start (it stops when a step covers no more).
const MEAN_SHIFT_STEPS: usize = 20;

/// Fine cells per coarse cell side.
const FINE_PER_CELL: f64 = 4.0;

/// The cover stops when no disc could newly cover this fraction of the
/// total weight or more: a guess scored below it would rank below every
/// real guess of the set and add nothing measurable.
pub(crate) const MASS_FLOOR: f64 = 1e-3;

/// The greedy disc cover of the weighted points `(x, y, weight)`: up to
/// `max_candidates` candidates, in the order chosen (the first is the
/// single disc holding the most mass, chosen whatever its mass), stopping
/// early when the best further disc would cover less than [`MASS_FLOOR`]
/// of the total weight. Points
/// with a weight that is not finite and > 0, or a non-finite coordinate,
/// are left out; without any point the list is empty. `radius_px` must be
/// finite and > 0 (checked by the callers' parameters).
pub fn greedy_disc_cover(
    points: &[(f64, f64, f64)],
    max_candidates: usize,
    radius_px: f64,
    search: CentreSearch,
) -> Vec<Candidate> {
    let points: Vec<(f64, f64, f64)> = points
        .iter()
        .copied()
        .filter(|&(x, y, w)| x.is_finite() && y.is_finite() && w.is_finite() && w > 0.0)
        .collect();
    let total: f64 = points.iter().map(|p| p.2).sum();
    if points.is_empty() || !(total.is_finite() && total > 0.0) {
        return Vec::new();
    }
    let mut cover = Cover::new(points, total, radius_px);
    let mut candidates = Vec::new();
    // The first disc is always chosen (a frame always gets its best guess).
    while candidates.len() < max_candidates
        && (candidates.is_empty() || cover.uncovered_mass >= MASS_FLOOR)
    {
        let (x, y, mass) = match search {
            CentreSearch::CellsWithMeanShift => cover.best_refined_centre(),
            CentreSearch::Points => cover.best_point_centre(),
        };
        if mass < MASS_FLOOR && !candidates.is_empty() {
            break;
        }
        cover.cover(x, y);
        candidates.push(Candidate { x, y, mass });
    }
    candidates
}

/// The points, normalised, bucketed by cell, and which are covered.
struct Cover {
    /// `(x, y, weight / total)`.
    points: Vec<(f64, f64, f64)>,
    covered: Vec<bool>,
    uncovered_mass: f64,
    radius: f64,
    /// Coarse cell (side `radius`) → indices of its points, in input order.
    cells: HashMap<(i64, i64), Vec<usize>>,
}

impl Cover {
    fn new(points: Vec<(f64, f64, f64)>, total: f64, radius: f64) -> Self {
        let points: Vec<(f64, f64, f64)> = points
            .into_iter()
            .map(|(x, y, w)| (x, y, w / total))
            .collect();
        let mut cells: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (index, &(x, y, _)) in points.iter().enumerate() {
            cells.entry(cell_of(x, y, radius)).or_default().push(index);
        }
        Self {
            covered: vec![false; points.len()],
            uncovered_mass: points.iter().map(|p| p.2).sum(),
            points,
            radius,
            cells,
        }
    }

    /// The uncovered points within `reach` (the radius or twice it) of
    /// `(x, y)`, visited in a fixed order (the cells around it row by row,
    /// each in input order).
    fn for_each_near(&self, x: f64, y: f64, reach: f64, mut visit: impl FnMut(usize)) {
        let (ci, cj) = cell_of(x, y, self.radius);
        let cells = (reach / self.radius).ceil() as i64;
        let reach2 = reach * reach;
        for dj in -cells..=cells {
            for di in -cells..=cells {
                let Some(indices) = self.cells.get(&(ci + di, cj + dj)) else {
                    continue;
                };
                for &index in indices {
                    let (px, py, _) = self.points[index];
                    if !self.covered[index] && (px - x).powi(2) + (py - y).powi(2) <= reach2 {
                        visit(index);
                    }
                }
            }
        }
    }

    /// The uncovered mass within the radius of `(x, y)`.
    fn mass_at(&self, x: f64, y: f64) -> f64 {
        let mut mass = 0.0;
        self.for_each_near(x, y, self.radius, |index| mass += self.points[index].2);
        mass
    }

    /// The weighted mean of the uncovered points within `reach` of `(x, y)`
    /// (`None` if there is none).
    fn mean_near(&self, x: f64, y: f64, reach: f64) -> Option<(f64, f64)> {
        let (mut sx, mut sy, mut sw) = (0.0, 0.0, 0.0);
        self.for_each_near(x, y, reach, |index| {
            let (px, py, w) = self.points[index];
            sx += w * px;
            sy += w * py;
            sw += w;
        });
        (sw > 0.0).then(|| (sx / sw, sy / sw))
    }

    /// Marks the points within the radius of `(x, y)` covered.
    fn cover(&mut self, x: f64, y: f64) {
        let mut newly = Vec::new();
        self.for_each_near(x, y, self.radius, |index| newly.push(index));
        for index in newly {
            self.covered[index] = true;
            self.uncovered_mass -= self.points[index].2;
        }
    }

    /// The exhaustive reference: the point, as a centre, covering the most
    /// uncovered mass (the first of equals), and that mass.
    fn best_point_centre(&self) -> (f64, f64, f64) {
        let mut best = (self.points[0].0, self.points[0].1, f64::NEG_INFINITY);
        for &(x, y, _) in &self.points {
            let mass = self.mass_at(x, y);
            if mass > best.2 {
                best = (x, y, mass);
            }
        }
        best
    }

    /// The best centre among the fine cells' uncovered means, each of the
    /// best [`REFINED_STARTS`] moved by mean shift while that covers more.
    fn best_refined_centre(&self) -> (f64, f64, f64) {
        let mut starts: Vec<(f64, f64, f64)> = self
            .fine_cell_means()
            .into_iter()
            .map(|(x, y)| (x, y, self.mass_at(x, y)))
            .collect();
        // Stable: equal masses keep the cells' order.
        starts.sort_by(|a, b| b.2.total_cmp(&a.2));
        starts.truncate(REFINED_STARTS);
        let mut best = (0.0, 0.0, f64::NEG_INFINITY);
        for (mut x, mut y, mut mass) in starts {
            // Each step moves to the better of the uncovered means within
            // the radius (the flat kernel's mean shift, to a local mode)
            // and within twice it (every point a disc could cover: it
            // finds the middle of two clumps closer than a diameter).
            for _ in 0..MEAN_SHIFT_STEPS {
                let mut step = (x, y, mass);
                for reach in [self.radius, 2.0 * self.radius] {
                    if let Some((nx, ny)) = self.mean_near(x, y, reach) {
                        let shifted = self.mass_at(nx, ny);
                        if shifted > step.2 {
                            step = (nx, ny, shifted);
                        }
                    }
                }
                if step.2 <= mass {
                    break;
                }
                (x, y, mass) = step;
            }
            if mass > best.2 {
                best = (x, y, mass);
            }
        }
        best
    }

    /// The weighted mean of the uncovered points of each occupied fine cell
    /// (side radius / [`FINE_PER_CELL`]), in the order the cells are first
    /// met in the input.
    fn fine_cell_means(&self) -> Vec<(f64, f64)> {
        let side = self.radius / FINE_PER_CELL;
        let mut slot: HashMap<(i64, i64), usize> = HashMap::new();
        let mut sums: Vec<(f64, f64, f64)> = Vec::new();
        for (index, &(x, y, w)) in self.points.iter().enumerate() {
            if self.covered[index] {
                continue;
            }
            let next = sums.len();
            let at = *slot.entry(cell_of(x, y, side)).or_insert(next);
            if at == next {
                sums.push((0.0, 0.0, 0.0));
            }
            let sum = &mut sums[at];
            sum.0 += w * x;
            sum.1 += w * y;
            sum.2 += w;
        }
        sums.into_iter()
            .map(|(sx, sy, sw)| (sx / sw, sy / sw))
            .collect()
    }
}

/// The cell of side `side` holding `(x, y)`.
fn cell_of(x: f64, y: f64, side: f64) -> (i64, i64) {
    // Saturating casts: coordinates are finite; far-off ones share a cell.
    ((x / side).floor() as i64, (y / side).floor() as i64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    /// `n` points drawn from a round Gaussian of standard deviation `sd`
    /// about `(x, y)`, each of weight `weight`.
    fn blob(
        rng: &mut ChaCha8Rng,
        n: usize,
        (x, y): (f64, f64),
        sd: f64,
        weight: f64,
    ) -> Vec<(f64, f64, f64)> {
        use crate::sim::gaussian::standard_normal;
        (0..n)
            .map(|_| {
                (
                    x + sd * standard_normal(rng),
                    y + sd * standard_normal(rng),
                    weight,
                )
            })
            .collect()
    }

    #[test]
    fn two_separated_modes_give_two_candidates_with_their_masses() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        // 70 % of the mass about (5, 5), 30 % about (12, 9), each within
        // 0.2 px (a disc of 1 px holds all of a mode: 5 σ).
        let mut points = blob(&mut rng, 700, (5.0, 5.0), 0.2, 1.0);
        points.extend(blob(&mut rng, 300, (12.0, 9.0), 0.2, 1.0));
        for search in [CentreSearch::CellsWithMeanShift, CentreSearch::Points] {
            let candidates = greedy_disc_cover(&points, 4, 1.0, search);
            assert_eq!(candidates.len(), 2, "{search:?}: {candidates:?}");
            let [first, second] = [candidates[0], candidates[1]];
            // Each mode's mass to rounding. Every disc holding a whole
            // mode (its points lie within about 0.6 px of it) is as good,
            // so a centre is anywhere within about 0.4 px of its mode.
            assert!((first.mass - 0.7).abs() < 1e-12, "{first:?}");
            assert!((second.mass - 0.3).abs() < 1e-12, "{second:?}");
            assert!(((first.x - 5.0).powi(2) + (first.y - 5.0).powi(2)).sqrt() < 0.5);
            assert!(((second.x - 12.0).powi(2) + (second.y - 9.0).powi(2)).sqrt() < 0.5);
        }
    }

    #[test]
    fn one_tight_mode_gives_one_candidate_of_all_the_mass() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        // σ = 0.3 px: 1 − exp(−1/(2·0.09)) = 0.996 of the mass within 1 px
        // of the mode; a few points in the tail.
        let points = blob(&mut rng, 5000, (8.0, 3.0), 0.3, 1.0);
        let candidates = greedy_disc_cover(&points, 3, 1.0, CentreSearch::CellsWithMeanShift);
        assert!(!candidates.is_empty());
        assert!(candidates[0].mass > 0.99, "{candidates:?}");
        // The rest, if any, hold the tail only: at most 1 % in all.
        let rest: f64 = candidates[1..].iter().map(|c| c.mass).sum();
        assert!(rest < 0.01, "{candidates:?}");
        // Weights need not be normalised: scaled, the same cover.
        let scaled: Vec<_> = points.iter().map(|&(x, y, w)| (x, y, 1e-9 * w)).collect();
        let again = greedy_disc_cover(&scaled, 3, 1.0, CentreSearch::CellsWithMeanShift);
        assert_eq!(again.len(), candidates.len());
        assert!((again[0].mass - candidates[0].mass).abs() < 1e-12);
    }

    #[test]
    fn the_list_stops_at_the_mass_floor_and_at_the_count() {
        // Three points: masses 0.6, 0.3995 and 0.0005 (below the floor).
        let points = [(0.0, 0.0, 0.6), (5.0, 0.0, 0.3995), (10.0, 0.0, 0.0005)];
        let candidates = greedy_disc_cover(&points, 5, 1.0, CentreSearch::CellsWithMeanShift);
        assert_eq!(candidates.len(), 2, "{candidates:?}");
        assert_eq!((candidates[0].x, candidates[1].x), (0.0, 5.0));
        let one = greedy_disc_cover(&points, 1, 1.0, CentreSearch::CellsWithMeanShift);
        assert_eq!(one.len(), 1);
        // Nothing to cover: no candidate.
        let none = greedy_disc_cover(
            &[(0.0, 0.0, 0.0), (f64::NAN, 1.0, 1.0)],
            3,
            1.0,
            CentreSearch::Points,
        );
        assert!(none.is_empty());
    }

    #[test]
    fn a_disc_between_two_close_modes_beats_any_point_on_either() {
        // Two clumps 1.6 px apart, of 0.5 each: a disc of 1 px centred
        // between them holds both, one centred on either clump only that
        // clump.
        let points = [(0.0, 0.0, 0.5), (1.6, 0.0, 0.5)];
        let points_only = greedy_disc_cover(&points, 1, 1.0, CentreSearch::Points);
        let refined = greedy_disc_cover(&points, 1, 1.0, CentreSearch::CellsWithMeanShift);
        assert!((points_only[0].mass - 0.5).abs() < 1e-12);
        assert!((refined[0].mass - 1.0).abs() < 1e-12, "{refined:?}");
    }

    #[test]
    fn the_refined_search_covers_at_least_what_the_points_do() {
        // Posteriors like the filter's: a main mode, a weaker elongated
        // one, a scatter; the total covered by 1 to 4 discs, summed over
        // 20 posteriors, by the default search against the exhaustive one.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut sums = [[0.0; 2]; 4];
        for trial in 0..20 {
            let spread = 0.4 + 0.1 * trial as f64;
            let mut points = blob(&mut rng, 600, (10.0, 10.0), spread, 1.0);
            points.extend(blob(&mut rng, 300, (11.5, 10.5), 1.5 * spread, 0.8));
            points.extend(blob(&mut rng, 100, (10.0, 10.0), 3.0, 0.5));
            for (j, search) in [CentreSearch::CellsWithMeanShift, CentreSearch::Points]
                .into_iter()
                .enumerate()
            {
                let candidates = greedy_disc_cover(&points, 4, 1.0, search);
                let mut covered = 0.0;
                for (k, sum) in sums.iter_mut().enumerate() {
                    covered += candidates.get(k).map_or(0.0, |c| c.mass);
                    sum[j] += covered;
                }
            }
        }
        // Tolerance 0.2 % of the covered mass: the greedy choices may
        // differ, but the refined centres may not lose on the whole.
        for (k, [refined, points_only]) in sums.iter().enumerate() {
            assert!(
                *refined >= points_only * 0.998,
                "{} discs: refined {refined} against points {points_only}",
                k + 1
            );
        }
    }
}
