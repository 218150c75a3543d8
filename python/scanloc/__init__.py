"""scanloc from Python: numpy in, pandas out.

Quantum-dot localisation and tracking for point-scanning two-photon
microscopy, a drop-in for TrackPy's ``locate`` / ``batch``, ``link`` and
``emsd``. Every function is a thin call into the scanloc Rust library (the
same code as the ``scanloc`` command line), which releases the GIL while it
works, takes numpy stacks without copying them where the layout allows
(C-ordered uint8, uint16, uint32, float32 or float64), raises ``ValueError``
/ ``FileNotFoundError`` with the command line's message, stops on Ctrl-C
(``KeyboardInterrupt``) within a fraction of a second, and shows progress
with tqdm when it is installed.

``track`` runs the command line's one-command pipeline (``scanloc
track``) on a recording: localisation, linking and a bias-corrected D.

The API, and how each call maps to TrackPy's and to the command line:
docs/python.md.
"""

from __future__ import annotations

import io
import json
import os
import warnings
from typing import Any, Iterable, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import pandas as pd

from . import _scanloc

__all__ = [
    "Microscope",
    "Registry",
    "simulate",
    "simulate_recording",
    "locate",
    "batch",
    "link",
    "diffusion",
    "emsd",
    "score",
    "track",
    "TrackResult",
    "is_zero_copy",
]

__version__ = _scanloc._version()

#: TrackPy's columns of ``locate`` / ``batch``, in its order.
FEATURE_COLUMNS = ["y", "x", "mass", "size", "ecc", "signal", "raw_mass", "ep", "frame"]


def _progress(progress: Optional[bool]) -> bool:
    """Whether to show a tqdm bar: asked for, or by default when tqdm is
    installed."""
    if progress is not None:
        return bool(progress)
    try:
        import tqdm  # noqa: F401
    except ImportError:
        return False
    return True


class Microscope:
    """The microscope: every field of a manifest's ``microscope:`` section
    (the ``scanloc simulate`` flags), with the command line's defaults (the
    paper's microscope).

    ``Microscope()`` is the paper's; ``Microscope(height=64, width=64)``,
    ``Microscope({"height": 64, "brightness": "uniform:5,9"})`` or
    ``Microscope("microscope.yaml")`` (a manifest-style file, as
    ``--microscope FILE.yaml``) set fields; keyword arguments override the
    dict's or the file's. A per-frame parameter (``diffusion_um2_s``,
    ``brightness``, ``background``, ``z_start``) is a number or
    ``"uniform:LOW,HIGH"``; ``emitters`` a count or ``"choice:0,1,2"``.
    Fields read as attributes (``m.height``); ``m.to_dict()`` gives them all.
    """

    def __init__(self, spec: Union[None, Mapping[str, Any], str, os.PathLike, "Microscope"] = None, **fields: Any):
        stated: list = []
        if isinstance(spec, Microscope):
            base = dict(spec._fields)
            stated = list(spec._stated)
        elif spec is None:
            base = None
        elif isinstance(spec, Mapping):
            base = dict(spec)
        elif isinstance(spec, (str, os.PathLike)):
            params, stated = _scanloc._microscope_file(os.fspath(spec))
            base = json.loads(params)
        else:
            raise TypeError(
                f"Microscope: expected a dict, a YAML path or a Microscope, got {type(spec).__name__}"
            )
        section = dict(base or {})
        section.update(fields)
        section = {k: _flag_form(v) for k, v in section.items()}
        if isinstance(spec, (str, os.PathLike)) and not fields:
            self._fields = base
            self._stated = sorted(set(stated))
            return
        params, named = _scanloc._microscope("Microscope", json.dumps({"microscope": section}))
        self._fields = json.loads(params)
        given = set(named) if base is None or isinstance(spec, Mapping) else set(fields)
        self._stated = sorted(set(stated) | given)

    @classmethod
    def from_yaml(cls, path: Union[str, os.PathLike]) -> "Microscope":
        """The ``microscope:`` section of a manifest-style YAML file."""
        return cls(os.fspath(path))

    def to_dict(self) -> dict:
        """Every field and its value."""
        return dict(self._fields)

    @property
    def stated(self) -> list:
        """The fields set explicitly (the others are defaults)."""
        return list(self._stated)

    def validate(self) -> "Microscope":
        """Checks every field as ``scanloc simulate`` does (``ValueError``)."""
        _scanloc._validate_microscope(self._json())
        return self

    def _json(self) -> str:
        return json.dumps(self._fields)

    def __getattr__(self, name: str) -> Any:
        fields = self.__dict__.get("_fields") or {}
        if name in fields:
            return fields[name]
        raise AttributeError(f"Microscope has no field {name!r}")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Microscope) and self._fields == other._fields

    def __repr__(self) -> str:
        fields = self.__dict__.get("_fields") or {}
        shown = ", ".join(f"{k}={v!r}" for k, v in fields.items())
        return f"Microscope({shown})"


