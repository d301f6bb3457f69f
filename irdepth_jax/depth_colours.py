"""Coloured depth images that can be read: a colour map over a stated depth range, with a colour
bar under the image labelled near and far (`irdepth predict --depth-range --cmap`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from irdepth_jax.errors import RunError

BAR_HEIGHT = 8
"""Rows of the colour gradient under the image."""
LABEL_HEIGHT = 14
"""Rows of the label strip under the gradient."""
AUTO_PERCENTILES = (2.0, 98.0)
"""--depth-range auto: the range of a frame's valid depths, without its extreme 2 % each side."""


@dataclasses.dataclass(frozen=True)
class DepthColours:
    """How depth maps are coloured: `cmap` from near (`low`) to far (`high`), both None for
    each frame's own range (`AUTO_PERCENTILES` of its depths > 0); `relative` labels the bar
    'near' / 'far' with 'relative' instead of metres."""

    low: float | None
    high: float | None
    cmap: str = "turbo"
    relative: bool = False

    def range_of(self, depth: np.ndarray) -> tuple[float, float]:
        """(near, far) of the colour map for depth (H, W)."""
        if self.low is not None and self.high is not None:
            return self.low, self.high
        valid = depth[np.isfinite(depth) & (depth > 0)]
        if valid.size == 0:
            return 0.0, 1.0
        low, high = np.percentile(valid, AUTO_PERCENTILES)
        return float(low), float(max(high, low + 1e-6))

    def colorize(self, depth: np.ndarray, low: float, high: float) -> np.ndarray:
        """Depth (H, W) -> (H, W, 3) uint8 RGB, near (`low`) at the colour map's end 1."""
        from matplotlib import colormaps

        x = 1.0 - np.clip((depth - low) / max(high - low, 1e-6), 0.0, 1.0)
        return (colormaps[self.cmap](x)[..., :3] * 255).astype(np.uint8)

    def image(self, depth: np.ndarray) -> np.ndarray:
        """The coloured depth (H, W) with its colour bar: (H + bar rows, W, 3) uint8 RGB."""
        low, high = self.range_of(depth)
        return np.concatenate([self.colorize(depth, low, high),
                               self.bar(depth.shape[1], low, high)], axis=0)

    def bar(self, width: int, low: float, high: float) -> np.ndarray:
        """(BAR_HEIGHT + LABEL_HEIGHT, width, 3) uint8 RGB: the gradient near (left) to far
        (right), labelled with the range ('near' / 'far' for a relative model)."""
        import cv2

        ramp = np.linspace(low, high, width)[None].repeat(BAR_HEIGHT, axis=0)
        labels = np.zeros((LABEL_HEIGHT, width, 3), np.uint8)
        if self.relative:
            left, right = "near", "far (relative)"
        else:
            left, right = f"{low:.3g} m", f"{high:.3g} m"
        font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.3
        (right_width, _), _ = cv2.getTextSize(right, font, scale, 1)
        cv2.putText(labels, left, (1, LABEL_HEIGHT - 4), font, scale, (255, 255, 255), 1,
                    cv2.LINE_AA)
        cv2.putText(labels, right, (max(width - right_width - 1, 0), LABEL_HEIGHT - 4), font,
                    scale, (255, 255, 255), 1, cv2.LINE_AA)
        return np.concatenate([self.colorize(ramp, low, high), labels], axis=0)


def depth_colours(spec: str | None, max_depth: float, relative: bool,
                  cmap: str = "turbo") -> DepthColours:
    """`DepthColours` of ``--depth-range`` (None: 0 to `max_depth` m for a metric model, each
    frame's own range for a relative one; 'auto'; 'MIN:MAX' in metres) and ``--cmap`` (a
    matplotlib colour map name). RunError naming the flag for a bad value."""
    from matplotlib import colormaps

    if cmap not in colormaps:
        raise RunError(f"`cmap` {cmap}: not a matplotlib colour map (e.g. turbo, viridis, "
                       "magma, inferno, plasma)")
    if spec is None:
        spec = "auto" if relative else f"0:{max_depth}"
    if spec == "auto":
        return DepthColours(None, None, cmap, relative)
    try:
        low, high = (float(v) for v in spec.split(":"))
    except ValueError:
        low = high = float("nan")
    if not (np.isfinite(low) and np.isfinite(high) and 0 <= low < high):
        raise RunError(f"`depth_range` {spec}: expected auto or MIN:MAX with 0 <= MIN < MAX")
    return DepthColours(low, high, cmap, relative)
