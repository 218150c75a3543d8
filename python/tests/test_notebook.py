"""The notebook example (examples/python-tracking.ipynb) runs top to
bottom: simulate → TIFF → locate → link → D, beside TrackPy, with plots."""

import os
import pathlib

import nbformat
from nbclient import NotebookClient

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_the_notebook_runs_top_to_bottom(tmp_path, monkeypatch):
    monkeypatch.setenv("SCANLOC_NOTEBOOK_FRAMES", "120")
    notebook = nbformat.read(ROOT / "examples" / "python-tracking.ipynb", as_version=4)
    NotebookClient(notebook, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "faster than trackpy.batch" in text and "faster than trackpy.link" in text
    assert any("image/png" in o.get("data", {}) for o in outputs), "no figure"
