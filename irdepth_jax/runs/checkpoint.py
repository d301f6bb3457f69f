"""Orbax checkpoints: periodic saves, keep-last-K, exact resume and the Stage I -> II hand-off.

A checkpoint step directory holds three items:

* ``model``: ``{'params', 'batch_stats'}`` - all a later stage, `evaluate` or `predict` needs;
* ``train``: ``{'opt_state', 'step', 'rng'}`` - the optimizer's progress, for resuming;
* ``frozen`` (optional): non-trained variables the model needs (Stage II: the frozen Stage I
  UNet), so a Stage II checkpoint alone can predict;
* ``meta``: JSON ``{'stage', 'step', 'config', 'data_state', ...}`` - the stage tag
  (``stage1_i1`` | ``stage1_i2`` | ``stage2``), the run's config (`config.to_dict`) and the
  loader position (``Loader.get_state()``), so a resumed run continues with the next batch.

Orbax writes each step into a temporary directory and renames it when complete, so a run killed
during a save leaves a ``<step>.orbax-checkpoint-tmp-*`` directory that is never listed as a
step: restore picks the last finalised one (and the manager removes the leftover on start).
A save that cannot fit on the disk is refused before it starts (OSError ENOSPC), and a finished
run whose weights hold NaN / inf is refused when it is loaded (`restore_items`).

Renamed keys (`runs.legacy_names`: the gradient branch's modules, an optimizer group) are
mapped on restore, so checkpoints written under the old names still load and resume.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from etils import epath

from irdepth_jax.errors import IrdepthError
from irdepth_jax.runs.legacy_names import from_legacy, has_legacy_keys, to_legacy

STAGES = ("stage1_i1", "stage1_i2", "stage2")
"""The training phases a run directory holds checkpoints of (``checkpoints/<stage>``)."""

FINALIZED = "batch_stats"
"""The meta field of a phase's last checkpoint that holds `train.phase.Phase.finalize`'s record
(Stage I: how its exact BatchNorm statistics were made). Absent from a Stage I run finished
before phases had one: its statistics are training's running averages until it is resumed."""


class CheckpointError(IrdepthError, ValueError):
    """A checkpoint that is missing, of another stage or of another shape (one-line message)."""


def _not_read_only_notice(record: logging.LogRecord) -> bool:
    """Log filter: drops orbax's warning that a read_only=True manager's directory is read only."""
    return not str(record.msg).startswith("Given directory is read only")


def _not_a_save_error_report(record: logging.LogRecord) -> bool:
    """Log filter: drops reports, with tracebacks, of errors raised in orbax's code (its save
    threads and asyncio tasks log each failure, then its secondary failures): orbax raises the
    failure to the caller at the next save or `Checkpointer.wait`, where the CLI reports it in
    one line (`train.stages` naming the disk when it is full; IRDEPTH_DEBUG=1: its traceback)."""
    tb = record.exc_info[2] if record.exc_info else None
    while tb is not None:
        if tb.tb_frame.f_globals.get("__name__", "").startswith("orbax."):
            return False
        tb = tb.tb_next
    return True


