//! The CNN localiser: training works, models round-trip through disk and
//! bytes, training is deterministic, bad settings are refused.
//!
//! Everything here uses a tiny network (8 channels) and a few hundred
//! 24×25 frames so the whole file runs in seconds.

use scanloc::detect::cnn::model::OUTPUT_CHANNELS;
use scanloc::detect::cnn::{
    self, CnnArchitecture, CnnHead, CnnScore, TrainedCnn, TrainingSettings, ValidationSet,
};
use scanloc::error::InputError;
use scanloc::metrics;
use scanloc::progress::hidden;
use scanloc::sim::{self, Distribution, RandomDistribution, SimParams};
use scanloc::types::{Dataset, FrameStack, Prediction};

fn params(brightness: f64) -> SimParams {
    SimParams {
        brightness: brightness.into(),
        margin_px: 4.0,
        diffusion_um2_s: Distribution::Random(RandomDistribution::Uniform([0.75, 1.75])),
        ..SimParams::default()
    }
}

fn tiny_architecture() -> CnnArchitecture {
    CnnArchitecture {
        channels: 8,
        dilations: vec![1, 2, 4, 2],
        ..CnnArchitecture::default()
    }
}

fn tiny_settings(epochs: usize) -> TrainingSettings {
    TrainingSettings {
        epochs,
        batch_size: 16,
        learning_rate: 1e-2,
        validation_fraction: 0.25,
        ..TrainingSettings::default()
    }
}

fn dataset(brightness: f64, frames: usize, seed: u64) -> Dataset {
    sim::simulate(&params(brightness), seed, 0..frames, &hidden()).unwrap()
}

fn train_tiny(data: &Dataset, epochs: usize, seed: u64) -> TrainedCnn {
    cnn::train(
        &tiny_architecture(),
        &tiny_settings(epochs),
        data,
        None,
        seed,
        &metrics::paper_aucs,
        &hidden(),
    )
    .unwrap()
}

/// Each frame's top-scoring prediction (None for frames without one).
fn top_per_frame(predictions: &[Prediction], frames: usize) -> Vec<Option<Prediction>> {
    let mut top: Vec<Option<Prediction>> = vec![None; frames];
    for p in predictions {
        let slot = &mut top[p.frame];
        if slot.is_none_or(|best| p.score > best.score) {
            *slot = Some(*p);
        }
    }
    top
}

/// The median distance (px) from each frame's top prediction by `model` to
/// its QD's centroid, over the one-QD frames of `test` (∞ where a frame has
/// no prediction).
fn median_top_distance_px(model: &TrainedCnn, test: &Dataset) -> f64 {
    let predictions = model.locate(&test.frames, &hidden()).unwrap();
    let mut distances: Vec<f64> = top_per_frame(&predictions, test.frames.n)
        .iter()
        .zip(&test.truth)
        .map(|(p, t)| p.map_or(f64::INFINITY, |p| (p.x - t.x).hypot(p.y - t.y)))
        .collect();
    distances.sort_by(f64::total_cmp);
    distances[distances.len() / 2]
}

fn is_input_error(error: &anyhow::Error) -> bool {
    error.chain().any(|cause| cause.is::<InputError>())
}

#[test]
fn training_reduces_the_loss_and_localises_better_than_chance() {
    // Bright QDs (N_qd 40) so a tiny network learns within a few epochs.
    let data = dataset(40.0, 400, 11);
    let model = train_tiny(&data, 4, 5);
    let epochs = &model.record.epochs;
    assert_eq!(epochs.len(), 4);
    assert!(
        epochs.last().unwrap().loss < 0.7 * epochs[0].loss,
        "loss did not fall: {:?}",
        epochs.iter().map(|e| e.loss).collect::<Vec<_>>()
    );
    assert!(epochs.iter().all(|e| e.validation_auc.len() == 3));
    assert!((1..=4).contains(&model.record.best_epoch));

    let test = dataset(40.0, 200, 12);
    let predictions = model.locate(&test.frames, &hidden()).unwrap();
    let top = top_per_frame(&predictions, test.frames.n);
    let distances: Vec<f64> = top
        .iter()
        .zip(&test.truth)
        .map(|(p, t)| p.map_or(f64::INFINITY, |p| (p.x - t.x).hypot(p.y - t.y)))
        .collect();
    let mut sorted = distances.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    // Chance: a guess uniform over the 16×17 px start region lies a median
    // ~5 px from the centroid (and the frame centre ~3.5 px). A network that
    // learnt anything lands well within 1.5 px of the centroid for most frames;
    // 1.5 px leaves room for the tiny model and short training while staying
    // far below both chance levels.
    eprintln!(
        "losses {:?}, median distance {median:.3} px",
        epochs.iter().map(|e| e.loss).collect::<Vec<_>>()
    );
    assert!(median < 1.5, "median distance {median:.2} px");
}

#[test]
fn save_and_load_give_identical_predictions() {
    let data = dataset(40.0, 120, 21);
    // Three epochs lift some scores above the 0.02 floor, so there is
    // something to compare.
    let model = train_tiny(&data, 3, 3);
    let dir = tempfile::tempdir().unwrap();
    model.save(dir.path()).unwrap();
    for file in [cnn::WEIGHTS_FILE, cnn::CONFIG_FILE, cnn::TRAINING_FILE] {
        assert!(dir.path().join(file).is_file(), "{file} missing");
    }
    let loaded = TrainedCnn::load(dir.path()).unwrap();
    assert_eq!(loaded.architecture, model.architecture);
    assert_eq!(loaded.settings, model.settings);
    assert_eq!(loaded.record, model.record);
    let test = dataset(40.0, 50, 22);
    let before = model.locate(&test.frames, &hidden()).unwrap();
    let after = loaded.locate(&test.frames, &hidden()).unwrap();
    assert!(!before.is_empty());
    assert_eq!(before, after);
}

#[test]
fn bytes_round_trip_is_exact() {
    let data = dataset(40.0, 120, 31);
    let model = train_tiny(&data, 1, 4);
    let bytes = model.to_bytes().unwrap();
    let restored = TrainedCnn::from_bytes(&bytes).unwrap();
    assert_eq!(restored.to_bytes().unwrap(), bytes);
    let test = dataset(40.0, 50, 32);
    assert_eq!(
        model.locate(&test.frames, &hidden()).unwrap(),
        restored.locate(&test.frames, &hidden()).unwrap()
    );
    // Damaged blobs are refused as bad input, not a panic.
    for bad in [&b"not a model"[..], &bytes[..bytes.len() / 2]] {
        let error = TrainedCnn::from_bytes(bad).unwrap_err();
        assert!(is_input_error(&error), "{error:#}");
    }
}

