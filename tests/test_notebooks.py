"""Every notebook under notebooks/ executes end to end (small budgets), so none of them rots."""

from __future__ import annotations

from pathlib import Path

import nbclient
import nbformat
import pytest

NOTEBOOKS = sorted((Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


def test_the_notebooks_are_there():
    assert [p.name for p in NOTEBOOKS] == [
        "01_quickstart.ipynb",
        "02_train_ppo.ipynb",
        "03_handcrafted_and_protocol.ipynb",
    ]


@pytest.mark.slow
@pytest.mark.timeout(400)
# The quickstart in the default suite; the others (a training, the protocol) in `pytest -m slow`.
@pytest.mark.parametrize(
    "path",
    [p if p.stem.startswith("01_") else pytest.param(p, marks=pytest.mark.slow) for p in NOTEBOOKS],
    ids=[p.stem for p in NOTEBOOKS],
)
def test_notebook_executes(path, tmp_path):
    notebook = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        notebook, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()  # raises CellExecutionError, naming the cell, when one fails
    errors = [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