def _flag_form(value: Any) -> Any:
    """A field written as on the command line (``"uniform:5,9"``,
    ``"choice:0,1,2/weights:1,1,2"``) in the manifest's form."""
    if not isinstance(value, str):
        return value
    text = value.strip()
    if text.startswith("uniform:"):
        return {"uniform": [float(v) for v in text[len("uniform:"):].split(",")]}
    if text.startswith("choice:"):
        counts, _, weights = text[len("choice:"):].partition("/weights:")
        choice: dict = {"choice": [int(v) for v in counts.split(",")]}
        if weights:
            choice["weights"] = [float(v) for v in weights.split(",")]
        return choice
    return value


def _microscope(microscope: Any) -> Microscope:
    if microscope is None:
        return Microscope()
    if isinstance(microscope, Microscope):
        return microscope
    return Microscope(microscope)


def simulate(frames: int = 100, seed: int = 0, microscope: Any = None, *, progress: Optional[bool] = None) -> Tuple[np.ndarray, pd.DataFrame]:
    """Simulate point-scanning 2PM frames of diffusing QDs (``scanloc
    simulate``): independent frames, frame i depending only on (microscope,
    seed, i).

    Returns ``(frames, truth)``: an ``(n, H, W)`` uint16 array of photon
    counts (uint32 if a count exceeds 65,535), and the ground truth
    DataFrame (frame, x, y, x_start, y_start, x_end, y_end, z_mean,
    diffusion; TrackPy coordinates, pixels).
    """
    m = _microscope(microscope)
    stack, truth = _scanloc._simulate(m._json(), int(frames), int(seed), _progress(progress))
    return stack, pd.read_csv(io.StringIO(truth))


def simulate_recording(
    frames: int = 200,
    seed: int = 0,
    microscope: Any = None,
    *,
    qd_density: float = 0.05,
    qd_count: Optional[int] = None,
    margin_um: float = 1.5,
    half_depth_um: float = 4.0,
    blink_on_ms: Optional[float] = None,
    blink_off_ms: Optional[float] = None,
    dead_time_ms: float = 0.0,
    progress: Optional[bool] = None,
) -> Tuple[np.ndarray, pd.DataFrame]:
    """A continuous recording of QDs diffusing through the field (``scanloc
    simulate-recording``). The microscope gives the scan (height, width,
    pixel_size_um, dwell_us, retrace_ms, sigma_xy_um), sigma_z_um,
    substeps, and fixed brightness, background and diffusion_um2_s.

    Returns ``(frames, truth)``: an ``(n, H, W)`` uint16 array and the truth
    DataFrame (the CLI's ``--truth`` table: one row per QD and frame with
    its id ``qd``, positions and times). ``truth.attrs["qds"]`` is the
    number of QDs in the volume.
    """
    m = _microscope(microscope)
    stack, truth, qds = _scanloc._simulate_recording(
        m._json(), int(frames), int(seed), float(qd_density),
        None if qd_count is None else int(qd_count), float(margin_um), float(half_depth_um),
        None if blink_on_ms is None else float(blink_on_ms),
        None if blink_off_ms is None else float(blink_off_ms),
        float(dead_time_ms), _progress(progress),
    )
    table = pd.read_csv(io.StringIO(truth))
    table.attrs["qds"] = qds
    return stack, table


def is_zero_copy(frames: Any) -> bool:
    """Whether ``locate(frames)`` (crocker-grier) reads the array in place:
    a C-ordered ``(n, H, W)`` (or ``(H, W)``) array of uint8, uint16,
    uint32, float32 or float64. Other layouts are copied once, in C order."""
    array = _as_stack(frames, copy_ok=False)
    return array is not None and _scanloc._is_zero_copy(array)


