"""Depth metrics (with alignment) and sky metrics (image quality and mIoU: `irdepth_jax.image_metrics`).

Depth metrics follow Depth Anything V2's `metric_depth/util/metric.py` (per image, then the mean
over images), with the validity range of its training script and the MS2 protocol's prediction
clamp and per-image alignment:

* valid = mask & (min_depth <= gt <= max_depth); images with fewer than 10 valid pixels are
  skipped (they count in no mean and not in 'count');
* alignment (optional, per image, on the valid pixels): 'median' scales pred by
  median(gt) / median(pred) (metric models in the MS2 protocol); 'scale_shift' fits s, t by
  least squares on depth, min sum (s * pred + t - gt)^2 (for a relative model that predicts
  disparity, invert it to depth first);
* then pred is clamped to [min_depth, max_depth];
* a prediction that is NaN or +-inf on a valid pixel makes every metric of its image NaN (the
  clamp would otherwise turn +-inf into max_depth / min_depth, and comparisons with NaN into
  d_k = 0), so it also makes every mean the image enters NaN; non-finite predicted pixels are
  counted ('nonfinite') over the whole image, valid or not;
* thresh = max(gt / p, p / gt); d_k = mean(thresh < 1.25^k); abs_rel = mean(|p - gt| / gt);
  sq_rel = mean((p - gt)^2 / gt); rmse = sqrt(mean((p - gt)^2));
  rmse_log = sqrt(mean((ln p - ln gt)^2)); log10 = mean(|log10 p - log10 gt|);
  silog = sqrt(mean(d^2) - 0.5 * mean(d)^2) with d = ln p - ln gt: the SiLog *loss* formula with
  lambda 0.5 and no x100 factor, exactly as Depth Anything V2 evaluates it (KITTI's benchmark
  uses lambda 1 and x100; the numbers are not comparable with that one).
"""

from __future__ import annotations

import functools
from typing import Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from irdepth_jax.losses import silog_loss

__all__ = [
    "DEPTH_METRICS",
    "DepthMetricAccumulator",
    "SKY_METRICS",
    "SkyMetricAccumulator",
    "depth_metrics",
    "per_image_depth_metrics",
    "per_image_sky_metrics",
]

DEPTH_METRICS: tuple[str, ...] = (
    "d1", "d2", "d3", "abs_rel", "sq_rel", "rmse", "rmse_log", "log10", "silog"
)
MIN_VALID_PIXELS = 10
_ALIGNMENTS = (None, "median", "scale_shift")


def _masked_median(x: jnp.ndarray, valid: jnp.ndarray) -> jnp.ndarray:
    """Median over (H, W) of each image's valid pixels, (B,); NaN for an image with none."""
    return jnp.nanmedian(jnp.where(valid, x, jnp.nan), axis=(1, 2))


def _align(pred: jnp.ndarray, gt: jnp.ndarray, valid: jnp.ndarray, align: str | None):
    """Per-image alignment of pred (B, H, W) to gt on the valid pixels."""
    if align is None:
        return pred
    if align == "median":
        med_pred = _masked_median(pred, valid)
        med_gt = _masked_median(gt, valid)
        ok = jnp.isfinite(med_pred) & (med_pred > 0) & jnp.isfinite(med_gt)
        scale = jnp.where(ok, med_gt / jnp.where(ok, med_pred, 1.0), 1.0)
        return pred * scale[:, None, None]
    # Closed-form least squares for (s, t) from masked sums.
    w = valid.astype(pred.dtype)
    n = w.sum(axis=(1, 2))
    sp, sg = (w * pred).sum(axis=(1, 2)), (w * gt).sum(axis=(1, 2))
    spp, spg = (w * pred * pred).sum(axis=(1, 2)), (w * pred * gt).sum(axis=(1, 2))
    det = n * spp - sp * sp
    ok = det > 1e-12 * jnp.maximum(n * spp, 1.0)  # pred not constant on the valid pixels
    scale = jnp.where(ok, (n * spg - sp * sg) / jnp.where(ok, det, 1.0), 0.0)
    shift = (sg - scale * sp) / jnp.maximum(n, 1.0)
    return pred * scale[:, None, None] + shift[:, None, None]


