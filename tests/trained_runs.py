"""The trained tiny runs the CLI tests share: one synthetic dataset, one Stage I run (4 + 4
steps) and one Stage II run (2 steps) on it per test session, each made on first use by the
session fixtures of conftest.py (`synthetic_data`, `stage1_run`, `stage2_run`).

They are read-only: a test that continues, overwrites, interrupts or evaluates into a run works
on a copy (`copy_run`), and the session checks at its end that no shared file changed
(`Fingerprint`)."""

from __future__ import annotations

import hashlib
import os
import shutil

MODEL = ["unet.widths=(4, 4)"]
"""The CLI tests' model: the tiny preset with a two-level MTSA-UNet (see QUICK)."""

QUICK = ["--no-progress", "--devices", "1", "log_every=1", "checkpoint_every=50", "eval_every=0",
         *MODEL]
"""One device, a log line every step, no evaluation, a checkpoint at the end of each phase, and
a two-level tiny MTSA-UNet: the CLI tests are about the command's behaviour, not the model's
depth, and two levels instead of the preset's four halve the compile and trace time of every
Stage I step (6.6 s vs 12.7 s, 1.7 s vs 3.8 s on 2 cores) and shorten every Stage II and predict
program. The tests of the model itself use the preset (test_unet, test_unet_torch, ...)."""

DATA = dict(n=24, labeled=12, height=32, width=48, seed=1)
"""The shared dataset: 24 frames of 32x48 (12 labelled); test_export's too (same compiled
steps)."""

STEPS = {"stage1": 4, "stage2": 2}
"""Optimizer steps per phase: Stage I-1 and I-2 each 4, Stage II 2."""


LEARNING = ["data.num_frames=48", "data.num_labeled=24", "data.height=32", "data.width=48",
            "stage1.epochs_i1=4", "stage1.epochs_i2=4", "stage2.epochs=4", "eval_every=0"]
"""A shortened tiny run that learns (48 frames of 32x48, 4 epochs per phase): the fast learning
test's and the quickstart notebook's (`learned_run`)."""


def train_and_evaluate_learning(workdir):
    """`workflow.train_and_evaluate` of the `LEARNING` config into `workdir`; its result."""
    from irdepth_jax.config import apply_overrides, get_config
    from irdepth_jax.workflow import train_and_evaluate

    return train_and_evaluate(apply_overrides(get_config("tiny"), LEARNING), str(workdir),
                              devices=1, progress=False, log=lambda line: None)


def write_data(path):
    from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset

    write_synthetic_dataset(path, **DATA, progress=False)
    return path


def train(stage: str, data, work, *extra) -> None:
    """`irdepth train <stage> --steps STEPS[stage]` with QUICK, which must succeed."""
    from irdepth_jax import cli

    argv = ["train", stage, "--data", data, "--workdir", work, "--steps", STEPS[stage], *extra,
            *QUICK]
    assert cli.main([str(a) for a in argv]) == 0, argv


def unfinalise(run, cfg, phases) -> None:
    """Rewrites the last checkpoint of each Stage I phase in `phases` of the run `run` (a
    private copy) as runs finished before `train.batch_statistics` left it: fresh-init BatchNorm
    statistics in place of the exact ones, and no `train.phase.FINALIZED` record."""
    import jax

    from irdepth_jax.runs.checkpoint import FINALIZED, Checkpointer
    from irdepth_jax.runs.variables import init_unet
    from irdepth_jax.train.state import TrainState, stage1_optimizer

    stale = init_unet(cfg)["batch_stats"]
    for phase in phases:
        ckpt = Checkpointer(os.path.join(run, "checkpoints", phase), phase, max_to_keep=None)
        try:
            tx, lr_fns = stage1_optimizer(cfg, phase)
            template = TrainState.create(init_unet(cfg)["params"], stale, tx, jax.random.PRNGKey(0), lr_fns)
            state, meta = ckpt.restore(template)
            ckpt.replace(ckpt.latest_step(), state.replace(batch_stats=stale),
                         {k: v for k, v in meta.items() if k != FINALIZED})
        finally:
            ckpt.close()


def copy_run(run, dest):
    """A private copy of a shared run (or dataset) at `dest`, to change at will."""
    shutil.copytree(run, dest, symlinks=True)
    return dest


class Fingerprint:
    """Size and SHA-1 of every file under a directory, to check it was left as it was."""

    def __init__(self, root):
        self.root = str(root)
        self.files = self._read()

    def _read(self) -> dict[str, tuple[int, str]]:
        files = {}
        for folder, _, names in os.walk(self.root):
            for name in names:
                path = os.path.join(folder, name)
                with open(path, "rb") as f:
                    digest = hashlib.sha1(f.read()).hexdigest()
                files[os.path.relpath(path, self.root)] = (os.path.getsize(path), digest)
        return files

    def changes(self) -> list[str]:
        """Files added, removed or changed since the fingerprint was taken."""
        now = self._read()
        return sorted(name for name in set(now) | set(self.files)
                      if now.get(name) != self.files.get(name))


def untrained_stage2(work, cfg):
    """Saves an untrained Stage II model of `cfg` (random UNet and Depth Anything V2) as a run
    in `work`; returns (work, unet variables, depth params)."""
    from irdepth_jax.runs.variables import init_unet, random_depth
    from irdepth_jax.train.state import save_model

    unet, depth = init_unet(cfg), random_depth(cfg)
    save_model(str(work), cfg, unet, depth)
    return work, unet, depth
