"""Plots one raw 14-bit frame through every classical 14->8-bit baseline (tonemap.TONEMAPS).

    python experiments/plot_tonemap_baselines.py                       # synthetic frame
    python experiments/plot_tonemap_baselines.py --raw frame.png       # a uint16 PNG or .npy

Writes experiments/results/tonemap_baselines.png (or --out): the raw frame (linear min-max view
and its histogram), then each baseline with its entropy in bits and its runtime. The input and
the command line are written into the figure's title.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from irdepth_jax.image_metrics import entropy  # noqa: E402
from irdepth_jax.imaging.tonemap import TONEMAPS  # noqa: E402

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "tonemap_baselines.png"
TITLES = {
    "linear": "linear 1-99 %",
    "he": "HE",
    "clahe": "CLAHE (clip 2, 8x8)",
    "plateau": "plateau HE (P = T_up)",
    "double_plateau": "double-plateau HE",
    "dde": "DDE",
    "camera": "camera-like (IRCBA stand-in)",
}


def load_raw(path: Path) -> np.ndarray:
    """Reads a (H, W) uint16 raw frame from .npy or a 16-bit PNG/TIFF."""
    if path.suffix == ".npy":
        raw = np.load(path)
    else:
        import cv2

        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ValueError(f"--raw {path}: OpenCV cannot read this file")
    return np.asarray(raw)


def procedural_frame(seed: int, height: int, width: int) -> np.ndarray:
    """Fallback frame: warm-ground gradient, cold sky band, hot blobs, column stripes, noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:height, :width].astype(np.float64)
    x = 3000 + 900 * yy / height
    x[: height // 3] -= 600
    for _ in range(6):
        cy, cx, r = rng.uniform(0, height), rng.uniform(0, width), rng.uniform(4, 20)
        x += rng.uniform(150, 900) * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * r * r))
    x += rng.normal(0, 8, width)[None, :] + rng.normal(0, 12, (height, width))
    return np.clip(x, 0, 2**14 - 1).astype(np.uint16)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--raw", type=Path, help="uint16 raw frame (.npy or 16-bit PNG/TIFF)")
    parser.add_argument("--seed", type=int, default=3, help="synthetic scene seed")
    parser.add_argument("--condition", default="dusk", help="synthetic condition: day|dusk|night")
    parser.add_argument("--height", type=int, default=256)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)

    if args.raw is not None:
        raw = load_raw(args.raw)
        source = f"raw file {args.raw.name}"
    else:
        try:
            from irdepth_jax.data.synthetic import render_scene
        except ImportError:
            raw = procedural_frame(args.seed, args.height, args.width)
            source = f"procedural gradient + blobs + noise frame (seed {args.seed})"
        else:
            raw = render_scene(args.seed, args.condition, args.height, args.width)["raw14"]
            source = f"synthetic render_scene(seed={args.seed}, '{args.condition}')"

    outputs = {}
    for name, fn in TONEMAPS.items():
        fn(raw)  # warm-up, then time one call
        start = time.perf_counter()
        outputs[name] = fn(raw)
        outputs[name + "_ms"] = 1e3 * (time.perf_counter() - start)

    fig, axes = plt.subplots(3, 3, figsize=(13, 10.5))
    axes = axes.ravel()
    lo, hi = int(raw.min()), int(raw.max())
    axes[0].imshow(raw, cmap="gray", vmin=lo, vmax=hi)
    axes[0].set_title(f"raw 14-bit, min-max view [{lo}, {hi}]")
    counts = np.bincount(raw.ravel(), minlength=2**14)[lo : hi + 1]
    axes[1].fill_between(np.arange(lo, hi + 1), counts, step="mid", color="0.3")
    axes[1].set_title("raw histogram (counts)")
    axes[1].set_xlabel("raw level")
    for ax, name in zip(axes[2:], TONEMAPS):
        img = outputs[name]
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        ax.set_title(
            f"{TITLES.get(name, name)}\nH = {float(entropy(img)):.2f} bits, "
            f"{outputs[name + '_ms']:.1f} ms"
        )
    for ax in axes:
        if ax is not axes[1]:
            ax.axis("off")
    command = "python " + " ".join(shlex.quote(a) for a in [sys.argv[0], *(argv or sys.argv[1:])])
    fig.suptitle(
        f"14-bit -> 8-bit baselines on a {raw.shape[0]}x{raw.shape[1]} {source}\n"
        f"made by: {command}",
        fontsize=11,
    )
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