_DTYPES = (np.uint8, np.uint16, np.uint32, np.float32, np.float64)


def _as_stack(frames: Any, copy_ok: bool = True) -> Optional[np.ndarray]:
    """``frames`` as a 3-D array of a dtype the library takes, without a
    copy where it already is one (a 2-D frame becomes a stack of one, a
    view)."""
    array = np.asarray(frames)
    if array.ndim == 2:
        array = array[np.newaxis]
    if array.ndim != 3:
        raise ValueError(f"frames: expected an array of shape (n, H, W) or (H, W), got shape {array.shape}")
    if array.dtype.byteorder not in ("=", "|", "<" if np.little_endian else ">"):
        if not copy_ok:
            return None
        array = array.astype(array.dtype.newbyteorder("="))
    if array.dtype not in _DTYPES:
        if not copy_ok:
            return None
        if array.dtype == np.bool_ or np.issubdtype(array.dtype, np.integer):
            if array.size and array.min() < 0:
                raise ValueError(
                    f"frames: dtype {array.dtype} with negative values; give uint8, uint16, uint32, float32 or float64"
                )
            if array.size and int(array.max()) > np.iinfo(np.uint32).max:
                raise ValueError(f"frames: dtype {array.dtype} with values above 2³²−1")
            array = array.astype(np.uint32)
        elif np.issubdtype(array.dtype, np.floating):
            array = array.astype(np.float64)
        else:
            raise ValueError(
                f"frames: expected an array of uint8, uint16, uint32, float32 or float64, got dtype {array.dtype}"
            )
    return array


def locate(
    frames: Any,
    diameter: int = 7,
    minmass: Optional[float] = None,
    maxsize: Optional[float] = None,
    separation: Optional[float] = None,
    noise_size: float = 1.0,
    smoothing_size: Optional[int] = None,
    threshold: Optional[float] = None,
    invert: bool = False,
    percentile: float = 64.0,
    topn: Optional[int] = None,
    preprocess: bool = True,
    max_iterations: int = 10,
    *,
    method: str = "crocker-grier",
    model: Any = None,
    registry: Union[str, os.PathLike] = "registry",
    microscope: Any = None,
    particles: int = 20_000,
    score_radius_px: float = 1.0,
    seed: int = 0,
    max_candidates: Optional[int] = None,
    candidate_radius_px: Optional[float] = None,
    progress: Optional[bool] = None,
) -> pd.DataFrame:
    """Locate QDs in every frame of ``frames`` (``(n, H, W)`` or one
    ``(H, W)`` frame), as ``scanloc locate``.

    ``method="crocker-grier"`` (default) is TrackPy 0.7's ``locate`` with
    its parameters and defaults (``diameter`` 7 here), run on every frame as
    ``trackpy.batch``: columns ``y, x, mass, size, ecc, signal, raw_mass,
    ep, frame``, rows by frame then descending mass. Integer frames are
    rescaled to their dtype's range and float frames to 0–255 to find the
    peaks, as TrackPy does, so the features are TrackPy's for any dtype.
    ``minmass=None`` is TrackPy's default (no minimum, its 0).

    ``method="cnn", model=...``: a model folder (written by ``scanloc
    train``) or a model of ``registry`` named ``RUN:DETECTOR`` or by content
    key; columns frame, x, y, sigma_x, sigma_y, score (and candidate for a
    categorical model). ``method="likelihood"``: the particle filter under
    ``microscope`` (columns frame, x, y, score). Both need photon counts.
    """
    stack = _as_stack(frames)
    show = _progress(progress)
    if invert:
        raise ValueError("invert: not supported (scanloc's frames are photon counts: bright QDs on a dark background)")
    if method == "crocker-grier":
        for name, value in (("model", model), ("microscope", microscope)):
            if value is not None:
                raise ValueError(f"{name}: not a parameter of method='crocker-grier'")
        columns = _scanloc._locate_crocker_grier(
            stack, int(diameter), _opt_float(minmass), _opt_float(maxsize), _opt_float(separation),
            float(noise_size), None if smoothing_size is None else int(smoothing_size),
            _opt_float(threshold), float(percentile), None if topn is None else int(topn),
            bool(preprocess), int(max_iterations), show,
        )
        return pd.DataFrame(columns, columns=FEATURE_COLUMNS)
    if method == "cnn":
        if model is None:
            raise ValueError("model: required with method='cnn' (a model folder or a registry RUN:DETECTOR)")
        reference = os.fspath(model) if isinstance(model, os.PathLike) else str(model)
        columns, origin = _scanloc._locate_cnn(
            stack, reference, os.fspath(registry), max_candidates, _opt_float(candidate_radius_px), show
        )
        table = pd.DataFrame(columns)
        table.attrs["model"] = origin
        return table
    if method == "likelihood":
        m = _microscope(microscope)
        columns = _scanloc._locate_likelihood(
            stack, m._json(), m.stated, int(particles), float(score_radius_px), int(seed),
            max_candidates, _opt_float(candidate_radius_px), show,
        )
        return pd.DataFrame(columns)
    raise ValueError(f"method: expected 'crocker-grier', 'cnn' or 'likelihood', got {method!r}")


