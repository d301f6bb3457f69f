"""Training losses: SiLog, sky, reconstruction, pixel cross-entropy and their weighted sum.

All are pure `jax.numpy` functions returning a float32 scalar, jit-able and differentiable. Masks
select the pixels that count; an empty mask gives a loss of 0 with a finite (zero) gradient:
masked-out entries are replaced by safe values *before* any log / sqrt / divide (the "double
where"), because `where(mask, f(x), 0)` alone still back-propagates NaN from f at masked pixels.

Depth maps may be (B, H, W) or (B, H, W, 1); masks have the same shape (or broadcast to it).
"""

from __future__ import annotations

from typing import Mapping

import jax.numpy as jnp
import optax

__all__ = [
    "cross_entropy_loss",
    "multitask_loss",
    "reconstruction_loss",
    "silog_loss",
    "sky_loss",
]


def _masked_mean(x: jnp.ndarray, mask: jnp.ndarray, axis=None) -> jnp.ndarray:
    """Mean of `x` over `mask` (bool, broadcastable to x) along `axis`; 0 where nothing is valid."""
    mask = jnp.broadcast_to(mask, x.shape)
    total = jnp.sum(jnp.where(mask, x, 0.0), axis=axis)
    count = jnp.sum(mask, axis=axis)
    return total / jnp.maximum(count, 1).astype(total.dtype)


def _safe_sqrt(x: jnp.ndarray) -> jnp.ndarray:
    """sqrt(x) for x > 0, 0 for x <= 0 (with a finite, zero gradient there), NaN for NaN."""
    nonpositive = x <= 0
    return jnp.where(nonpositive, 0.0, jnp.sqrt(jnp.where(nonpositive, 1.0, x)))


def silog_loss(
    pred: jnp.ndarray,
    target: jnp.ndarray,
    mask: jnp.ndarray,
    lambd: float = 0.5,
    eps: float = 1e-6,
) -> jnp.ndarray:
    """Scale-invariant log loss, as in Depth Anything V2's metric fine-tuning.

    d = log(target) - log(pred) over the valid pixels of the whole batch (pooled, not per
    image); loss = sqrt(mean(d^2) - lambd * mean(d)^2). With lambd = 1 it is fully invariant to a
    global scale of `pred`; 0.5 keeps some pressure on the absolute scale.

    Args:
      pred: (B, H, W) or (B, H, W, 1) predicted depth (> 0 where valid; values below `eps` are
        clamped to `eps` before the log, so a ReLU head at 0 gives a finite loss and gradient).
      target: ground-truth depth, same shape.
      mask: bool, same shape (or broadcastable): pixels that count.
      lambd: variance weight lambda in [0, 1].
      eps: lower clamp of pred and target inside the logs.
    Returns:
      float32 scalar; 0 (zero gradient) when the mask is empty; NaN when `pred` is NaN or
      +-inf on any pixel of the mask (the eps clamp would otherwise turn -inf into a finite
      loss; the mask should come from the ground truth only, never from `pred`).
    """
    pred = jnp.asarray(pred, jnp.float32)
    target = jnp.asarray(target, jnp.float32)
    mask = jnp.broadcast_to(jnp.asarray(mask, bool), pred.shape)
    safe_pred = jnp.maximum(jnp.where(mask, pred, 1.0), eps)
    safe_target = jnp.maximum(jnp.where(mask, target, 1.0), eps)
    d = jnp.log(safe_target) - jnp.log(safe_pred)
    mean_d = _masked_mean(d, mask)
    mean_d2 = _masked_mean(d * d, mask)
    nonfinite = jnp.any(mask & ~jnp.isfinite(pred))
    return jnp.where(nonfinite, jnp.nan, _safe_sqrt(mean_d2 - lambd * mean_d * mean_d))


def _pointwise_error(diff: jnp.ndarray, kind: str) -> jnp.ndarray:
    if kind == "l1":
        return jnp.abs(diff)
    if kind == "l2":
        return diff * diff
    raise ValueError(f"losses: `kind` must be 'l1' or 'l2', got {kind!r}")


