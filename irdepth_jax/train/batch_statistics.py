"""Exact BatchNorm statistics for a finished Stage I phase ("precise BN").

Training keeps each BatchNorm's mean and variance as a running average (momentum
`unet.bn_momentum`) of batch statistics taken while the weights moved; evaluation, prediction and
the HSV image Stage II reads use those averages. At the end of each Stage I phase they are
replaced by the statistics of the final weights: the mean, over `PRECISE_BN_FRAMES` training
frames of the phase (un-augmented, as evaluation sees frames; batches of `stage1.batch_size`), of
each batch's statistics. On the synthetic benchmark the running averages had cost the long
reconstruction-only models 3 to 10 dB of PSNR (docs/experiments.md, "BatchNorm statistics").
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from collections.abc import Callable, Iterable

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.config import Config
from irdepth_jax.models.pipeline import unet_input
from irdepth_jax.models.unet import MTSAUNet

PRECISE_BN_FRAMES = 256
"""Training frames the statistics are taken over (fewer when the phase has fewer)."""

def recompute_batch_stats(cfg: Config, variables: dict, batches: Iterable[dict]) -> tuple[dict, int]:
    """(the MTSA-UNet's 'batch_stats' recomputed exactly, frames used).

    Each BatchNorm's mean and variance is the mean over `batches` (dicts with 'raw14' (B, H, W)
    and optionally 'brightness' (B,), as a loader yields them) of that batch's statistics, from
    train-mode passes at momentum 0 (the running average is then the batch's own); the weights
    in `variables` ({'params', 'batch_stats'}, host arrays) are used unchanged.
    """
    total, count, frames = None, 0, 0
    for batch in batches:
        brightness = batch.get("brightness")
        stats = _batch_statistics(cfg, variables, jnp.asarray(batch["raw14"]),
                                  None if brightness is None else jnp.asarray(brightness))
        total = stats if total is None else jax.tree.map(jnp.add, total, stats)
        count, frames = count + 1, frames + len(batch["raw14"])
    if count == 0:
        raise ValueError("recompute_batch_stats: no batch")
    return jax.tree.map(lambda x: np.asarray(x / count), total), frames


@functools.partial(jax.jit, static_argnums=0)
def _batch_statistics(cfg: Config, variables: dict, raw, brightness) -> dict:
    """One batch's BatchNorm statistics: a train-mode pass at momentum 0 (compiled once per
    config and batch shape, so a run's two phases share it)."""
    exact = MTSAUNet(dataclasses.replace(cfg.unet, bn_momentum=0.0))
    _, updated = exact.apply(variables, unet_input(raw, cfg, brightness), train=True,
                             mutable=["batch_stats"])
    return updated["batch_stats"]


def phase_batch_stats(cfg: Config, dataset, indices: np.ndarray, phase: str
                      ) -> Callable[[dict], tuple[dict, dict]]:
    """The `train.phase.Phase.finalize` of a Stage I phase trained on `indices` of `dataset`:
    variables ({'params', 'batch_stats'}, host arrays) -> (recomputed batch_stats, the record
    stored in the final checkpoint's meta, `runs.checkpoint.FINALIZED`). Every process takes the same
    batches (a fixed shuffle of seed `cfg.seed`), so replicas stay identical."""
    from irdepth_jax.data.loader import Loader

    batch_size = min(cfg.stage1.batch_size, len(indices))
    batches = max(min(PRECISE_BN_FRAMES, len(indices)) // batch_size, 1)

    def finalize(variables: dict) -> tuple[dict, dict]:
        loader = Loader(dataset, indices, batch_size=batch_size, seed=cfg.seed, shuffle=True,
                        drop_remainder=True, augment=False, process_index=0, process_count=1)
        stats, frames = recompute_batch_stats(cfg, variables, itertools.islice(iter(loader), batches))
        return stats, {"recomputed": True, "frames": frames, "batch_size": batch_size,
                       "from": f"{phase} training frames, un-augmented"}

    return finalize
