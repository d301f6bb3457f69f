"""Train and eval steps, written once with an axis name.

`make_train_step(loss_fn, axis_name, accum_steps)` turns a per-device loss into a full update
``(state, batch, frozen) -> (state, metrics)``. The same function runs

* on one device (``axis_name=None``: no collectives),
* under ``jax.shard_map`` over a device mesh, and
* under ``jax.pmap``

(see `irdepth_jax.train.parallel`). With an axis name the loss, the metrics and the gradients
are averaged over devices (``lax.pmean``) and BatchNorm statistics are synchronised by the model
itself (it is built with the same ``axis_name``).

Gradient reduction: the gradient is taken with respect to a *device-varying* copy of the
replicated parameters (``lax.pcast(..., to='varying')``), so each device gets the gradient of
its own loss and one explicit ``pmean`` averages them. Under shard_map (``check_vma=True``)
differentiating the replicated parameters directly would already *sum* the gradients over
devices, and a further pmean would give N-times gradients; under pmap the gradients are
per-device. The explicit cast makes both mappings (and one device) give the same numbers.

Gradient accumulation: the per-device batch is split into ``accum_steps`` micro-batches that
are scanned with `lax.scan`; gradients and metrics are averaged, BatchNorm statistics are
threaded through the micro-batches (each micro-batch normalises with its own statistics and
updates the running averages once, as the paper's PyTorch accumulation does). One call is one
optimizer update, so the step counter, schedules and checkpoints count updates. Without
BatchNorm this equals one step on the whole batch (tested); with BatchNorm it differs exactly as
accumulation does in PyTorch. (``optax.MultiSteps`` would instead spread one update over several
calls and keep the partial sum in the optimizer state.)

A loss function has the signature
``loss_fn(params, batch_stats, frozen, batch, rng) -> (loss, (metrics, new_batch_stats))``
with `batch` the per-device (micro-)batch, `frozen` non-differentiated variables (the frozen
Stage I model in Stage II) and `metrics` a dict of scalars. Both stage losses trace their models
inside `xla_cpu.training_layers()`, the one choice of how the layers are computed on a CPU.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax
from jax import lax

from irdepth_jax.config import IGNORE_LABEL, Config
from irdepth_jax.imaging.gradients import gradient_magnitude
from irdepth_jax.losses import cross_entropy_loss, multitask_loss, reconstruction_loss, silog_loss, sky_loss
from irdepth_jax.models.pipeline import pipeline_outputs, unet_input
from irdepth_jax.models.unet import MTSAUNet
from irdepth_jax.train.state import TrainState
from irdepth_jax.xla_cpu import training_layers

LossFn = Callable[[Any, Any, Any, Any, jax.Array], tuple[jax.Array, tuple[dict, Any]]]


def pmean_if(tree: Any, axis_name: str | None) -> Any:
    """`lax.pmean` over `axis_name`, or the identity when it is None."""
    return tree if axis_name is None else lax.pmean(tree, axis_name)


def device_rng(rng: jax.Array, step: jax.Array, axis_name: str | None) -> jax.Array:
    """The key of one step (and one device under a mapping): fold_in(rng, step[, device])."""
    key = jax.random.fold_in(rng, step)
    if axis_name is not None:
        key = jax.random.fold_in(key, lax.axis_index(axis_name))
    return key


def split_micro_batches(batch: Any, accum_steps: int) -> Any:
    """Reshapes every leaf (B, ...) to (accum_steps, B // accum_steps, ...)."""

    def split(x):
        if x.shape[0] % accum_steps:
            raise ValueError(f"per-device batch of {x.shape[0]} does not split into "
                             f"{accum_steps} accumulation micro-batches")
        return x.reshape((accum_steps, x.shape[0] // accum_steps) + x.shape[1:])

    return jax.tree.map(split, batch)


def make_train_step(loss_fn: LossFn, axis_name: str | None = None, accum_steps: int = 1
                    ) -> Callable[[TrainState, Any, Any], tuple[TrainState, dict]]:
    """One optimizer update of `loss_fn` (see the module docstring).

    Args:
      loss_fn: per-device loss, see `LossFn`.
      axis_name: the mapped axis, or None on one device.
      accum_steps: micro-batches per update (the per-device batch must split evenly).
    Returns:
      ``train_step(state, batch, frozen) -> (new_state, metrics)``; `batch` is a tree of
      per-device arrays with leading batch axis, metrics are device-averaged float32 scalars
      (``loss``, the loss function's terms, ``grad_norm`` and ``lr_<group>``).
    """

    def grads_of(params, batch_stats, frozen, batch, rng):
        if axis_name is not None:
            params = lax.pcast(params, axis_name, to="varying")
        grad_fn = jax.value_and_grad(loss_fn, has_aux=True)
        (loss, (metrics, new_stats)), grads = grad_fn(params, batch_stats, frozen, batch, rng)
        return grads, new_stats, {"loss": loss, **metrics}

    def train_step(state: TrainState, batch: Any, frozen: Any = None):
        rng = device_rng(state.rng, state.step, axis_name)
        if accum_steps == 1:
            grads, new_stats, metrics = grads_of(state.params, state.batch_stats, frozen, batch,
                                                 rng)
        else:
            micro = split_micro_batches(batch, accum_steps)

            def body(carry, xs):
                grad_sum, stats = carry
                mb, i = xs
                grads, stats, metrics = grads_of(state.params, stats, frozen, mb,
                                                 jax.random.fold_in(rng, i))
                return (jax.tree.map(jnp.add, grad_sum, grads), stats), metrics

            # the metrics are the scan's outputs, not its carry: the carry's shapes are then
            # known without tracing the loss a second time (gradients have the parameters')
            init = (_like_varying(jax.tree.map(jnp.zeros_like, state.params), axis_name),
                    state.batch_stats)
            (grad_sum, new_stats), micro_metrics = lax.scan(
                body, init, (micro, jnp.arange(accum_steps)))
            grads = jax.tree.map(lambda g: g / accum_steps, grad_sum)
            metrics = jax.tree.map(lambda m: jnp.sum(m, axis=0) / accum_steps, micro_metrics)
        grads = pmean_if(grads, axis_name)
        metrics = pmean_if(metrics, axis_name)
        new_state = state.apply_gradients(grads, new_stats)
        metrics = {k: jnp.asarray(v, jnp.float32) for k, v in metrics.items()}
        metrics["grad_norm"] = optax.tree.norm(grads)
        metrics.update(new_state.learning_rates())
        return new_state, metrics

    return train_step


def _like_varying(tree: Any, axis_name: str | None) -> Any:
    """Marks a zero-initialised scan carry as device-varying (it accumulates varying values)."""
    return tree if axis_name is None else lax.pcast(tree, axis_name, to="varying")


# --------------------------------------------------------------------------- stage losses
def stage1_targets(ir8: jax.Array, grad_scale: float) -> tuple[jax.Array, jax.Array]:
    """Stage I targets from the camera's 8-bit image (B, H, W) uint8.

    Returns:
      (recon target (B, H, W, 1) = ir8 / 255,
       gradient-branch (saturation) target (B, H, W, 1) = clip(GCM(ir8 / 255) / grad_scale,
       0, 1)).
    """
    target = ir8.astype(jnp.float32)[..., None] / 255.0
    return target, jnp.clip(gradient_magnitude(target) / grad_scale, 0.0, 1.0)


def stage1_loss_fn(cfg: Config, phase: str, axis_name: str | None = None) -> LossFn:
    """The per-device Stage I loss of `phase` for `make_train_step`.

    * ``stage1_i1``: recon + w_grad * loss_gradient (all frames; labels unused).
    * ``stage1_i2`` (multitask): w_seg * CE + w_rec * (recon + w_grad * loss_gradient): every
      branch trains, the auxiliary branches keep their I-1 balance at the weight w_rec.

    The metrics are the terms (``recon``, ``loss_gradient``: the gradient branch's error against
    its target, not to be confused with the step's ``grad_norm``; ``ce`` in I-2) and ``psnr``.
    * ``stage1_i2`` with ``stage1.multitask=False``: CE only (the single-task segmentation
      baseline; the optimizer also freezes the recon / gradient branches).

    Batch keys: ``raw14`` (B, H, W) uint16, ``ir8`` (B, H, W) uint8, ``seg`` (B, H, W) uint8
    (255 = unlabelled: frames without labels add only ignored pixels, never NaN).
    """
    s1 = cfg.stage1
    model = MTSAUNet(cfg.unet, axis_name=axis_name)
    if phase not in ("stage1_i1", "stage1_i2"):
        raise ValueError(f"unknown Stage I phase {phase!r}")

    def loss_fn(params, batch_stats, frozen, batch, rng):
        x = unet_input(batch["raw14"], cfg, batch.get("brightness"))
        with training_layers():
            out, updates = model.apply({"params": params, "batch_stats": batch_stats}, x,
                                       train=True, mutable=["batch_stats"])
        recon_t, sat_t = stage1_targets(batch["ir8"], s1.grad_target_scale)
        terms = {"recon": reconstruction_loss(out["recon"], recon_t, kind=s1.recon_loss),
                 "loss_gradient": reconstruction_loss(out["saturation"], sat_t,
                                                      kind=s1.recon_loss)}
        if phase == "stage1_i1":
            weights = {"recon": 1.0, "loss_gradient": s1.w_grad}
        else:
            terms["ce"] = cross_entropy_loss(out["seg_logits"], batch["seg"], IGNORE_LABEL)
            aux = s1.w_rec if s1.multitask else 0.0
            weights = {"ce": s1.w_seg, "recon": aux, "loss_gradient": aux * s1.w_grad}
        total, _ = multitask_loss(terms, weights)
        mse = jnp.mean((out["recon"] - recon_t) ** 2)
        metrics = {**terms, "psnr": -10.0 * jnp.log10(jnp.maximum(mse, 1e-10))}
        return total, (metrics, updates["batch_stats"])

    return loss_fn


def stage2_loss_fn(cfg: Config, ref_depth: float, axis_name: str | None = None) -> LossFn:
    """SiLog + lambda_sky * sky loss (Stage II) for `make_train_step`.

    The sky loss is the mean relative error |pred / ref_depth - 1| (L1; squared for 'l2') over
    the sky pixels of the frozen segmentation branch (argmax == sky), so lambda_sky weighs it
    against SiLog in comparable units.

    `frozen` = ``{'unet': Stage I variables}`` (never differentiated), params = Depth Anything
    V2 params. Batch keys: ``raw14``, ``depth`` (B, H, W) metres, ``valid`` (B, H, W) bool,
    and ``image`` for non-HSV pre-processing. `ref_depth`: the sky's target depth
    (`train.stages.sky_reference_depth`: 0.99 x the largest depth the head and metrics
    allow). `axis_name` is unused (no BatchNorm in Depth Anything
    V2; the frozen UNet runs in eval mode): it keeps the signature of `stage1_loss_fn`.
    """
    s2, d = cfg.stage2, cfg.data

    def loss_fn(params, batch_stats, frozen, batch, rng):
        unet = None if frozen is None else frozen.get("unet")
        with training_layers():  # the pipeline traced here, not a cached trace of its jit
            out = pipeline_outputs(unet, params, batch.get("raw14"), cfg, image=batch.get("image"),
                                   brightness=batch.get("brightness"))
        pred, sky = out["depth"], out["sky"]
        gt = batch["depth"].astype(jnp.float32)
        valid = batch["valid"].astype(bool) & (gt >= d.min_depth) & (gt <= d.max_depth)
        terms = {"silog": silog_loss(pred, gt, valid, s2.silog_lambda)}
        weights = {"silog": 1.0}
        if s2.sky_loss:
            # Relative error |pred / ref - 1|: in metres (|pred - ref|, tens of metres on an
            # untrained model) the sky term outweighs SiLog (log units, ~1) at any small lambda
            # and drives the sigmoid head into saturation.
            terms["sky"] = sky_loss(pred / ref_depth, sky, 1.0, s2.sky_loss_kind)
            weights["sky"] = s2.lambda_sky
        total, _ = multitask_loss(terms, weights)
        ratio = jnp.maximum(pred / jnp.maximum(gt, 1e-6), gt / jnp.maximum(pred, 1e-6))
        d1 = jnp.sum((ratio < 1.25) & valid) / jnp.maximum(jnp.sum(valid), 1)
        return total, ({**terms, "d1": d1}, batch_stats)

    return loss_fn
