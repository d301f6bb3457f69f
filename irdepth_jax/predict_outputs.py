"""What `irdepth predict` writes of one frame: the images (16-bit depth PNG through the one
depth codec, `data.depth_png`; coloured depth; pseudo-RGB and HSV), the panels of a video frame,
and a thread pool that writes them while the next batch computes (PNG encoding releases the GIL).
"""

from __future__ import annotations

import os
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from irdepth_jax.config import Config
from irdepth_jax.data.depth_png import OverRange, encode_depth
from irdepth_jax.data.inputs import Frame
from irdepth_jax.depth_colours import DepthColours
from irdepth_jax.fileio import write_bytes, write_png

WRITERS = 2
"""Threads encoding and writing output files."""


def colorize_depth(depth: np.ndarray, max_depth: float) -> np.ndarray:
    """Depth (H, W) metres -> (H, W, 3) uint8 RGB (matplotlib 'turbo', near = red)."""
    return DepthColours(0.0, max_depth).colorize(depth, 0.0, max_depth)


def display_raw(raw: np.ndarray, bits: int) -> np.ndarray:
    """A raw frame (H, W) for display: (H, W, 3) uint8 grey, linear 1-99 % percentile stretch."""
    from irdepth_jax.imaging.tonemap import linear_tail

    return np.repeat(linear_tail(raw, 1.0, 99.0, bits)[..., None], 3, axis=-1)


def to_uint8(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] (any shape) -> uint8 0..255, rounded (out-of-range values clipped)."""
    return np.clip(np.round(x * 255), 0, 255).astype(np.uint8)


def frame_label(frame: Frame) -> str:
    """How messages name a frame: ``frame OUT_DIR/NAME`` (its outputs' stem under --out)."""
    return f"frame {os.path.join(frame.out_dir, frame.name)}"


def depth_suffix(cfg: Config) -> str:
    """The file suffix of a model's depth output: 'depth' (metres) for a metric model,
    'depth_relative' for a relative one (depth.metric=false: depth up to an unknown scale)."""
    return "depth" if cfg.depth.metric else "depth_relative"


def output_pngs(images: dict, colours: DepthColours, depth_name: str = "depth",
                name: str = "depth", over_range: OverRange | None = None) -> dict:
    """The PNGs (OpenCV BGR order) of one frame's finite predictions (depth (H, W) metres;
    rgb, hsv (H, W, 3) in [0, 1]), by file suffix: rgb, hsv (8-bit), `depth_name` (16-bit,
    `data.depth_png.encode_depth` of the depth map `name`, its over-range values counted in
    `over_range`) and `depth_name`_color (with its colour bar, `colours`)."""
    pngs = {}
    if "rgb" in images:
        # reversed for OpenCV, so that the files hold R, G, B and H, S, V in channel order
        pngs["rgb"] = to_uint8(images["rgb"])[..., ::-1]
        pngs["hsv"] = to_uint8(images["hsv"])[..., ::-1]
    if "depth" in images:
        pngs[depth_name] = encode_depth(images["depth"], name=name, over_range=over_range)
        pngs[f"{depth_name}_color"] = colours.image(images["depth"])[..., ::-1]
    return pngs


def video_panels(raw: np.ndarray, images: dict, bits: int, colours: DepthColours) -> np.ndarray:
    """One video frame (H, k*W, 3) uint8 RGB of a raw frame (H, W) and its predictions:
    raw tone-mapped | pseudo-RGB (| coloured depth, its colour bar under the panels)."""
    panels = [display_raw(raw, bits)]
    if "rgb" in images:
        panels.append(to_uint8(images["rgb"]))
    if "depth" not in images:
        return np.concatenate(panels, axis=1)
    depth = colours.image(images["depth"])
    height = raw.shape[0]
    panels = [np.pad(p, ((0, depth.shape[0] - height), (0, 0), (0, 0))) for p in panels]
    return np.concatenate(panels + [depth], axis=1)


DARK_RGB_MEAN = 0.02
"""A pseudo-RGB image (values in [0, 1]) whose mean is under this (5 of 255) is nearly black."""


class DarkImages:
    """The pseudo-RGB images that came out nearly black (mean under `DARK_RGB_MEAN`), counted
    over a run for one warning at its end: the depth network then sees almost no image."""

    def __init__(self):
        self.dark = self.images = 0
        self.first = ""
        """The frame of the first nearly black image."""

    def add(self, rgb: np.ndarray, name: str) -> None:
        """Counts the pseudo-RGB image (H, W, 3) in [0, 1] of the frame `name`."""
        self.images += 1
        if float(np.mean(rgb)) < DARK_RGB_MEAN:
            self.dark += 1
            self.first = self.first or name

    def message(self) -> str | None:
        """One line counting the nearly black images, or None when there were none."""
        if not self.dark:
            return None
        return (f"{self.dark} of {self.images} pseudo-RGB images are nearly black (mean under "
                f"{DARK_RGB_MEAN:.0%} of white; the first: {self.first}): the Stage I model makes "
                "almost no texture (Value) of these frames, so the depth network's input is almost "
                "empty and depth from it is not to be trusted; a model trained on frames like "
                "these is needed")


class Writers:
    """A thread pool writing output files; `check` raises the first failed write (in order).
    Counted over the run: `over_range`, the depth values over what a depth PNG holds, and
    `dark_rgb`, the nearly black pseudo-RGB images."""

    def __init__(self):
        self.pool = ThreadPoolExecutor(WRITERS, thread_name_prefix="irdepth-write")
        self.futures: list[tuple[str, Future]] = []
        self.written: list[str] = []
        self.over_range = OverRange()
        self.dark_rgb = DarkImages()

    def submit(self, path: str, image: np.ndarray) -> None:
        """Writes `image` ((H, W) or (H, W, 3) BGR) as the PNG `path` on the pool."""
        self.futures.append((path, self.pool.submit(write_png, path, image)))
        self.check(block=False)

    def submit_bytes(self, path: str, data: bytes) -> None:
        """Writes `data` to `path` on the pool."""
        self.futures.append((path, self.pool.submit(write_bytes, path, data)))
        self.check(block=False)

    def check(self, block: bool = True) -> None:
        """Records the finished writes (all of them with `block`); raises the first failure."""
        while self.futures and (block or self.futures[0][1].done()):
            path, future = self.futures.pop(0)
            future.result()
            self.written.append(path)

    def close(self) -> None:
        """Waits for every submitted write (all of them, also after an error)."""
        self.pool.shutdown(wait=True)
