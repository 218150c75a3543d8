"""Errors as Python exceptions with the command line's message, never a
crash; Ctrl-C stops a long locate within a second."""

import _thread
import threading
import time

import numpy as np
import pandas as pd
import pytest

import scanloc

FRAMES = np.ones((2, 20, 20), np.uint16)


@pytest.mark.parametrize("call,message", [
    (lambda: scanloc.locate(FRAMES, 8), "diameter: must be an odd integer ≥ 3, got 8"),
    (lambda: scanloc.locate(FRAMES, 7, percentile=120), "percentile"),
    (lambda: scanloc.locate(np.ones((2, 2, 3, 3)), 7), "shape (n, H, W) or (H, W)"),
    (lambda: scanloc.locate(np.ones((2, 9, 9), complex), 7), "dtype complex128"),
    (lambda: scanloc.locate(-FRAMES.astype(np.int32), 7), "negative values"),
    (lambda: scanloc.locate(np.full((1, 9, 9), np.nan), 7), "value at flat index 0 is NaN"),
    (lambda: scanloc.locate(FRAMES, 7, method="magic"), "method: expected"),
    (lambda: scanloc.locate(FRAMES, method="cnn"), "model: required"),
    (lambda: scanloc.locate(FRAMES.astype(float) + 0.5, method="likelihood"), "photon counts"),
    (lambda: scanloc.link(pd.DataFrame({"frame": [0], "x": [1.0], "y": [1.0]})), "search_range: needed"),
    (lambda: scanloc.link(pd.DataFrame({"frame": [0], "x": [1.0], "y": [1.0]}), -1), "search_range"),
    (lambda: scanloc.link(pd.DataFrame({"frame": [0], "x": [1.0], "y": [1.0]}), 3, linker="x"), "linker: expected"),
    (lambda: scanloc.link(pd.DataFrame({"frame": [0], "x": [np.nan], "y": [1.0]}), 3), "column x: expected a finite number"),
    (lambda: scanloc.link(pd.DataFrame({"frame": [-1], "x": [1.0], "y": [1.0]}), 3), "column frame"),
    (lambda: scanloc.link(pd.DataFrame({"x": [1.0], "y": [1.0]}), 3), "no column 'frame'"),
    (lambda: scanloc.simulate(3, microscope={"height": 0}), "height"),
    (lambda: scanloc.simulate(3, microscope={"colour": 3}), "colour"),
    (lambda: scanloc.Microscope(sigma_xy_um=-1).validate(), "sigma_xy_um"),
    (lambda: scanloc.simulate_recording(3, blink_on_ms=5), "blink_on_ms and blink_off_ms"),
    (lambda: scanloc.diffusion(pd.DataFrame({"frame": [0, 1], "x": [1.0, 2], "y": [1.0, 1], "particle": [0, 0]}), min_points=1), "--min-points"),
    (lambda: scanloc.diffusion(pd.DataFrame({"frame": [0, 0], "x": [1.0, 2], "y": [1.0, 1], "particle": [0, 0]})), "particle 0 appears twice in frame 0"),
    (lambda: scanloc.diffusion(pd.DataFrame({"frame": [0, 1], "x": [1.0, 2], "y": [1.0, 1], "particle": [0, 1]})), "no track has two localisations"),
    (lambda: scanloc.score(pd.DataFrame({"frame": [0], "x": [1.0], "y": [1.0]}), pd.DataFrame({"frame": [0], "x": [1.0], "y": [1.0], "score": [1.0]}), eps=(0,)), "eps"),
    (lambda: scanloc.score(pd.DataFrame({"frame": [0], "x": [1.0], "y": [1.0]}), pd.DataFrame({"frame": [5], "x": [1.0], "y": [1.0], "score": [1.0]})), "frame"),
])
def test_bad_input_is_a_value_error_with_the_clis_message(call, message):
    with pytest.raises(ValueError) as raised:
        call()
    assert message in str(raised.value), str(raised.value)


def test_missing_files_are_file_not_found_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        scanloc.Microscope(tmp_path / "missing.yaml")
    with pytest.raises(FileNotFoundError, match="no such folder"):
        scanloc.Registry(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="not a model folder"):
        scanloc.locate(FRAMES, method="cnn", model="RUN:cnn", registry=tmp_path / "nowhere")


def test_a_bad_yaml_file_names_its_line(tmp_path):
    path = tmp_path / "m.yaml"
    path.write_text("microscope:\n  height: 30\n  dwell_us: fast\n")
    with pytest.raises(ValueError, match="m.yaml"):
        scanloc.Microscope(path)
    path.write_text("microscope:\n  height: 30\n  brightness: {uniform: [5, 9]}\n")
    m = scanloc.Microscope(path)
    assert m.height == 30 and m.width == 25 and m.stated == ["brightness", "height"]
    assert scanloc.Microscope(path, width=31).width == 31


def test_microscope_defaults_are_the_clis():
    m = scanloc.Microscope()
    assert (m.height, m.width, m.pixel_size_um, m.dwell_us, m.retrace_ms) == (24, 25, 0.07, 2.0, 1.1)
    assert m.stated == [] and scanloc.Microscope({"height": 30}).stated == ["height"]
    assert scanloc.Microscope(m) == m


def _ctrl_c_latency(call, what):
    """Seconds from a Ctrl-C sent 0.5 s into ``call`` to its
    ``KeyboardInterrupt``."""
    pressed = {}

    def press():
        pressed["at"] = time.monotonic()
        _thread.interrupt_main()

    timer = threading.Timer(0.5, press)
    started = time.monotonic()
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            call()
    finally:
        timer.cancel()
    stopped = time.monotonic()
    assert "at" in pressed, f"the {what} ended in {stopped - started:.2f} s, before Ctrl-C"
    latency = stopped - pressed["at"]
    print(f"Ctrl-C latency: {latency:.3f} s")
    return latency


def test_ctrl_c_stops_a_long_locate_within_a_second():
    # Seconds of work on 2 cores: 3,000 frames of 256 × 256 (390 MB).
    base = np.random.default_rng(1).poisson(8, (10, 256, 256)).astype(np.uint16)
    stack = np.tile(base, (300, 1, 1))
    latency = _ctrl_c_latency(lambda: scanloc.locate(stack, 7, progress=False), "locate")
    assert latency < 1.0, latency


def test_ctrl_c_stops_a_long_simulated_recording_within_a_second():
    # About 40 s of work if it ran on: one walk of 3,000 frames of
    # 128 × 128, which cannot be split, so it must stop from within.
    microscope = scanloc.Microscope(height=128, width=128)

    def simulate():
        scanloc.simulate_recording(3000, seed=1, microscope=microscope, qd_density=0.05, progress=False)

    latency = _ctrl_c_latency(simulate, "simulation")
    assert latency < 1.0, latency
