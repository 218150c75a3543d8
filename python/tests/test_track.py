"""scanloc.track against `scanloc track` on the same small recording: one
library call behind both, so the same tracks and D to the last digit; a
path and an array give the same result; bad input is refused with the
command's message; nothing is written."""

import _thread
import json
import os
import threading
import time

import numpy as np
import pandas as pd
import pytest
import tifffile

import scanloc

SEED = int(np.random.SeedSequence(6363).generate_state(1)[0])

SCOPE = """microscope:
  height: 32
  width: 32
  pixel_size_um: 0.1
  dwell_us: 4.0
  retrace_ms: 0.6
  sigma_xy_um: 0.21
  sigma_z_um: 1.36
  background: 8.4
  brightness: 7.5
"""


def simulate(cli, out, frames, size):
    cli("simulate-recording", "--height", size, "--width", size, "--pixel-size-um", 0.1, "--dwell-us", 4,
        "--retrace-ms", 0.6, "--brightness", 7.5, "--frames", frames, "--diffusion", 0.5, "--seed", SEED,
        "--out", out)
    return out


@pytest.fixture(scope="module")
def run(tmp_path_factory, cli):
    """A 32 × 32 recording of 150 frames, the microscope's YAML, and
    `scanloc track --json` on them (about a second)."""
    folder = tmp_path_factory.mktemp("track")
    (folder / "scope.yaml").write_text(SCOPE)
    recording = simulate(cli, folder / "rec.npy", 150, 32)
    result = cli("track", recording, "--microscope", folder / "scope.yaml", "--out", folder / "out", "--json")
    return folder, json.loads(result.stdout)


def cli_outputs(out):
    return (
        pd.read_csv(out / "tracks.csv"),
        pd.read_csv(out / "diffusion.csv", dtype={"particle": str}),
        json.loads((out / "settings.json").read_text()),
    )


def assert_same(result, out, summary):
    tracks, diffusion, settings = cli_outputs(out)
    pd.testing.assert_frame_equal(result.tracks, tracks)
    pd.testing.assert_frame_equal(result.diffusion, diffusion)
    assert result.settings == settings
    assert result.summary == summary
    for key in ("d_um2_s", "standard_error", "low_95", "high_95", "steps", "interval_valid"):
        assert result.ensemble[key] == summary["ensemble"][key], key


def test_track_equals_the_cli(run):
    folder, summary = run
    result = scanloc.track(folder / "rec.npy", folder / "scope.yaml", progress=False)
    assert_same(result, folder / "out", summary)
    assert len(result.tracks) > 50 and result.tracks["particle"].nunique() > 5
    assert list(result.tracks.columns[:3]) == ["frame", "x", "y"] and result.tracks.columns[-1] == "particle"
    assert result.ensemble["bias_corrected"] and result.ensemble["warnings"] == summary["warnings"]
    assert list(result.diffusion["particle"].iloc[-2:]) == ["ensemble", "ensemble-corrected"]
    assert result.settings["recipe"] == "scanloc-track-recording/1"


def test_an_array_a_path_and_a_tiff_give_the_same_result(run, tmp_path):
    folder, summary = run
    frames = np.load(folder / "rec.npy")
    scope = scanloc.Microscope(folder / "scope.yaml")
    tifffile.imwrite(tmp_path / "rec.tif", frames)
    inputs = [
        frames,
        frames.astype(np.uint32),
        np.asfortranarray(frames),
        frames.astype(np.float64),
        str(tmp_path / "rec.tif"),
    ]
    for recording in inputs:
        result = scanloc.track(recording, scope, progress=False)
        assert_same(result, folder / "out", summary)


def test_the_flags_are_the_commands(run, cli, tmp_path):
    folder, _ = run
    flags = {"min_score": 30.0, "bias_correction": False, "max_gap": 1, "seed": 5}
    result = scanloc.track(folder / "rec.npy", folder / "scope.yaml", progress=False, **flags)
    ran = cli("track", folder / "rec.npy", "--microscope", folder / "scope.yaml", "--out", tmp_path / "out",
              "--min-score", 30, "--no-bias-correction", "--max-gap", 1, "--seed", 5, "--json")
    assert_same(result, tmp_path / "out", json.loads(ran.stdout))
    assert not result.ensemble["bias_corrected"] and result.settings["min_score"] == 30.0


def cli_message(cli, *args):
    ran = cli("track", *args, check=False)
    assert ran.returncode == 2, ran.stderr
    message = ran.stderr.strip()
    assert message.startswith("error: ") and len(message.splitlines()) == 1, message
    return message[len("error: "):]


