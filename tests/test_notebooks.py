"""The notebooks: committed with the outputs of one run each (`python notebooks/regenerate.py`),
and executed here on tiny settings (nbclient, kernel python3) into temporary copies.

The quickstart runs on the session's trained `workflow.train_and_evaluate` run (conftest
`learned_run`), found as an `irdepth quickstart` run; the ablations notebook reads the committed
results in experiments/results/.
"""

from __future__ import annotations

import os

import nbformat
import pytest
from nbclient import NotebookClient
from trained_runs import copy_run

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOKS = os.path.join(REPO, "notebooks")


NOTEBOOK_BYTES = 1_500_000
"""Most bytes the committed notebooks may take together (their PNGs at modest dpi)."""


def execute(name: str, out_dir, cwd: str = NOTEBOOKS) -> nbformat.NotebookNode:
    """Runs notebooks/<name> in a python3 kernel (in `cwd`), writes the executed copy to
    `out_dir` and returns it; a failing cell raises with its traceback."""
    nb = nbformat.read(os.path.join(NOTEBOOKS, name), as_version=4)
    client = NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(cwd)}})
    client.execute()
    nbformat.write(nb, os.path.join(str(out_dir), name))
    return nb


def images(nb) -> int:
    return sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code"
               for o in c.get("outputs", []))


def text(nb) -> str:
    return "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                   for o in c.get("outputs", []))


@pytest.mark.parametrize("name", ["quickstart.ipynb", "ablations.ipynb"])
def test_committed_with_the_outputs_of_one_run(name):
    """Every code cell ran once, top to bottom (execution counts 1, 2, ...), without an error;
    the figures are there; no machine path in the outputs."""
    nb = nbformat.read(os.path.join(NOTEBOOKS, name), as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert [c.execution_count for c in code] == list(range(1, len(code) + 1))
    assert not any(o.output_type == "error" for c in code for o in c.outputs)
    assert any("parameters" in c.metadata.get("tags", []) for c in code)
    assert images(nb) >= 3
    out = text(nb)
    assert "/tmp/" not in out and "/home/" not in out and "/work/" not in out
    if name == "quickstart.ipynb":  # of an `irdepth quickstart` run, not a QUICK plumbing run
        assert "run: ../irdepth_quickstart | stage: stage2 | preset: tiny" in out


def test_committed_notebooks_are_modest():
    total = sum(os.path.getsize(os.path.join(NOTEBOOKS, n)) for n in os.listdir(NOTEBOOKS)
                if n.endswith(".ipynb"))
    assert total < NOTEBOOK_BYTES, f"{total} bytes"


def test_quickstart_runs(learned_run, monkeypatch, tmp_path):
    """On a copy of the session's `workflow.train_and_evaluate` run (what `irdepth quickstart`
    runs) in irdepth_quickstart/ beside it: the notebook finds and reuses it (its training
    branch is that same call)."""
    monkeypatch.setenv("IRDEPTH_NB_PRESET", "tiny")
    monkeypatch.setenv("IRDEPTH_NB_QUICK", "1")
    monkeypatch.delenv("IRDEPTH_NB_WORKDIR", raising=False)
    copy_run(learned_run[0], tmp_path / "irdepth_quickstart")
    nb = execute("quickstart.ipynb", tmp_path, cwd=tmp_path)
    assert images(nb) >= 3  # scenes, H/S/V + pseudo-RGB, depth maps
    out = text(nb)
    assert "run: irdepth_quickstart | stage: stage2" in out
    assert "these scenes:" in out and "abs_rel" in out
    # the test split by condition: all, then those of its frames (24 rendered frames: a few)
    assert "\nall   " in out
    assert any(f"\n{group:6s}" in out for group in ("day", "dusk", "night"))


def test_ablations_runs(monkeypatch, tmp_path):
    results = os.path.join(REPO, "experiments", "results")
    monkeypatch.setenv("IRDEPTH_RESULTS_DIR", results)
    nb = execute("ablations.ipynb", tmp_path)
    from irdepth_experiments import claims

    records = claims.load_results(results)
    assert len(records) == 7
    assert images(nb) == len(records)
    out = text(nb)
    for record in records.values():
        assert record["title"] in out
    assert out.count("seeds agree") == len(claims.check_claims(records))
