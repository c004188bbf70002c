"""The notebooks are documentation: they must run from top to bottom."""
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path):
    notebook = nbformat.read(path, as_version=4)
    NotebookClient(notebook, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for cell in notebook.cells for o in cell.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    images = [o for cell in notebook.cells for o in cell.get("outputs", []) if "image/png" in o.get("data", {})]
    assert images, "the notebook should draw its figures"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_stored_without_outputs(path):
    # docs/notebooks.md: stored without outputs (small diffs, no stale figures); the tests run them
    notebook = nbformat.read(path, as_version=4)
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert code, "a notebook without code cells"
    assert [i for i, cell in enumerate(code) if cell.get("outputs")] == [], "cells with stored outputs"
    assert [i for i, cell in enumerate(code) if cell.get("execution_count") is not None] == [], "stored execution counts"


def test_every_notebook_is_listed_in_the_docs():
    listed = (ROOT / "docs" / "notebooks.md").read_text(encoding="utf-8")
    assert {"quickstart", "estimate", "reflectance_map", "integrability", "torch_modules", "features",
            "geometry_db"} <= {p.stem for p in NOTEBOOKS}
    assert [p.name for p in NOTEBOOKS if f"`{p.name}`" not in listed] == []
