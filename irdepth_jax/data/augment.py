"""The paper's paired augmentation: one random draw applied to every aligned map of a sample.

Draws, in this order, from the given `np.random.Generator` (so a seed fixes the result):
  1. centre crop with probability 0.1, side ratio in [0.8, 1.0], resized back to (H, W);
  2. brightness factor in [0.8, 1.2] with probability 0.1;
  3. horizontal flip with probability 0.5.
All numbers are drawn whether or not a step fires, so one step's probability never shifts the
next step's draw.

Per map:
  * crop + resize: intensity maps (raw14, ir8, rgb) bilinearly (raw stays uint16); label-like
    maps (depth, depth_dense, valid, seg) with exact nearest neighbour, so no value is
    interpolated across objects: every output depth / label value occurs in the input, and
    `valid` keeps marking exactly the pixels whose depth is > 0.
  * brightness: ir8 and rgb are multiplied by the factor (clipped to 0..255). raw14 holds
    physical counts, not brightness: it gets the radiometric analogue, a responsivity (gain)
    change around the frame mean, `mean + factor * (raw - mean)` clipped to 14 bits, so the
    absolute level of the scene is kept and only the contrast of the counts scales.
  * flip: every map.
Non-map entries (id, condition, labeled, has_rgb, ...) are passed through.
"""

from __future__ import annotations

import cv2
import numpy as np

from irdepth_jax.imaging.raw import RAW_MAX

INTENSITY_KEYS = ("raw14", "ir8", "rgb")
LABEL_KEYS = ("depth", "depth_dense", "valid", "seg")


def augment(sample: dict, rng: np.random.Generator, *, p_crop: float = 0.1,
            crop_range: tuple[float, float] = (0.8, 1.0), p_brightness: float = 0.1,
            brightness_range: tuple[float, float] = (0.8, 1.2), p_flip: float = 0.5) -> dict:
    """Augments one sample (host side, numpy / OpenCV); returns a new dict, the input is untouched.

    Args:
      sample: dict with any of raw14 (H, W) uint16, ir8 (H, W) uint8, rgb (H, W, 3) uint8,
        depth / depth_dense (H, W) float32, valid (H, W) bool, seg (H, W) uint8, plus
        pass-through entries. All maps must share (H, W).
      rng: the random generator (e.g. `np.random.default_rng((seed, epoch, index))`).
      p_crop, crop_range, p_brightness, brightness_range, p_flip: the paper's values by default.

    Returns:
      dict with the same keys, shapes and dtypes.
    """
    maps = [k for k in INTENSITY_KEYS + LABEL_KEYS if k in sample]
    if not maps:
        raise ValueError(f"sample has none of the map keys {INTENSITY_KEYS + LABEL_KEYS}")
    shape = np.shape(sample[maps[0]])[:2]
    for k in maps:
        if np.shape(sample[k])[:2] != shape:
            raise ValueError(
                f"sample[{k!r}] has shape {np.shape(sample[k])}, {maps[0]!r} has {shape}")
    u = rng.random(3)
    ratio = rng.uniform(*crop_range)
    factor = rng.uniform(*brightness_range)
    out = dict(sample)
    if u[0] < p_crop:
        for k in maps:
            out[k] = _crop_resize(np.asarray(out[k]), ratio, k in INTENSITY_KEYS)
    if u[1] < p_brightness:
        for k in ("ir8", "rgb"):
            if k in out:
                out[k] = np.clip(np.rint(out[k] * factor), 0, 255).astype(np.uint8)
        if "raw14" in out:
            raw = np.asarray(out["raw14"], np.float64)
            mean = raw.mean()
            scaled = np.rint(mean + factor * (raw - mean))
            out["raw14"] = np.clip(scaled, 0, RAW_MAX).astype(np.uint16)
    if u[2] < p_flip:
        for k in maps:
            out[k] = np.ascontiguousarray(np.asarray(out[k])[:, ::-1])
    return out


def _crop_resize(img: np.ndarray, ratio: float, intensity: bool) -> np.ndarray:
    """Centre crop of side ratio `ratio`, resized back to the input's (H, W)."""
    h, w = img.shape[:2]
    ch, cw = max(1, round(h * ratio)), max(1, round(w * ratio))
    top, left = (h - ch) // 2, (w - cw) // 2
    crop = img[top:top + ch, left:left + cw]
    interp = cv2.INTER_LINEAR if intensity else cv2.INTER_NEAREST_EXACT
    if img.dtype == np.bool_:
        return cv2.resize(crop.view(np.uint8), (w, h), interpolation=interp).astype(bool)
    return cv2.resize(np.ascontiguousarray(crop), (w, h), interpolation=interp)