def batch(frames: Any, diameter: int = 7, **kwargs: Any) -> pd.DataFrame:
    """``trackpy.batch``: :func:`locate` over every frame of a stack."""
    return locate(frames, diameter, **kwargs)


def _opt_float(value: Any) -> Optional[float]:
    return None if value is None else float(value)


def _column(table: pd.DataFrame, name: str, what: str) -> pd.Series:
    if name not in table.columns:
        raise ValueError(f"{what}: no column {name!r} (columns: {', '.join(map(str, table.columns))})")
    return table[name]


def _frames_column(table: pd.DataFrame, what: str, name: str = "frame") -> np.ndarray:
    column = _column(table, name, what)
    values = column.to_numpy()
    if not np.issubdtype(values.dtype, np.integer):
        as_float = np.asarray(values, dtype=np.float64)
        bad = ~np.isfinite(as_float) | (np.floor(as_float) != as_float)
        if bad.any():
            row = int(np.argmax(bad))
            raise ValueError(f"{what}: row {row}: column {name}: expected a whole frame index, got {values[row]}")
        values = as_float
    return np.ascontiguousarray(values, dtype=np.int64)


def _coordinate(table: pd.DataFrame, name: str, what: str) -> np.ndarray:
    return np.ascontiguousarray(_column(table, name, what).to_numpy(), dtype=np.float64)


def link(
    f: pd.DataFrame,
    search_range: Optional[float] = None,
    memory: Optional[int] = None,
    *,
    linker: str = "trackpy",
    max_gap: Optional[int] = None,
    diffusion: Optional[float] = None,
    frame_time_ms: Optional[float] = None,
    pixel_size_um: Optional[float] = None,
    gate: Optional[float] = None,
    t_column: str = "frame",
    pos_columns: Sequence[str] = ("x", "y"),
    progress: Optional[bool] = None,
) -> pd.DataFrame:
    """Link localisations into trajectories (``scanloc link``): ``f`` with
    a column ``particle`` added (a copy; the index kept).

    ``linker="trackpy"`` is TrackPy 0.7's ``link(f, search_range,
    memory)``: the same trajectories. ``linker="lap"`` links by a
    linear assignment with gap closing up to ``max_gap`` frames (2), from
    ``search_range`` or from ``diffusion`` (µm²/s) with ``frame_time_ms``
    and ``pixel_size_um``, gated at ``gate`` σ; it adds ``gate_x``,
    ``gate_y`` (docs/tracking.md). ``sigma_x``/``sigma_y`` columns, if
    present, are the localisations' errors.
    """
    what = "features"
    if len(pos_columns) != 2:
        raise ValueError("pos_columns: scanloc links in 2-D: give the x and y columns")
    x_name, y_name = pos_columns
    frame = _frames_column(f, what, t_column)
    x = _coordinate(f, x_name, what)
    y = _coordinate(f, y_name, what)
    sigma_x = sigma_y = None
    if "sigma_x" in f.columns and "sigma_y" in f.columns:
        sigma_x = _coordinate(f, "sigma_x", what)
        sigma_y = _coordinate(f, "sigma_y", what)
    particle, gates = _scanloc._link(
        frame, x, y, sigma_x, sigma_y, linker, _opt_float(search_range),
        None if memory is None else int(memory), None if max_gap is None else int(max_gap),
        _opt_float(diffusion), _opt_float(frame_time_ms), _opt_float(pixel_size_um), _opt_float(gate),
        _progress(progress) and len(f) > 100_000,
    )
    out = f.copy()
    out["particle"] = particle
    if gates is not None:
        for name, values in gates.items():
            out[name] = values
    return out


