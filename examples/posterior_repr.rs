//! How much of the likelihood filter's list AUC survives when its posterior
//! is written the way the CNN's categorical head writes one (docs/cnn.md,
//! "Candidates"): a mass per pixel, the mean position of that mass and
//! its spread. Simulates frames of the paper's microscope, runs the filter
//! (D unknown), and scores the ranked lists decoded from each form:
//!
//! ```text
//! cargo run --release --locked --example posterior_repr -- FRAMES D SEED PARTICLES MAX_CANDIDATES
//! ```
use scanloc::detect::candidates::{CentreSearch, greedy_disc_cover};
use scanloc::detect::cnn::inference::GAUSS_HERMITE;
use scanloc::detect::likelihood::{LikelihoodParams, posterior_clouds};
use scanloc::sim::{self, SimParams};
use scanloc::types::{Distribution, Prediction, RandomDistribution};

/// The cloud binned into cells of side `cell` px centred on multiples of
/// `cell`: per cell its mass, mean and per-axis sd (capped at `cap`), as
/// 3 × 3 Gauss–Hermite points; `spread` false: one point at the mean;
/// `centre` true: the point at the cell's centre instead of the mean.
fn binned(
    cloud: &[(f64, f64, f64)],
    cell: f64,
    cap: f64,
    spread: bool,
    centre: bool,
) -> Vec<(f64, f64, f64)> {
    use std::collections::BTreeMap;
    let mut cells: BTreeMap<(i64, i64), [f64; 5]> = BTreeMap::new();
    for &(x, y, w) in cloud {
        let key = ((x / cell).round() as i64, (y / cell).round() as i64);
        let c = cells.entry(key).or_default();
        c[0] += w;
        c[1] += w * x;
        c[2] += w * y;
        c[3] += w * x * x;
        c[4] += w * y * y;
    }
    let mut points = Vec::new();
    for (&(i, j), c) in &cells {
        let m = c[0];
        if m < 1e-4 {
            continue;
        }
        let (mx, my) = if centre {
            (i as f64 * cell, j as f64 * cell)
        } else {
            (c[1] / m, c[2] / m)
        };
        if !spread {
            points.push((mx, my, m));
            continue;
        }
        let sx = (c[3] / m - (c[1] / m).powi(2)).max(0.0).sqrt().min(cap);
        let sy = (c[4] / m - (c[2] / m).powi(2)).max(0.0).sqrt().min(cap);
        for (v, wv) in GAUSS_HERMITE {
            for (u, wu) in GAUSS_HERMITE {
                points.push((mx + u * sx, my + v * sy, m * wu * wv));
            }
        }
    }
    points
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 6 {
        anyhow::bail!("usage: posterior_repr FRAMES D SEED PARTICLES MAX_CANDIDATES");
    }
    let frames: usize = args[1].parse()?;
    let diffusion: f64 = args[2].parse()?;
    let seed: u64 = args[3].parse()?;
    let particles: usize = args[4].parse()?;
    let max_candidates: usize = args[5].parse()?;
    let microscope = SimParams {
        brightness: Distribution::Fixed(7.5),
        margin_px: 4.0,
        diffusion_um2_s: Distribution::Fixed(diffusion),
        ..SimParams::default()
    };
    let hidden = scanloc::progress::hidden();
    let dataset = sim::simulate(&microscope, seed, 0..frames, &hidden)?;
    let settings = LikelihoodParams {
        particles,
        diffusion_um2_s: Some(Distribution::Random(RandomDistribution::Uniform([
            0.75, 1.75,
        ]))),
        ..LikelihoodParams::default()
    };
    let all: Vec<usize> = (0..frames).collect();
    let clouds = posterior_clouds(&dataset.frames, &all, &microscope, &settings, 1, &hidden)?;
    type Form = Box<dyn Fn(&[(f64, f64, f64)]) -> Vec<(f64, f64, f64)>>;
    let forms: Vec<(&str, Form)> = vec![
        ("particles", Box::new(|c| c.to_vec())),
        (
            "pixel: mean + sd<=0.5",
            Box::new(|c| binned(c, 1.0, 0.5, true, false)),
        ),
        (
            "pixel: mean, no spread",
            Box::new(|c| binned(c, 1.0, 0.5, false, false)),
        ),
        (
            "pixel: centre + sd<=0.5",
            Box::new(|c| binned(c, 1.0, 0.5, true, true)),
        ),
        (
            "half pixel: mean + sd<=0.25",
            Box::new(|c| binned(c, 0.5, 0.25, true, false)),
        ),
    ];
    for (name, form) in &forms {
        let mut list = Vec::new();
        let mut best = Vec::new();
        for (frame, cloud) in clouds.iter().enumerate() {
            let points = form(cloud);
            let guesses = greedy_disc_cover(
                &points,
                max_candidates,
                1.0,
                CentreSearch::CellsWithMeanShift,
            );
            for (rank, g) in (1..).zip(guesses) {
                let p = Prediction {
                    candidate: Some(rank),
                    ..Prediction::new(frame, g.x, g.y, g.mass)
                };
                if rank == 1 {
                    best.push(p);
                }
                list.push(p);
            }
        }
        let auc_list = scanloc::metrics::paper_aucs(&list, &dataset)?;
        let auc_best = scanloc::metrics::paper_aucs(&best, &dataset)?;
        println!(
            "D {diffusion} {name:30} list {:.3} / {:.3} / {:.3}   best {:.3} / {:.3} / {:.3}",
            auc_list[0], auc_list[1], auc_list[2], auc_best[0], auc_best[1], auc_best[2]
        );
    }
    Ok(())
}
