"""scanloc.Registry over a registry made by `scanloc run` (the smoke
manifest), against `scanloc registry` on the same folder; the CNN it
trained, located with from Python and from the command line."""

import json

import numpy as np
import pandas as pd
import pytest

import scanloc


def test_runs_and_the_auc_table_equal_the_clis(smoke_registry, cli):
    registry = scanloc.Registry(smoke_registry)
    runs = registry.runs()
    theirs = json.loads(cli("registry", "runs", "--json", "--registry", smoke_registry).stdout)
    assert list(runs["id"]) == [run["id"] for run in theirs]
    run = runs["id"].iloc[0]
    auc = registry.auc(run)
    assert set(auc["detector"]) == {"trackpy", "cnn"}
    assert len(auc) == 2 * 3 * 3 and auc["auc"].between(0, 1).all()
    assert registry.run(run[:8])["id"] == run
    steps = registry.steps(run)
    assert len(steps) > 0


def test_artefacts_by_key_and_verify(smoke_registry):
    registry = scanloc.Registry(smoke_registry)
    run = registry.runs()["id"].iloc[0]
    record = registry.run(run)
    keys = [step["artefact_key"] for step in record["steps"]]
    contents = [registry.artefact(key) for key in keys]
    frames = [c["frames.npy"] for c in contents if "frames.npy" in c]
    assert frames and all(f.ndim == 3 and f.dtype.kind == "u" for f in frames)
    predictions = [c["predictions.csv"] for c in contents if "predictions.csv" in c]
    assert predictions and all(isinstance(p, pd.DataFrame) and {"frame", "x", "y"} <= set(p.columns) for p in predictions)
    report = registry.verify()
    assert report["bad"] == [] and report["blobs_checked"] > 0
    with pytest.raises(ValueError):
        registry.artefact("zzzz-no-such-key")


def test_locate_with_the_registrys_cnn_equals_the_cli(smoke_registry, cli, tmp_path):
    registry = scanloc.Registry(smoke_registry)
    run = registry.runs()["id"].iloc[0]
    frames, _ = scanloc.simulate(20, seed=11, progress=False)
    np.save(tmp_path / "f.npy", frames)
    ours = scanloc.locate(frames, method="cnn", model=f"{run}:cnn", registry=smoke_registry, progress=False)
    cli("locate", "--method", "cnn", "--model", f"{run}:cnn", "--registry", smoke_registry,
        "--input", tmp_path / "f.npy", "--out", tmp_path / "cnn.csv")
    theirs = pd.read_csv(tmp_path / "cnn.csv")
    assert len(ours) == len(theirs) > 0
    for column in theirs.columns:
        np.testing.assert_array_equal(ours[column].to_numpy(), theirs[column].to_numpy(), err_msg=column)
    assert ours.attrs["model"]