def test_bad_input_is_refused_with_the_commands_message(run, cli, tmp_path):
    folder, _ = run
    scope = folder / "scope.yaml"
    out = tmp_path / "out"
    # Frames of 24 × 24 px, a microscope of 32 × 32.
    small = simulate(cli, tmp_path / "small.npy", 5, 24)
    with pytest.raises(ValueError) as raised:
        scanloc.track(small, scope)
    assert str(raised.value) == cli_message(cli, small, "--microscope", scope, "--out", out)
    assert "height/width: the recording's frames are 24 × 24 px, the microscope's 32 × 32" in str(raised.value)
    with pytest.raises(ValueError, match="^recording: height/width: the recording's frames are 24 × 24 px"):
        scanloc.track(np.load(small), scope)
    # A colour stack: RGB pages in a TIFF, an (n, H, W, 3) array or .npy.
    colour = np.zeros((4, 32, 32, 3), np.uint8)
    colour[:, 10:12, 10:12, 0] = 200
    tifffile.imwrite(tmp_path / "colour.tif", colour, photometric="rgb")
    with pytest.raises(ValueError) as raised:
        scanloc.track(tmp_path / "colour.tif", scope)
    assert str(raised.value) == cli_message(cli, tmp_path / "colour.tif", "--microscope", scope, "--out", out)
    np.save(tmp_path / "colour.npy", colour)
    expected = cli_message(cli, tmp_path / "colour.npy", "--microscope", scope, "--out", out)
    with pytest.raises(ValueError) as raised:
        scanloc.track(colour, scope)
    assert str(raised.value) == expected.replace(str(tmp_path / "colour.npy"), "recording")
    # A missing file.
    missing = tmp_path / "missing.npy"
    with pytest.raises(FileNotFoundError) as raised:
        scanloc.track(missing, scope)
    assert str(raised.value) == cli_message(cli, missing, "--microscope", scope, "--out", out)
    # A microscope without its timing; a bad flag; a float that is no count.
    bare = {"height": 32, "width": 32}
    with pytest.raises(ValueError, match="^pixel_size_um: the microscope must state it"):
        scanloc.track(folder / "rec.npy", bare)
    with pytest.raises(ValueError, match="^--diameter: must be an odd number"):
        scanloc.track(folder / "rec.npy", scope, diameter=4)
    with pytest.raises(ValueError, match=r"^recording: value at flat index 0 \(0.5\) is not a photon count"):
        scanloc.track(np.full((3, 32, 32), 0.5), scope)
    assert not out.exists()


def test_nothing_is_written(run, tmp_path, monkeypatch):
    folder, _ = run
    monkeypatch.chdir(tmp_path)
    before = {p: sorted(os.listdir(p)) for p in (folder, tmp_path)}
    scanloc.track(folder / "rec.npy", folder / "scope.yaml", progress=False, bias_recordings=1)
    assert {p: sorted(os.listdir(p)) for p in (folder, tmp_path)} == before


def test_ctrl_c_stops_a_track(cli, tmp_path):
    (tmp_path / "scope.yaml").write_text(SCOPE.replace("32", "64"))
    recording = simulate(cli, tmp_path / "long.npy", 400, 64)
    pressed = []

    def press():
        time.sleep(0.4)
        pressed.append(time.perf_counter())
        _thread.interrupt_main()

    threading.Thread(target=press, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        scanloc.track(recording, tmp_path / "scope.yaml", progress=False)
    latency = time.perf_counter() - pressed[0]
    # Tolerance: the call returns within a poll (25 ms) and the time to
    # take the GIL on a loaded 2-core machine.
    assert latency < 1.0, latency
    # The run itself stops at its next stop point (a phase, a stack of
    # frames, a simulated frame): then the process is idle.
    deadline = time.perf_counter() + 60
    while True:
        cpu = time.process_time()
        time.sleep(1.0)
        if time.process_time() - cpu < 0.1:
            break
        assert time.perf_counter() < deadline, "the interrupted run is still computing after a minute"


def test_progress_is_one_tqdm_bar_to_its_end(run, monkeypatch):
    tqdm_auto = pytest.importorskip("tqdm.auto")
    bars = []

    class Spy(tqdm_auto.tqdm):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            bars.append(self)

    monkeypatch.setattr(tqdm_auto, "tqdm", Spy)
    folder, summary = run
    result = scanloc.track(folder / "rec.npy", folder / "scope.yaml", progress=True)
    assert result.summary == summary
    assert len(bars) == 1 and bars[0].desc == "tracking"
    # Every phase ran (threshold chosen, bias corrected): the bar ends full.
    assert bars[0].n == bars[0].total > 150