#[test]
fn same_seed_gives_identical_weights_whatever_the_thread_count() {
    let data = dataset(40.0, 150, 41);
    let train_with_threads = |threads: usize, seed: u64| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| train_tiny(&data, 2, seed).to_bytes().unwrap())
    };
    let one = train_with_threads(1, 7);
    let two = train_with_threads(2, 7);
    assert!(one == two, "weights differ between 1 and 2 threads");
    assert!(
        train_with_threads(2, 8) != two,
        "a different seed gave the same weights"
    );
}

#[test]
fn fresh_frames_are_used_and_seeded() {
    let data = dataset(40.0, 60, 51);
    let settings = TrainingSettings {
        fresh_frames_per_epoch: 64,
        validation_fraction: 1.0,
        ..tiny_settings(2)
    };
    let arch = tiny_architecture();
    let run = || {
        cnn::train(
            &arch,
            &settings,
            &data,
            Some(&params(40.0)),
            9,
            &metrics::paper_aucs,
            &hidden(),
        )
        .unwrap()
    };
    let model = run();
    assert_eq!(model.record.training_frames, 0);
    assert_eq!(model.record.validation_frames, 60);
    assert!(model.record.epochs.iter().all(|e| e.samples == 64));
    assert_eq!(model.to_bytes().unwrap(), run().to_bytes().unwrap());
}

#[test]
fn locates_in_frames_of_another_size_with_several_qds() {
    let data = dataset(40.0, 200, 61);
    let model = train_tiny(&data, 3, 6);
    let big = SimParams {
        height: 48,
        width: 64,
        emitters: 3.into(),
        ..params(40.0)
    };
    let test = sim::simulate(&big, 62, 0..20, &hidden()).unwrap();
    let predictions = model.locate(&test.frames, &hidden()).unwrap();
    assert!(predictions.iter().all(|p| {
        p.x >= -1.0 && p.x <= 64.0 && p.y >= -1.0 && p.y <= 48.0 && p.score > 0.0 && p.score < 1.0
    }));
    // At least two of the three QDs found within 3 px in most frames.
    let found = (0..test.frames.n)
        .filter(|&f| {
            let truth = test.truth.iter().filter(|t| t.frame == f);
            truth
                .filter(|t| {
                    predictions
                        .iter()
                        .any(|p| p.frame == f && (p.x - t.x).hypot(p.y - t.y) <= 3.0)
                })
                .count()
                >= 2
        })
        .count();
    eprintln!("{found} of 20 frames had ≥ 2 of 3 QDs found");
    assert!(
        found >= 14,
        "only {found} of 20 frames had ≥ 2 of 3 QDs found"
    );
    // An empty stack gives no predictions.
    let empty = FrameStack::zeros(0, 48, 64);
    assert!(model.locate(&empty, &hidden()).unwrap().is_empty());
}

