"""Shared fixtures: the scanloc command line (built by `cargo build
--release`, which `make test` runs first) and a small registry made by it."""

import os
import pathlib
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


def scanloc_bin() -> pathlib.Path:
    path = pathlib.Path(os.environ.get("SCANLOC_BIN", ROOT / "target" / "release" / "scanloc"))
    if not path.exists():
        raise RuntimeError(f"{path}: no scanloc binary; run `cargo build --release` first (make test does)")
    return path


@pytest.fixture(scope="session")
def cli():
    """Runs `scanloc ARGS...`, failing the test on a non-zero exit."""

    def run(*args, check=True):
        result = subprocess.run([str(scanloc_bin()), *map(str, args)], capture_output=True, text=True)
        if check and result.returncode != 0:
            raise AssertionError(f"scanloc {' '.join(map(str, args))}: exit {result.returncode}: {result.stderr}")
        return result

    return run


@pytest.fixture(scope="session")
def smoke_registry(tmp_path_factory, cli):
    """A registry holding one run of experiments/smoke.yaml (seconds)."""
    folder = tmp_path_factory.mktemp("registry") / "registry"
    cli("run", ROOT / "experiments" / "smoke.yaml", "--registry", folder)
    return folder
