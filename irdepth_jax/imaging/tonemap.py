"""Classical raw -> 8-bit tone mapping of raw LWIR frames (the paper's baselines).

Every function takes one raw frame, a 2-D integer array (H, W) (normally uint16) with counts in
[0, 2^bits - 1], `bits` = 14 (default) or 16 (checked by `irdepth_jax.imaging.raw.check_raw`;
8-bit, float, NaN, negative or over-`bits` input raises ValueError), and returns a `uint8` array
(H, W). They are NumPy / OpenCV (not JAX): they run in data pipelines and in the synthetic
renderer, not inside a jitted model. Histogram methods build a lookup table over the raw levels
0..max(frame) from `np.bincount` + `np.cumsum` and apply it with `np.take`; nothing loops over
pixels. The maps are histogram- or span-relative, so `bits` only sets the accepted range.

A constant frame has no contrast to map: every method returns mid-grey (128) for it.

The maps live in two modules and are imported from here: `tonemap_histogram` (linear, HE,
plateau, double-plateau, CLAHE) and `tonemap_camera` (guided filter, DDE, frequency-domain
clean-up, the camera-like chain).

Registry `TONEMAPS` (name -> function of the raw frame with default parameters):
'linear', 'he', 'clahe', 'plateau', 'double_plateau', 'dde', 'camera'.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from irdepth_jax.imaging.tonemap_camera import camera_like, dde, frequency_denoise, guided_filter
from irdepth_jax.imaging.tonemap_histogram import (
    MID_GREY,
    OUT_LEVELS,
    clahe,
    double_plateau_he,
    double_plateau_thresholds,
    histogram_equalization,
    linear_tail,
    plateau_he,
)

__all__ = [
    "MID_GREY",
    "OUT_LEVELS",
    "TONEMAPS",
    "camera_like",
    "clahe",
    "dde",
    "double_plateau_he",
    "double_plateau_thresholds",
    "frequency_denoise",
    "guided_filter",
    "histogram_equalization",
    "linear_tail",
    "plateau_he",
]

TONEMAPS: dict[str, Callable[..., np.ndarray]] = {
    "linear": linear_tail,
    "he": histogram_equalization,
    "clahe": clahe,
    "plateau": plateau_he,
    "double_plateau": double_plateau_he,
    "dde": dde,
    "camera": camera_like,
}
"""Name -> function raw (H, W) uint16 -> (H, W) uint8, called with its default parameters and
`bits=` the run's bit depth ('plateau' then uses the adaptive T_up of the double-plateau rule as
its single plateau)."""
