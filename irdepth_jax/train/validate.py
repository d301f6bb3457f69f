"""Checks a run before anything is created: run lengths, batch sizes, learning rates, the
resume target and (Stage II) that the training split has depth to learn from.

Each check raises a one-line `RunError` naming the key, option or directory and the reason, so
that a run that cannot train fails at once instead of at its first logged step.
"""

from __future__ import annotations

import dataclasses
import math

from irdepth_jax.config import Config
from irdepth_jax.data.source import phase_frames
from irdepth_jax.errors import RunError
from irdepth_jax.train.phase import RunOptions
from irdepth_jax.train.workdir_lock import held_stages

STAGES = ("stage1", "stage2")

# (key, smallest value, may be None): run lengths and sizes of each stage's section.
# stage1.steps_i1 / steps_i2 may be 0: that phase is skipped (the experiments train I-1 alone
# with steps_i2=0); a Stage I with no step at all is refused.
_COUNTS = {
    "stage1": (("batch_size", 1, False), ("accum_steps", 1, False), ("epochs_i1", 1, False),
               ("epochs_i2", 1, False), ("steps_i1", 0, True), ("steps_i2", 0, True)),
    "stage2": (("batch_size", 1, False), ("epochs", 1, False), ("steps", 1, True)),
}
_TOP_COUNTS = (("log_every", 1), ("checkpoint_every", 1), ("keep_checkpoints", 1),
               ("eval_every", 0))


def check_run(cfg: Config, source, opts: RunOptions, stage: str) -> None:
    """Refuses a `stage` run ('stage1' | 'stage2') that cannot train, before it writes anything.

    Checks the section's epochs, steps, batch size and accumulation steps (integers >= 1;
    stage1.steps_i1 / steps_i2 >= 0), the logging / checkpoint intervals, every learning rate
    and rate multiplier of the section (finite and > 0), ``opts.steps`` / ``opts.stop_at``
    (>= 1), that a resumed workdir holds no run of the other stage, and for Stage II that the
    training split has at least one valid depth pixel (reading frames up to the first one).

    Raises:
      RunError: one line naming the key, option, directory or data and what is wrong.
    """
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; choose one of {STAGES}")
    section = getattr(cfg, stage)
    for key, low, optional in _COUNTS[stage]:
        _check_count(f"{stage}.{key}", getattr(section, key), low, optional)
    for key, low in _TOP_COUNTS:
        _check_count(key, getattr(cfg, key), low, optional=False)
    if stage == "stage1" and opts.steps is None and 0 == section.steps_i1 == section.steps_i2:
        raise RunError("stage1.steps_i1=0 and stage1.steps_i2=0: Stage I would train nothing")
    for field in dataclasses.fields(section):
        if "learning_rate" in field.name or field.name.endswith("_multiplier"):
            rate = getattr(section, field.name)
            if not math.isfinite(rate) or rate <= 0:  # a number: the config's types are checked
                raise RunError(f"{stage}.{field.name}={rate!r}: a learning rate (or rate "
                               "multiplier) must be a finite number > 0")
    for name, value in (("steps", opts.steps), ("stop_at", opts.stop_at)):
        if value is not None and value < 1:
            raise RunError(f"`{name}` {value}: must be >= 1")
    other = held_stages(opts.workdir) - {stage}
    if opts.resume and other:
        raise RunError(f"`resume`: workdir {opts.workdir} holds a {', '.join(sorted(other))} run, "
                       f"which train {stage} cannot continue; choose another `workdir`")
    if stage == "stage2":
        _check_depth(source, cfg)


def _check_count(key: str, value, low: int, optional: bool) -> None:
    if value is None and optional:
        return
    if value < low:  # an integer: the config's types are checked
        none = " (or none)" if optional else ""
        raise RunError(f"{key}={value!r}: must be an integer >= {low}{none}")


def _check_depth(source, cfg: Config) -> None:
    """RunError unless a Stage II training frame has valid depth (stops at the first one), and
    for stage2.preprocessing=rgb unless every training frame has its visible image (a frame
    without one would train on a black image)."""
    dataset, indices = phase_frames(source, "stage2", cfg)
    if cfg.stage2.preprocessing == "rgb":
        records = getattr(dataset, "records", None)
        missing = ([r["id"] for r in (records[int(i)] for i in indices) if r.get("has_rgb") is False]
                   if records is not None else
                   [] if dataset[int(indices[0])]["has_rgb"] else [dataset[int(indices[0])]["id"]])
        if missing:
            raise RunError(f"`data` {source.path}: {len(missing)} training frame(s) have no visible "
                           f"image (e.g. {missing[0]}), which stage2.preprocessing=rgb trains on; "
                           "use a dataset with rgb/ images")
    for i in indices:
        if dataset[int(i)]["valid"].any():
            return
    raise RunError(f"`data` {source.path}: none of the {len(indices)} Stage II training frames "
                   "has valid depth (every depth map is 0): nothing to learn from")