#[test]
fn bad_settings_are_refused_naming_the_field() {
    let data = dataset(40.0, 20, 71);
    let arch = tiny_architecture();
    let base = tiny_settings(1);
    let cases: Vec<(TrainingSettings, CnnArchitecture, &str)> = vec![
        (
            TrainingSettings {
                epochs: 0,
                ..base.clone()
            },
            arch.clone(),
            "epochs",
        ),
        (
            TrainingSettings {
                batch_size: 0,
                ..base.clone()
            },
            arch.clone(),
            "batch_size",
        ),
        (
            TrainingSettings {
                learning_rate: f64::NAN,
                ..base.clone()
            },
            arch.clone(),
            "learning_rate",
        ),
        (
            TrainingSettings {
                validation_fraction: 1.5,
                ..base.clone()
            },
            arch.clone(),
            "validation_fraction",
        ),
        (
            TrainingSettings {
                validate_from_epoch: 0,
                ..base.clone()
            },
            arch.clone(),
            "validate_from_epoch",
        ),
        (
            TrainingSettings {
                validate_from_epoch: 2,
                ..base.clone()
            },
            arch.clone(),
            "validate_from_epoch",
        ),
        (
            TrainingSettings {
                score_floor: 1.0,
                ..base.clone()
            },
            arch.clone(),
            "score_floor",
        ),
        (
            TrainingSettings {
                fresh_frames_per_epoch: 10,
                ..base.clone()
            },
            arch.clone(),
            "fresh_frames_per_epoch",
        ),
        (
            TrainingSettings {
                members: 0,
                ..base.clone()
            },
            arch.clone(),
            "training.members",
        ),
        (
            TrainingSettings {
                members: cnn::MAX_MEMBERS + 1,
                ..base.clone()
            },
            arch.clone(),
            "training.members",
        ),
        (
            TrainingSettings {
                teacher_particles: 1,
                ..base.clone()
            },
            arch.clone(),
            "training.teacher_particles",
        ),
        (
            // Teaching the fresh frames needs a teacher …
            TrainingSettings {
                teacher_fresh_frames: true,
                fresh_frames_per_epoch: 10,
                ..base.clone()
            },
            arch.clone(),
            "training.teacher_fresh_frames",
        ),
        (
            // … and fresh frames.
            TrainingSettings {
                teacher_particles: 100,
                teacher_fresh_frames: true,
                ..base.clone()
            },
            arch.clone(),
            "training.teacher_fresh_frames",
        ),
        (
            // A teacher needs the training frames' simulator parameters
            // (None here).
            TrainingSettings {
                teacher_particles: 100,
                ..base.clone()
            },
            arch.clone(),
            "training.teacher_particles",
        ),
        (
            base.clone(),
            CnnArchitecture {
                channels: 0,
                ..arch.clone()
            },
            "channels",
        ),
        (
            base.clone(),
            CnnArchitecture {
                dilations: vec![],
                ..arch.clone()
            },
            "dilations",
        ),
        (
            base.clone(),
            CnnArchitecture {
                dilations: vec![1, 0],
                ..arch.clone()
            },
            "dilations",
        ),
    ];
    for (settings, architecture, field) in cases {
        let error = cnn::train(
            &architecture,
            &settings,
            &data,
            None,
            0,
            &metrics::paper_aucs,
            &hidden(),
        )
        .unwrap_err();
        assert!(is_input_error(&error), "{field}: {error:#}");
        assert!(format!("{error:#}").contains(field), "{field}: {error:#}");
    }
    // Unknown fields in a serialised config are refused too.
    let error = serde_json::from_str::<TrainingSettings>(r#"{"epoch": 3}"#).unwrap_err();
    assert!(
        error.to_string().contains("unknown field `epoch`"),
        "{error}"
    );
    let error = serde_json::from_str::<CnnArchitecture>(r#"{"channel": 3}"#).unwrap_err();
    assert!(
        error.to_string().contains("unknown field `channel`"),
        "{error}"
    );
}

#[test]
fn a_diverging_loss_stops_training_naming_epoch_and_batch() {
    let data = dataset(40.0, 100, 81);
    let settings = TrainingSettings {
        learning_rate: 1e30,
        cosine_decay: false,
        ..tiny_settings(3)
    };
    let error = cnn::train(
        &tiny_architecture(),
        &settings,
        &data,
        None,
        1,
        &metrics::paper_aucs,
        &hidden(),
    )
    .unwrap_err();
    let message = format!("{error:#}");
    assert!(
        message.contains("epoch") && message.contains("batch"),
        "{message}"
    );
}

#[test]
fn all_zero_and_huge_count_frames_give_finite_scores() {
    let data = dataset(40.0, 80, 51);
    let mut model = train_tiny(&data, 1, 5);
    // Without a score floor every frame's highest peak is a prediction, so
    // the checks below cannot pass on an empty list (on these frames the
    // trained floor may well leave none).
    model.settings.score_floor = 0.0;
    let mut one_huge_pixel = vec![0u32; 24 * 25];
    one_huge_pixel[12 * 25 + 12] = u32::MAX;
    let stacks = [0u32, 1_000_000_000, u32::MAX]
        .map(|value| (format!("{value} everywhere"), vec![value; 2 * 24 * 25]))
        .into_iter()
        .chain([("one u32::MAX pixel among zeros".to_string(), one_huge_pixel)]);
    for (what, counts) in stacks {
        let n = counts.len() / (24 * 25);
        let frames = FrameStack::from_vec(n, 24, 25, counts).unwrap();
        let raw = model.raw_output(&frames).unwrap();
        assert_eq!(raw.len(), n * OUTPUT_CHANNELS * 24 * 25, "{what}");
        assert!(raw.iter().all(|v| v.is_finite()), "{what}: raw output");
        let predictions = model.locate(&frames, &hidden()).unwrap();
        for frame in 0..n {
            assert!(
                predictions.iter().any(|p| p.frame == frame),
                "{what}: no prediction in frame {frame}"
            );
        }
        for p in &predictions {
            assert!(
                p.x.is_finite() && p.y.is_finite() && p.score.is_finite(),
                "{what}: {p:?}"
            );
        }
    }
}

/// With `validation_fraction: 1` the training set never trains, also when
/// a set of its own selects (a cross-validation's held-out fold): the fresh
/// frames alone train, so any training set of that frame size gives the
/// same weights.
#[test]
fn a_recipe_of_fresh_frames_only_keeps_to_them_when_another_set_selects() {
    let validation = dataset(40.0, 30, 74);
    let fresh_only = TrainingSettings {
        fresh_frames_per_epoch: 48,
        validation_fraction: 1.0,
        ..tiny_settings(2)
    };
    let train_on = |settings: &TrainingSettings, training: &Dataset| {
        cnn::train_selecting_on(
            &tiny_architecture(),
            settings,
            training,
            ValidationSet {
                dataset: &validation,
                score: &metrics::paper_aucs,
            },
            Some(&params(40.0)),
            10,
            &hidden(),
        )
        .unwrap()
    };
    let training = dataset(40.0, 90, 75);
    let model = train_on(&fresh_only, &training);
    assert_eq!(model.record.training_frames, 0);
    assert_eq!(model.record.validation_frames, 30);
    assert!(model.record.epochs.iter().all(|e| e.samples == 48));
    let other = train_on(&fresh_only, &dataset(20.0, 60, 76));
    assert!(model.to_bytes().unwrap() == other.to_bytes().unwrap());
    // A recipe that trains on its training set does so, all of it.
    let mixed = TrainingSettings {
        validation_fraction: 0.1,
        ..fresh_only
    };
    let mixed = train_on(&mixed, &training);
    assert_eq!(mixed.record.training_frames, 90);
    assert!(mixed.record.epochs.iter().all(|e| e.samples == 90 + 48));
}

#[test]
fn selection_on_a_validation_set_of_its_own_keeps_its_best_epoch() {
    let training = dataset(40.0, 120, 71);
    let validation = dataset(40.0, 50, 72);
    let model = cnn::train_selecting_on(
        &tiny_architecture(),
        &tiny_settings(3),
        &training,
        ValidationSet {
            dataset: &validation,
            score: &metrics::paper_aucs,
        },
        None,
        8,
        &hidden(),
    )
    .unwrap();
    // Nothing of the training set is held out (validation_fraction unused).
    assert_eq!(model.record.training_frames, 120);
    assert_eq!(model.record.validation_frames, 50);
    let means: Vec<f64> = model
        .record
        .epochs
        .iter()
        .map(|e| e.validation_mean_auc.unwrap())
        .collect();
    let best = means.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let first_best = means.iter().position(|&m| m == best).unwrap() + 1;
    assert_eq!(model.record.best_epoch, first_best, "{means:?}");
    // The kept weights are the ones scored on the validation set: scoring
    // them again there gives the recorded AUC exactly.
    let predictions = model.locate(&validation.frames, &hidden()).unwrap();
    let score = scanloc::metrics::score(
        &predictions,
        &validation.truth,
        validation.frames.n,
        &scanloc::metrics::PAPER_EPS_PX,
        false,
    )
    .unwrap();
    let mean = score.per_eps.iter().map(|e| e.auc).sum::<f64>() / 3.0;
    assert_eq!(mean, best);

    let other_size = sim::simulate(
        &SimParams {
            height: 30,
            ..params(40.0)
        },
        73,
        0..5,
        &hidden(),
    )
    .unwrap();
    let error = cnn::train_selecting_on(
        &tiny_architecture(),
        &tiny_settings(1),
        &training,
        ValidationSet {
            dataset: &other_size,
            score: &metrics::paper_aucs,
        },
        None,
        8,
        &hidden(),
    )
    .unwrap_err();
    assert!(is_input_error(&error), "{error:#}");
}

#[test]
fn validating_from_a_later_epoch_scores_and_keeps_only_those_epochs() {
    let data = dataset(40.0, 120, 74);
    let train_from = |validate_from_epoch: usize| {
        cnn::train(
            &tiny_architecture(),
            &TrainingSettings {
                validate_from_epoch,
                ..tiny_settings(4)
            },
            &data,
            None,
            9,
            &metrics::paper_aucs,
            &hidden(),
        )
        .unwrap()
    };
    let every = train_from(1);
    let late = train_from(3);
    // Epochs 1 and 2 are not scored; 3 and 4 are, as in the run that
    // scores every epoch: leaving the validation out changes no weights.
    for (record, full) in late.record.epochs.iter().zip(&every.record.epochs) {
        assert_eq!(record.loss, full.loss, "epoch {}", record.epoch);
        if record.epoch < 3 {
            assert!(record.validation_auc.is_empty(), "epoch {}", record.epoch);
            assert_eq!(record.validation_mean_auc, None);
        } else {
            assert_eq!(record.validation_auc, full.validation_auc);
            assert!(record.validation_mean_auc.is_some());
        }
    }
    assert_eq!(late.record.epochs.len(), 4);
    // The best of epochs 3 and 4 is kept (the earlier on a tie).
    let mean = |epoch: usize| late.record.epochs[epoch - 1].validation_mean_auc.unwrap();
    let best = if mean(4) > mean(3) { 4 } else { 3 };
    assert_eq!(late.record.best_epoch, best);
    // The setting travels with the model; the default is left out, so
    // models trained before it keep their bytes.
    assert!(late.to_bytes().unwrap() != every.to_bytes().unwrap());
    let settings = |model: &TrainedCnn| serde_json::to_string(&model.settings).unwrap();
    assert!(
        settings(&late).contains("\"validate_from_epoch\":3"),
        "{}",
        settings(&late)
    );
    assert!(
        !settings(&every).contains("validate_from_epoch"),
        "{}",
        settings(&every)
    );
}

/// Mean over frames of `what` of each frame's top prediction (frames
/// without a prediction skipped), and how many frames had one.
fn mean_of_top(
    predictions: &[Prediction],
    frames: usize,
    what: impl Fn(&Prediction) -> f64,
) -> (f64, usize) {
    let values: Vec<f64> = top_per_frame(predictions, frames)
        .iter()
        .flatten()
        .map(&what)
        .collect();
    (
        values.iter().sum::<f64>() / values.len().max(1) as f64,
        values.len(),
    )
}

/// Runs `scanloc locate --method cnn --model MODEL --input FRAMES --out OUT`.
fn locate_cli(model: &str, frames: &str, out: &str) -> std::process::Output {
    locate_cli_with(model, frames, out, &[])
}

/// `scanloc locate --method cnn` with further options.
fn locate_cli_with(model: &str, frames: &str, out: &str, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "locate", "--method", "cnn", "--model", model, "--input", frames, "--out", out,
    ];
    args.extend_from_slice(extra);
    crate::common::scanloc(&args)
}

#[test]
fn a_static_in_focus_qd_gets_a_smaller_uncertainty_than_a_fast_one() {
    // Trained on static to fast QDs, so the network sees both and can learn
    // that a fast QD's centroid is harder to place (the beam sees the path
    // only where it passes).
    let training_params = SimParams {
        diffusion_um2_s: Distribution::Random(RandomDistribution::Uniform([0.0, 2.5])),
        ..params(40.0)
    };
    let data = sim::simulate(&training_params, 91, 0..400, &hidden()).unwrap();
    let mut model = train_tiny(&data, 4, 9);
    // Scored by the within-1-px head, whatever the default.
    model.architecture.score = CnnScore::Within1px;
    let frames = 40;
    let set = |diffusion: f64, seed: u64| {
        let params = SimParams {
            diffusion_um2_s: Distribution::Fixed(diffusion),
            ..params(40.0)
        };
        sim::simulate(&params, seed, 0..frames, &hidden()).unwrap()
    };
    // In focus (z starts at 0) and static, against D = 2.5 µm²/s.
    let (easy, hard) = (set(0.0, 92), set(2.5, 93));
    let mut report = Vec::new();
    let mut figures = |data: &Dataset| {
        let predictions = model.locate(&data.frames, &hidden()).unwrap();
        assert!(
            predictions.iter().all(|p| p
                .sigma
                .is_some_and(|s| { s.x.is_finite() && s.y.is_finite() && s.x > 0.0 && s.y > 0.0 }))
        );
        let truth = &data.truth;
        let (error, found) = mean_of_top(&predictions, frames, |p| {
            let t = &truth[p.frame];
            (p.x - t.x).hypot(p.y - t.y)
        });
        let (sigma, _) = mean_of_top(&predictions, frames, |p| {
            let s = p.sigma.unwrap();
            (s.x * s.y).sqrt()
        });
        let (score, _) = mean_of_top(&predictions, frames, |p| p.score);
        report.push(format!(
            "{found} frames found, mean error {error:.3} px, mean σ {sigma:.3} px, mean score {score:.3}"
        ));
        (found, error, sigma, score)
    };
    let (easy_found, easy_error, easy_sigma, easy_score) = figures(&easy);
    let (hard_found, hard_error, hard_sigma, hard_score) = figures(&hard);
    eprintln!("easy: {}\nhard: {}", report[0], report[1]);
    // The network learnt something: it finds the static QD and places it
    // well within a pixel, and really does worse on the fast one.
    assert!(
        easy_found >= frames * 3 / 4 && easy_error < 0.7,
        "{report:?}"
    );
    assert!(hard_found > 0 && hard_error > easy_error, "{report:?}");
    // And it knows: a larger σ and a lower probability of being within
    // 1 px for the hard frames.
    assert!(hard_sigma > easy_sigma, "{report:?}");
    // Not only ordered but of the right size: σ (read from the
    // within-1-px head) is about the error it stands for. The σ maps, which
    // learn the offsets' error only at the centroid's own pixel, came out
    // 3–4 times too small here (RMS error/σ 2.9 and 3.8, 24 % of the axis
    // errors within 1 σ); the within head's σ gives 1.4 and 1.6, 62 %.
    assert!(hard_sigma > 1.5 * easy_sigma, "{report:?}");
    let hard_predictions = model.locate(&hard.frames, &hidden()).unwrap();
    let calibration = metrics::score(&hard_predictions, &hard.truth, frames, &[1.0], false)
        .unwrap()
        .uncertainty
        .expect("the CNN reports σ");
    assert!(
        calibration.rms_normalised_error_x < 2.0
            && calibration.rms_normalised_error_y < 2.0
            && calibration.within_one_sigma > 0.45,
        "{calibration:?}"
    );
    assert!(hard_score < easy_score, "{report:?}");

    // `scanloc locate --method cnn` writes the uncertainty columns, and
    // `scanloc score` reads the table back.
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_string_lossy().into_owned();
    model.save(&dir.path().join("model")).unwrap();
    scanloc::io::write_frames(&dir.path().join("easy.npy"), &easy.frames).unwrap();
    scanloc::io::csv_tables::write_truth(&dir.path().join("truth.csv"), &easy.truth).unwrap();
    let out = locate_cli(&path("model"), &path("easy.npy"), &path("locs.csv"));
    assert!(out.status.success(), "{}", crate::common::stderr(&out));
    let table = std::fs::read_to_string(path("locs.csv")).unwrap();
    assert!(
        table.starts_with("frame,x,y,sigma_x,sigma_y,score\n"),
        "{table}"
    );
    // A peaks model gives no list: asking for one is bad input.
    let out = locate_cli_with(
        &path("model"),
        &path("easy.npy"),
        &path("list.csv"),
        &["--max-candidates", "2"],
    );
    assert_eq!(out.status.code(), Some(2));
    let err = crate::common::stderr(&out);
    assert!(
        err.contains("max_candidates") && err.trim().lines().count() == 1,
        "{err}"
    );
    assert!(!dir.path().join("list.csv").exists());
    let read = scanloc::io::csv_tables::read_predictions(&dir.path().join("locs.csv")).unwrap();
    assert_eq!(read, model.locate(&easy.frames, &hidden()).unwrap());
    let out = crate::common::scanloc(&[
        "score",
        "--truth",
        &path("truth.csv"),
        "--locs",
        &path("locs.csv"),
    ]);
    assert!(out.status.success(), "{}", crate::common::stderr(&out));
    // ... and says how well the σ describes the errors.
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains(&format!(
            "uncertainty (sigma_x, sigma_y of each frame's top prediction), {easy_found} localisations"
        )),
        "{stdout}"
    );
}