@functools.partial(jax.jit, static_argnames=("align",))
def _per_image(pred, gt, mask, align, min_depth, max_depth):
    valid = mask & (gt >= min_depth) & (gt <= max_depth)
    nonfinite = ~jnp.isfinite(pred)
    pred = jnp.clip(_align(pred, gt, valid, align), min_depth, max_depth)
    # Safe values off the mask so no log / divide sees a zero (gradients stay finite too).
    p = jnp.where(valid, pred, 1.0)
    g = jnp.where(valid, gt, 1.0)
    count = valid.sum(axis=(1, 2))
    denom = jnp.maximum(count, 1).astype(jnp.float32)

    def mean(x):
        return jnp.where(valid, x, 0.0).sum(axis=(1, 2)) / denom

    thresh = jnp.maximum(g / p, p / g)
    diff = p - g
    diff_log = jnp.log(p) - jnp.log(g)
    out = {
        "d1": mean(thresh < 1.25),
        "d2": mean(thresh < 1.25**2),
        "d3": mean(thresh < 1.25**3),
        "abs_rel": mean(jnp.abs(diff) / g),
        "sq_rel": mean(diff * diff / g),
        "rmse": jnp.sqrt(mean(diff * diff)),
        "rmse_log": jnp.sqrt(mean(diff_log * diff_log)),
        "log10": mean(jnp.abs(diff_log) / jnp.log(10.0)),
        "silog": jax.vmap(lambda a, b, m: silog_loss(a[None], b[None], m[None], lambd=0.5))(
            p, g, valid
        ),
    }
    broken = jnp.any(valid & nonfinite, axis=(1, 2))
    out = {k: jnp.where(broken, jnp.nan, v) for k, v in out.items()}
    out["nonfinite"] = nonfinite.sum(axis=(1, 2))
    out["used"] = count >= MIN_VALID_PIXELS
    return out


def _as_bhw(x, name: str) -> jnp.ndarray:
    x = jnp.asarray(x)
    if x.ndim == 4 and x.shape[-1] == 1:
        x = x[..., 0]
    if x.ndim != 3:
        raise ValueError(
            f"depth metrics: `{name}` must be (B, H, W) or (B, H, W, 1), got {x.shape}"
        )
    return x


def per_image_depth_metrics(
    pred,
    gt,
    mask=None,
    align: str | None = None,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
) -> dict[str, jnp.ndarray]:
    """Depth metrics of each image (see the module docstring for the definitions).

    Args:
      pred: (B, H, W) or (B, H, W, 1) predicted depth.
      gt: ground-truth depth, same shape.
      mask: optional bool, same shape: pixels with a label (None: all).
      align: None, 'median' or 'scale_shift'.
      min_depth, max_depth: valid gt range and prediction clamp.
    Returns:
      dict of (B,) float32 arrays, one per name in `DEPTH_METRICS` (NaN for an image whose
      prediction is non-finite on a valid pixel), plus 'used' (B,) bool: whether the image has
      >= 10 valid pixels (the metrics of unused images are meaningless), and 'nonfinite' (B,)
      int32: the image's pixels where pred is NaN or +-inf (valid or not).
    """
    if align not in _ALIGNMENTS:
        raise ValueError(f"depth metrics: `align` must be one of {_ALIGNMENTS}, got {align!r}")
    pred = _as_bhw(pred, "pred").astype(jnp.float32)
    gt = _as_bhw(gt, "gt").astype(jnp.float32)
    if pred.shape != gt.shape:
        raise ValueError(f"depth metrics: `pred` {pred.shape} and `gt` {gt.shape} differ")
    mask = jnp.ones(gt.shape, bool) if mask is None else _as_bhw(mask, "mask").astype(bool)
    return _per_image(pred, gt, mask, align, min_depth, max_depth)


def depth_metrics(
    pred,
    gt,
    mask=None,
    align: str | None = None,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
) -> dict[str, float]:
    """Depth metrics averaged over the images of a batch that have >= 10 valid pixels.

    Args: as `per_image_depth_metrics`.
    Returns:
      dict: each name in `DEPTH_METRICS` -> float (NaN when no image is usable or a usable one
      has a non-finite prediction on a valid pixel), 'count' -> int, the number of images
      averaged, and 'nonfinite_pixels' / 'nonfinite_images' -> int (see
      `DepthMetricAccumulator.result`).
    """
    acc = DepthMetricAccumulator(align=align, min_depth=min_depth, max_depth=max_depth)
    acc.update(pred, gt, mask)
    return acc.result()["all"]


