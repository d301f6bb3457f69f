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
  * brightness: one factor for every intensity map, as the same change of the normalised image:
    ir8 and rgb are multiplied by it (clipped to 0..255), and the sample gets
    ``brightness`` = the factor (1.0 when the step does not fire), which the model applies to its
    normalised raw input (`irdepth_jax.models.pipeline.unet_input`: clip(factor * x, 0, 1)).
    The counts themselves are left alone: they are physical, and no change of them could brighten
    the input under percentile normalisation (a gain on the counts is undone by it), so scaling
    the counts while the 8-bit target gets brighter would teach contradictory pairs.
  * flip: every map.
Non-map entries (id, condition, labeled, has_rgb, ...) are passed through.
"""

from __future__ import annotations

import cv2
import numpy as np

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
      dict with the same keys, shapes and dtypes, plus ``brightness`` (float32 factor).
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
    out["brightness"] = np.float32(1.0)
    if u[1] < p_brightness:
        for k in ("ir8", "rgb"):
            if k in out:
                out[k] = np.clip(np.rint(out[k] * factor), 0, 255).astype(np.uint8)
        out["brightness"] = np.float32(factor)
    if u[2] < p_flip:
        for k in maps:
            out[k] = np.ascontiguousarray(np.asarray(out[k])[:, ::-1])
    return out


def _crop_resize(img: np.ndarray, ratio: float, intensity: bool) -> np.ndarray:
    """Centre crop of side ratio `ratio`, resized back to the input's (H, W)."""
    h, w = img.shape[:2]
    ch, cw = max(1, round(h * ratio)), max(1, round(w * ratio))
    top, left = (h - ch) // 2, (w - cw) // 2
    return _resize(img[top:top + ch, left:left + cw], (h, w), intensity)


def _resize(img: np.ndarray, size: tuple[int, int], intensity: bool) -> np.ndarray:
    """(h, w, ...) -> (size[0], size[1], ...): bilinear for intensity maps, exact nearest
    neighbour for label-like maps (no value is made up between objects)."""
    interp = cv2.INTER_LINEAR if intensity else cv2.INTER_NEAREST_EXACT
    if img.dtype == np.bool_:
        return cv2.resize(np.ascontiguousarray(img).view(np.uint8), size[::-1],
                          interpolation=interp).astype(bool)
    return cv2.resize(np.ascontiguousarray(img), size[::-1], interpolation=interp)


def resize_sample(sample: dict, height: int, width: int) -> dict:
    """A sample with every map resized to (height, width) (same rules as the crop above);
    non-map entries are passed through. Used to mix frames of another size into a dataset."""
    out = dict(sample)
    for k in INTENSITY_KEYS + LABEL_KEYS:
        if k in out and np.shape(out[k])[:2] != (height, width):
            out[k] = _resize(np.asarray(out[k]), (height, width), k in INTENSITY_KEYS)
    return out
