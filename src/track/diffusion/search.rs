//! One-dimensional searches for the likelihood fits: a minimum on a
//! bracket (Brent's method) and a level crossing on a bracket (regula falsi
//! with the Illinois modification).
//!
//! Both converge superlinearly on smooth functions, which is what makes
//! the maximum-likelihood fit cheap: its profile over the localisation
//! variance is itself a minimisation, so every evaluation the outer
//! searches save is a whole inner search saved. Each falls back to a
//! golden-section or bisection step where interpolation does not help, so
//! neither needs more than a fixed number of evaluations, and both accept
//! `+∞` (a covariance that is not positive definite) as a value. Written
//! here rather than taken from a crate (argmin, roots): forty lines each,
//! where a crate would bring a solver framework into the build.

/// `(3 − √5)/2`: the golden section's share of a bracket.
const GOLDEN_SHARE: f64 = 0.381_966_011_250_105_1;

/// Most evaluations of a search: far more than either needs to reach its
/// tolerance on any function met here (10–20), a bound where it cannot.
const MAX_EVALUATIONS: usize = 100;

/// The minimiser and minimum of `f` on `[low, high]`, found to within
/// `tolerance` (absolute, in x) plus a relative 1e-10 of |x|, by Brent's
/// method: a parabola through the three best points where it steps inside
/// the bracket and shrinks the steps fast enough, else a golden-section
/// step. Exact for unimodal `f` up to the tolerance.
pub(crate) fn minimise(f: impl Fn(f64) -> f64, low: f64, high: f64, tolerance: f64) -> (f64, f64) {
    let (low, high) = (low.min(high), low.max(high));
    let x = low + GOLDEN_SHARE * (high - low);
    let fx = f(x);
    brent(&f, (low, high), [(x, fx); 3], 0.0, tolerance)
}

/// [`minimise`] starting from `start` (a point in `[low, high]` and `f`
/// there), where the minimum is expected within `reach`: `f` at `reach`
/// either side of the start, the bracket
/// widened fourfold downhill (within `[low, high]`) until the middle point
/// is the lowest, then Brent's method from those three points, whose first
/// step is already a parabola's. For a sequence of searches whose minima
/// move little (the profile over σ² at nearby D), 6–8 evaluations where a
/// search of the whole bracket takes 12–16.
pub(crate) fn minimise_near(
    f: impl Fn(f64) -> f64,
    (start, at_start): (f64, f64),
    reach: f64,
    (low, high): (f64, f64),
    tolerance: f64,
) -> (f64, f64) {
    let mut middle = (start, at_start);
    let mut left = ((start - reach).max(low), f((start - reach).max(low)));
    let mut right = ((start + reach).min(high), f((start + reach).min(high)));
    let mut reach = reach;
    for _ in 0..MAX_EVALUATIONS {
        let downhill_left = left.1 < middle.1 && left.0 > low;
        let downhill_right = right.1 < middle.1 && right.0 < high && !downhill_left;
        if !(downhill_left || downhill_right) {
            break;
        }
        reach *= 4.0;
        if downhill_left {
            let next = (middle.0 - reach).max(low);
            (right, middle, left) = (middle, left, (next, f(next)));
        } else {
            let next = (middle.0 + reach).min(high);
            (left, middle, right) = (middle, right, (next, f(next)));
        }
    }
    if left.1 < middle.1 || right.1 < middle.1 {
        // The minimum at a limit of [low, high]: the lowest point found.
        return [left, middle, right]
            .into_iter()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or(middle);
    }
    let (second, third) = if left.1 <= right.1 {
        (left, right)
    } else {
        (right, left)
    };
    let last_step = (right.0 - left.0) / 2.0;
    brent(
        &f,
        (left.0, right.0),
        [middle, second, third],
        last_step,
        tolerance,
    )
}

/// Brent's iterations on the bracket `(a, b)` from its best point, second
/// best and the one before (`x`, `w`, `v` with their values), the step
/// before the last being `e`.
fn brent(
    f: &impl Fn(f64) -> f64,
    (mut a, mut b): (f64, f64),
    [(mut x, mut fx), (mut w, mut fw), (mut v, mut fv)]: [(f64, f64); 3],
    mut e: f64,
    tolerance: f64,
) -> (f64, f64) {
    // The step taken last.
    let mut d = e;
    for _ in 0..MAX_EVALUATIONS {
        let middle = 0.5 * (a + b);
        let tol1 = 1e-10 * x.abs() + tolerance;
        let tol2 = 2.0 * tol1;
        if (x - middle).abs() <= tol2 - 0.5 * (b - a) {
            break;
        }
        let mut parabolic = None;
        if e.abs() > tol1 {
            let r = (x - w) * (fx - fv);
            let q = (x - v) * (fx - fw);
            let mut p = (x - v) * q - (x - w) * r;
            let mut q = 2.0 * (q - r);
            if q > 0.0 {
                p = -p;
            } else {
                q = -q;
            }
            // Comparisons with NaN (from +∞ values) are false: golden.
            if p.abs() < (0.5 * q * e).abs() && p > q * (a - x) && p < q * (b - x) {
                let step = p / q;
                let u = x + step;
                parabolic = Some(if u - a < tol2 || b - u < tol2 {
                    tol1.copysign(middle - x)
                } else {
                    step
                });
            }
        }
        match parabolic {
            Some(step) => {
                e = d;
                d = step;
            }
            None => {
                e = if x >= middle { a - x } else { b - x };
                d = GOLDEN_SHARE * e;
            }
        }
        let u = if d.abs() >= tol1 {
            x + d
        } else {
            x + tol1.copysign(d)
        };
        let fu = f(u);
        if fu <= fx {
            if u >= x {
                a = x;
            } else {
                b = x;
            }
            (v, fv, w, fw, x, fx) = (w, fw, x, fx, u, fu);
        } else {
            if u < x {
                a = u;
            } else {
                b = u;
            }
            if fu <= fw || w == x {
                (v, fv, w, fw) = (w, fw, u, fu);
            } else if fu <= fv || v == x || v == w {
                (v, fv) = (u, fu);
            }
        }
    }
    (x, fx)
}

