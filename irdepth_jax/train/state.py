"""Train states, parameter groups and the optimizers of the paper's three training phases.

A run has three phases, each with its own `TrainState` (optax's `tx` is static, so a new phase
means a new state):

* ``stage1_i1``: MTSA-UNet pre-training (reconstruction + gradient branch, all frames),
  AdaDelta with an explicit rate (``optax.adadelta(None)`` would do gradient *ascent*),
  AdamW as an option.
* ``stage1_i2``: soft multi-task fine-tuning on the labelled frames; two parameter groups,
  ``seg`` (the segmentation decoder + head) at ``seg_lr_multiplier`` x the rate of ``shared``
  (encoder, reconstruction and gradient branches). With ``stage1.multitask=False`` the
  reconstruction / gradient branches are the group ``no_update`` (``optax.set_to_zero``): the
  single-task segmentation baseline of the paper's table 3.
* ``stage2``: Depth Anything V2 fine-tuning, AdamW (0.9, 0.999, wd 0.01) with the ViT
  backbone (top-level ``pretrained``) at 1/``head_lr_multiplier`` of the head's rate, both
  with poly decay (power 0.9) to zero over the run.

Groups are assigned from the parameter path (``"decoder_seg/up_0/conv/kernel"``) by the first
matching regular expression of a rule list, so a new module needs one rule, not new code.
"""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from irdepth_jax.config import Config, resolved_raw_bits, to_dict
from irdepth_jax.runs.checkpoint import Checkpointer, path_to_str

# Parameter path rules (first match wins), after the module names of `models.unet.MTSAUNet`
# (decoders dec_<task>_up<i>, heads head_<task>) and `models.depth_anything.DepthAnythingV2`
# (backbone "pretrained", head "depth_head").
SEG_BRANCH_PATTERN = r"^(dec_seg_|head_seg(/|$))"
AUX_BRANCH_PATTERN = r"^(dec_(recon|grad)_|head_(recon|saturation)(/|$))"
BACKBONE_PATTERN = r"^pretrained(/|$)"

NO_UPDATE = "no_update"
"""Group of the parameters a phase leaves as they are (``optax.set_to_zero``)."""

Schedule = Callable[[jax.Array], jax.Array]


class TrainState(struct.PyTreeNode):
    """Everything one training phase carries from step to step.

    Attributes:
      step: int32 scalar, number of optimizer updates done.
      params: the trainable parameters (a `flax` params tree).
      batch_stats: BatchNorm running statistics ({} for models without BatchNorm).
      opt_state: the optax state of `tx`.
      rng: uint32[2] base PRNG key; step t uses ``fold_in(rng, t)`` so a resumed run draws the
        same numbers as an uninterrupted one.
      tx: the optimizer (static).
      lr_fns: group name -> learning-rate schedule of the step (static; for logging).
    """

    step: jax.Array
    params: Any
    batch_stats: Any
    opt_state: Any
    rng: jax.Array
    tx: optax.GradientTransformation = struct.field(pytree_node=False)
    lr_fns: Mapping[str, Schedule] = struct.field(pytree_node=False, default_factory=dict)

    @classmethod
    def create(cls, params: Any, batch_stats: Any, tx: optax.GradientTransformation,
               rng: jax.Array, lr_fns: Mapping[str, Schedule] | None = None) -> "TrainState":
        """A step-0 state with a fresh optimizer state for `params`."""
        return cls(step=jnp.zeros((), jnp.int32), params=params, batch_stats=batch_stats or {},
                   opt_state=tx.init(params), rng=jnp.asarray(rng, jnp.uint32), tx=tx,
                   lr_fns=dict(lr_fns or {}))

    def apply_gradients(self, grads: Any, batch_stats: Any) -> "TrainState":
        """One optimizer update with `grads` (same tree as params); stores new `batch_stats`."""
        updates, opt_state = self.tx.update(grads, self.opt_state, self.params)
        return self.replace(step=self.step + 1, params=optax.apply_updates(self.params, updates),
                            opt_state=opt_state, batch_stats=batch_stats)

    def learning_rates(self) -> dict[str, jax.Array]:
        """Group -> learning rate used by the update that produced this step (for logs)."""
        return {f"lr_{name}": jnp.asarray(fn(jnp.maximum(self.step - 1, 0)), jnp.float32)
                for name, fn in self.lr_fns.items()}

    def checkpoint_items(self) -> dict[str, Any]:
        """The arrays to checkpoint, split into the model and the optimizer's progress."""
        return {"model": {"params": self.params, "batch_stats": self.batch_stats},
                "train": {"opt_state": self.opt_state, "step": self.step, "rng": self.rng}}

    def from_checkpoint_items(self, items: Mapping[str, Any]) -> "TrainState":
        """Inverse of `checkpoint_items` (``train`` may be absent: model weights only)."""
        model = items["model"]
        state = self.replace(params=model["params"], batch_stats=model.get("batch_stats") or {})
        if "train" in items and items["train"] is not None:
            train = items["train"]
            state = state.replace(opt_state=train["opt_state"], step=train["step"],
                                  rng=train["rng"])
        return state