// ---- deep ensembles (training.members) -----------------------------------

/// The settings of the tiny ensembles below: `members` networks, one epoch,
/// every local maximum a prediction (so a barely trained network still
/// predicts and there is something to compare).
fn ensemble_settings(members: usize) -> TrainingSettings {
    TrainingSettings {
        members,
        score_floor: 0.0,
        ..tiny_settings(1)
    }
}

/// A 2-member ensemble trained on 80 frames (60 trained on, 20 validate),
/// trained once for the file, with its training data and the progress bar
/// it trained with.
fn tiny_ensemble() -> &'static (Dataset, TrainedCnn, indicatif::ProgressBar) {
    static ENSEMBLE: std::sync::OnceLock<(Dataset, TrainedCnn, indicatif::ProgressBar)> =
        std::sync::OnceLock::new();
    ENSEMBLE.get_or_init(|| {
        let data = dataset(40.0, 80, 101);
        let bar = hidden();
        bar.set_message("train tiny");
        let model = cnn::train(
            &tiny_architecture(),
            &ensemble_settings(2),
            &data,
            None,
            5,
            &metrics::paper_aucs,
            &bar,
        )
        .unwrap();
        (data, model, bar)
    })
}

#[test]
fn an_ensembles_first_member_is_the_single_network_and_the_second_differs() {
    let (data, ensemble, bar) = tiny_ensemble();
    assert_eq!(ensemble.members(), 2);
    assert_eq!(ensemble.other_records.len(), 1);
    assert!(ensemble.member(2).is_none());
    // One bar over both members: 60 frames in batches of 16 = 4 steps each.
    assert_eq!(bar.length(), Some(8));
    assert_eq!(bar.position(), 8);
    // Its message keeps the caller's name for the training and names the
    // member (in a cross-validation log: which fold, which member).
    let message = bar.message();
    assert!(
        message.starts_with("train tiny · member 2/2: loss "),
        "{message:?}"
    );
    // Member 1 trains from the seed itself: bit for bit the single network.
    let single = cnn::train(
        &tiny_architecture(),
        &ensemble_settings(1),
        data,
        None,
        5,
        &metrics::paper_aucs,
        &hidden(),
    )
    .unwrap();
    let first = ensemble.member(0).unwrap();
    let second = ensemble.member(1).unwrap();
    assert!(first.to_bytes().unwrap() == single.to_bytes().unwrap());
    // Member 2 from a seed of its own: other weights, other output.
    assert_eq!(ensemble.record.seed, 5);
    let second_seed = ensemble.other_records[0].seed;
    assert_ne!(second_seed, 5);
    assert_eq!(second.record.seed, second_seed);
    let test = dataset(40.0, 10, 102);
    assert_ne!(
        first.raw_output(&test.frames).unwrap(),
        second.raw_output(&test.frames).unwrap()
    );
    // Deterministic: the same ensemble again.
    let again = cnn::train(
        &tiny_architecture(),
        &ensemble_settings(2),
        data,
        None,
        5,
        &metrics::paper_aucs,
        &hidden(),
    )
    .unwrap();
    assert!(again.to_bytes().unwrap() == ensemble.to_bytes().unwrap());
}

