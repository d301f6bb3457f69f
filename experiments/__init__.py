"""The paper's experiments (tables 1-7) on our synthetic benchmark or a user's dataset.

* `irdepth_experiments.runner`: the table declarations (`Arm`, `Table`) and the command line every
  ``table*.py`` script shares (`main`);
* `irdepth_experiments.cache`: the datasets (training data and the separate evaluation set) and the
  cached training runs a table reads (`Context`, `context` for notebooks);
* `irdepth_experiments.report`: a table's outputs (results.md / .json, frames.npz, figure.png);
* `irdepth_experiments.claims`: the paper's claims, seed-level intervals, detectable effects and
  verdicts (``python experiments/claims.py``).

The folder ``experiments/`` installs as the package ``irdepth_experiments`` (a top-level
``experiments`` in site-packages would collide with other projects'), with an editable install of
the checkout (``pip install -e .``): notebooks and tests import ``irdepth_experiments``, the scripts
run as ``python experiments/<name>.py``. The experiments read and write their checkout
(``experiments/results/``, ``workdir/``, its git commit), so a copy installed by ``pip install .``
refuses to be imported instead of writing into site-packages.
"""

import os

_CHECKOUT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if not os.path.isfile(os.path.join(_CHECKOUT, "pyproject.toml")):
    raise ImportError(f"irdepth_experiments at {os.path.dirname(os.path.abspath(__file__))} is not in a source "
                      "checkout (no pyproject.toml beside it): the experiments run from a checkout installed "
                      "with `pip install -e .`")
