"""Frames of several sources seen as one dataset: Stage I-1 on all splits, and Stage I-2 with
segmentation labels from another source (rendered scenes or a user's labelled folder) mixed with a
dataset that has none (MS2).

Each class has the dataset interface the loader and the evaluators use: ``len(ds)`` and
``ds[i]`` -> sample dict (raw14, ir8, rgb, has_rgb, depth, valid, seg, labeled, condition, id).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from irdepth_jax.data.augment import resize_sample

SAMPLE_KEYS = ("raw14", "ir8", "rgb", "has_rgb", "depth", "valid", "seg", "labeled",
               "condition", "id")
"""The keys every source yields (the folder format's `depth_dense` is dropped when mixing)."""


class ConcatFrames:
    """The selected frames of several datasets, in order: frame i of `parts[0]`'s indices first.

    Args:
      parts: (dataset, indices) pairs.
      size: (height, width) every frame is resized to (`augment.resize_sample`), or None to
        require equal sizes (the loader refuses a batch of mixed sizes).
    """

    def __init__(self, parts: Sequence[tuple[Any, np.ndarray]],
                 size: tuple[int, int] | None = None):
        self._parts = [(ds, np.asarray(idx, np.int64)) for ds, idx in parts if len(idx)]
        self._ends = np.cumsum([len(idx) for _, idx in self._parts])
        self.size = size

    def __len__(self) -> int:
        return int(self._ends[-1]) if len(self._ends) else 0

    def __getitem__(self, i: int) -> dict:
        if not 0 <= i < len(self):
            raise IndexError(f"frame {i} of {len(self)}")
        part = int(np.searchsorted(self._ends, i, side="right"))
        dataset, idx = self._parts[part]
        start = int(self._ends[part - 1]) if part else 0
        sample = {k: dataset[int(idx[i - start])][k] for k in SAMPLE_KEYS}
        return sample if self.size is None else resize_sample(sample, *self.size)


class SyntheticLabeled:
    """`n` rendered labelled street scenes (`data.synthetic.render_scene`), made on demand.

    Args:
      n: number of frames.
      height, width: frame size (the dataset's they are mixed into).
      seed: frame i is rendered from (seed, i); conditions cycle day, dusk, night.
      raw_bits: 16 scales the renderer's 14-bit counts by 4, so that a fixed normalisation of
        16-bit data sees them at the same level.
      scenes: the renderer's scene distribution ('street' or 'varied').
    """

    def __init__(self, n: int, height: int, width: int, seed: int = 0, raw_bits: int = 14,
                 scenes: str = "street"):
        if n < 1:
            raise ValueError(f"stage1.synthetic_labeled must be >= 1, got {n}")
        self.n, self.height, self.width, self.seed, self.scenes = n, height, width, seed, scenes
        self.gain = 4 if int(raw_bits) == 16 else 1

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> dict:
        from irdepth_jax.data.synthetic import CONDITIONS, render_scene

        if not 0 <= i < self.n:
            raise IndexError(f"frame {i} of {self.n}")
        condition = CONDITIONS[i % len(CONDITIONS)]
        frame_seed = int(np.random.SeedSequence([self.seed, 0x5E6, i]).generate_state(1)[0])
        s = render_scene(frame_seed, condition, self.height, self.width, self.scenes)
        return dict(raw14=(s["raw14"] * self.gain).astype(np.uint16), ir8=s["ir8"], rgb=s["rgb"],
                    has_rgb=True, depth=s["depth_lidar"], valid=s["valid"], seg=s["seg"],
                    labeled=True, condition=condition, id=f"synthetic_{i:06d}")