#[test]
fn an_ensembles_maps_are_its_members_maps_combined_per_pixel() {
    use scanloc::detect::cnn::model::{
        LOG_SIGMA_X_CHANNEL, LOG_SIGMA_Y_CHANNEL, OFFSET_X_CHANNEL, OFFSET_Y_CHANNEL,
        SCORE_CHANNEL, WITHIN_1PX_CHANNEL,
    };
    let (_, ensemble, _) = tiny_ensemble();
    let test = dataset(40.0, 6, 103);
    let len = test.frames.frame_len();
    let combined = ensemble.raw_output(&test.frames).unwrap();
    let first = ensemble
        .member(0)
        .unwrap()
        .raw_output(&test.frames)
        .unwrap();
    let second = ensemble
        .member(1)
        .unwrap()
        .raw_output(&test.frames)
        .unwrap();
    assert_eq!(combined.len(), first.len());
    let mut sigma_raised = 0;
    for frame in 0..test.frames.n {
        for pixel in 0..len {
            let at = |channel: usize| (frame * OUTPUT_CHANNELS + channel) * len + pixel;
            let mean = |channel: usize| {
                ((first[at(channel)] as f64 + second[at(channel)] as f64) / 2.0) as f32
            };
            for channel in [
                SCORE_CHANNEL,
                OFFSET_X_CHANNEL,
                OFFSET_Y_CHANNEL,
                WITHIN_1PX_CHANNEL,
            ] {
                assert_eq!(
                    combined[at(channel)],
                    mean(channel),
                    "{frame} {pixel} {channel}"
                );
            }
            for (offset, log_sigma) in [
                (OFFSET_X_CHANNEL, LOG_SIGMA_X_CHANNEL),
                (OFFSET_Y_CHANNEL, LOG_SIGMA_Y_CHANNEL),
            ] {
                // Two members: the offsets' variance is (half their gap)².
                let half_gap = (first[at(offset)] as f64 - second[at(offset)] as f64) / 2.0;
                let variance = |maps: &[f32]| (2.0 * maps[at(log_sigma)] as f64).exp();
                let expected =
                    ((variance(&first) + variance(&second)) / 2.0 + half_gap * half_gap).sqrt();
                let got = (combined[at(log_sigma)] as f64).exp();
                assert!(
                    (got / expected - 1.0).abs() < 1e-5,
                    "{frame} {pixel} {log_sigma}: σ {got} against {expected}"
                );
                let largest = variance(&first).max(variance(&second)).sqrt();
                if got > largest {
                    sigma_raised += 1;
                }
            }
        }
    }
    // The members disagree somewhere, and there σ exceeds both members'.
    assert!(sigma_raised > 0);
}

