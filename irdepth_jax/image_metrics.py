"""Image and segmentation metrics: PSNR, SSIM, entropy (dm-pix / by definition), the confusion
matrix, per-class IoU and mIoU (the depth metrics are in `irdepth_jax.metrics`)."""

from __future__ import annotations

import functools

import dm_pix
import jax
import jax.numpy as jnp

__all__ = ["confusion_matrix", "entropy", "mean_iou", "per_class_iou", "psnr", "ssim"]


def _as_images(a, b, name: str) -> tuple[jnp.ndarray, jnp.ndarray, bool]:
    """(H, W) / (H, W, C) / (B, H, W, C) -> float32 NHWC-compatible rank 3 or 4, + batched?"""
    a = jnp.asarray(a, jnp.float32)
    b = jnp.asarray(b, jnp.float32)
    if a.shape != b.shape:
        raise ValueError(f"{name}: image shapes differ: {a.shape} vs {b.shape}")
    if a.ndim == 2:
        return a[..., None], b[..., None], False
    if a.ndim in (3, 4):
        return a, b, a.ndim == 4
    raise ValueError(f"{name}: expected (H, W), (H, W, C) or (B, H, W, C), got {a.shape}")


@jax.jit
def psnr(a, b, data_range: float = 1.0) -> jnp.ndarray:
    """Peak signal-to-noise ratio in dB, 10 log10(data_range^2 / MSE) (inf for equal images).

    Args:
      a, b: (H, W), (H, W, C) or (B, H, W, C) images of the same shape.
      data_range: max - min of the value range (1.0 for [0, 1], 255 for 8-bit values).
    Returns:
      scalar for a single image, (B,) for a batch.
    """
    a, b, _ = _as_images(a, b, "psnr")
    return dm_pix.psnr(a / data_range, b / data_range)


@jax.jit
def ssim(a, b, data_range: float = 1.0) -> jnp.ndarray:
    """Structural similarity, Gaussian window 11x11 (sigma 1.5), k1 0.01, k2 0.03.

    `dm_pix.ssim`: equal (to float32 precision) to
    skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=data_range[, channel_axis=-1]): both average the
    SSIM map over the region the window fits in and average channels equally.

    Args:
      a, b: (H, W), (H, W, C) or (B, H, W, C) images of the same shape, H, W >= 11.
      data_range: max - min of the value range.
    Returns:
      scalar for a single image, (B,) for a batch.
    """
    a, b, _ = _as_images(a, b, "ssim")
    return dm_pix.ssim(a, b, max_val=data_range)


@jax.jit
def entropy(img) -> jnp.ndarray:
    """Shannon entropy in bits of the 256-bin histogram of all values of an 8-bit image.

    Args:
      img: uint8 array of any shape (one image; call per image for a batch).
    Returns:
      float32 scalar in [0, 8].
    """
    img = jnp.asarray(img)
    if img.dtype != jnp.uint8:
        raise ValueError(f"entropy: `img` must be uint8, got {img.dtype}")
    p = jnp.bincount(img.ravel(), length=256) / img.size
    return -jnp.sum(jnp.where(p > 0, p * jnp.log2(jnp.where(p > 0, p, 1.0)), 0.0))


@functools.partial(jax.jit, static_argnames=("num_classes", "ignore_label"))
def confusion_matrix(pred_labels, labels, num_classes: int, ignore_label: int = 255):
    """Confusion matrix counts, rows = ground truth, columns = prediction.

    Pixels whose label is `ignore_label` (or outside [0, num_classes), as is a prediction out of
    range) are not counted.

    Args:
      pred_labels: integer array (any shape), predicted classes.
      labels: integer array of the same shape, ground truth.
      num_classes: C.
      ignore_label: label of unlabelled pixels.
    Returns:
      (C, C) int32. Sum batches on the host in int64 for large datasets (int32 overflows past
      2^31 pixels).
    """
    pred_labels = jnp.asarray(pred_labels).astype(jnp.int32).ravel()
    labels = jnp.asarray(labels).astype(jnp.int32).ravel()
    valid = (
        (labels != ignore_label)
        & (labels >= 0) & (labels < num_classes)
        & (pred_labels >= 0) & (pred_labels < num_classes)
    )
    index = jnp.where(valid, labels * num_classes + pred_labels, 0)
    counts = jnp.bincount(index, weights=valid.astype(jnp.int32), length=num_classes**2)
    return counts.astype(jnp.int32).reshape(num_classes, num_classes)


def per_class_iou(cm) -> tuple[jnp.ndarray, jnp.ndarray]:
    """IoU of each class from a confusion matrix: TP / (TP + FP + FN).

    Args:
      cm: (C, C) counts, rows = ground truth, columns = prediction.
    Returns:
      (iou (C,) float32, present (C,) bool): present = the class occurs in the ground truth or
      in the prediction; absent classes get IoU 0 (no NaN).
    """
    cm = jnp.asarray(cm, jnp.float32)
    tp = jnp.diag(cm)
    union = cm.sum(axis=0) + cm.sum(axis=1) - tp
    present = union > 0
    return jnp.where(present, tp / jnp.where(present, union, 1.0), 0.0), present


def mean_iou(cm) -> jnp.ndarray:
    """Mean IoU over the classes present in the ground truth or the prediction.

    A class absent from both has no defined IoU and is left out (counting it as 1 or 0 would
    move the mean with the number of classes a split happens to lack). A class predicted but
    absent from the ground truth counts, with IoU 0. No class present -> 0.

    Args:
      cm: (C, C) counts, rows = ground truth, columns = prediction.
    Returns:
      float32 scalar in [0, 1].
    """
    iou, present = per_class_iou(cm)
    return jnp.sum(iou) / jnp.maximum(jnp.sum(present), 1)