class Checkpointer:
    """An orbax `CheckpointManager` for one stage's run directory.

    Args:
      directory: where step directories go (created if missing, unless `read_only`).
      stage: the stage tag written into (and expected from) the checkpoints.
      max_to_keep: keep the last K finalised steps (None: all).
      save_every: periodic saves every this many steps (`save(..., force=True)` always saves).
      read_only: open an existing directory without creating or cleaning anything.
    """

    def __init__(self, directory: str, stage: str, max_to_keep: int | None = 3,
                 save_every: int = 1, read_only: bool = False):
        if stage not in STAGES:
            raise ValueError(f"unknown stage {stage!r}; choose one of {STAGES}")
        self.directory = os.path.abspath(directory)
        self.stage = stage
        if read_only and not os.path.isdir(self.directory):
            raise CheckpointError(f"checkpoint directory {directory} does not exist")
        options = ocp.CheckpointManagerOptions(
            max_to_keep=max_to_keep,
            save_interval_steps=0 if read_only else max(int(save_every), 1),
            cleanup_tmp_directories=not read_only, create=not read_only, read_only=read_only)
        handlers = {"model": ocp.StandardCheckpointHandler(),
                    "train": ocp.StandardCheckpointHandler(),
                    "frozen": ocp.StandardCheckpointHandler(), "meta": ocp.JsonCheckpointHandler()}
        if not read_only:
            _recover_replaced(self.directory)
        absl_log = logging.getLogger("absl")
        if read_only:
            absl_log.addFilter(_not_read_only_notice)
        else:  # kept: a failed save is reported once it reaches the main thread
            for name in ("absl", "asyncio"):  # orbax's threads, its asyncio tasks
                logging.getLogger(name).addFilter(_not_a_save_error_report)
        try:
            self.manager = ocp.CheckpointManager(self.directory, options=options,
                                                 item_handlers=handlers)
        finally:
            absl_log.removeFilter(_not_read_only_notice)

    def latest_step(self) -> int | None:
        """The last finalised step (None when there is none)."""
        return self.manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self.manager.all_steps())

    def save(self, step: int, state: Any, meta: Mapping[str, Any], frozen: Any = None,
             force: bool = False) -> bool:
        """Saves `state` (host or replicated arrays) and `frozen` at `step` if due (or `force`).

        Returns whether a save was started (saves are asynchronous; see `wait`). Raises the
        error of the previous save if it failed, and OSError(ENOSPC) without starting the save
        when the disk has less room than the last finished checkpoint takes, or before the
        first than its arrays (rather than leaving orbax's threads to fail half-way).
        """
        items = state.checkpoint_items()
        meta = {**meta, "stage": self.stage, "step": int(step)}
        args = {"model": ocp.args.StandardSave(items["model"]),
                "train": ocp.args.StandardSave(items["train"]),
                "meta": ocp.args.JsonSave(_jsonable(meta))}
        if frozen is not None:
            args["frozen"] = ocp.args.StandardSave(frozen)
        if not (force or self.manager.should_save(int(step))):
            return False
        self.manager.wait_until_finished()  # as orbax's save would; the last step is final
        self._check_room(sum(getattr(x, "nbytes", 0) for x in jax.tree.leaves((items, frozen))))
        return self.manager.save(int(step), force=force, args=ocp.args.Composite(**args))

    def replace(self, step: int, state: Any, meta: Mapping[str, Any], frozen: Any = None) -> None:
        """Rewrites the finalised step `step` with `state` and `meta` (a finished phase's last
        step, finalised after the fact: `train.phase.Phase.finalize`). The old step folder is
        moved aside (``<step>.replaced``) and deleted once the new one is final; a process killed
        in between leaves it aside, and the next Checkpointer on the directory puts it back
        (`_recover_replaced`), so the step is never lost."""
        self.manager.wait_until_finished()
        folder = os.path.join(self.directory, str(int(step)))
        os.rename(folder, folder + REPLACED)
        self.manager.reload()
        self.save(step, state, meta, frozen=frozen, force=True)
        self.manager.wait_until_finished()
        shutil.rmtree(folder + REPLACED)

    def _check_room(self, array_bytes: int) -> None:
        """OSError(ENOSPC) when the disk's free space is below what the next checkpoint needs
        at least: the size of the last finished one (on disk, blocks included), or before the
        first, `array_bytes` (the arrays alone)."""
        last, need = self.latest_step(), array_bytes
        if last is not None:
            need = 0
            for folder, _, names in os.walk(os.path.join(self.directory, str(last))):
                for name in names:
                    st = os.stat(os.path.join(folder, name))
                    need += max(getattr(st, "st_blocks", 0) * 512, st.st_size)
        free = shutil.disk_usage(self.directory).free
        if free < need:
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: a checkpoint takes "
                          f"{need} bytes, {free} are free", self.directory)

    def read_meta(self, step: int | None = None) -> dict:
        """The JSON meta of `step` (latest by default); CheckpointError if there is none."""
        step = self._resolve(step)
        with _readable(f"{self.directory} step {step}"):
            return dict(self.manager.restore(
                step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"])

    def restore(self, template: Any, step: int | None = None, model_only: bool = False
                ) -> tuple[Any, dict]:
        """Restores a training state into the structure, shapes and shardings of `template`.

        Args:
          template: a state of this stage built from the same config (its values are ignored).
          step: which step (the latest finalised by default).
          model_only: restore params + batch_stats only (keep `template`'s optimizer and step).
        Returns:
          (state, meta).
        Raises:
          CheckpointError naming the directory when there is no checkpoint, it is of another
          stage, or its arrays do not match the template (first mismatching path).
        """
        items = template.checkpoint_items()
        names = ("model",) if model_only else ("model", "train")
        restored, meta = self.restore_items({n: items[n] for n in names}, step,
                                            check_finite=False)
        return template.from_checkpoint_items(restored), meta

    def restore_items(self, templates: Mapping[str, Any], step: int | None = None,
                      stages: Sequence[str] | None = None, check_finite: bool = True
                      ) -> tuple[dict, dict]:
        """The one restore path: items of `step` (the latest finalised by default).

        Args:
          templates: item name ('model', 'train', 'frozen') -> tree with the expected shapes
            (and shardings).
          stages: accepted stage tags (default: this Checkpointer's stage).
          check_finite: refuse NaN / inf weights (a finished model; a resumed run may restore
            the state it stopped at).
        Returns:
          ({item: restored tree}, meta). CheckpointError for a missing / other-stage /
          other-shape / non-finite checkpoint, naming it.
        """
        step = self._resolve(step)
        stages = tuple(stages or (self.stage,))
        meta = self.read_meta(step)
        if meta.get("stage") not in stages:
            raise CheckpointError(f"checkpoint {self.directory} step {step} is a "
                                  f"{meta.get('stage')!r} checkpoint, expected "
                                  f"{' or '.join(map(repr, stages))}")
        with _readable(f"{self.directory} step {step}"):
            stored = self._item_metadata(step, list(templates))
        legacy = set()  # items stored under old key names (`runs.legacy_names`)
        for name, template in templates.items():
            if stored.get(name) is None:
                raise CheckpointError(f"checkpoint {self.directory} step {step} has no {name!r}")
            if has_legacy_keys(stored[name].tree):
                legacy.add(name)
            _check_shapes(stored[name].tree, to_legacy(template) if name in legacy else template,
                          f"{self.directory} step {step} {name}")
        with _readable(f"{self.directory} step {step}"):
            restored = self.manager.restore(step, args=ocp.args.Composite(**{
                name: ocp.args.StandardRestore(_abstract(to_legacy(t) if name in legacy else t))
                for name, t in templates.items()}))
        items = {name: from_legacy(restored[name]) if name in legacy else restored[name]
                 for name in templates}
        if check_finite:
            _check_finite(items, f"{self.directory} step {step}")
        return items, meta

    def _item_metadata(self, step: int, names: Sequence[str]) -> Mapping[str, Any]:
        """The stored tree metadata of the items `names` only: a model restore does not read
        the optimizer state's (twice the model's arrays; two thirds of the metadata time of a
        warm `irdepth predict`). A step folder of another layout: every item's, by orbax."""
        folder = os.path.join(self.directory, str(step))
        if not all(os.path.isdir(os.path.join(folder, name)) for name in names):
            return self.manager.item_metadata(step)
        handler = ocp.StandardCheckpointHandler()
        return {name: handler.metadata(epath.Path(folder) / name) for name in names}

    def wait(self) -> None:
        """Blocks until pending asynchronous saves are finalised."""
        self.manager.wait_until_finished()

    def close(self) -> None:
        self.manager.close()

    def _resolve(self, step: int | None) -> int:
        if step is None:
            step = self.latest_step()
            if step is None:
                raise CheckpointError(f"no finished checkpoint in {self.directory}")
        elif step not in self.manager.all_steps():
            raise CheckpointError(f"no checkpoint step {step} in {self.directory}")
        return step


REPLACED = ".replaced"
"""Suffix of a step folder `Checkpointer.replace` has moved aside (not a step orbax lists)."""


def _recover_replaced(directory: str) -> None:
    """Finishes a `Checkpointer.replace` a killed process left: each ``<step>.replaced`` folder
    is deleted where ``<step>`` was written, else moved back to ``<step>``."""
    if not os.path.isdir(directory):
        return
    for name in os.listdir(directory):
        if name.endswith(REPLACED) and name[:-len(REPLACED)].isdigit():
            aside, folder = os.path.join(directory, name), os.path.join(directory, name[:-len(REPLACED)])
            if os.path.isdir(folder):
                shutil.rmtree(aside)
            else:
                os.rename(aside, folder)


@contextlib.contextmanager
def _readable(where: str):
    """Within the block, an error of orbax / TensorStore reading checkpoint `where` (a truncated
    or bit-flipped file: a bare Exception, or a ValueError of ~1,000 characters of settings) is
    one line naming it as corrupt; the original error is chained (IRDEPTH_DEBUG=1 shows it)."""
    try:
        yield
    except CheckpointError:
        raise
    except Exception as err:  # noqa: BLE001 - whatever orbax raises on a damaged file
        raise CheckpointError(f"checkpoint {where} is corrupt: its files cannot be read "
                              f"({type(err).__name__}; IRDEPTH_DEBUG=1 shows the detail)") from err


def has_checkpoint(directory: str) -> bool:
    """Whether `directory` holds a finished checkpoint step."""
    return os.path.isdir(directory) and any(n.isdigit() for n in os.listdir(directory))


def find_checkpoint(path: str, stages: Sequence[str] = ("stage2", "stage1_i2", "stage1_i1")
                    ) -> tuple[str, str]:
    """The one checkpoint lookup: (checkpoint directory, stage) of `path`, a run's workdir (its
    ``checkpoints/<stage>`` of the first of `stages` that holds a finished step, so the latest
    stage by default) or a checkpoint directory itself (its stage read from its meta, which
    must be one of `stages`). CheckpointError (one line naming `path`) otherwise."""
    for stage in stages:
        candidate = os.path.join(path, "checkpoints", stage)
        if has_checkpoint(candidate):
            return candidate, stage
    if has_checkpoint(path):
        stage = str(read_meta(path).get("stage"))
        if stage not in stages:
            raise CheckpointError(f"{path}: a {stage!r} checkpoint, expected "
                                  f"{' or '.join(map(repr, stages))}")
        return path, stage
    raise CheckpointError(f"{path}: no {' / '.join(stages)} checkpoint there (expected a run's "
                          "workdir or one of its checkpoints/<stage> directories)")


def read_meta(directory: str, step: int | None = None) -> dict:
    """The one meta reader: the JSON meta (stage, step, config, ...) of a checkpoint directory's
    `step` (the latest finalised by default), opened read-only."""
    reader = Checkpointer(directory, "stage2", max_to_keep=None, read_only=True)
    try:
        return reader.read_meta(step)
    finally:
        reader.close()


def restore_items(directory: str, stage: str | Sequence[str], templates: Mapping[str, Any],
                  step: int | None = None) -> tuple[dict, dict]:
    """Reads items of a finished run of `stage` (accepted stage tag or tags), e.g. Stage I for
    Stage II, or a model for predict: `Checkpointer.restore_items` of the directory opened
    read-only, weights checked to be finite."""
    stages = (stage,) if isinstance(stage, str) else tuple(stage)
    reader = Checkpointer(directory, stages[0], max_to_keep=None, read_only=True)
    try:
        return reader.restore_items(templates, step, stages)
    finally:
        reader.close()


def _check_finite(items: Mapping[str, Any], where: str) -> None:
    """Raises CheckpointError when a floating-point value of `items` is NaN or inf (a diverged
    run: a model that predicts NaN, which a depth PNG would store as 0, "no depth"), naming
    how many of how many and in which top-level modules (``enc0``, ``depth_head``; a frozen
    model's by its name, ``frozen/unet``)."""
    bad: dict[str, int] = {}
    total = 0
    for path, leaf in jax.tree_util.tree_flatten_with_path(dict(items))[0]:
        if not jnp.issubdtype(jnp.result_type(leaf), jnp.inexact):
            continue
        total += int(np.size(leaf))
        # on the host: one numpy pass per leaf (a jnp op per leaf shape compiled each run)
        count = int(np.size(leaf) - np.count_nonzero(np.isfinite(np.asarray(leaf))))
        if count:
            item, *names = [n for n in path_to_str(path).split("/")
                            if n not in ("params", "batch_stats")]
            module = "/".join(([] if item == "model" else [item]) + names[:1])
            bad[module] = bad.get(module, 0) + count
    if bad:
        modules = ", ".join(f"{m} ({n})" for m, n in sorted(bad.items(), key=lambda x: -x[1]))
        raise CheckpointError(f"checkpoint {where}: {sum(bad.values())} of {total} parameters "
                              f"are not finite (NaN / inf), in {modules}: the run diverged; "
                              "retrain it (e.g. with a lower learning rate)")


def restore_model(directory: str, stage: str | tuple[str, ...], template_model: Mapping[str, Any],
                  step: int | None = None) -> tuple[dict, dict]:
    """``{'params', 'batch_stats'}`` and meta of a finished run of `stage` (see `restore_items`)."""
    items, meta = restore_items(directory, stage, {"model": template_model}, step)
    return dict(items["model"]), meta


def _abstract(tree: Any) -> Any:
    """ShapeDtypeStructs of `tree`, keeping shardings of jax arrays (host arrays: device 0)."""
    default = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])

    def spec(x):
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding or default)
        sharding = x.sharding if isinstance(x, jax.Array) else default
        return jax.ShapeDtypeStruct(np.shape(x), np.asarray(x).dtype if not isinstance(
            x, jax.Array) else x.dtype, sharding=sharding)

    return jax.tree.map(spec, tree)