class DepthMetricAccumulator:
    """Streams per-image depth metrics over batches; overall and per-condition means.

    Usage:
      acc = DepthMetricAccumulator(align="median")
      for batch in data: acc.update(pred, gt, mask, conditions=batch["condition"])
      acc.result()  # {'all': {...}, 'day': {...}, 'night': {...}}

    Sums of per-image metrics are kept in float64 on the host, so the result is the mean over
    all usable images seen (not a mean of batch means).
    """

    def __init__(self, align: str | None = None, min_depth: float = 1e-3, max_depth: float = 80.0,
                 keep_per_image: bool = False):
        if align not in _ALIGNMENTS:
            raise ValueError(f"DepthMetricAccumulator: `align` must be one of {_ALIGNMENTS}")
        self.align, self.min_depth, self.max_depth = align, min_depth, max_depth
        self._sums: dict[str, np.ndarray] = {}
        self._counts: dict[str, int] = {}
        self._nonfinite: dict[str, np.ndarray] = {}  # group -> [pixels, images]
        self._rows: list[np.ndarray] | None = [] if keep_per_image else None
        self._conditions: list[str | None] = []

    def update(self, pred, gt, mask=None, conditions: str | Sequence[str] | None = None) -> None:
        """Adds a batch.

        Args:
          pred, gt, mask: as `per_image_depth_metrics`.
          conditions: None, one name for the whole batch, or B names (e.g. 'day', 'night').
        """
        per_image = per_image_depth_metrics(
            pred, gt, mask, self.align, self.min_depth, self.max_depth
        )
        values = np.stack([np.asarray(per_image[k], np.float64) for k in DEPTH_METRICS], axis=1)
        used = np.asarray(per_image["used"])
        nonfinite = np.asarray(per_image["nonfinite"], np.int64)
        batch = values.shape[0]
        if conditions is None:
            names: Iterable[str | None] = [None] * batch
        elif isinstance(conditions, str):
            names = [conditions] * batch
        else:
            names = list(conditions)
            if len(names) != batch:
                raise ValueError(
                    f"DepthMetricAccumulator.update: {len(names)} conditions for {batch} images"
                )
        if self._rows is not None:
            self._rows.append(np.where(used[:, None], values, np.nan))
            self._conditions += names
        for row, is_used, bad, name in zip(values, used, nonfinite, names):
            for group in ("all",) if name is None else ("all", str(name)):
                if bad:
                    self._nonfinite[group] = self._nonfinite.get(group, 0) + np.array([bad, 1])
                if is_used:
                    self._sums[group] = self._sums.get(group, 0.0) + row
                    self._counts[group] = self._counts.get(group, 0) + 1

    def per_image(self) -> dict[str, np.ndarray]:
        """Every image seen, in order (needs keep_per_image=True): each `DEPTH_METRICS` name ->
        (N,) float64 (NaN for an image with < 10 valid pixels), 'condition' -> (N,) str."""
        if self._rows is None:
            raise ValueError("DepthMetricAccumulator.per_image: made without keep_per_image=True")
        values = (np.concatenate(self._rows) if self._rows
                  else np.zeros((0, len(DEPTH_METRICS))))
        out = {k: values[:, j] for j, k in enumerate(DEPTH_METRICS)}
        out["condition"] = np.asarray([str(c) for c in self._conditions])
        return out

    def result(self) -> dict[str, dict[str, float]]:
        """{'all': metrics, condition: metrics, ...}; each has the `DEPTH_METRICS` means,
        'count', and 'nonfinite_pixels' / 'nonfinite_images': the predicted pixels that were
        NaN or +-inf and the images holding any, over every image seen (used or not). An image
        with a non-finite prediction on a valid pixel makes the group's means NaN. 'all' is
        present even when empty (NaN metrics, count 0)."""
        out = {}
        groups = (set(self._counts) | set(self._nonfinite)) - {"all"}
        for group in ["all"] + sorted(groups):
            n = self._counts.get(group, 0)
            means = self._sums[group] / n if n else np.full(len(DEPTH_METRICS), np.nan)
            out[group] = {k: float(v) for k, v in zip(DEPTH_METRICS, means)}
            pixels, images = self._nonfinite.get(group, (0, 0))
            out[group].update(count=n, nonfinite_pixels=int(pixels), nonfinite_images=int(images))
        return out


SKY_METRICS: tuple[str, ...] = ("sky_far", "skyline_abs_rel")
"""What the usual depth metrics cannot see (they exclude sky pixels, which have no depth): the
sky loss's target and the boundary it sharpens (`per_image_sky_metrics`)."""