def _tracks_csv(tracks: pd.DataFrame) -> str:
    """A tracks DataFrame as the CLI's tracks table (frame, x, y, particle
    and the optional sigma_x, sigma_y, time, gate_x, gate_y)."""
    what = "tracks"
    columns = ["frame", "x", "y", "particle"]
    for name in columns:
        _column(tracks, name, what)
    extra = [c for c in ("sigma_x", "sigma_y", "time", "gate_x", "gate_y") if c in tracks.columns]
    table = tracks[columns + extra].copy()
    table["frame"] = _frames_column(tracks, what)
    return table.to_csv(index=False, float_format="%.17g")


def diffusion(
    tracks: pd.DataFrame,
    microscope: Any = None,
    estimator: Optional[str] = None,
    *,
    dead_time_ms: float = 0.0,
    exposure: str = "auto",
    min_points: int = 3,
    detection_profile: bool = True,
    ensemble_gate: float = 2.0 / 3.0,
    ensemble_margin_px: float = 0.0,
    given_sigma: bool = False,
) -> Tuple[pd.DataFrame, pd.DataFrame]:
    """D per track and for the ensemble (``scanloc diffusion``), by the
    scan-aware estimators ``"ml"``, ``"cve"`` and ``"msd"`` (all three, or
    the one ``estimator`` names), on the scan of ``microscope`` (its
    height, width, pixel_size_um, dwell_us, retrace_ms, sigma_xy_um) and
    ``dead_time_ms``.

    Returns ``(per_track, ensemble)``: DataFrames with columns particle,
    points, method, d_um2_s, standard_error, low_95, high_95,
    localisation_variance_um2, interval_valid (the CLI's table).
    """
    m = _microscope(microscope)
    if estimator is not None and estimator not in ("ml", "cve", "msd"):
        raise ValueError(f"estimator: expected 'ml', 'cve' or 'msd', got {estimator!r}")
    per_track, ensemble, notes = _scanloc._diffusion(
        _tracks_csv(tracks), m._json(), float(dead_time_ms), exposure, int(min_points),
        bool(detection_profile), float(ensemble_gate), float(ensemble_margin_px), bool(given_sigma),
    )
    for note in notes:
        warnings.warn(note, stacklevel=2)
    tables = []
    for text in (per_track, ensemble):
        table = pd.read_csv(io.StringIO(text), dtype={"particle": str})
        if estimator is not None:
            table = table[table["method"] == estimator].reset_index(drop=True)
        tables.append(table)
    tables[0]["particle"] = pd.to_numeric(tables[0]["particle"])
    return tables[0], tables[1]