def sky_loss(
    pred: jnp.ndarray,
    sky_mask: jnp.ndarray,
    ref_depth: float | jnp.ndarray,
    kind: str = "l1",
) -> jnp.ndarray:
    """Pulls predicted depth on sky pixels towards a far reference depth.

    Per image: mean of |pred - ref_depth| (kind 'l1') or (pred - ref_depth)^2 ('l2') over that
    image's sky pixels; then the mean over the images that have any sky. Images without sky add
    nothing (and do not dilute the mean); a batch without sky gives 0. Averaging per image (rather
    than pooling the batch's sky pixels) follows the paper's "mean error over the sky pixels of
    an image" and keeps frames with a little sky from being drowned by frames that are mostly
    sky. L1 is the default: robust to the few mislabelled sky pixels the segmentation branch
    produces, and in depth units (metres), so its weight is easy to read next to SiLog.

    Args:
      pred: (B, H, W) or (B, H, W, 1) predicted depth.
      sky_mask: bool, same shape (or broadcastable): sky pixels.
      ref_depth: scalar reference depth (the paper: 0.99 x the largest training depth).
      kind: 'l1' or 'l2'.
    Returns:
      float32 scalar.
    """
    pred = jnp.asarray(pred, jnp.float32)
    sky_mask = jnp.broadcast_to(jnp.asarray(sky_mask, bool), pred.shape)
    err = _pointwise_error(pred - jnp.asarray(ref_depth, jnp.float32), kind)
    image_axes = tuple(range(1, pred.ndim))
    per_image = _masked_mean(err, sky_mask, axis=image_axes)
    has_sky = jnp.any(sky_mask, axis=image_axes)
    return _masked_mean(per_image, has_sky)


def reconstruction_loss(
    pred: jnp.ndarray,
    target: jnp.ndarray,
    mask: jnp.ndarray | None = None,
    kind: str = "l1",
) -> jnp.ndarray:
    """Mean absolute ('l1') or squared ('l2') error, over the masked elements.

    Args:
      pred: any shape, e.g. (B, H, W, 1) reconstruction in [0, 1].
      target: same shape.
      mask: optional bool broadcastable to pred (None: every element).
      kind: 'l1' or 'l2'.
    Returns:
      float32 scalar; 0 for an empty mask.
    """
    pred = jnp.asarray(pred, jnp.float32)
    err = _pointwise_error(pred - jnp.asarray(target, jnp.float32), kind)
    if mask is None:
        return jnp.mean(err)
    return _masked_mean(err, jnp.asarray(mask, bool))


def cross_entropy_loss(
    logits: jnp.ndarray, labels: jnp.ndarray, ignore_label: int = 255
) -> jnp.ndarray:
    """Pixel-wise softmax cross-entropy, mean over the pixels whose label is not `ignore_label`.

    Args:
      logits: (B, H, W, C) unnormalised class scores.
      labels: (B, H, W) integer labels in [0, C) or `ignore_label`.
      ignore_label: label of unlabelled pixels.
    Returns:
      float32 scalar; 0 (zero gradient) when every pixel is ignored.
    """
    logits = jnp.asarray(logits, jnp.float32)
    labels = jnp.asarray(labels)
    if logits.shape[:-1] != labels.shape:
        raise ValueError(
            f"cross_entropy_loss: `logits` {logits.shape} must be `labels` {labels.shape} + (C,)"
        )
    valid = labels != ignore_label
    safe_labels = jnp.where(valid, labels, 0).astype(jnp.int32)
    ce = optax.softmax_cross_entropy_with_integer_labels(logits, safe_labels)
    return _masked_mean(ce, valid)


def multitask_loss(
    terms: Mapping[str, jnp.ndarray], weights: Mapping[str, float]
) -> tuple[jnp.ndarray, dict[str, jnp.ndarray]]:
    """Weighted sum of named scalar losses, plus a flat dict for logging.

    Args:
      terms: name -> scalar loss.
      weights: name -> weight; every term needs one (extra weights are ignored, so one weight
        table serves configurations that switch a term off).
    Returns:
      (total, logs) with logs = {name: raw term, name + '_weighted': weight * term, 'total'}.
    """
    missing = sorted(set(terms) - set(weights))
    if missing:
        raise ValueError(f"multitask_loss: no weight for loss terms {missing}")
    logs: dict[str, jnp.ndarray] = {}
    total = jnp.zeros((), jnp.float32)
    for name, term in terms.items():
        weighted = weights[name] * jnp.asarray(term, jnp.float32)
        logs[name] = term
        logs[f"{name}_weighted"] = weighted
        total = total + weighted
    logs["total"] = total
    return total, logs
