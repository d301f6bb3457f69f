"""Synthetic datasets in our folder format: the frame records (`synthetic_manifest`, the paper's
split proportions) and the writer behind `irdepth synth` (`write_synthetic_dataset`: renders
each frame with `irdepth_jax.data.synthetic.render_scene` and writes it with
`irdepth_jax.data.folder.write_sample`)."""

from __future__ import annotations

import math
import pathlib
import shutil

import numpy as np
from tqdm import tqdm

from irdepth_jax.data.folder import MAP_FOLDERS, SPLITS, DatasetError, write_manifest, write_sample
from irdepth_jax.data.synthetic import CONDITIONS, SCENES, render_scene

DEPTH_SPLIT = (1500, 400, 392)
"""The paper's Stage II train / val / test frame counts (2292 frames)."""
SEG_SPLIT = (600, 100, 100)
"""The paper's Stage I-2 train / val / test labelled frame counts (800 frames)."""


def split_counts(n: int, proportions: tuple[int, ...]) -> tuple[int, ...]:
    """Splits n items in the given proportions (largest remainder; sums to n exactly)."""
    total = sum(proportions)
    exact = [n * p / total for p in proportions]
    counts = [math.floor(e) for e in exact]
    order = sorted(range(len(exact)), key=lambda k: counts[k] - exact[k])
    for k in order[: n - sum(counts)]:
        counts[k] += 1
    return tuple(counts)


def synthetic_manifest(n: int, labeled: int, seed: int, split: str | None = None) -> list[dict]:
    """Frame records of a synthetic dataset: the paper's split proportions scaled to n / labeled,
    or (`split` 'train' | 'val' | 'test') every frame in that one split, the first `labeled` of
    them labelled (an evaluation set rendered apart from the training data).

    Conditions cycle day, dusk, night over the frame index; the depth split is a seeded random
    assignment (1500:400:392); the labelled frames are drawn inside the depth splits so that
    segmentation train / val / test frames (600:100:100) are depth train / val / test frames too
    (no test image is seen in Stage I training). Requires labeled <= n and each labelled split to
    fit its depth split.
    """
    if n < 1 or not 0 <= labeled <= n:
        raise ValueError(f"need n >= 1 and 0 <= labeled <= n, got n={n}, labeled={labeled}")
    if split is not None and split not in SPLITS:
        raise ValueError(f"split {split!r}: must be one of {SPLITS}")
    rng = np.random.default_rng([seed, 0x5EC])
    one = [int(s == split) for s in SPLITS]
    depth_n = split_counts(n, DEPTH_SPLIT if split is None else one)
    seg_n = split_counts(labeled, SEG_SPLIT if split is None else one)
    order = rng.permutation(n)
    records = [dict(id=f"{i:06d}", split=None, seg_split=None,
                    condition=CONDITIONS[i % len(CONDITIONS)], labeled=False) for i in range(n)]
    start = 0
    for split, dn, sn in zip(SPLITS, depth_n, seg_n):
        members = order[start:start + dn]
        start += dn
        if sn > dn:
            raise ValueError(f"{labeled} labelled of {n} frames: {sn} {split} labels do not fit in "
                             f"{dn} {split} frames; use fewer labelled frames")
        for j, i in enumerate(members):
            records[i]["split"] = split
            if j < sn:
                records[i]["labeled"], records[i]["seg_split"] = True, split
    return records


def write_synthetic_dataset(out_dir, n: int, labeled: int, height: int, width: int, seed: int = 0,
                            progress: bool = True, overwrite: bool = False,
                            split: str | None = None, scenes: str = "street") -> pathlib.Path:
    """Renders n synthetic frames into a folder dataset (what `irdepth synth` runs).

    Args:
      out_dir: dataset directory; must be absent or empty unless overwrite=True, which removes
        an existing dataset's manifest and map folders first (other files are left alone).
      n, labeled: total and labelled frame counts (splits: see `synthetic_manifest`).
      split: None (the paper's proportions) or one split holding every frame.
      height, width: frame size.
      seed: dataset seed; frame i is `render_scene(seed_i, condition_i, ...)` with seed_i
        derived from (seed, i).
      progress: show a tqdm progress bar.
      scenes: the renderer's scene distribution ('street' or 'varied', `render_scene`); recorded
        in the manifest.

    Returns:
      the dataset directory.
    """
    if scenes not in SCENES:
        raise ValueError(f"scenes must be one of {SCENES}, got {scenes!r}")
    out = pathlib.Path(out_dir)
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: exists and is not a directory")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise DatasetError(f"{out}: directory exists and is not empty; choose another path or "
                               "pass `overwrite` to replace the dataset")
        (out / "manifest.json").unlink(missing_ok=True)
        for field in MAP_FOLDERS:
            shutil.rmtree(out / field, ignore_errors=True)
    records = synthetic_manifest(n, labeled, seed, split)
    for r in tqdm(records, desc=f"synth {out.name}", disable=not progress, unit="frame"):
        frame_seed = int(np.random.SeedSequence([seed, int(r["id"])]).generate_state(1)[0])
        s = render_scene(frame_seed, r["condition"], height, width, scenes)
        sample = dict(raw14=s["raw14"], ir8=s["ir8"], rgb=s["rgb"], depth=s["depth_lidar"],
                      valid=s["valid"], seg=s["seg"], labeled=r["labeled"], depth_dense=s["depth"])
        r.update(write_sample(out, r["id"], sample))
    write_manifest(out, records, height, width, source="synthetic", seed=int(seed), scenes=scenes)
    return out
