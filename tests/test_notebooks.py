"""The notebooks run from top to bottom (at the smoke size) and draw their figures."""
import os
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")   # in the test extras; importorskip names it
from nbclient import NotebookClient            # noqa: E402

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


@pytest.fixture(scope="module")
def smoke_out(tmp_path_factory):
    """One output directory for all notebooks: 03 reuses the workloads 02 recorded."""
    return tmp_path_factory.mktemp("notebooks")


@pytest.mark.parametrize("name", ["01_image_comparison.ipynb", "02_speedup.ipynb",
                                  "03_hwsim.ipynb"])
def test_notebook_runs_and_draws(name, smoke_out, monkeypatch):
    monkeypatch.setenv("PARTPM_NOTEBOOK_SIZE", "smoke")
    monkeypatch.setenv("PARTPM_NOTEBOOK_OUT", str(smoke_out))
    if os.environ.get("PARTPM_DATA"):    # the kernel runs in notebooks/: make it absolute
        monkeypatch.setenv("PARTPM_DATA", str(Path(os.environ["PARTPM_DATA"]).resolve()))
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    for cell in notebook.cells:          # run what is committed, not its stored outputs
        if cell.cell_type == "code":
            cell.outputs = []
    client = NotebookClient(notebook, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(NOTEBOOKS)}})
    client.execute()                     # raises CellExecutionError with the cell's traceback
    outputs = [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if {"image/png", "image/jpeg"} & set(o.get("data", {}))]
    assert images, f"{name} drew no figure"
    text = "".join(o.get("text", "") for o in outputs)
    assert "size: smoke" in text
