"""Regenerates the committed outputs of notebooks/*.ipynb.

    python notebooks/regenerate.py

Runs `irdepth quickstart` into irdepth_quickstart/ in the repository root (a few minutes on a
CPU) unless that folder already holds a quickstart run, which the quickstart notebook then
reuses; executes each notebook in place from notebooks/ (nbclient, kernel python3), without the
IRDEPTH_NB_* / IRDEPTH_RESULTS_DIR settings the tests use and without per-cell timings, so that a
rerun changes only what the notebooks compute.
"""

from __future__ import annotations

import os
import sys

import nbformat
from nbclient import NotebookClient

NOTEBOOKS = os.path.dirname(os.path.abspath(__file__))
QUICKSTART_RUN = os.path.join(os.path.dirname(NOTEBOOKS), "irdepth_quickstart")
NAMES = ("quickstart.ipynb", "ablations.ipynb")


def main() -> int:
    for key in [k for k in os.environ if k.startswith("IRDEPTH_NB_")] + ["IRDEPTH_RESULTS_DIR"]:
        os.environ.pop(key, None)
    if not os.path.exists(os.path.join(QUICKSTART_RUN, "stage2", "eval_test.json")):
        from irdepth_jax.cli import main as irdepth

        code = irdepth(["quickstart", "--workdir", QUICKSTART_RUN, "--no-progress"])
        if code:
            return code
    for name in NAMES:
        path = os.path.join(NOTEBOOKS, name)
        nb = nbformat.read(path, as_version=4)
        NotebookClient(nb, timeout=1800, kernel_name="python3", record_timing=False,
                       resources={"metadata": {"path": NOTEBOOKS}}).execute()
        nbformat.write(nb, path)
        print(f"{name}: executed, {os.path.getsize(path) / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
