"""The paper's experiments (tables 1-7) on our synthetic benchmark or a user's dataset.

* `experiments.runner`: the table declarations (`Arm`, `Table`) and the command line every
  ``table*.py`` script shares (`main`);
* `experiments.cache`: the datasets (training data and the separate evaluation set) and the
  cached training runs a table reads (`Context`, `context` for notebooks);
* `experiments.report`: a table's outputs (results.md / .json, frames.npz, figure.png);
* `experiments.claims`: the paper's claims, seed-level intervals, detectable effects and
  verdicts (``python experiments/claims.py``).

Installed with the package (``pip install -e .``): notebooks and tests import it as
``experiments``; the scripts run as ``python experiments/<name>.py``.
"""
