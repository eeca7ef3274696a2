"""examples/*.ipynb run from a fresh copy of the repository's tracked files, by a Jupyter
kernel (nbclient + ipykernel), cell by cell: a notebook that stops working fails here."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "examples").glob("*.ipynb"))


def _fresh_copy(dest: Path) -> Path:
    """The repository's tracked files (as they are in the working tree) under ``dest``: what a
    fresh clone holds, without run folders, caches or anything else left lying around."""
    try:
        files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, check=True, capture_output=True).stdout.split(b"\0")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: no list of tracked files to copy")
    for f in filter(None, files):
        src = ROOT / f.decode()
        if src.is_file():
            (dest / f.decode()).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / f.decode())
    return dest


@pytest.mark.parametrize("notebook", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_runs_from_a_fresh_copy(tmp_path, monkeypatch, notebook):
    import nbformat
    from nbclient import NotebookClient

    repo = _fresh_copy(tmp_path / "repo")
    nb_path = repo / notebook.relative_to(ROOT)
    # The kernel is this interpreter (ipykernel in this environment), importing the copy.
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(repo), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("JUPYTER_PATH", str(tmp_path / "jupyter"))  # no user kernel spec named python3 in the way
    monkeypatch.setenv("MPLBACKEND", "Agg")
    # The API keeps results it was given no folder for in a temporary one (the user's to read):
    # under the test's own, so that the notebook leaves nothing in /tmp.
    (tmp_path / "tmp").mkdir()
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))
    monkeypatch.delenv("SWARM_NOTEBOOK_DISTRIBUTED", raising=False)
    figures = tmp_path / "figures"
    figures.mkdir()
    monkeypatch.setenv("SWARM_NOTEBOOK_FIGURES", str(figures))
    nb = nbformat.read(nb_path, as_version=4)
    client = NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(nb_path.parent)}})
    t0 = time.monotonic()
    client.execute()
    took = time.monotonic() - t0
    print(f"{notebook.name}: {len(nb.cells)} cells in {took:.1f} s ({sys.executable})")
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    if notebook.name == "quickstart.ipynb":
        # Its figures were drawn, and the objects behind them hold what they should.
        assert {p.name for p in figures.iterdir()} == {"quickstart-errors.png", "quickstart-compare.png"}
        shown = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "execute_result"]
        html = "".join(o["data"].get("text/html", "") for o in shown)
        assert "others_pos_m" in html and "relative.rms.pos_m mean" in html  # res.rms and the comparison table