def label_params(params: Any, rules: Sequence[tuple[str, str]], default: str) -> Any:
    """Labels every leaf of `params` with the group of the first rule whose regex matches its path.

    Args:
      params: a params tree.
      rules: ``(regex, label)`` pairs, tried in order with `re.search` on the ``a/b/c`` path.
      default: label of leaves no rule matches.
    Returns:
      A tree of the same structure with a string label per leaf.
    """
    compiled = [(re.compile(pattern), label) for pattern, label in rules]

    def label(path, _):
        text = path_to_str(path)
        for regex, name in compiled:
            if regex.search(text):
                return name
        return default

    return jax.tree_util.tree_map_with_path(label, params)


def base_optimizer(name: str, learning_rate: float | Schedule, weight_decay: float = 0.0
                   ) -> optax.GradientTransformation:
    """AdaDelta (rho 0.9, eps 1e-6, always with an explicit rate) or AdamW (0.9, 0.999)."""
    if name == "adadelta":
        if learning_rate is None:
            raise ValueError("adadelta needs an explicit learning rate (None means ascent)")
        return optax.adadelta(learning_rate=learning_rate, rho=0.9, eps=1e-6)
    if name == "adamw":
        return optax.adamw(learning_rate, b1=0.9, b2=0.999, weight_decay=weight_decay)
    raise ValueError(f"unknown optimizer {name!r}; choose adadelta or adamw")


def _constant(value: float) -> Schedule:
    return lambda step: jnp.full((), value, jnp.float32)


@functools.lru_cache(maxsize=64)
def stage1_optimizer(cfg: Config, phase: str
                     ) -> tuple[optax.GradientTransformation, dict[str, Schedule]]:
    """The Stage I optimizer of `phase` ('stage1_i1' | 'stage1_i2').

    Cached per (config, phase), with the parameter groups found from the params when the
    optimizer is initialised: the optimizer is a static field of `TrainState`, so equal runs
    (resumed, repeated, the tests' many short runs) get the same object and reuse the compiled
    train step instead of tracing it again (~7 s per tiny Stage I run on 2 CPU cores).

    Returns:
      (tx, lr_fns): the optax transformation and group -> schedule (for logging).
    """
    s1 = cfg.stage1
    if phase == "stage1_i1":
        return base_optimizer(s1.optimizer, s1.learning_rate, s1.weight_decay), {
            "all": _constant(s1.learning_rate)}
    if phase != "stage1_i2":
        raise ValueError(f"unknown Stage I phase {phase!r}")
    shared_lr = s1.i2_learning_rate
    seg_lr = shared_lr * s1.seg_lr_multiplier
    rules = ((SEG_BRANCH_PATTERN, "seg"),
             (AUX_BRANCH_PATTERN, "shared" if s1.multitask else NO_UPDATE))
    transforms = {"seg": base_optimizer(s1.optimizer, seg_lr, s1.weight_decay),
                  "shared": base_optimizer(s1.optimizer, shared_lr, s1.weight_decay),
                  NO_UPDATE: optax.set_to_zero()}
    lr_fns = {"seg": _constant(seg_lr), "shared": _constant(shared_lr)}
    labels = functools.partial(label_params, rules=rules, default="shared")
    return optax.multi_transform(transforms, labels), lr_fns


@functools.lru_cache(maxsize=64)
def stage2_optimizer(cfg: Config, total_steps: int
                     ) -> tuple[optax.GradientTransformation, dict[str, Schedule]]:
    """AdamW with backbone / head rates and poly decay over `total_steps` updates (cached per
    (config, total_steps), parameter groups found at init; see `stage1_optimizer`)."""
    s2 = cfg.stage2
    steps = max(int(total_steps), 1)
    lr_fns = {
        "backbone": optax.polynomial_schedule(s2.learning_rate, 0.0, s2.poly_power, steps),
        "head": optax.polynomial_schedule(s2.learning_rate * s2.head_lr_multiplier, 0.0,
                                          s2.poly_power, steps),
    }
    labels = functools.partial(label_params, rules=((BACKBONE_PATTERN, "backbone"),),
                               default="head")
    transforms = {name: base_optimizer("adamw", fn, s2.weight_decay) for name, fn in lr_fns.items()}
    return optax.multi_transform(transforms, labels), lr_fns


def save_model(workdir: str, cfg: Config, unet_vars: dict | None, da_params: Any,
               segmentation: dict | None = None) -> str:
    """Writes a Stage II checkpoint that `runs.variables.load_model` (so eval, predict, export)
    reads: e.g. a Stage I model with released Depth Anything V2 weights, or untrained weights
    for a benchmark.

    Args:
      workdir: a new run directory (its ``checkpoints/stage2``).
      cfg: the config the variables belong to (`data.raw_bits` 14 or 16).
      unet_vars: Stage I ``{'params', 'batch_stats'}`` (None for a baseline without Stage I).
      da_params: Depth Anything V2 params.
      segmentation: what the segmentation branch was trained on (recorded in the meta).
    Returns:
      the checkpoint directory.
    """
    resolved_raw_bits(cfg)
    tx, lr_fns = stage2_optimizer(cfg, 1)
    state = TrainState.create(da_params, {}, tx, jax.random.PRNGKey(cfg.seed), lr_fns)
    directory = os.path.join(workdir, "checkpoints", "stage2")
    ckpt = Checkpointer(directory, "stage2")
    try:
        ckpt.save(0, state, {"config": to_dict(cfg), "segmentation": segmentation},
                  frozen=None if unet_vars is None else {"unet": unet_vars}, force=True)
        ckpt.wait()
    finally:
        ckpt.close()
    return directory
