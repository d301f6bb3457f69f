"""Grid of synthetic frames per condition: raw, ir8, rgb, depth (dense + LiDAR), seg.

    python experiments/render_examples.py [--rows-per-condition 2] [--size 256x320]
        [--out experiments/results/synthetic_examples.png]
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from irdepth_jax.config import CLASS_NAMES  # noqa: E402
from irdepth_jax.data.synthetic import CONDITIONS, render_scene  # noqa: E402

_PALETTE = np.array([[110, 170, 255], [150, 90, 60], [230, 40, 40], [250, 200, 0],
                     [120, 120, 120], [40, 150, 40]], np.uint8)


def seg_to_rgb(seg: np.ndarray) -> np.ndarray:
    """(H, W) uint8 labels -> (H, W, 3) uint8 colours; 255 (unlabelled) is black."""
    out = np.zeros(seg.shape + (3,), np.uint8)
    known = seg < len(_PALETTE)
    out[known] = _PALETTE[seg[known]]
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows-per-condition", type=int, default=2)
    ap.add_argument("--size", default="256x320")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="experiments/results/synthetic_examples.png")
    args = ap.parse_args(argv)
    height, width = map(int, args.size.lower().split("x"))
    n = args.rows_per_condition * len(CONDITIONS)
    cols = ["raw14", "ir8", "rgb", "depth (dense)", "LiDAR depth", "seg"]
    fig, axes = plt.subplots(n, len(cols), figsize=(3.0 * len(cols), 2.6 * n), squeeze=False)
    for row in range(n):
        cond = CONDITIONS[row // args.rows_per_condition]
        seed = args.seed + row
        s = render_scene(seed, cond, height, width)
        raw = s["raw14"].astype(np.float32)
        lo, hi = np.percentile(raw, [1, 99])
        lidar = np.ma.masked_where(~s["valid"], s["depth_lidar"])
        dense = np.ma.masked_where(s["depth"] == 0, s["depth"])
        panels = [(raw, dict(cmap="gray", vmin=lo, vmax=hi)),
                  (s["ir8"], dict(cmap="gray", vmin=0, vmax=255)),
                  (s["rgb"], {}), (dense, dict(cmap="magma_r", vmin=0, vmax=80)),
                  (lidar, dict(cmap="magma_r", vmin=0, vmax=80, interpolation="nearest")),
                  (seg_to_rgb(s["seg"]), {})]
        for col, (img, kw) in enumerate(panels):
            ax = axes[row, col]
            if col == 4:
                ax.set_facecolor("black")
            ax.imshow(img, **kw)
            ax.set_xticks([]), ax.set_yticks([])
            if row == 0:
                ax.set_title(cols[col])
        axes[row, 0].set_ylabel(f"{cond} (seed {seed})")
    cmd = "python " + " ".join([pathlib.Path(sys.argv[0]).as_posix()] + (argv or sys.argv[1:]))
    colours = ["blue", "brown", "red", "yellow", "grey", "green"]
    legend = ", ".join(f"{c}={name}" for c, name in zip(colours, CLASS_NAMES))
    fig.suptitle(f"render_scene at {height}x{width}, raw 1-99 % stretch, depth 0-80 m, "
                 f"seg: {legend}, "
                 f"black = unlabelled/no return\n{cmd}", fontsize=10)
    fig.tight_layout()
    out = pathlib.Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
