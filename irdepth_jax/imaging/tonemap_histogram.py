"""Histogram and percentile tone maps of raw LWIR frames: linear stretch with tail rejection,
global HE, plateau HE, double-plateau HE (Liang et al. 2012) and CLAHE, plus the frame check and
lookup-table helpers the detail-enhancing maps of `tonemap_camera` share. The conventions (input,
output, constant frames) are `irdepth_jax.imaging.tonemap`'s; that module is where to import them
from.
"""

from __future__ import annotations

import cv2
import numpy as np

from irdepth_jax.imaging.raw import check_raw

OUT_LEVELS = 256
MID_GREY = 128


def _check_raw(raw: np.ndarray, bits: int, arg: str = "raw") -> np.ndarray:
    """Validates one raw frame (2-D, integer counts 0..2^bits-1); returns it as uint16."""
    try:
        check_raw(raw, bits)
    except ValueError as err:
        raise ValueError(f"tonemap: `{arg}`: {err}") from None
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise ValueError(
            f"tonemap: `{arg}` must be one 2-D (H, W) raw frame, got shape {raw.shape}"
        )
    return raw.astype(np.uint16, copy=False)


def _histogram(levels: np.ndarray) -> np.ndarray:
    """Counts of each raw level 0..levels.max(), int64 (levels.max() + 1,)."""
    return np.bincount(levels.ravel())


def _equalizing_lut(hist: np.ndarray) -> np.ndarray:
    """Lookup table (K,) float64 in [0, 255] that equalises a (possibly clipped) histogram (K,).

    Same rule as OpenCV's `equalizeHist`, over K raw levels instead of 256: with c the cumulative
    histogram and c0 the count of the lowest occupied level,
    lut[v] = 255 * (c[v] - c0) / (c[-1] - c0). The lowest occupied level maps to 0 and the
    highest to 255. A histogram with one occupied level maps to mid-grey.
    """
    cdf = np.cumsum(hist, dtype=np.float64)
    first = cdf[np.flatnonzero(hist)[0]]
    span = cdf[-1] - first
    if span <= 0:
        return np.full(hist.size, float(MID_GREY))
    return np.clip((cdf - first) * ((OUT_LEVELS - 1) / span), 0.0, OUT_LEVELS - 1)


