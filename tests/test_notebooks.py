"""Every notebook in notebooks/ runs top to bottom (STYLE.md section 7: no drifting notebooks).

Executed in memory with nbclient on the ``python3`` kernel, which jupyter_client
starts with this interpreter (the venv's), with the repository root as working
directory; the files on disk are left as they are.
"""

from __future__ import annotations

from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
#: Per cell, s.  03_campaign's campaign cell fits the first bar of 4 recordings, each
#: within a 60 CPU s budget, and refits 3 from their neighbours: 397-403 s beside another
#: fit on this 2-core machine (with the campaign's default 600 s budget it ran past a
#: 600 s cell limit and failed CI); a cell
#: that hangs still fails inside the 900 s test timeout.
TIMEOUT_S = 800


def test_there_are_notebooks():
    assert any(p.name == "01_model.ipynb" for p in NOTEBOOKS)


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path: Path, repo_root: Path):
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=TIMEOUT_S,
                                     resources={"metadata": {"path": str(repo_root)}})
    client.execute()  # raises CellExecutionError naming the cell on any exception
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
