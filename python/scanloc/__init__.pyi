"""Type stubs of the scanloc package (docs/python.md)."""

import os
from typing import Any, Iterable, Mapping, Optional, Sequence, Tuple, Union

import numpy as np
import pandas as pd

__version__: str
FEATURE_COLUMNS: list[str]

MicroscopeSpec = Union[None, Mapping[str, Any], str, os.PathLike, "Microscope"]

class Microscope:
    height: int
    width: int
    pixel_size_um: float
    dwell_us: float
    retrace_ms: float
    sigma_xy_um: float
    sigma_z_um: float
    background: Any
    brightness: Any
    diffusion_um2_s: Any
    z_start: Any
    margin_px: float
    substeps: int
    emitters: Any
    detector_noise: Any
    psf_cutoff_sigma: Optional[float]
    def __init__(self, spec: MicroscopeSpec = ..., **fields: Any) -> None: ...
    @classmethod
    def from_yaml(cls, path: Union[str, os.PathLike]) -> "Microscope": ...
    def to_dict(self) -> dict: ...
    @property
    def stated(self) -> list[str]: ...
    def validate(self) -> "Microscope": ...

def simulate(frames: int = ..., seed: int = ..., microscope: MicroscopeSpec = ..., *, progress: Optional[bool] = ...) -> Tuple[np.ndarray, pd.DataFrame]: ...
def simulate_recording(
    frames: int = ...,
    seed: int = ...,
    microscope: MicroscopeSpec = ...,
    *,
    qd_density: float = ...,
    qd_count: Optional[int] = ...,
    margin_um: float = ...,
    half_depth_um: float = ...,
    blink_on_ms: Optional[float] = ...,
    blink_off_ms: Optional[float] = ...,
    dead_time_ms: float = ...,
    progress: Optional[bool] = ...,
) -> Tuple[np.ndarray, pd.DataFrame]: ...
def is_zero_copy(frames: Any) -> bool: ...
def locate(
    frames: Any,
    diameter: int = ...,
    minmass: Optional[float] = ...,
    maxsize: Optional[float] = ...,
    separation: Optional[float] = ...,
    noise_size: float = ...,
    smoothing_size: Optional[int] = ...,
    threshold: Optional[float] = ...,
    invert: bool = ...,
    percentile: float = ...,
    topn: Optional[int] = ...,
    preprocess: bool = ...,
    max_iterations: int = ...,
    *,
    method: str = ...,
    model: Any = ...,
    registry: Union[str, os.PathLike] = ...,
    microscope: MicroscopeSpec = ...,
    particles: int = ...,
    score_radius_px: float = ...,
    seed: int = ...,
    max_candidates: Optional[int] = ...,
    candidate_radius_px: Optional[float] = ...,
    progress: Optional[bool] = ...,
) -> pd.DataFrame: ...
def batch(frames: Any, diameter: int = ..., **kwargs: Any) -> pd.DataFrame: ...
def link(
    f: pd.DataFrame,
    search_range: Optional[float] = ...,
    memory: Optional[int] = ...,
    *,
    linker: str = ...,
    max_gap: Optional[int] = ...,
    diffusion: Optional[float] = ...,
    frame_time_ms: Optional[float] = ...,
    pixel_size_um: Optional[float] = ...,
    gate: Optional[float] = ...,
    t_column: str = ...,
    pos_columns: Sequence[str] = ...,
    progress: Optional[bool] = ...,
) -> pd.DataFrame: ...
def diffusion(
    tracks: pd.DataFrame,
    microscope: MicroscopeSpec = ...,
    estimator: Optional[str] = ...,
    *,
    dead_time_ms: float = ...,
    exposure: str = ...,
    min_points: int = ...,
    detection_profile: bool = ...,
    ensemble_gate: float = ...,
    ensemble_margin_px: float = ...,
    given_sigma: bool = ...,
) -> Tuple[pd.DataFrame, pd.DataFrame]: ...
def emsd(traj: pd.DataFrame, mpp: float, fps: float, max_lagtime: int = ..., detail: bool = ..., pos_columns: Optional[Sequence[str]] = ...) -> Union[pd.Series, pd.DataFrame]: ...
class TrackResult:
    """The outputs of ``scanloc track``: tracks, diffusion, ensemble, settings, summary."""
    tracks: pd.DataFrame
    diffusion: pd.DataFrame
    ensemble: dict
    settings: dict
    summary: dict

def track(
    recording: Union[str, os.PathLike, np.ndarray],
    microscope: MicroscopeSpec,
    *,
    method: str = ...,
    diameter: Optional[int] = ...,
    min_score: Optional[float] = ...,
    search_range: Optional[float] = ...,
    max_gap: Optional[int] = ...,
    ensemble_margin_px: Optional[float] = ...,
    max_diffusion: Optional[float] = ...,
    min_points: Optional[int] = ...,
    bias_correction: bool = ...,
    bias_recordings: Optional[int] = ...,
    dead_time_ms: Optional[float] = ...,
    seed: Optional[int] = ...,
    progress: Optional[bool] = ...,
) -> TrackResult:
    """Localise, link and read D from a recording (``scanloc track``)."""
    ...
def score(truth: pd.DataFrame, predictions: pd.DataFrame, eps: Iterable[float] = ..., frames: Optional[int] = ...) -> pd.DataFrame: ...

class Registry:
    path: str
    def __init__(self, path: Union[str, os.PathLike] = ...) -> None: ...
    def runs(self) -> pd.DataFrame: ...
    def run(self, run_id: str) -> dict: ...
    def auc(self, run_id: str) -> pd.DataFrame: ...
    def steps(self, run_id: str) -> pd.DataFrame: ...
    def artefact(self, key: str) -> dict: ...
    def verify(self) -> dict: ...