def _apply_lut(lut: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Rounds the float LUT to uint8 (half to even, as OpenCV) and indexes it with the levels."""
    return np.take(np.rint(lut).astype(np.uint8), levels)


def linear_tail(raw: np.ndarray, low: float = 1.0, high: float = 99.0, bits: int = 14
                ) -> np.ndarray:
    """Linear stretch with tail rejection: clip to the [low, high] percentiles, scale to 0-255.

    Args:
      raw: (H, W) uint16 raw frame.
      low, high: percentiles in [0, 100], low < high. They are the inverted-CDF percentiles of the
        raw histogram (the smallest level whose cumulative share reaches p %).
      bits: bit depth of the counts, 14 or 16 (the accepted range 0..2^bits-1).
    Returns:
      (H, W) uint8; levels <= the low percentile -> 0, >= the high one -> 255.
    """
    raw = _check_raw(raw, bits)
    if not 0.0 <= low < high <= 100.0:
        raise ValueError(f"linear_tail: need 0 <= low < high <= 100, got low={low}, high={high}")
    hist = _histogram(raw)
    cdf = np.cumsum(hist)
    lo, hi = np.searchsorted(cdf, [low / 100.0 * cdf[-1], high / 100.0 * cdf[-1]])
    if hi <= lo:
        # More than (high - low) % of the pixels on one level: use the full occupied range.
        occupied = np.flatnonzero(hist)
        lo, hi = occupied[0], occupied[-1]
        if hi == lo:
            return np.full(raw.shape, MID_GREY, np.uint8)
    levels = np.arange(hist.size, dtype=np.float64)
    lut = np.clip((levels - lo) * ((OUT_LEVELS - 1) / (hi - lo)), 0.0, OUT_LEVELS - 1)
    return _apply_lut(lut, raw)


def histogram_equalization(raw: np.ndarray, bits: int = 14) -> np.ndarray:
    """Global histogram equalisation over the raw levels (OpenCV `equalizeHist` rule).

    Args:
      raw: (H, W) uint16 raw frame.
      bits: bit depth of the counts, 14 or 16 (the accepted range 0..2^bits-1).
    Returns:
      (H, W) uint8; the lowest raw level present -> 0, the highest -> 255. For raw values that
      all lie in [0, 255] this equals `cv2.equalizeHist(raw.astype(np.uint8))` (except for a
      constant frame, which gives 128 here and the input value in OpenCV).
    """
    raw = _check_raw(raw, bits)
    return _apply_lut(_equalizing_lut(_histogram(raw)), raw)


def _check_plateau(plateau: float | None, fn: str) -> None:
    if plateau is not None and not plateau > 0:
        raise ValueError(f"{fn}: `plateau` must be > 0 or None, got {plateau}")


def _plateau_lut(levels: np.ndarray, plateau: float | None) -> np.ndarray:
    """Equalising LUT (K,) of the histogram of `levels` clipped at `plateau` (None: the
    adaptive T_up of `double_plateau_thresholds`)."""
    hist = _histogram(levels)
    cap = double_plateau_thresholds(hist)[0] if plateau is None else plateau
    return _equalizing_lut(np.minimum(hist, cap))


def plateau_he(raw: np.ndarray, plateau: float | None = None, bits: int = 14) -> np.ndarray:
    """Plateau histogram equalisation: clip every bin at `plateau`, then equalise.

    Limits the contrast a large uniform background (sky, road) takes from small objects;
    `plateau = inf` is plain HE, `plateau = 1` spreads the occupied levels evenly.

    Args:
      raw: (H, W) uint16 raw frame.
      plateau: bin cap in pixels, > 0; None (default): the adaptive upper plateau T_up of the
        double-plateau rule (`double_plateau_thresholds`).
      bits: bit depth of the counts, 14 or 16 (the accepted range 0..2^bits-1).
    Returns:
      (H, W) uint8.
    """
    raw = _check_raw(raw, bits)
    _check_plateau(plateau, "plateau_he")
    return _apply_lut(_plateau_lut(raw, plateau), raw)


def double_plateau_thresholds(hist: np.ndarray, window: int = 5) -> tuple[float, float]:
    """Adaptive upper / lower plateaus of Liang et al. 2012 (double-plateau HE for IR images).

    Rule used here:
      1. keep the non-zero bins of `hist`, in level order (L of them, N pixels in all);
      2. a local maximum is a bin equal to the maximum of the `window` bins centred on it (the
         sequence is padded with zeros, so its ends count when they top their neighbours);
         T_up = the mean of the local maxima;
      3. T_down = min(N, T_up * L) / 256 (256 = output levels): the bin height a histogram of
         L bins would have if it spread min(N, T_up * L) pixels over the 256 output levels.
         It is capped at T_up.

    Args:
      hist: (K,) non-negative bin counts (one per raw level).
      window: odd size >= 3 of the neighbourhood that defines a local maximum.
    Returns:
      (t_up, t_down) floats; (0, 0) for an empty histogram.
    """
    hist = np.asarray(hist, dtype=np.float64)
    if window < 3 or window % 2 == 0:
        raise ValueError(f"double_plateau_thresholds: `window` must be odd >= 3, got {window}")
    nz = hist[hist > 0]
    if nz.size == 0:
        return 0.0, 0.0
    r = window // 2
    padded = np.pad(nz, r)
    neighbourhood_max = np.lib.stride_tricks.sliding_window_view(padded, window).max(axis=1)
    t_up = float(nz[nz >= neighbourhood_max].mean())
    t_down = min(float(nz.sum()), t_up * nz.size) / OUT_LEVELS
    return t_up, min(t_down, t_up)


def _double_plateau_lut(levels: np.ndarray, window: int) -> np.ndarray:
    """Equalising LUT (K,) of the double-plateau-modified histogram of integer levels."""
    hist = _histogram(levels).astype(np.float64)
    t_up, t_down = double_plateau_thresholds(hist, window)
    occupied = hist > 0
    modified = np.where(occupied, np.clip(hist, t_down, t_up), 0.0)
    return _equalizing_lut(modified)


def double_plateau_he(raw: np.ndarray, window: int = 5, bits: int = 14) -> np.ndarray:
    """Double-plateau HE (Liang et al. 2012) with adaptive thresholds.

    Histogram modification before equalisation: empty bins stay 0; 0 < h <= T_down -> T_down
    (rare levels, e.g. small hot objects, keep some grey-level room); h >= T_up -> T_up (the
    background cannot take over the range); other bins unchanged. Thresholds: see
    `double_plateau_thresholds`.

    Args:
      raw: (H, W) uint16 raw frame.
      window: local-maximum window of the T_up rule (odd >= 3).
      bits: bit depth of the counts, 14 or 16 (the accepted range 0..2^bits-1).
    Returns:
      (H, W) uint8.
    """
    raw = _check_raw(raw, bits)
    return _apply_lut(_double_plateau_lut(raw, window), raw)


def clahe(
    raw: np.ndarray,
    clip_limit: float = 2.0,
    tiles: tuple[int, int] = (8, 8),
    levels: int | None = 1024,
    bits: int = 14,
) -> np.ndarray:
    """Contrast-limited adaptive HE with OpenCV's CLAHE on a 16-bit image.

    OpenCV handles uint16 with a 65536-bin histogram per tile, caps each bin at
    max(1, int(clipLimit * tile_area / 65536)) pixels, spreads the excess over all 65536 bins and
    maps through a LUT scaled to [0, 65535]. Fed raw counts directly, the cap is 1 pixel
    at any usual tile size (`clip_limit` does nothing) and the excess spread over unreachable bins
    squeezes the output into a narrow grey band. We therefore:
      1. quantise the frame's span [lo, hi] to n = min(levels, hi - lo + 1) histogram levels
         (levels=None: n = hi - lo + 1, one level per raw count, no quantisation) and spread
         them evenly over [0, 65535];
      2. pass clipLimit = clip_limit * 65536 / n, so the cap is int(clip_limit * tile_area / n)
         pixels (at least 1): `clip_limit` times the mean count per level, the meaning it has
         for an 8-bit image (n = 256). With n levels the cap exceeds 1 only when a tile holds
         more than n / clip_limit pixels (default n = 1024, clip 2: tiles of >= 512 pixels,
         e.g. 8x8 tiles on 256x320); a finer quantisation keeps more of the raw precision
         but makes the limit coarser;
      3. return round(out * 255 / 65535).
    With levels=256 this is OpenCV's 8-bit CLAHE of the min-max-stretched frame, and for a frame
    whose levels span exactly 0-255 it matches `cv2.createCLAHE` on the 8-bit image, within one
    level, wherever no bin is clipped. Where bins are clipped the two differ by a few levels:
    OpenCV hands the part of the excess E that does not divide evenly one pixel per bin every
    floor(histSize / E) bins starting at bin 0, which covers a different share of the range
    with 256 bins than with 65536 (either can stop short of the top). That is OpenCV's
    behaviour and we keep it.

    Args:
      raw: (H, W) uint16 raw frame.
      clip_limit: contrast limit, > 0 (2-3 usual).
      tiles: tile grid as (rows, cols).
      levels: histogram levels the frame's span is quantised to, >= 2, or None.
      bits: bit depth of the counts, 14 or 16 (the accepted range 0..2^bits-1).
    Returns:
      (H, W) uint8.
    """
    raw = _check_raw(raw, bits)
    if not clip_limit > 0:
        raise ValueError(f"clahe: `clip_limit` must be > 0, got {clip_limit}")
    if levels is not None and levels < 2:
        raise ValueError(f"clahe: `levels` must be >= 2 or None, got {levels}")
    lo, hi = int(raw.min()), int(raw.max())
    if lo == hi:
        return np.full(raw.shape, MID_GREY, np.uint8)
    n = hi - lo + 1 if levels is None else min(levels, hi - lo + 1)
    bins = (np.arange(hi - lo + 1) * n) // (hi - lo + 1)  # raw offset -> level in [0, n)
    stretched = np.take(np.rint(bins * (65535.0 / (n - 1))).astype(np.uint16), raw - lo)
    tiles_xy = (int(tiles[1]), int(tiles[0]))  # OpenCV's Size is (width, height)
    engine = cv2.createCLAHE(clipLimit=float(clip_limit) * 65536 / n, tileGridSize=tiles_xy)
    out16 = engine.apply(stretched)
    return ((out16.astype(np.uint32) * 255 + 32767) // 65535).astype(np.uint8)