#[test]
fn an_ensemble_round_trips_through_bytes_and_folders_and_locate() {
    let (_, ensemble, _) = tiny_ensemble();
    let test = dataset(40.0, 20, 104);
    let predictions = ensemble.locate(&test.frames, &hidden()).unwrap();
    assert!(!predictions.is_empty());
    // The ensemble's predictions are neither member's.
    for index in 0..2 {
        let member = ensemble.member(index).unwrap();
        assert_ne!(member.locate(&test.frames, &hidden()).unwrap(), predictions);
    }

    let bytes = ensemble.to_bytes().unwrap();
    let restored = TrainedCnn::from_bytes(&bytes).unwrap();
    assert!(restored.to_bytes().unwrap() == bytes);
    assert_eq!(restored.other_records, ensemble.other_records);
    assert_eq!(
        restored.locate(&test.frames, &hidden()).unwrap(),
        predictions
    );
    for bad in [&bytes[..bytes.len() - 10], &bytes[..bytes.len() / 2]] {
        let error = TrainedCnn::from_bytes(bad).unwrap_err();
        assert!(is_input_error(&error), "{error:#}");
    }

    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("model");
    ensemble.save(&folder).unwrap();
    for file in [
        cnn::WEIGHTS_FILE,
        "model-2.bpk",
        cnn::CONFIG_FILE,
        cnn::TRAINING_FILE,
        "training-2.json",
    ] {
        assert!(folder.join(file).is_file(), "{file} missing");
    }
    let config = std::fs::read_to_string(folder.join(cnn::CONFIG_FILE)).unwrap();
    assert!(config.contains("\"members\": 2"), "{config}");
    let loaded = TrainedCnn::load(&folder).unwrap();
    assert!(loaded.to_bytes().unwrap() == bytes);
    assert_eq!(loaded.locate(&test.frames, &hidden()).unwrap(), predictions);

    // `scanloc locate` reads the folder and predicts as the library does.
    let path = |name: &str| dir.path().join(name).to_string_lossy().into_owned();
    scanloc::io::write_frames(&dir.path().join("frames.npy"), &test.frames).unwrap();
    let locate = || locate_cli(&path("model"), &path("frames.npy"), &path("locs.csv"));
    let out = locate();
    assert!(out.status.success(), "{}", crate::common::stderr(&out));
    let read = scanloc::io::csv_tables::read_predictions(&dir.path().join("locs.csv")).unwrap();
    assert_eq!(read, predictions);

    // A member missing, or one too many, is bad input naming the file.
    let refused = |needle: &str| {
        let out = locate();
        let text = crate::common::stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{text}");
        assert_eq!(text.trim().lines().count(), 1, "{text}");
        assert!(text.contains(needle), "{needle} not in {text}");
        assert!(!text.contains("panicked"), "{text}");
    };
    let second = std::fs::read(folder.join("model-2.bpk")).unwrap();
    std::fs::remove_file(folder.join("model-2.bpk")).unwrap();
    refused("model-2.bpk");
    std::fs::write(folder.join("model-2.bpk"), &second).unwrap();
    std::fs::write(folder.join("model-3.bpk"), &second).unwrap();
    refused("model-3.bpk");

    // A single network saved over the folder leaves no member of the
    // ensemble behind.
    let first = ensemble.member(0).unwrap();
    first.save(&folder).unwrap();
    for gone in ["model-2.bpk", "model-3.bpk", "training-2.json"] {
        assert!(!folder.join(gone).exists(), "{gone} left behind");
    }
    let config = std::fs::read_to_string(folder.join(cnn::CONFIG_FILE)).unwrap();
    assert!(!config.contains("members"), "{config}");
    assert!(TrainedCnn::load(&folder).unwrap().to_bytes().unwrap() == first.to_bytes().unwrap());
}

#[test]
fn cross_validation_trains_every_member_and_selects_each_on_the_held_out_fold() {
    let training = dataset(40.0, 48, 105);
    let validation = dataset(40.0, 20, 106);
    let train = |members: usize| {
        cnn::train_selecting_on(
            &tiny_architecture(),
            &ensemble_settings(members),
            &training,
            ValidationSet {
                dataset: &validation,
                score: &metrics::paper_aucs,
            },
            None,
            12,
            &hidden(),
        )
        .unwrap()
    };
    let ensemble = train(3);
    assert_eq!(ensemble.members(), 3);
    for record in ensemble.records() {
        assert_eq!(record.training_frames, 48);
        assert_eq!(record.validation_frames, 20);
    }
    let seeds: Vec<u64> = ensemble.records().map(|r| r.seed).collect();
    assert_eq!(seeds[0], 12);
    assert!(seeds[1] != seeds[0] && seeds[2] != seeds[1] && seeds[2] != seeds[0]);
    assert!(ensemble.member(0).unwrap().to_bytes().unwrap() == train(1).to_bytes().unwrap());
}

#[test]
fn train_refuses_a_member_count_out_of_range_naming_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("model");
    for members in ["0", "17"] {
        let output = crate::common::scanloc(&[
            "train",
            "--members",
            members,
            "--frames",
            "10",
            "--out",
            out.to_str().unwrap(),
        ]);
        let text = crate::common::stderr(&output);
        assert_eq!(output.status.code(), Some(2), "{text}");
        assert!(text.contains("training.members"), "{text}");
        assert!(!out.exists());
    }
}

// ---- posterior targets (training.teacher_particles) ------------------------