def _msd_n(n: int, t: np.ndarray) -> np.ndarray:
    """TrackPy's effective number of independent measurements of the MSD
    at lags ``t`` of a track ``n`` frames long (Qian et al. 1991)."""
    t = np.asarray(t, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(
            t > n / 2,
            1 / (1 + ((n - t) ** 3 + 5 * t - 4 * (n - t) ** 2 * t - n) / (6 * (n - t) * t ** 2)),
            6 * (n - t) ** 2 * t / (2 * n - t + 4 * n * t ** 2 - 5 * t ** 3),
        )


def emsd(traj: pd.DataFrame, mpp: float, fps: float, max_lagtime: int = 100, detail: bool = False, pos_columns: Optional[Sequence[str]] = None) -> Union[pd.Series, pd.DataFrame]:
    """The ensemble mean squared displacement, TrackPy's ``emsd`` (same
    signature, same numbers): each particle's MSD at lags 1 …
    ``max_lagtime`` frames (gaps left out), averaged over the particles
    weighted by their effective numbers of independent measurements;
    ``mpp`` µm per pixel, ``fps`` frames per second. A Series ``msd`` (µm²)
    indexed by ``lagt`` (s), or with ``detail=True`` a DataFrame with
    ``<x>, <y>, <x^2>, <y^2>, msd, N, lagt``. The MSD is not scan-aware:
    :func:`diffusion` gives D.
    """
    pos = list(pos_columns) if pos_columns is not None else ["x", "y"]
    what = "traj"
    frame = _frames_column(traj, what)
    particle = _column(traj, "particle", what).to_numpy()
    coords = np.stack([np.asarray(_column(traj, c, what).to_numpy(), dtype=np.float64) for c in pos], axis=1) * float(mpp)
    order = np.lexsort((frame, particle))
    frame, particle, coords = frame[order], particle[order], coords[order]
    lags_all = np.arange(1, int(max_lagtime) + 1)
    width = 2 * len(pos)
    # Per lag: TrackPy's weighted mean over the particles that reach it,
    # mean(stat · N) / mean(N), each mean over its non-missing values.
    sums = np.zeros((len(lags_all), width + 1))
    present = np.zeros((len(lags_all), width + 1))
    n_sum = np.zeros(len(lags_all))
    n_count = np.zeros(len(lags_all))
    starts = np.flatnonzero(np.r_[True, particle[1:] != particle[:-1], True])
    for a, b in zip(starts[:-1], starts[1:]):
        fr = frame[a:b]
        length = int(fr[-1] - fr[0]) + 1
        lags = lags_all[: max(0, min(int(max_lagtime), length - 1))]
        if len(lags) == 0:
            continue
        filled = np.full((length, len(pos)), np.nan)
        filled[fr - fr[0]] = coords[a:b]
        stats = np.empty((len(lags), width + 1))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            for i, lag in enumerate(lags):
                diff = filled[lag:] - filled[:-lag]
                stats[i, : len(pos)] = np.nanmean(diff, axis=0)
                stats[i, len(pos) : width] = np.nanmean(diff ** 2, axis=0)
        msd = stats[:, len(pos) : width].sum(axis=1)
        n = _msd_n(length, lags) * (b - a) / length
        if length != b - a:
            # Gaps: no weight where the MSD is undefined, the total kept.
            desired = n.sum()
            n = np.where(np.isnan(msd), 0.0, n)
            if n.sum() != desired:
                n = n * desired / n.sum()
        stats[:, width] = np.where(np.isnan(msd), 0.0, msd)
        k = len(lags)
        weighted = stats * n[:, None]
        ok = ~np.isnan(weighted)
        sums[:k] += np.where(ok, weighted, 0.0)
        present[:k] += ok
        n_sum[:k] += n
        n_count[:k] += 1
    valid = n_count > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        means = (sums[valid] / present[valid]) / (n_sum[valid] / n_count[valid])[:, None]
    names = [f"<{c}>" for c in pos] + [f"<{c}^2>" for c in pos] + ["msd"]
    lags = lags_all[valid]
    result = pd.DataFrame(means, columns=names, index=pd.Index(lags, name="frame"))
    result["N"] = n_sum[valid]
    result["lagt"] = lags / float(fps)
    if not detail:
        return result.set_index("lagt")["msd"]
    return result


class TrackResult:
    """What :func:`track` returns: the outputs of ``scanloc track``.

    - ``tracks``: DataFrame, tracks.csv (frame, x, y, gate_x, gate_y, …,
      particle: TrackPy's columns);
    - ``diffusion``: DataFrame, diffusion.csv (one ``ml`` row per track
      with a D of its own, then ``ensemble`` as read and, with the bias
      correction, ``ensemble-corrected``; columns particle, points, method,
      d_um2_s, standard_error, low_95, high_95, localisation_variance_um2,
      interval_valid);
    - ``ensemble``: dict, the ensemble D to report (corrected where there
      is a correction) as ``--json`` prints it: d_um2_s, standard_error,
      low_95, high_95 (``None`` for an unbounded interval), steps,
      interval_valid, plus bias_corrected and warnings (empty when the D
      can be trusted); ``{}`` with a warning when there is none;
    - ``settings``: dict, settings.json (every setting chosen or given);
    - ``summary``: dict, the whole ``--json`` summary (counts of frames,
      localisations, linked, tracks; the uncorrected ensemble).
    """

    def __init__(self, tracks: pd.DataFrame, diffusion: pd.DataFrame, settings: dict, summary: dict):
        self.tracks = tracks
        self.diffusion = diffusion
        self.settings = settings
        self.summary = summary
        self.ensemble = dict(summary.get("ensemble") or {})
        self.ensemble["bias_corrected"] = summary["bias_corrected"]
        self.ensemble["warnings"] = list(summary["warnings"])

    def __repr__(self) -> str:
        d = self.ensemble.get("d_um2_s")
        shown = "no ensemble D" if d is None else f"D = {d:.4g} µm²/s ± {self.ensemble['standard_error']:.2g}"
        return (
            f"TrackResult({self.summary['frames']} frames, {len(self.tracks)} localisations in "
            f"{self.summary['tracks']} tracks, {shown}{', bias-corrected' if self.ensemble['bias_corrected'] else ''})"
        )


def track(
    recording: Any,
    microscope: Any,
    *,
    method: str = "crocker-grier",
    diameter: Optional[int] = None,
    min_score: Optional[float] = None,
    search_range: Optional[float] = None,
    max_gap: Optional[int] = None,
    ensemble_margin_px: Optional[float] = None,
    max_diffusion: Optional[float] = None,
    min_points: Optional[int] = None,
    bias_correction: bool = True,
    bias_recordings: Optional[int] = None,
    dead_time_ms: Optional[float] = None,
    seed: Optional[int] = None,
    progress: Optional[bool] = None,
) -> TrackResult:
    """Localise, link and read D from a recording in one call: ``scanloc
    track REC --microscope scope.yaml`` (the same library function, the
    same numbers), returning its outputs instead of writing them
    (:class:`TrackResult`: ``tracks``, ``diffusion``, ``ensemble``,
    ``settings``). Nothing is written anywhere.

    ``recording`` is a path (``.npy`` or TIFF, read as the command reads
    it) or an array ``(n, H, W)`` of photon counts (uint8, uint16, uint32,
    or whole float values ≥ 0; copied once into uint32 counts, as the
    command reads a file). ``microscope`` is a :class:`Microscope`, a dict
    or a YAML path, and must state ``height``, ``width``,
    ``pixel_size_um``, ``dwell_us`` and ``retrace_ms``; its PSF,
    brightness and background make the simulations that choose the
    settings.

    The keywords are the command's flags, ``None`` their defaults (chosen
    by simulation of the microscope, recorded in ``settings``):
    ``diameter`` (odd, px; from the PSF), ``min_score`` (the mass to link
    at; the F1-best on a simulated recording), ``search_range`` (px),
    ``max_gap`` (2), ``ensemble_margin_px`` (σxy in px),
    ``max_diffusion`` (3 µm²/s), ``min_points`` (3),
    ``bias_correction`` (``--no-bias-correction`` is ``False``),
    ``bias_recordings`` (2), ``dead_time_ms`` (0), ``seed`` (20261207).
    Bad input raises ``ValueError`` (a missing file ``FileNotFoundError``)
    with the command's message; Ctrl-C raises ``KeyboardInterrupt`` at the
    next phase or stack of frames located; ``progress`` shows one tqdm bar.
    """
    m = _microscope(microscope)
    if isinstance(recording, (str, os.PathLike)):
        source: Any = os.fspath(recording)
    else:
        array = np.asarray(recording)
        if array.ndim not in (2, 3):
            raise ValueError(f"recording: expected shape (n, H, W) or (H, W), got {list(array.shape)}")
        source = _as_stack(array)
    tracks, diffusion_csv, settings, summary = _scanloc._track(
        source, m._json(), m.stated, str(method),
        None if diameter is None else int(diameter), _opt_float(min_score), _opt_float(search_range),
        None if max_gap is None else int(max_gap), _opt_float(ensemble_margin_px), _opt_float(max_diffusion),
        None if min_points is None else int(min_points), bool(bias_correction),
        None if bias_recordings is None else int(bias_recordings), _opt_float(dead_time_ms),
        None if seed is None else int(seed), _progress(progress),
    )
    diffusion_table = pd.read_csv(io.StringIO(diffusion_csv), dtype={"particle": str})
    return TrackResult(
        pd.read_csv(io.StringIO(tracks)),
        diffusion_table,
        json.loads(settings),
        json.loads(summary),
    )


def score(truth: pd.DataFrame, predictions: pd.DataFrame, eps: Iterable[float] = (1, 2, 3), frames: Optional[int] = None) -> pd.DataFrame:
    """The paper's precision–recall AUC of ``predictions`` (frame, x, y and
    a ``score`` column, or TrackPy's ``mass``) against ``truth`` (frame, x,
    y) at each matching radius in ``eps`` (pixels), as ``scanloc score``:
    one row per radius with eps_px, auc, true_positives, false_positives
    and the other figures of the CLI's JSON. ``frames`` is the size of the
    test set (default, as the CLI's: one past the last frame of the truth).
    """
    what = "predictions"
    if "score" not in predictions.columns:
        if "mass" not in predictions.columns:
            raise ValueError("predictions: no column 'score' (nor TrackPy's 'mass' to score by)")
        predictions = predictions.assign(score=predictions["mass"])
    p = pd.DataFrame({
        "frame": _frames_column(predictions, what),
        "x": _coordinate(predictions, "x", what),
        "y": _coordinate(predictions, "y", what),
        "score": _coordinate(predictions, "score", what),
    })
    t = pd.DataFrame({
        "frame": _frames_column(truth, "truth"),
        "x": _coordinate(truth, "x", "truth"),
        "y": _coordinate(truth, "y", "truth"),
    })
    if frames is None:
        frames = int(t["frame"].max()) + 1 if len(t) else 0
    result = json.loads(_scanloc._score(t.to_csv(index=False, float_format="%.17g"), p.to_csv(index=False, float_format="%.17g"), int(frames), [float(e) for e in eps]))
    rows = []
    for entry in result["per_eps"]:
        rows.append({k: v for k, v in entry.items() if not isinstance(v, (list, dict))})
    table = pd.DataFrame(rows)
    table.attrs.update({k: v for k, v in result.items() if not isinstance(v, (list, dict))})
    return table


class Registry:
    """A scanloc registry (``registry/`` of ``scanloc run``), read-only.

    ``runs()`` lists the runs (as ``scanloc registry runs``), ``run(id)``
    gives a run's record, ``auc(id)`` its AUC table, ``artefact(key)`` an
    artefact's contents by content key (frames as an array, predictions
    and truth as DataFrames, scores as dicts), ``verify()`` checks every
    blob (as ``scanloc registry verify``).
    """

    def __init__(self, path: Union[str, os.PathLike] = "registry"):
        self.path = os.fspath(path)
        if not os.path.isdir(self.path):
            raise FileNotFoundError(f"registry {self.path}: no such folder")

    def runs(self) -> pd.DataFrame:
        """Every run, newest first."""
        return pd.DataFrame(json.loads(_scanloc._registry_runs(self.path)))

    def run(self, run_id: str) -> dict:
        """A run's record (a run id or a unique prefix)."""
        return json.loads(_scanloc._registry_run(self.path, run_id))

    def auc(self, run_id: str) -> pd.DataFrame:
        """A run's AUC table: detector, dataset, diffusion, eps_px, auc, …"""
        return pd.DataFrame(self.run(run_id).get("auc", []))

    def steps(self, run_id: str) -> pd.DataFrame:
        """A run's steps with their content keys."""
        return pd.DataFrame(self.run(run_id).get("steps", []))

    def artefact(self, key: str) -> dict:
        """An artefact by content key (or unique prefix): ``{"record": …,
        role: contents}`` with ``frames.npy`` an array, ``*.csv`` a
        DataFrame, ``*.json`` a dict and ``model.bin`` bytes."""
        record, blobs = _scanloc._registry_artefact(self.path, key)
        out: dict = {"record": json.loads(record)}
        for role, data in blobs:
            if role.endswith(".npy"):
                out[role] = np.load(io.BytesIO(data), allow_pickle=False)
            elif role.endswith(".csv"):
                out[role] = pd.read_csv(io.BytesIO(data))
            elif role.endswith(".json"):
                out[role] = json.loads(data)
            else:
                out[role] = data
        return out

    def verify(self) -> dict:
        """Checks every blob's hash; the report (``bad`` lists the damaged)."""
        return json.loads(_scanloc._registry_verify(self.path))

    def __repr__(self) -> str:
        return f"Registry({self.path!r})"
