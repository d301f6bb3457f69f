"""Detail-enhancing tone maps of raw LWIR frames: the guided filter, DDE (base / detail split,
plateau HE on the base) and `camera_like`, our stand-in for a camera's built-in raw -> 8-bit
chain (the paper's IRCBA). Conventions as in `irdepth_jax.imaging.tonemap`, where to import them
from.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from irdepth_jax.imaging.tonemap_histogram import (
    MID_GREY,
    OUT_LEVELS,
    _check_plateau,
    _check_raw,
    _double_plateau_lut,
    _histogram,
    _plateau_lut,
)


def guided_filter(guide: np.ndarray, src: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """Guided filter of He et al. (2010/2013), box-filter form (cv2.ximgproc is not in the
    opencv-python-headless wheel, so we write the five box filters ourselves).

    Args:
      guide, src: (H, W) float32 images (use guide = src for the edge-preserving smoother).
      radius: box radius r (window 2r + 1).
      eps: regulariser in squared intensity units: edges with local variance >> eps are kept,
        flat regions with variance << eps are averaged.
    Returns:
      (H, W) float32 filtered image.
    """
    size = (2 * radius + 1, 2 * radius + 1)

    def box(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, cv2.CV_32F, size, borderType=cv2.BORDER_REFLECT)

    # Centred copies: raw counts ~ 5000 squared lose the small local variances to float32
    # cancellation in E[I^2] - E[I]^2. The filter is shift-equivariant, so add the mean back.
    offset = np.float32(src.mean())
    guide = np.asarray(guide, np.float32) - np.float32(guide.mean())
    src = np.asarray(src, np.float32) - offset
    mean_i, mean_p = box(guide), box(src)
    cov_ip = box(guide * src) - mean_i * mean_p
    var_i = box(guide * guide) - mean_i * mean_i
    a = cov_ip / (var_i + np.float32(eps))
    b = mean_p - a * mean_i
    return box(a) * guide + box(b) + offset


def _robust_span(hist: np.ndarray) -> float:
    """Distance between the 1st and 99th percentile levels of a histogram (>= 1)."""
    cdf = np.cumsum(hist)
    lo, hi = np.searchsorted(cdf, [0.01 * cdf[-1], 0.99 * cdf[-1]])
    return float(max(hi - lo, 1))


def _to_levels(x: np.ndarray, bits: int) -> np.ndarray:
    """Float raw-count image -> integer levels in [0, 2^bits - 1] for histogramming."""
    return np.clip(np.rint(x), 0, 2**bits - 1).astype(np.intp)


def _dde_float(
    x: np.ndarray,
    radius: int,
    edge_rel: float,
    gain: float,
    detail_clip_rel: float,
    base_lut: Callable[[np.ndarray], np.ndarray],
    bits: int,
) -> np.ndarray:
    """DDE core on a float32 raw-count image of `bits`-bit counts; `base_lut(levels)` -> a LUT
    over the levels 0..levels.max() in [0, 255]."""
    hist = _histogram(_to_levels(x, bits))
    span = _robust_span(hist)
    base = guided_filter(x, x, radius, (edge_rel * span) ** 2)
    detail = np.clip(x - base, -detail_clip_rel * span, detail_clip_rel * span)
    base_levels = _to_levels(base, bits)
    base8 = np.take(base_lut(base_levels).astype(np.float32), base_levels)
    out = base8 + detail * np.float32(gain * (OUT_LEVELS - 1) / span)
    lo, hi = float(out.min()), float(out.max())
    if hi - lo < 1e-6:
        return np.full(x.shape, MID_GREY, np.uint8)
    return np.rint((out - lo) * ((OUT_LEVELS - 1) / (hi - lo))).astype(np.uint8)


def dde(
    raw: np.ndarray,
    radius: int = 2,
    edge_rel: float = 0.02,
    gain: float = 3.0,
    detail_clip_rel: float = 0.05,
    plateau: float | None = None,
    bits: int = 14,
) -> np.ndarray:
    """Digital detail enhancement: guided-filter base/detail split, plateau HE on the base.

    base = self-guided filter of the raw frame (radius `radius`, eps = (edge_rel * S)^2 with S the
    1-99 % raw span); detail = raw - base, clipped to +-detail_clip_rel * S (bounds halos and
    hot-pixel spikes) and amplified: gain * 255 / S display levels per raw count, i.e. `gain`
    times the slope of a linear 1-99 % stretch. base -> plateau HE (plateau `plateau`, default
    the adaptive T_up of `double_plateau_thresholds` on the base histogram); sum; min-max
    rescale to [0, 255].

    Args:
      raw: (H, W) uint16 raw frame.
      radius: guided-filter box radius (window 2 radius + 1).
      edge_rel: guided-filter edge scale as a fraction of the 1-99 % span S.
      gain: detail amplification relative to a linear 1-99 % stretch.
      detail_clip_rel: detail clip as a fraction of S.
      plateau: base plateau in pixels, or None (adaptive T_up).
      bits: bit depth of the counts, 14 or 16 (the accepted range 0..2^bits-1).
    Returns:
      (H, W) uint8.
    """
    raw = _check_raw(raw, bits)
    _check_plateau(plateau, "dde")
    return _dde_float(
        raw.astype(np.float32), radius, edge_rel, gain, detail_clip_rel,
        lambda levels: _plateau_lut(levels, plateau), bits,
    )


def frequency_denoise(
    x: np.ndarray, cutoff: float = 0.35, destripe: bool = True, stripe_width: int = 7
) -> np.ndarray:
    """Camera-style clean-up of a raw frame: column-stripe removal, then a Gaussian low-pass
    applied in the frequency domain.

    Stripes: microbolometer read-out gives each column a small offset (fixed-pattern noise).
    The offset of a column is estimated as the median over rows of (x - its horizontal local
    mean over `stripe_width` columns) and subtracted. We do not notch the ky = 0 line of the
    spectrum: that line also holds every scene structure that spans whole columns (the mean of
    each column), so a notch blurs full-height edges and smears a hot object into a full-height
    band; the median ignores objects that cover less than half of a column's rows.

    Low-pass: the rfft2 spectrum is weighted by exp(-f^2 / (2 cutoff^2)), f in cycles/pixel
    (Nyquist = 0.5); cutoff 0.35 damps pixel noise only mildly (a spatial sigma of 0.45 px).

    Args:
      x: (H, W) raw counts (any real dtype).
      cutoff: Gaussian sigma in cycles/pixel.
      destripe: remove column offsets first.
      stripe_width: odd width of the horizontal local mean, >= 3.
    Returns:
      (H, W) float32.
    """
    if stripe_width < 3 or stripe_width % 2 == 0:
        raise ValueError(f"frequency_denoise: `stripe_width` must be odd >= 3, got {stripe_width}")
    x = np.asarray(x, np.float32)
    h, w = x.shape
    if destripe:
        local = cv2.blur(x, (stripe_width, 1), borderType=cv2.BORDER_REFLECT)
        x = x - np.median(x - local, axis=0)[None, :]
    fy = np.fft.fftfreq(h).astype(np.float32)[:, None]
    fx = np.fft.rfftfreq(w).astype(np.float32)[None, :]
    gain = np.exp(-(fx * fx + fy * fy) / np.float32(2 * cutoff * cutoff))
    return np.fft.irfft2(np.fft.rfft2(x) * gain, s=(h, w)).astype(np.float32)


def camera_like(
    raw: np.ndarray,
    radius: int = 2,
    edge_rel: float = 0.02,
    gain: float = 3.0,
    detail_clip_rel: float = 0.05,
    cutoff: float = 0.35,
    window: int = 5,
    bits: int = 14,
) -> np.ndarray:
    """Our stand-in for a camera's built-in raw -> 8-bit chain (the paper's IRCBA).

    `frequency_denoise` (column-stripe removal + frequency-domain Gaussian low-pass) -> DDE
    (`dde`'s base/detail split) whose base is mapped by double-plateau HE (`double_plateau_he`'s
    adaptive thresholds). Used as the 8-bit reconstruction target when a
    dataset has no camera output.

    Args:
      raw: (H, W) uint16 raw frame.
      radius, edge_rel, gain, detail_clip_rel: DDE parameters (see `dde`).
      cutoff: low-pass sigma in cycles/pixel (see `frequency_denoise`).
      window: local-maximum window of the double-plateau thresholds.
      bits: bit depth of the counts, 14 or 16 (the accepted range 0..2^bits-1).
    Returns:
      (H, W) uint8.
    """
    raw = _check_raw(raw, bits)
    if raw.min() == raw.max():
        return np.full(raw.shape, MID_GREY, np.uint8)
    clean = frequency_denoise(raw, cutoff=cutoff)
    return _dde_float(
        clean, radius, edge_rel, gain, detail_clip_rel, lambda lv: _double_plateau_lut(lv, window),
        bits,
    )