#[test]
fn the_teachers_targets_are_posterior_means_near_the_truth_and_seeded() {
    // Static bright QDs in small frames (the prior over the start is the
    // 6 × 6 px inside the margin): the posterior of the centroid is narrow,
    // so its mean lies close to the true centroid (N_qd 40, 4,000
    // particles: within 0.3 px, far below the ≈ 2 px of a guess); a frame
    // with two QDs keeps its truth.
    let static_params = SimParams {
        height: 14,
        width: 14,
        diffusion_um2_s: Distribution::Fixed(0.0),
        ..params(40.0)
    };
    let single = sim::simulate(&static_params, 3, 0..6, &hidden()).unwrap();
    let pair_params = SimParams {
        emitters: sim::EmitterCount::Fixed(2),
        ..static_params.clone()
    };
    let pair = sim::simulate(&pair_params, 4, 0..1, &hidden()).unwrap();
    let mut data = single.frames.data.clone();
    data.extend_from_slice(&pair.frames.data);
    let mut truth = single.truth.clone();
    truth.extend(
        pair.truth
            .iter()
            .map(|row| scanloc::types::TruthRow { frame: 6, ..*row }),
    );
    let mixed = Dataset {
        frames: FrameStack {
            n: 7,
            data,
            ..single.frames.clone()
        },
        truth,
    };
    let teach = |seed| {
        cnn::training::teacher_targets(&mixed, &static_params, 4000, seed, &hidden()).unwrap()
    };
    let targets = teach(1);
    assert_eq!(targets.len(), 7);
    for (frame, row) in single.truth.iter().enumerate() {
        let [(x, y)] = targets[frame][..] else {
            panic!("frame {frame}: {:?}", targets[frame]);
        };
        let off = (x - row.x).hypot(y - row.y);
        assert!(
            off > 0.0 && off < 0.3,
            "frame {frame}: {off:.3} px from the truth"
        );
    }
    let pair_truth: Vec<(f64, f64)> = pair.truth.iter().map(|row| (row.x, row.y)).collect();
    assert_eq!(targets[6], pair_truth);
    assert_eq!(teach(1), targets);
    assert_ne!(teach(2), targets);
}

#[test]
fn a_teacher_changes_what_is_learnt_and_the_network_still_localises() {
    let data = dataset(40.0, 300, 11);
    let train = |teacher_particles| {
        cnn::train(
            &tiny_architecture(),
            &TrainingSettings {
                teacher_particles,
                ..tiny_settings(4)
            },
            &data,
            Some(&params(40.0)),
            5,
            &metrics::paper_aucs,
            &hidden(),
        )
        .unwrap()
    };
    let taught = train(300);
    assert_eq!(taught.settings.teacher_particles, 300);
    assert_ne!(taught.to_bytes().unwrap(), train(0).to_bytes().unwrap());
    assert_eq!(taught.to_bytes().unwrap(), train(300).to_bytes().unwrap());
    // It learnt the QD's position (as in the first test of this file:
    // median within 1.5 px, chance ≈ 5 px).
    let test = dataset(40.0, 200, 12);
    let median = median_top_distance_px(&taught, &test);
    assert!(median < 1.5, "median distance {median:.2} px");
}

#[test]
fn teaching_the_fresh_frames_too_changes_what_is_learnt_and_the_network_still_localises() {
    let data = dataset(40.0, 200, 13);
    let train = |teacher_fresh_frames| {
        cnn::train(
            &tiny_architecture(),
            &TrainingSettings {
                teacher_particles: 300,
                teacher_fresh_frames,
                fresh_frames_per_epoch: 150,
                ..tiny_settings(3)
            },
            &data,
            Some(&params(40.0)),
            5,
            &metrics::paper_aucs,
            &hidden(),
        )
        .unwrap()
    };
    let all_taught = train(true);
    assert!(all_taught.settings.teacher_fresh_frames);
    let bytes = all_taught.to_bytes().unwrap();
    assert_ne!(bytes, train(false).to_bytes().unwrap());
    assert_eq!(bytes, train(true).to_bytes().unwrap());
    // It learnt the QD's position (median within 1.5 px, chance ≈ 5 px).
    let test = dataset(40.0, 200, 14);
    let median = median_top_distance_px(&all_taught, &test);
    assert!(median < 1.5, "median distance {median:.2} px");
}

fn categorical_architecture(max_candidates: usize) -> CnnArchitecture {
    CnnArchitecture {
        head: CnnHead::Categorical,
        max_candidates,
        ..tiny_architecture()
    }
}

fn categorical_settings(epochs: usize) -> TrainingSettings {
    TrainingSettings {
        offset_radius_px: 0,
        score_floor: 0.0,
        ..tiny_settings(epochs)
    }
}

#[test]
fn a_teacher_gives_the_categorical_head_its_posterior_and_the_network_still_localises() {
    // The categorical head learns the teacher's posterior over the pixels
    // (docs/cnn.md, "Posterior targets"): a model of its own key, other
    // weights than the untaught one's, the same on a second training, and
    // still a localiser (as above: median within 1.5 px, chance ≈ 5 px).
    let data = dataset(40.0, 300, 11);
    let train = |teacher_particles| {
        cnn::train(
            &categorical_architecture(3),
            &TrainingSettings {
                teacher_particles,
                ..categorical_settings(4)
            },
            &data,
            Some(&params(40.0)),
            5,
            &metrics::paper_aucs,
            &hidden(),
        )
        .unwrap()
    };
    let taught = train(300);
    assert_ne!(taught.to_bytes().unwrap(), train(0).to_bytes().unwrap());
    assert_eq!(taught.to_bytes().unwrap(), train(300).to_bytes().unwrap());
    let test = dataset(40.0, 200, 12);
    let median = median_top_distance_px(&taught, &test);
    assert!(median < 1.5, "median distance {median:.2} px");
    let spec = |teacher_particles| {
        scanloc::manifest::DetectorSpec::Cnn(scanloc::manifest::CnnSpec {
            architecture: categorical_architecture(3),
            training: TrainingSettings {
                teacher_particles,
                ..categorical_settings(4)
            },
            training_set: "train".to_string(),
        })
    };
    assert_eq!(
        spec(300).code_version(),
        "scanloc-cnn/3+scanloc-likelihood/2+posterior/1"
    );
    assert_eq!(spec(0).code_version(), "scanloc-cnn/3");
}

