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


def test_every_notebook_is_listed_in_the_docs():
    listed = (ROOT / "docs" / "notebooks.md").read_text(encoding="utf-8")
    assert {"quickstart", "reflectance_map", "integrability", "torch_modules"} <= {p.stem for p in NOTEBOOKS}
    assert [p.name for p in NOTEBOOKS if f"`{p.name}`" not in listed] == []
