"""The Python API against the scanloc command line on the same inputs:
one library behind both, so the same numbers."""

import io
import json

import numpy as np
import pandas as pd
import pytest

import scanloc

SEED = int(np.random.SeedSequence(63).generate_state(1)[0])


def test_simulate_equals_the_cli(tmp_path, cli):
    m = scanloc.Microscope(height=30, width=28, emitters="choice:0,1,2", brightness="uniform:5,9")
    frames, truth = scanloc.simulate(15, seed=SEED, microscope=m, progress=False)
    cli("simulate", "--frames", 15, "--seed", SEED, "--height", 30, "--width", 28,
        "--emitters", "choice:0,1,2", "--brightness", "uniform:5,9",
        "--out", tmp_path / "f.npy", "--truth", tmp_path / "t.csv")
    assert frames.shape == (15, 30, 28)
    np.testing.assert_array_equal(frames, np.load(tmp_path / "f.npy"))
    pd.testing.assert_frame_equal(truth, pd.read_csv(tmp_path / "t.csv"))


def test_simulate_recording_equals_the_cli(tmp_path, cli):
    m = scanloc.Microscope(height=32, width=32, diffusion_um2_s=0.5)
    frames, truth = scanloc.simulate_recording(25, seed=SEED, microscope=m, qd_density=0.2, progress=False)
    cli("simulate-recording", "--frames", 25, "--seed", SEED, "--height", 32, "--width", 32,
        "--diffusion", 0.5, "--qd-density", 0.2, "--out", tmp_path / "r.npy", "--truth", tmp_path / "t.csv")
    np.testing.assert_array_equal(frames, np.load(tmp_path / "r.npy"))
    pd.testing.assert_frame_equal(truth, pd.read_csv(tmp_path / "t.csv"))
    assert truth["qd"].nunique() > 1


@pytest.fixture(scope="module")
def recording(tmp_path_factory, cli):
    folder = tmp_path_factory.mktemp("recording")
    cli("simulate-recording", "--frames", 40, "--seed", SEED, "--height", 48, "--width", 48,
        "--qd-density", 0.15, "--brightness", 30, "--out", folder / "r.npy", "--truth", folder / "t.csv")
    return folder


def test_locate_equals_the_cli(recording, cli):
    frames = np.load(recording / "r.npy")
    ours = scanloc.locate(frames, 7, minmass=10, progress=False)
    cli("locate", "--input", recording / "r.npy", "--out", recording / "locs.csv", "--diameter", 7, "--minmass", 10)
    theirs = pd.read_csv(recording / "locs.csv")
    assert len(ours) == len(theirs) > 40
    for column in ["frame", "x", "y", "mass", "size", "ecc", "signal", "raw_mass", "ep"]:
        np.testing.assert_array_equal(ours[column].to_numpy(), theirs[column].to_numpy(), err_msg=column)


@pytest.mark.parametrize("linker,args", [("trackpy", {"memory": 1}), ("lap", {"max_gap": 2})])
def test_link_equals_the_cli(recording, cli, linker, args):
    frames = np.load(recording / "r.npy")
    features = scanloc.locate(frames, 7, minmass=10, progress=False)
    features.to_csv(recording / "feats.csv", index=False)
    ours = scanloc.link(features, 4.0, linker=linker, **args)
    flags = [f"--{k.replace('_', '-')}={v}" for k, v in args.items()]
    cli("link", "--locs", recording / "feats.csv", "--out", recording / "tracks.csv",
        "--linker", linker, "--search-range", 4.0, *flags)
    theirs = pd.read_csv(recording / "tracks.csv")
    merged = ours.merge(theirs, on=["frame", "x", "y"], suffixes=("", "_cli"))
    assert len(merged) == len(ours) == len(theirs)
    pairs = set(zip(merged["particle"], merged["particle_cli"]))
    # The same partition: labels correspond one to one.
    assert len(pairs) == ours["particle"].nunique() == theirs["particle"].nunique()
    if linker == "lap":
        np.testing.assert_allclose(merged["gate_x"], merged["gate_x_cli"], equal_nan=True)


def test_diffusion_equals_the_cli(recording, cli):
    truth = pd.read_csv(recording / "t.csv")
    tracks = truth.rename(columns={"qd": "particle"})[["frame", "x", "y", "particle"]]
    tracks.to_csv(recording / "true_tracks.csv", index=False)
    m = scanloc.Microscope(height=48, width=48)
    per_track, ensemble = scanloc.diffusion(tracks, microscope=m)
    result = cli("diffusion", "--tracks", recording / "true_tracks.csv", "--height", 48, "--width", 48)
    theirs = pd.read_csv(io.StringIO(result.stdout), dtype={"particle": str})
    cli_tracks = theirs[theirs["particle"] != "ensemble"].reset_index(drop=True)
    cli_ensemble = theirs[theirs["particle"] == "ensemble"].reset_index(drop=True)
    assert len(per_track) == len(cli_tracks) > 0
    np.testing.assert_array_equal(per_track["particle"].to_numpy(), cli_tracks["particle"].astype(int).to_numpy())
    for column in ["points", "d_um2_s", "standard_error", "low_95", "high_95", "localisation_variance_um2"]:
        np.testing.assert_array_equal(per_track[column].to_numpy(), cli_tracks[column].to_numpy(), err_msg=column)
        np.testing.assert_array_equal(ensemble[column].to_numpy(), cli_ensemble[column].to_numpy(), err_msg=column)
    assert list(ensemble["method"]) == list(cli_ensemble["method"])
    ml = ensemble[ensemble["method"] == "ml"]
    # True positions of D = 1 µm²/s QDs: the ML ensemble's interval holds it
    # (a 95 % interval: this seed's draw, fixed, is checked once).
    assert float(ml["low_95"].iloc[0]) <= 1.0 <= float(ml["high_95"].iloc[0])
    only_ml, _ = scanloc.diffusion(tracks, microscope=m, estimator="ml")
    assert set(only_ml["method"]) == {"ml"}


def test_score_equals_the_cli(tmp_path, cli):
    frames, truth = scanloc.simulate(60, seed=SEED, microscope=scanloc.Microscope(brightness=14), progress=False)
    features = scanloc.locate(frames, 7, progress=False)
    truth.to_csv(tmp_path / "t.csv", index=False)
    features.to_csv(tmp_path / "p.csv", index=False)
    table = scanloc.score(truth, features, eps=(1, 2, 3))
    result = cli("score", "--truth", tmp_path / "t.csv", "--locs", tmp_path / "p.csv", "--score-column", "mass", "--json")
    theirs = json.loads(result.stdout)
    assert list(table["eps_px"]) == [1.0, 2.0, 3.0]
    assert list(table["auc"]) == [entry["auc"] for entry in theirs["per_eps"]]
    assert 0 < table["auc"].iloc[2] <= 1