/// Where `f` crosses `level` between `inside` (where `f` is at most the
/// level; `f_inside` its value there) and `outside` (above it, possibly
/// +∞), to within `tolerance` in x: regula falsi on the bracket, the kept
/// end's value halved whenever the same end is kept twice (Illinois), a
/// bisection where the secant is not defined.
pub(crate) fn crossing(
    f: impl Fn(f64) -> f64,
    (inside, f_inside): (f64, f64),
    (outside, f_outside): (f64, f64),
    level: f64,
    tolerance: f64,
) -> f64 {
    // `a` below the level, `b` above it; their heights over the level.
    let (mut a, mut ha) = (inside, f_inside - level);
    let (mut b, mut hb) = (outside, f_outside - level);
    let mut kept = 0i8;
    let mut c = 0.5 * (a + b);
    for _ in 0..MAX_EVALUATIONS {
        if (b - a).abs() <= tolerance {
            break;
        }
        let secant = (a * hb - b * ha) / (hb - ha);
        let strictly_between = (secant - a) * (secant - b) < 0.0;
        c = if secant.is_finite() && strictly_between {
            secant
        } else {
            0.5 * (a + b)
        };
        let hc = f(c) - level;
        if hc <= 0.0 {
            (a, ha) = (c, hc);
            if kept == 1 {
                hb *= 0.5;
            }
            kept = 1;
        } else {
            (b, hb) = (c, hc);
            if kept == -1 {
                ha *= 0.5;
            }
            kept = -1;
        }
        if hc.abs() <= 1e-6 * level.abs().max(1e-3) {
            break;
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    #[test]
    fn the_minimum_of_a_smooth_function_is_found_in_few_evaluations() {
        let calls = Cell::new(0);
        let f = |x: f64| {
            calls.set(calls.get() + 1);
            (x - 0.3).powi(2) * (1.0 + 0.2 * x) + (x - 0.3).powi(4)
        };
        let (x, fx) = minimise(f, -2.0, 3.0, 1e-7);
        assert!((x - 0.3).abs() < 1e-6, "{x}");
        assert!(fx < 1e-11);
        // Golden section alone needs 36 evaluations for this bracket.
        assert!(calls.get() <= 20, "{} evaluations", calls.get());
    }

    #[test]
    fn the_minimum_is_found_where_part_of_the_bracket_is_infinite() {
        let f = |x: f64| {
            if x < 0.5 {
                f64::INFINITY
            } else {
                (x - 1.7).powi(2) + 1.0 / x
            }
        };
        let (x, _) = minimise(f, -3.0, 4.0, 1e-8);
        // d/dx: 2(x − 1.7) − 1/x² = 0.
        assert!((2.0 * (x - 1.7) - 1.0 / (x * x)).abs() < 1e-6, "{x}");
    }

    #[test]
    fn a_minimum_at_the_bracket_end_is_approached() {
        let (x, _) = minimise(|x| x, 1.0, 2.0, 1e-9);
        assert!((x - 1.0).abs() < 1e-7, "{x}");
        let (x, _) = minimise_near(|x| -x, (1.0, -1.0), 0.01, (0.0, 2.0), 1e-9);
        assert_eq!(x, 2.0);
    }

    #[test]
    fn a_search_near_the_last_minimum_finds_it_in_few_evaluations() {
        for (start, reach) in [(0.31, 0.01), (0.2, 0.001), (1.9, 0.01), (-1.5, 0.1)] {
            let calls = Cell::new(0);
            let f = |x: f64| {
                calls.set(calls.get() + 1);
                (x - 0.3).powi(2) * (1.0 + 0.2 * x) + (x - 0.3).powi(4)
            };
            let (x, _) = minimise_near(f, (start, f(start)), reach, (-2.0, 3.0), 1e-7);
            assert!((x - 0.3).abs() < 1e-6, "{x} from {start}");
            let most = if start == 0.31 { 8 } else { 16 };
            assert!(
                calls.get() <= most,
                "{} evaluations from {start}",
                calls.get()
            );
        }
    }

    #[test]
    fn the_crossing_of_a_level_is_found_from_a_bracket_with_an_infinite_end() {
        let calls = Cell::new(0);
        let f = |x: f64| {
            calls.set(calls.get() + 1);
            if x > 5.0 {
                f64::INFINITY
            } else {
                x * x * (1.0 + 0.1 * x)
            }
        };
        let x = crossing(f, (0.0, 0.0), (8.0, f64::INFINITY), 3.84, 1e-9);
        assert!((f(x) - 3.84).abs() < 1e-5, "{x}");
        assert!(calls.get() <= 30, "{} evaluations", calls.get());
        // And from the other side.
        let x = crossing(f, (0.0, 0.0), (-8.0, f(-8.0)), 3.84, 1e-9);
        assert!(x < 0.0 && (f(x) - 3.84).abs() < 1e-5, "{x}");
    }
}
