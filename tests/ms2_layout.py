"""A partial MS2 download for tests: the official split lists, only some sequences on disk."""

import pathlib
import shutil
from collections.abc import Sequence

import cv2
import numpy as np

LIST_NAMES = ("train_list.txt", "val_list.txt", "test_day_list.txt", "test_night_list.txt",
              "test_rainy_list.txt")


def official_sequences(lists: pathlib.Path, name: str) -> list[str]:
    """The sequence names of one official split list (e.g. 'test_day_list.txt')."""
    return (lists / name).read_text().split()


def partial_ms2(lists: pathlib.Path, root: pathlib.Path, present: Sequence[str], frames: int = 3,
                size: tuple[int, int] = (16, 20), seed: int = 0) -> pathlib.Path:
    """Writes an MS2 root holding the official lists (copied from `lists`) and, for each
    sequence in `present` only, `frames` raw thermal PNGs (H, W) uint16 (counts 3000-6000) with
    their depth_filtered PNGs (metres x 256, 30% of the pixels valid). Returns `root`."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    for name in LIST_NAMES:
        shutil.copy(lists / name, root / name)
    (root / "sync_data").mkdir(exist_ok=True)
    for seq in present:
        img_dir = root / "sync_data" / seq / "thr" / "img_left"
        depth_dir = root / "proj_depth" / seq / "thr" / "depth_filtered"
        img_dir.mkdir(parents=True)
        depth_dir.mkdir(parents=True)
        for k in range(frames):
            cv2.imwrite(str(img_dir / f"{k:06d}.png"),
                        rng.integers(3000, 6000, size).astype(np.uint16))
            depth = np.where(rng.random(size) < 0.3, rng.integers(256, 60 * 256, size), 0)
            cv2.imwrite(str(depth_dir / f"{k:06d}.png"), depth.astype(np.uint16))
    return root