def _check_shapes(stored: Any, expected: Any, where: str) -> None:
    """Raises CheckpointError at the first path whose presence or shape differs."""
    def table(tree):
        leaves = jax.tree_util.tree_flatten_with_path(
            tree, is_leaf=lambda x: hasattr(x, "shape") and not isinstance(x, dict))[0]
        return {path_to_str(p): tuple(getattr(v, "shape", ())) for p, v in leaves}

    have, want = table(stored), table(expected)
    for path in sorted(set(have) | set(want)):
        if path not in have:
            raise CheckpointError(f"checkpoint {where} lacks {path} (another model or config?)")
        if path not in want:
            raise CheckpointError(f"checkpoint {where} has unexpected {path} "
                                  "(another model or config?)")
        if have[path] != want[path]:
            raise CheckpointError(f"checkpoint {where}: {path} has shape {have[path]}, this "
                                  f"config expects {want[path]}")


def _jsonable(value: Any) -> Any:
    """Tuples -> lists, numpy scalars -> Python (orbax's JsonSave wants plain JSON)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


def path_to_str(path: tuple) -> str:
    """A `jax.tree_util` key path as ``"a/b/c"``."""
    parts = []
    for key in path:
        for attr in ("key", "name", "idx"):
            if hasattr(key, attr):
                parts.append(str(getattr(key, attr)))
                break
        else:
            parts.append(str(key))
    return "/".join(parts)
