"""scanloc.locate / batch / link against real TrackPy 0.7, on frames and
tables made here with random seeds (never seen by either beforehand)."""

import numpy as np
import pandas as pd
import pytest

import scanloc

trackpy = pytest.importorskip("trackpy")
assert trackpy.__version__.startswith("0.7"), trackpy.__version__
trackpy.quiet()

SEEDS = list(np.random.SeedSequence(20261207).generate_state(3))


def stack(seed, frames=12, size=40, emitters=4, brightness=60):
    microscope = scanloc.Microscope(height=size, width=size + 3, emitters=emitters, brightness=brightness, margin_px=-2)
    data, truth = scanloc.simulate(frames, seed=int(seed), microscope=microscope, progress=False)
    return data, truth


def by_position(table):
    return table.sort_values(["frame", "x", "y"]).reset_index(drop=True)


def assert_same_features(ours, theirs, rtol=1e-9, atol=1e-9):
    """Equal to TrackPy's features: the same rows, the same numbers (to
    1e-9 relative: the two sum in different orders)."""
    assert list(ours.columns) == ["y", "x", "mass", "size", "ecc", "signal", "raw_mass", "ep", "frame"]
    ours, theirs = by_position(ours), by_position(theirs[list(ours.columns)])
    assert len(ours) == len(theirs), (len(ours), len(theirs))
    assert len(ours) > 0
    assert (ours["frame"].to_numpy() == theirs["frame"].to_numpy()).all()
    for column in ["y", "x", "mass", "size", "ecc", "signal", "raw_mass", "ep"]:
        np.testing.assert_allclose(ours[column], theirs[column], rtol=rtol, atol=atol, equal_nan=True, err_msg=column)


@pytest.mark.parametrize("seed", SEEDS)
def test_batch_equals_trackpy_batch(seed):
    frames, _ = stack(seed)
    ours = scanloc.batch(frames, 7, progress=False)
    theirs = trackpy.batch(frames, 7)
    assert_same_features(ours, theirs)


@pytest.mark.parametrize("seed", SEEDS[:2])
def test_locate_with_parameters_equals_trackpy(seed):
    frames, _ = stack(seed, frames=6, size=48, emitters=6)
    kwargs = dict(minmass=20, separation=6, noise_size=1.2, percentile=50, topn=4)
    ours = scanloc.locate(frames, 9, progress=False, **kwargs)
    theirs = trackpy.batch(frames, 9, **kwargs)
    assert_same_features(ours, theirs)


@pytest.mark.parametrize("dtype", ["uint8", "float32", "float64"])
def test_every_dtype_equals_trackpy(dtype):
    frames, _ = stack(SEEDS[0], frames=5)
    if dtype == "uint8":
        data = np.clip(frames, 0, 255).astype(np.uint8)
    else:
        # Background-subtracted, fractional and negative values.
        data = (frames.astype(np.float64) - 8.4).astype(dtype) / 3
    # TrackPy sums a float32 image's masses in float32, scanloc in float64:
    # the same features, the numbers within 1 % (positions within 1e-3 px).
    tolerance = dict(rtol=1e-2, atol=1e-3) if dtype == "float32" else {}
    assert_same_features(scanloc.locate(data, 7, progress=False), trackpy.batch(data, 7), **tolerance)


def test_one_frame_equals_trackpy_locate():
    frames, _ = stack(SEEDS[1], frames=1)
    ours = scanloc.locate(frames[0], 7, progress=False)
    theirs = trackpy.locate(frames[0], 7).assign(frame=0)
    assert_same_features(ours, theirs)


def random_walks(seed, particles=60, frames=30, size=80.0, step=1.0, blink=0.1):
    """A table of random walks with blinking (missed localisations)."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(0, size, (particles, 2))
    steps = rng.normal(0, step, (frames, particles, 2))
    steps[0] = 0
    paths = start + np.cumsum(steps, axis=0)
    frame, particle = np.meshgrid(np.arange(frames), np.arange(particles), indexing="ij")
    table = pd.DataFrame({
        "frame": frame.ravel(),
        "x": paths[..., 0].ravel(),
        "y": paths[..., 1].ravel(),
        "mass": rng.uniform(10, 100, frame.size),
    })
    keep = rng.uniform(size=len(table)) > blink
    return table[keep].sample(frac=1, random_state=int(seed) % 2**32).reset_index(drop=True)


def partition(table):
    return {frozenset(group.index) for _, group in table.groupby("particle")}


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("search_range,memory", [(3.0, 0), (4.0, 2)])
def test_link_equals_trackpy_link(seed, search_range, memory):
    table = random_walks(seed)
    ours = scanloc.link(table, search_range, memory=memory, progress=False)
    theirs = trackpy.link(table, search_range, memory=memory)
    assert ours.index.equals(table.index)
    assert len(partition(theirs)) > 10
    assert partition(ours) == partition(theirs)


def test_link_of_located_features_equals_trackpy():
    frames, _ = stack(SEEDS[2], frames=15, emitters=5)
    features = scanloc.batch(frames, 7, progress=False)
    ours = scanloc.link(features, 5, memory=1)
    theirs = trackpy.link(features, 5, memory=1)
    assert partition(ours) == partition(theirs)


@pytest.mark.parametrize("seed", SEEDS[:2])
def test_emsd_equals_trackpy_emsd(seed):
    tracks = trackpy.link(random_walks(seed, particles=30, frames=40), 3.0, memory=2)
    ours = scanloc.emsd(tracks, 0.07, 10.0, max_lagtime=15)
    theirs = trackpy.emsd(tracks, 0.07, 10.0, max_lagtime=15)
    np.testing.assert_allclose(ours.index.to_numpy(), theirs.index.to_numpy())
    np.testing.assert_allclose(ours.to_numpy(), theirs.to_numpy(), rtol=1e-7)
    detail = scanloc.emsd(tracks, 0.07, 10.0, max_lagtime=15, detail=True)
    theirs_detail = trackpy.emsd(tracks, 0.07, 10.0, max_lagtime=15, detail=True)
    for column in ["<x>", "<y>", "<x^2>", "<y^2>", "msd", "N", "lagt"]:
        np.testing.assert_allclose(detail[column].to_numpy(), theirs_detail[column].to_numpy(), rtol=1e-7, atol=1e-12, err_msg=column)
