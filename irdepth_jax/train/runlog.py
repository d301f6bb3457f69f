"""A run's directory and its log: config.json, metrics.jsonl (one JSON object per logged step)
and TensorBoard event files, written by process 0.

Work directory of a run::

    WORKDIR/config.json             the full config (`config.to_dict`) of the run
    WORKDIR/metrics.jsonl           one JSON object per logged step (and per periodic eval)
    WORKDIR/tb/                     TensorBoard event files (tensorboardX)
    WORKDIR/checkpoints/<phase>/    orbax checkpoints of each phase (stage1_i1, stage1_i2, stage2)
    WORKDIR/data_fingerprint.json   what each stage trains on (`data.fingerprint`), checked on
                                    --resume
"""

from __future__ import annotations

import json
import os
import sys

import jax

from irdepth_jax.config import Config, to_dict, upgrade_dict
from irdepth_jax.errors import RunError
from irdepth_jax.fileio import write_bytes
from irdepth_jax.train.workdir_lock import holds_run

WALL_CLOCK_FIELDS = ("time", "img_per_s")
"""metrics.jsonl fields that depend on the machine's speed (the rest is deterministic)."""


class RunLog:
    """metrics.jsonl + TensorBoard writer of process 0 (other processes: no-ops)."""

    def __init__(self, workdir: str):
        self.enabled = jax.process_index() == 0
        self.path = os.path.join(workdir, "metrics.jsonl")
        self._tb = None
        if self.enabled:
            from tensorboardX import SummaryWriter
            self._tb = SummaryWriter(os.path.join(workdir, "tb"))

    def truncate_after(self, stage: str, step: int) -> None:
        """Drops lines of `stage` logged after `step` (written before an interruption)."""
        if not self.enabled or not os.path.exists(self.path):
            return
        keep = [json.dumps(r) + "\n" for r in read_metrics(self.path)
                if not (r.get("stage") == stage and r["step"] > step)]
        write_bytes(self.path, "".join(keep).encode())  # a kill here keeps the old file

    def info(self, stage: str, **fields) -> None:
        """States what a run is built from (weights loaded, labels used, resolved settings):
        printed to stderr as ``irdepth: STAGE: key: value`` lines and logged as one
        ``{"step": 0, "stage", "kind": "info", ...}`` record of metrics.jsonl (once: a resumed
        run that finds the same record does not write it again)."""
        if not self.enabled:
            return
        record = json.loads(json.dumps({"step": 0, "stage": stage, "kind": "info", **fields}))
        for key, value in fields.items():
            print(f"irdepth: {stage}: {key}: {value}", file=sys.stderr, flush=True)
        if os.path.exists(self.path):
            with open(self.path) as f:
                if any(ln.strip() and json.loads(ln) == record for ln in f):
                    return
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")

    def write(self, record: dict) -> None:
        if not self.enabled:
            return
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
        prefix = record["stage"] + ("/eval" if record.get("kind") == "eval" else "")
        for key, value in _flatten(record).items():
            if key not in ("step",) and isinstance(value, (int, float)):
                self._tb.add_scalar(f"{prefix}/{key}", value, record["step"])
        self._tb.flush()

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}/"))
        else:
            out[f"{prefix}{k}"] = v
    return out


def read_metrics(path: str) -> list[dict]:
    """The records of a metrics.jsonl, rewriting the file without a torn last line.

    A last line that is not JSON is what a run killed while logging leaves: it is dropped from
    the file, with a note on stderr. A line that is not JSON elsewhere raises RunError naming
    the file and the line.
    """
    with open(path) as f:
        lines = [(n, ln) for n, ln in enumerate(f, 1) if ln.strip()]
    records = []
    for k, (number, line) in enumerate(lines):
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as err:
            if k < len(lines) - 1:
                raise RunError(f"{path} line {number}: not a JSON record ({err.msg}); repair "
                               "or delete that line") from None
            print(f"irdepth: dropping the torn last line {number} of {path} (left by an "
                  "interrupted run)", file=sys.stderr, flush=True)
            write_bytes(path, "".join(json.dumps(r) + "\n" for r in records).encode())
    return records


def prepare_workdir(workdir: str, cfg: Config, resume: bool) -> None:
    """Creates `workdir` and its config.json; refuses to overwrite a run without `resume`.

    With `resume`, the stored config must equal `cfg` (a changed hyper-parameter would make the
    resumed run a different run), and a torn last line of metrics.jsonl is dropped
    (`read_metrics`).
    """
    path = os.path.join(workdir, "config.json")
    if holds_run(workdir) and not resume:
        raise RunError(f"workdir {workdir} already holds a run; pass `resume` to continue it or "
                       "choose another `workdir`")
    metrics = os.path.join(workdir, "metrics.jsonl")
    if resume and jax.process_index() == 0 and os.path.exists(metrics):
        read_metrics(metrics)
    if resume and os.path.exists(path):
        with open(path) as f:
            stored = upgrade_dict(json.load(f))  # a run started before a key was renamed
        current = json.loads(json.dumps(to_dict(cfg)))
        if stored != current:
            changed = sorted(k for k in _flatten(current)
                             if _flatten(stored).get(k) != _flatten(current)[k])
            raise RunError(f"`resume`: config differs from {path} in {', '.join(changed)}")
        return
    if jax.process_count() > 1:  # every process has checked before process 0 writes
        from jax.experimental import multihost_utils
        multihost_utils.sync_global_devices("irdepth:prepare_workdir")
    if jax.process_index() == 0:
        os.makedirs(workdir, exist_ok=True)
        write_bytes(path, json.dumps(to_dict(cfg), indent=2).encode())


DATA_FINGERPRINT = "data_fingerprint.json"


def check_same_data(workdir: str, stage: str, fingerprint: dict, data: str) -> None:
    """RunError naming what changed when the run in `workdir` recorded other training data for
    `stage` than `fingerprint` (`data.fingerprint.data_fingerprint` of `data` now). A run that
    recorded none (started before fingerprints were kept) is not checked."""
    from irdepth_jax.data.fingerprint import fingerprint_changes

    path = os.path.join(workdir, DATA_FINGERPRINT)
    if not os.path.exists(path):
        return
    with open(path) as f:
        recorded = json.load(f).get(stage)
    changes = fingerprint_changes(recorded or {}, fingerprint)
    if changes:
        raise RunError(f"`resume`: the dataset changed since this run started ({path}): `data` "
                       f"{data}: {'; '.join(changes)}; resume on the data it started with, or "
                       "start a new `workdir`")


def record_data(workdir: str, stage: str, fingerprint: dict) -> None:
    """Records `fingerprint` as what `stage` of the run in `workdir` trains on (process 0)."""
    if jax.process_index() != 0:
        return
    path = os.path.join(workdir, DATA_FINGERPRINT)
    doc = {}
    if os.path.exists(path):
        with open(path) as f:
            doc = json.load(f)
    write_bytes(path, json.dumps({**doc, stage: fingerprint}, indent=1).encode())
