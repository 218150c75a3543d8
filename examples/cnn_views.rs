//! Decodes a categorical CNN model with test-time views and a softmax
//! temperature, for measuring them (docs/cnn.md, "Candidates": why the
//! decoding uses neither):
//!
//! ```text
//! cargo run --release --locked --example cnn_views -- MODEL FRAMES.npy TRUTH.csv OUT.csv \
//!     VIEWS MODE TEMPERATURE SPREAD MAX_CANDIDATES [SIGMA_CAP [RADIUS]]
//! ```
//!
//! VIEWS: comma-separated `id`, `rot` (180°), `hflip` (columns reversed),
//! `vflip` (rows reversed): each view's maps are mapped back to the frame's
//! pixels (offsets negated on a flipped axis). MODE `points`: the views'
//! posteriors are mixed with equal weights (each with its own offsets and
//! σ); `logit`: the maps are combined as an ensemble's members are
//! (`combine_members`). TEMPERATURE divides the logits; SPREAD scales the σ
//! maps (capped at SIGMA_CAP, default 0.5 px); RADIUS is the cover's disc
//! radius (default 1). Writes the ranked guesses as `scanloc locate` does
//! (without σ) and prints the mean negative log-likelihood of the pixel
//! nearest each true centroid on standard error. With `id points 1 1 N` it
//! reproduces `scanloc locate --max-candidates N`.
use std::path::Path;

use scanloc::detect::candidates::{CentreSearch, greedy_disc_cover};
use scanloc::detect::cnn::TrainedCnn;
use scanloc::detect::cnn::inference::{MAX_SPREAD_SIGMA_PX, MIN_PIXEL_MASS, combine_members};
use scanloc::detect::cnn::model::*;
use scanloc::types::{FrameStack, Prediction};

#[derive(Clone, Copy)]
enum View {
    Id,
    Rot,
    HFlip,
    VFlip,
}

impl View {
    fn map(self, r: usize, c: usize, h: usize, w: usize) -> (usize, usize) {
        match self {
            View::Id => (r, c),
            View::Rot => (h - 1 - r, w - 1 - c),
            View::HFlip => (r, w - 1 - c),
            View::VFlip => (h - 1 - r, c),
        }
    }
    fn signs(self) -> (f32, f32) {
        match self {
            View::Id => (1.0, 1.0),
            View::Rot => (-1.0, -1.0),
            View::HFlip => (-1.0, 1.0),
            View::VFlip => (1.0, -1.0),
        }
    }
}

fn transform(frames: &FrameStack, v: View) -> FrameStack {
    let (h, w) = (frames.height, frames.width);
    let mut out = frames.clone();
    for i in 0..frames.n {
        for r in 0..h {
            for c in 0..w {
                let (r2, c2) = v.map(r, c, h, w);
                out.data[(i * h + r) * w + c] = frames.data[(i * h + r2) * w + c2];
            }
        }
    }
    out
}

/// Raw output of the view mapped back to the original pixels.
fn untransform(raw: &[f32], n: usize, h: usize, w: usize, v: View) -> Vec<f32> {
    let len = h * w;
    let mut out = vec![0.0; raw.len()];
    let (sx, sy) = v.signs();
    for i in 0..n {
        for ch in 0..OUTPUT_CHANNELS {
            for r in 0..h {
                for c in 0..w {
                    // original pixel (r2,c2) <- view pixel (r,c)
                    let (r2, c2) = v.map(r, c, h, w);
                    let mut val = raw[(i * OUTPUT_CHANNELS + ch) * len + r * w + c];
                    if ch == OFFSET_X_CHANNEL {
                        val *= sx;
                    }
                    if ch == OFFSET_Y_CHANNEL {
                        val *= sy;
                    }
                    out[(i * OUTPUT_CHANNELS + ch) * len + r2 * w + c2] = val;
                }
            }
        }
    }
    out
}