#[test]
fn the_categorical_head_learns_and_gives_ranked_guesses_whose_masses_are_a_distribution() {
    // Bright QDs (N_qd 40) as in the peaks test above, 4 epochs.
    let data = dataset(40.0, 400, 11);
    let model = cnn::train(
        &categorical_architecture(3),
        &categorical_settings(4),
        &data,
        None,
        5,
        &metrics::paper_aucs,
        &hidden(),
    )
    .unwrap();
    let losses: Vec<f64> = model.record.epochs.iter().map(|e| e.loss).collect();
    assert!(losses[3] < 0.7 * losses[0], "loss did not fall: {losses:?}");

    let test = dataset(40.0, 200, 12);
    let predictions = model.locate(&test.frames, &hidden()).unwrap();
    // Every frame has a list: ranks 1, 2, … in order, at most 3, masses
    // falling with the rank and summing to at most 1 (a distribution).
    let mut by_frame = vec![Vec::new(); test.frames.n];
    for p in &predictions {
        by_frame[p.frame].push(*p);
    }
    for (frame, list) in by_frame.iter().enumerate() {
        assert!((1..=3).contains(&list.len()), "frame {frame}: {list:?}");
        let ranks: Vec<u32> = list.iter().map(|p| p.candidate.unwrap()).collect();
        assert_eq!(ranks, (1..=list.len() as u32).collect::<Vec<_>>());
        assert!(list.windows(2).all(|w| w[0].score >= w[1].score - 1e-12));
        let total: f64 = list.iter().map(|p| p.score).sum();
        assert!(total <= 1.0 + 1e-9 && list.iter().all(|p| p.score > 0.0));
        assert!(list.iter().all(|p| p.sigma.is_some()));
    }
    // The best guess localises (chance is a median ~3.5–5 px, see above).
    let median = median_top_distance_px(&model, &test);
    assert!(median < 1.5, "median distance {median:.2} px");
    // The list scores at least as well as its best guesses alone at
    // ε = 1 px: the lower guesses rank below and only add true positives
    // (a small tolerance for the pooled ranking's interleaving).
    let score = metrics::score(&predictions, &test.truth, test.frames.n, &[1.0], false).unwrap();
    let eps1 = &score.per_eps[0];
    let best = eps1.auc_best_per_frame.unwrap();
    eprintln!(
        "categorical head: list AUC {:.3}, best guess {best:.3}",
        eps1.auc
    );
    assert!(eps1.auc >= best - 0.01, "list {} vs best {best}", eps1.auc);

    // `scanloc locate` writes the ranks, decodes the saved model as it
    // decodes itself, and re-decodes it into another list length.
    let dir = tempfile::tempdir().unwrap();
    let path = |name: &str| dir.path().join(name).to_string_lossy().into_owned();
    model.save(&dir.path().join("model")).unwrap();
    scanloc::io::write_frames(&dir.path().join("test.npy"), &test.frames).unwrap();
    let out = locate_cli(&path("model"), &path("test.npy"), &path("locs.csv"));
    assert!(out.status.success(), "{}", crate::common::stderr(&out));
    let table = std::fs::read_to_string(path("locs.csv")).unwrap();
    assert!(
        table.starts_with("frame,x,y,sigma_x,sigma_y,score,candidate\n"),
        "{table}"
    );
    let read = scanloc::io::csv_tables::read_predictions(&dir.path().join("locs.csv")).unwrap();
    assert_eq!(read, predictions);
    let out = locate_cli_with(
        &path("model"),
        &path("test.npy"),
        &path("one.csv"),
        &["--max-candidates", "1"],
    );
    assert!(out.status.success(), "{}", crate::common::stderr(&out));
    let one = scanloc::io::csv_tables::read_predictions(&dir.path().join("one.csv")).unwrap();
    assert_eq!(one.len(), test.frames.n);
    let firsts: Vec<Prediction> = predictions
        .iter()
        .filter(|p| p.candidate == Some(1))
        .copied()
        .collect();
    // The cover's first disc does not depend on how many follow it, and
    // (sorting by mass moving none of these frames' first discs) it is rank 1.
    assert_eq!(one, firsts);
}

#[test]
fn the_categorical_head_refuses_what_it_cannot_learn_naming_the_field() {
    let data = dataset(40.0, 40, 61);
    let train = |arch: &CnnArchitecture, settings: &TrainingSettings, data: &Dataset| {
        cnn::train(
            arch,
            settings,
            data,
            None,
            1,
            &metrics::paper_aucs,
            &hidden(),
        )
        .unwrap_err()
    };
    let error = train(&categorical_architecture(2), &tiny_settings(1), &data);
    assert!(is_input_error(&error), "{error:#}");
    assert!(
        format!("{error:#}").contains("offset_radius_px"),
        "{error:#}"
    );
    // The same recipe is refused when checked, before any training (a
    // manifest's `check`, `scanloc train`'s flags).
    let error = cnn::validate_recipe(&categorical_architecture(2), &tiny_settings(1)).unwrap_err();
    assert!(
        error.to_string().contains("training.offset_radius_px"),
        "{error}"
    );
    assert!(cnn::validate_recipe(&categorical_architecture(2), &categorical_settings(1)).is_ok());
    // Frames of two QDs: one softmax cannot hold two centroids.
    let two = sim::simulate(
        &SimParams {
            emitters: sim::EmitterCount::Fixed(2),
            ..params(40.0)
        },
        62,
        0..40,
        &hidden(),
    )
    .unwrap();
    let error = train(&categorical_architecture(2), &categorical_settings(1), &two);
    assert!(is_input_error(&error), "{error:#}");
    assert!(format!("{error:#}").contains("exactly one QD"), "{error:#}");
    // A list needs the categorical head.
    let peaks_with_a_list = CnnArchitecture {
        max_candidates: 2,
        ..tiny_architecture()
    };
    let error = peaks_with_a_list.validate().unwrap_err();
    assert!(error.to_string().contains("max_candidates"), "{error}");
}

#[test]
fn the_categorical_head_trains_and_decodes_to_the_same_bits_whatever_the_thread_count() {
    // The cross-entropy's gradient is summed in a fixed order and frames
    // are decoded in parallel each on its own: 1 and 2 threads must give
    // the same weights and the same ranked lists.
    let data = dataset(40.0, 150, 71);
    let test = dataset(40.0, 40, 72);
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let model = cnn::train(
                    &categorical_architecture(4),
                    &categorical_settings(2),
                    &data,
                    None,
                    9,
                    &metrics::paper_aucs,
                    &hidden(),
                )
                .unwrap();
                let predictions = model.locate(&test.frames, &hidden()).unwrap();
                (model.to_bytes().unwrap(), predictions)
            })
    };
    let (one_bytes, one_predictions) = run(1);
    let (two_bytes, two_predictions) = run(2);
    assert!(
        one_bytes == two_bytes,
        "weights differ between 1 and 2 threads"
    );
    assert!(!one_predictions.is_empty());
    assert_eq!(one_predictions, two_predictions);
}
