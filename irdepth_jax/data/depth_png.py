"""The 16-bit depth PNG (KITTI / MS2 convention): round(metres x 256) as uint16, 0 = no depth.

The one codec of every depth PNG the package writes (a dataset's depth labels, `irdepth
predict`'s NAME_depth.png) and reads. Its policy for a depth the encoding cannot hold: a valid
depth over `MAX_DEPTH` (255.996 m) is written as `MAX_DEPTH` and counted, and the count is
reported as a warning, never dropped silently; a valid depth under 1/512 m is written as one
count (1/256 m), so that it stays a depth; a depth <= 0 or marked not valid is 0, "no depth".
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

DEPTH_SCALE = 256.0
"""uint16 depth PNG counts per metre."""
MAX_COUNT = 65535
MAX_DEPTH = MAX_COUNT / DEPTH_SCALE
"""The largest depth a depth PNG holds, in metres (255.996)."""


class DepthRangeWarning(UserWarning):
    """Depth values over `MAX_DEPTH` were written as `MAX_DEPTH` (the message counts them)."""


@dataclasses.dataclass
class OverRange:
    """The depth values over `MAX_DEPTH` that `encode_depth` wrote as `MAX_DEPTH`, counted over
    many depth maps, for one warning at the end of a run."""

    values: int = 0
    maps: int = 0
    largest: float = 0.0
    first: str = ""
    """The name of the first depth map that had such values."""

    def add(self, values: int, largest: float, name: str) -> None:
        """Counts `values` over-range values of the depth map `name` (largest: metres)."""
        self.first = self.first or name
        self.values, self.maps = self.values + values, self.maps + 1
        self.largest = max(self.largest, largest)

    def message(self) -> str | None:
        """One line counting the saturated values, or None when there were none."""
        if not self.values:
            return None
        where = self.first if self.maps == 1 else f"{self.maps} depth maps (the first: {self.first})"
        return (f"{self.values} depth values of {where} are over {MAX_DEPTH:.3f} m (up to "
                f"{self.largest:.2f} m), the most a 16-bit depth PNG holds: written as "
                f"{MAX_DEPTH:.3f} m")


def encode_depth(depth: np.ndarray, valid: np.ndarray | None = None, name: str = "depth",
                 over_range: OverRange | None = None) -> np.ndarray:
    """Depth (H, W) metres (+ optional (H, W) bool mask, default depth > 0) -> (H, W) uint16
    counts of 1/256 m, 0 = no depth (the policy in the module docstring).

    Valid depths over `MAX_DEPTH` are counted in `over_range` when one is given (its caller
    reports them once, `OverRange.message`), else reported at once as a `DepthRangeWarning`
    that names `name`.
    """
    depth = np.asarray(depth, np.float64)
    valid = depth > 0 if valid is None else np.asarray(valid, bool) & (depth > 0)
    counts = np.rint(np.where(valid, depth, 0.0) * DEPTH_SCALE)
    over = counts > MAX_COUNT
    if over.any():
        tally = OverRange() if over_range is None else over_range
        tally.add(int(over.sum()), float(depth[over].max()), name)
        if over_range is None:
            warnings.warn(tally.message(), DepthRangeWarning, stacklevel=2)
    return np.where(valid, np.clip(counts, 1, MAX_COUNT), 0).astype(np.uint16)


def decode_depth(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) uint16 counts -> depth (H, W) float32 metres and valid (H, W) bool (counts > 0)."""
    return counts.astype(np.float32) / DEPTH_SCALE, counts > 0