fn softmax(l: &[f32], temp: f64) -> Vec<f64> {
    let m = l
        .iter()
        .fold(f64::NEG_INFINITY, |m, &x| m.max(x as f64 / temp));
    let e: Vec<f64> = l.iter().map(|&x| (x as f64 / temp - m).exp()).collect();
    let s: f64 = e.iter().sum();
    e.into_iter().map(|x| x / s).collect()
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 10 {
        anyhow::bail!(
            "usage: cnn_views MODEL FRAMES TRUTH OUT VIEWS MODE TEMPERATURE SPREAD MAX_CANDIDATES [SIGMA_CAP [RADIUS]]"
        );
    }
    let model = TrainedCnn::load(Path::new(&args[1]))?;
    let frames = scanloc::io::read_frames(Path::new(&args[2]))?;
    let truth = scanloc::io::csv_tables::read_truth(Path::new(&args[3]))?;
    let out = &args[4];
    let views: Vec<View> = args[5]
        .split(',')
        .map(|s| match s {
            "id" => Ok(View::Id),
            "rot" => Ok(View::Rot),
            "hflip" => Ok(View::HFlip),
            "vflip" => Ok(View::VFlip),
            other => Err(anyhow::anyhow!("unknown view `{other}`")),
        })
        .collect::<anyhow::Result<_>>()?;
    let mode = args[6].as_str();
    if !matches!(mode, "points" | "logit") {
        anyhow::bail!("MODE must be `points` or `logit`, got `{mode}`");
    }
    if truth.len() != frames.n || truth.iter().enumerate().any(|(i, t)| t.frame != i) {
        anyhow::bail!("TRUTH needs one row per frame (one QD per frame)");
    }
    let temp: f64 = args[7].parse()?;
    let spread: f64 = args[8].parse()?;
    let maxc: usize = args[9].parse()?;
    let cap: f64 = args
        .get(10)
        .map_or(Ok(MAX_SPREAD_SIGMA_PX), |s| s.parse())?;
    let radius: f64 = args.get(11).map_or(Ok(1.0), |s| s.parse())?;
    let (n, h, w) = (frames.n, frames.height, frames.width);
    let len = h * w;
    let outs: Vec<Vec<f32>> = views
        .iter()
        .map(|&v| {
            let raw = model.raw_output(&transform(&frames, v))?;
            Ok(untransform(&raw, n, h, w, v))
        })
        .collect::<anyhow::Result<_>>()?;
    let sets: Vec<Vec<f32>> = if mode == "logit" {
        vec![combine_members(&outs, len)]
    } else {
        outs
    };
    let mut preds = Vec::new();
    let mut nll = 0.0;
    for i in 0..n {
        let mut points = Vec::new();
        let mut ptruth = 0.0;
        let t = &truth[i];
        let tp = (t.y.round().clamp(0.0, (h - 1) as f64) as usize) * w
            + t.x.round().clamp(0.0, (w - 1) as f64) as usize;
        for set in &sets {
            let maps = &set[i * OUTPUT_CHANNELS * len..(i + 1) * OUTPUT_CHANNELS * len];
            let ch = |c: usize| &maps[c * len..(c + 1) * len];
            let probs = softmax(ch(SCORE_CHANNEL), temp);
            ptruth += probs[tp] / sets.len() as f64;
            for (p, &mass) in probs.iter().enumerate() {
                let mass = mass / sets.len() as f64;
                if mass < MIN_PIXEL_MASS / sets.len() as f64 {
                    continue;
                }
                let (row, col) = (p / w, p % w);
                let x = col as f64 + ch(OFFSET_X_CHANNEL)[p] as f64;
                let y = row as f64 + ch(OFFSET_Y_CHANNEL)[p] as f64;
                let sg = |ls: f32| {
                    ((ls as f64)
                        .clamp(LOG_SIGMA_RANGE.0, LOG_SIGMA_RANGE.1)
                        .exp()
                        * spread)
                        .min(cap)
                };
                let (sx, sy) = (
                    sg(ch(LOG_SIGMA_X_CHANNEL)[p]),
                    sg(ch(LOG_SIGMA_Y_CHANNEL)[p]),
                );
                const GH: [(f64, f64); 3] = [
                    (0.0, 2.0 / 3.0),
                    (-1.732_050_807_568_877_2, 1.0 / 6.0),
                    (1.732_050_807_568_877_2, 1.0 / 6.0),
                ];
                for (v, wv) in GH {
                    for (u, wu) in GH {
                        points.push((x + u * sx, y + v * sy, mass * wu * wv));
                    }
                }
            }
        }
        nll -= ptruth.max(1e-300).ln();
        let kept: f64 = points.iter().map(|p| p.2).sum();
        let mut g = greedy_disc_cover(&points, maxc, radius, CentreSearch::CellsWithMeanShift);
        for c in &mut g {
            c.mass *= kept;
        }
        g.sort_by(|a, b| b.mass.total_cmp(&a.mass));
        for (rank, c) in (1..).zip(g) {
            if c.mass < 0.001 {
                continue;
            }
            preds.push(Prediction {
                frame: i,
                x: c.x,
                y: c.y,
                score: c.mass,
                sigma: None,
                candidate: Some(rank),
            });
        }
    }
    eprintln!("pixel NLL {:.4}", nll / n as f64);
    scanloc::io::csv_tables::write_predictions(Path::new(out), &preds)?;
    Ok(())
}