@functools.partial(jax.jit, static_argnames=("radius",))
def per_image_sky_metrics(pred, gt, mask, sky, ref_depth, radius: int = 3, factor: float = 0.9,
                          min_depth: float = 1e-3, max_depth: float = 80.0) -> dict[str, jnp.ndarray]:
    """Sky metrics of each image.

    Args:
      pred: (B, H, W) predicted depth (metres); gt, mask: (B, H, W) depth and its valid pixels;
      sky: (B, H, W) bool, the true sky pixels (labels); ref_depth: the sky reference depth
        (metres) the sky loss pushes sky pixels to.
      radius: the skyline band's half-width in pixels (Chebyshev distance to a sky pixel).
      factor: a sky pixel counts as far when pred >= factor * ref_depth.
      min_depth, max_depth: valid gt range and prediction clamp of the band's AbsRel.
    Returns:
      {'sky_far': (B,) share of the sky pixels predicted at >= factor * ref_depth (NaN without
      sky), 'skyline_abs_rel': (B,) AbsRel of the valid non-sky pixels within `radius` px of
      the sky (NaN where there is none)}.
    """
    pred, gt = jnp.asarray(pred, jnp.float32), jnp.asarray(gt, jnp.float32)
    sky = jnp.asarray(sky, bool)
    n_sky = sky.sum(axis=(1, 2))
    far = (jnp.where(sky, jnp.nan_to_num(pred, nan=0.0), 0.0) >= factor * ref_depth) & sky
    size = 2 * radius + 1
    near_sky = jax.lax.reduce_window(sky, False, jax.lax.bitwise_or, (1, size, size), (1, 1, 1),
                                     "SAME")
    band = near_sky & ~sky & jnp.asarray(mask, bool) & (gt >= min_depth) & (gt <= max_depth)
    n_band = band.sum(axis=(1, 2))
    p = jnp.clip(pred, min_depth, max_depth)
    rel = jnp.where(band, jnp.abs(p - gt) / jnp.where(band, gt, 1.0), 0.0).sum(axis=(1, 2))
    return {"sky_far": jnp.where(n_sky > 0, far.sum(axis=(1, 2)) / jnp.maximum(n_sky, 1), jnp.nan),
            "skyline_abs_rel": jnp.where(n_band > 0, rel / jnp.maximum(n_band, 1), jnp.nan)}


class SkyMetricAccumulator:
    """Streams `per_image_sky_metrics` over batches of labelled frames; overall and
    per-condition means of the images that have each metric (frames without labels count in
    none).

    Args: ref_depth, radius, factor, min_depth, max_depth: as `per_image_sky_metrics`.
    """

    def __init__(self, ref_depth: float, radius: int = 3, factor: float = 0.9,
                 min_depth: float = 1e-3, max_depth: float = 80.0):
        self.kw = dict(ref_depth=ref_depth, radius=radius, factor=factor, min_depth=min_depth,
                       max_depth=max_depth)
        self._rows: list[np.ndarray] = []
        self._conditions: list[str] = []

    def update(self, pred, gt, mask, sky, labeled, conditions: Sequence[str]) -> None:
        """Adds a batch: pred, gt, mask, sky (B, H, W); labeled (B,) bool (sky labels exist);
        conditions: B names."""
        out = per_image_sky_metrics(pred, gt, mask, sky, **self.kw)
        values = np.stack([np.asarray(out[k], np.float64) for k in SKY_METRICS], axis=1)
        self._rows.append(np.where(np.asarray(labeled, bool)[:, None], values, np.nan))
        self._conditions += [str(c) for c in conditions]

    def per_image(self) -> dict[str, np.ndarray]:
        """Each `SKY_METRICS` name -> (N,) float64 of every image seen (NaN: not measurable)."""
        values = np.concatenate(self._rows) if self._rows else np.zeros((0, len(SKY_METRICS)))
        return {k: values[:, j] for j, k in enumerate(SKY_METRICS)}

    def result(self) -> dict[str, dict[str, float]]:
        """{'all': {name: mean, name_count: images}, condition: {...}, ...}."""
        values, conditions = self.per_image(), np.asarray(self._conditions)
        out = {}
        for group in ["all"] + sorted(set(self._conditions)):
            pick = slice(None) if group == "all" else conditions == group
            out[group] = {}
            for k, v in values.items():
                v = v[pick][np.isfinite(v[pick])]
                out[group][k] = float(v.mean()) if len(v) else float("nan")
                out[group][f"{k}_count"] = int(len(v))
        return out
