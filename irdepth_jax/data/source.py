"""Where training and evaluation frames come from: a dataset directory (our folder format or
MS2) by split, the frames each phase trains on, and the host side of a batch (the arrays a
phase's step takes, the tone-mapped input images of the baselines, the loader).
"""

from __future__ import annotations

import dataclasses
import os
import typing
from collections.abc import Iterator
from typing import Any

import jax
import numpy as np

from irdepth_jax.config import IGNORE_LABEL, STAGE1_IMAGES, Config, resolved_raw_bits
from irdepth_jax.config_schema import Preprocessing
from irdepth_jax.errors import RunError, one_line
from irdepth_jax.imaging.tonemap import TONEMAPS

PREPROCESSING = typing.get_args(Preprocessing)
"""Stage II input images (`stage2.preprocessing`): the Stage I images (`config.STAGE1_IMAGES`),
the visible image 'rgb', the tonemaps of the raw frame (`TONEMAPS`), and 'blank': a constant grey
image, the control of what the depth network learns from the scene layout alone."""
BLANK_GREY = 128


class DataSource:
    """Frames of a dataset directory by split: our folder format or MS2.

    Args:
      path: the dataset directory.
      fmt: 'auto' (MS2 when the directory has MS2's sync_data/, else the folder format),
        'folder' or 'ms2'.
      strict: MS2: a sequence of a split list that is not on disk is an error (default: the
        split is read without it, with one `DatasetWarning` per split naming the missing ones).
      raw_bits: bit depth of the raw counts (`DataConfig.raw_bits`: 14, 16 or 'auto'); every
        frame read is checked against it ('auto': up to 16 bits until `use_raw_bits` resolves
        it).
      depth_label: MS2: the depth label version (`data.ms2.DEPTH_LABELS`; None: the default,
        depth_filtered); refused for a folder dataset (one depth per frame).
    Raises:
      RunError (one line, naming the directory) when it is not a dataset.
    """

    def __init__(self, path: str, fmt: str = "auto", strict: bool = False,
                 raw_bits: int | str = 14, depth_label: str | None = None):
        from irdepth_jax.data.folder import DatasetError, FolderDataset
        from irdepth_jax.data.rawio import accepted_bits

        if fmt not in ("auto", "folder", "ms2"):
            raise RunError(f"`format` {fmt!r}: choose auto, folder or ms2")
        if not os.path.isdir(path):
            raise RunError(f"`data` {path}: no such directory")
        try:
            accepted_bits(raw_bits)
        except ValueError as err:
            raise RunError(str(err)) from None
        self.path, self.strict, self.raw_bits = path, strict, raw_bits
        self.depth_label = depth_label
        self.format = fmt if fmt != "auto" else (
            "ms2" if os.path.isdir(os.path.join(path, "sync_data")) else "folder")
        self._error = DatasetError
        self._ms2: dict = {}
        self._folder = None
        if self.format == "folder":
            if depth_label is not None:
                raise RunError(f"`gt` {depth_label}: depth label versions are MS2's; `data` "
                               f"{path} is a folder dataset (one depth per frame)")
            try:
                self._folder = FolderDataset(path, raw_bits=raw_bits)
            except (DatasetError, ValueError, OSError) as err:
                raise RunError(f"`data` {path}: {one_line(err)}") from None

    def frames(self, split: str, labeled: bool | None = None, optional: bool = False,
               stride: int = 1) -> tuple[Any, np.ndarray]:
        """(dataset, indices) of the frames of `split` (and labelled ones when `labeled`); with
        `stride` N > 1 only `indices[0:-1:N]` of the split's frames, in either format (the
        official MS2 test protocol, N = 10: `data.ms2.subsample`).

        A split the dataset lacks raises RunError, or gives (None, []) when `optional` (but
        a listed MS2 sequence missing under `strict` always raises).
        """
        from irdepth_jax.data.ms2 import MissingSequencesError, MS2Dataset, subsample

        if stride < 1:
            raise RunError(f"stride {stride}: must be >= 1")
        try:
            if self._folder is not None:
                return self._folder, subsample(
                    self._folder.indices(split=split, labeled=labeled), stride)
            if split not in self._ms2:
                self._ms2[split] = MS2Dataset(self.path, split, strict=self.strict,
                                              raw_bits=self.raw_bits,
                                              depth_label=self.depth_label or "depth_filtered")
            ds = self._ms2[split]
            return ds, subsample(ds.indices(labeled=labeled), stride)
        except (self._error, ValueError, OSError) as err:
            if optional and not isinstance(err, MissingSequencesError):
                return None, np.zeros(0, np.int64)
            raise RunError(f"`data` {self.path}: {one_line(err)}") from None

    def seg_frames(self, seg_split: str) -> tuple[Any, np.ndarray]:
        """(dataset, indices) of the labelled frames of segmentation split `seg_split` (train /
        val / test: the paper's 600/100/100 split, independent of the depth split); no frames
        for a dataset without labels (MS2)."""
        if self._folder is None or seg_split not in ("train", "val", "test"):
            return None, np.zeros(0, np.int64)
        return self._folder, self._folder.indices(labeled=True, seg_split=seg_split)

    def all_frames(self) -> tuple[Any, np.ndarray]:
        """(dataset, indices) of every frame of every split (Stage I-1 with i1_frames=all)."""
        if self._folder is not None:
            return self._folder, self._folder.indices()
        from irdepth_jax.data.mixed import ConcatFrames
        parts = [self.frames(split, optional=True) for split in ("train", "val", "test")]
        dataset = ConcatFrames(parts)
        return dataset, np.arange(len(dataset))

    def describe(self, split: str = "train") -> dict:
        """What the frames of `split` are, as a checkpoint records it: {'kind': 'synthetic'
        (a dataset `irdepth synth` rendered) or 'real', 'format': 'folder' | 'ms2', 'path'
        (absolute), 'frame_size': [H, W] (of the split's first frame)}."""
        dataset, idx = self.frames(split)
        synthetic = self._folder is not None and self._folder.meta.get("source") == "synthetic"
        height, width = (self._folder.height, self._folder.width) if self._folder is not None \
            else dataset.raw(int(idx[0])).shape
        return {"kind": "synthetic" if synthetic else "real", "format": self.format,
                "path": os.path.abspath(self.path), "frame_size": [int(height), int(width)]}

    def use_raw_bits(self, raw_bits: int | str) -> int:
        """Checks every frame read from now on against `raw_bits` (14, 16 or 'auto'), 'auto'
        resolved from the training frames (`data.rawio.detect_raw_bits`: 16 when a count exceeds
        14 bits); returns the bit depth, 14 or 16."""
        from irdepth_jax.data.rawio import detect_raw_bits

        self._set_raw_bits(raw_bits)
        if raw_bits == "auto":
            self._set_raw_bits(detect_raw_bits(*self.frames("train")))
        return int(self.raw_bits)

    def _set_raw_bits(self, raw_bits: int | str) -> None:
        from irdepth_jax.data.rawio import accepted_bits

        accepted = accepted_bits(raw_bits)
        self.raw_bits = raw_bits
        for dataset in [self._folder, *self._ms2.values()]:
            if dataset is not None:
                dataset.raw_bits = accepted

    def max_depth(self) -> float:
        """Largest depth of the training frames (metres)."""
        dataset, _ = self.frames("train")
        return float(dataset.max_depth(split="train"))


def resolve_raw_bits(cfg: Config, source: DataSource) -> Config:
    """`cfg` with data.raw_bits as 14 or 16 ('auto' resolved from the training frames by
    `DataSource.use_raw_bits`, which then checks every frame against it), so that config.json
    and the checkpoints store the bit depth the model is trained on and predict reuses it."""
    bits = source.use_raw_bits(cfg.data.raw_bits)
    return dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, raw_bits=bits))


def phase_frames(source: DataSource, phase: str, cfg: Config) -> tuple[Any, np.ndarray]:
    """(dataset, indices) a phase trains on.

    * stage1_i1: the depth train split, or every frame with ``stage1.i1_frames=all``;
    * stage1_i2: the labelled frames of segmentation split train, plus the frames of
      ``stage1.seg_labels`` when it names another source (`stage1_i2_frames`);
    * stage2: the depth train split.
    """
    if phase == "stage1_i2":
        return stage1_i2_frames(source, cfg)[:2]
    if phase == "stage1_i1" and cfg.stage1.i1_frames == "all":
        dataset, idx = source.all_frames()
    else:
        dataset, idx = source.frames("train")
    if len(idx) == 0:
        raise RunError(f"`data` {source.path}: no training frames")
    return dataset, np.asarray(idx)


def stage1_i2_frames(source: DataSource, cfg: Config) -> tuple[Any, np.ndarray, dict]:
    """(dataset, indices, description) of Stage I-2 by `cfg.stage1.seg_labels`.

    'dataset': the frames with seg_split == train. 'synthetic' or a folder dataset's path: those
    frames plus the extra source's labelled frames (rendered at the data's size / resized to it);
    when the dataset itself has no labels, its unlabelled train frames are mixed in, so the
    reconstruction and gradient branches keep seeing the real data. 'none': the depth train
    frames, labels ignored. Without any label (and seg_labels != 'none') a RunError says what to
    pass. The description (logged, and stored in the I-2 checkpoints) says where the labels came
    from and how many labelled frames there are (0: the segmentation branch stays untrained).
    """
    from irdepth_jax.data.mixed import ConcatFrames, SyntheticLabeled

    choice = cfg.stage1.seg_labels
    if choice == "none":
        dataset, idx = source.frames("train")
        return dataset, np.asarray(idx), {"seg_labels": "none", "labeled_frames": 0,
                                          "why": "trained with stage1.seg_labels=none"}
    own_ds, own_idx = source.seg_frames("train")
    parts, described = [(own_ds, own_idx)], {"dataset": int(len(own_idx))}
    train_ds, train_idx = source.frames("train")
    size = tuple(np.shape(train_ds[int(train_idx[0])]["raw14"]))  # extra frames get this size
    if choice == "synthetic":
        extra = SyntheticLabeled(cfg.stage1.synthetic_labeled, *size, cfg.seed,
                                 cfg.data.raw_bits, cfg.data.scenes)
        parts.append((extra, np.arange(len(extra))))
        described["synthetic"] = len(extra)
    elif choice != "dataset":
        if not os.path.isdir(choice):
            raise RunError(f"stage1.seg_labels {choice!r}: choose dataset, synthetic, none or "
                           "the path of a labelled folder-format dataset")
        extra_ds, extra_idx = DataSource(choice, "folder",
                                         raw_bits=cfg.data.raw_bits).seg_frames("train")
        if len(extra_idx) == 0:
            raise RunError(f"stage1.seg_labels {choice}: no labelled frames with seg_split "
                           "train there")
        parts.append((extra_ds, extra_idx))
        described[choice] = int(len(extra_idx))
    labeled = sum(described.values())
    if labeled == 0:
        raise RunError(
            f"`data` {source.path}: no segmentation labels (no labelled frame with seg_split "
            "train), so Stage I-2 would leave the segmentation branch untrained while Stage II "
            "takes its Hue channel and sky mask from it. Pass stage1.seg_labels=synthetic "
            "(rendered labelled scenes), stage1.seg_labels=PATH (a labelled folder dataset), "
            "or stage1.seg_labels=none (then Stage II needs stage2.hue_mode=constant "
            "stage2.sky_loss=false)")
    if len(parts) > 1 and len(own_idx) == 0:
        parts[0] = (train_ds, train_idx)
    if len(parts) == 1:
        return own_ds, np.asarray(own_idx), {"seg_labels": choice, "labeled_frames": labeled}
    mixed = ConcatFrames(parts, size=size)
    return mixed, np.arange(len(mixed)), {"seg_labels": choice, "labeled_frames": labeled,
                                          "labeled_by_source": described,
                                          "frames": len(mixed)}


def host_image(batch: dict, preprocessing: str, bits: int = 14) -> np.ndarray | None:
    """The Stage II input image (B, H, W, 3) uint8 made on the host, or None for the images the
    Stage I model makes (`config.STAGE1_IMAGES`: 'hsv', 'value').

    'rgb': the aligned visible image; 'blank': constant grey (the layout-prior control); a tonemap
    name ('he', 'clahe', 'camera', ...): the tone-mapped raw frame (B, H, W) of `bits`-bit counts
    replicated to three channels.
    """
    if preprocessing in STAGE1_IMAGES:
        return None
    if preprocessing == "blank":
        return np.full(np.shape(batch["raw14"]) + (3,), BLANK_GREY, np.uint8)
    if preprocessing == "rgb":
        return np.asarray(batch["rgb"], np.uint8)
    fn = TONEMAPS[preprocessing]
    grey = np.stack([fn(np.asarray(raw), bits=bits) for raw in batch["raw14"]])
    if "brightness" in batch:  # the augmentation's factor, as ir8 / rgb got it
        factor = np.asarray(batch["brightness"], np.float32).reshape(-1, 1, 1)
        grey = np.clip(np.rint(grey * factor), 0, 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


STAGE_KEYS = {
    "stage1_i1": ("raw14", "ir8"),
    "stage1_i2": ("raw14", "ir8", "seg"),
    "stage2": ("raw14", "depth", "valid"),
}


def device_batch(batch: dict, phase: str, cfg: Config) -> dict:
    """The arrays a phase's step needs from a loader batch (numpy, host side)."""
    out = {k: np.asarray(batch[k]) for k in STAGE_KEYS[phase] + ("brightness",) if k in batch}
    if phase == "stage1_i2" and cfg.stage1.seg_labels == "none":
        out["seg"] = np.full_like(out["seg"], IGNORE_LABEL)
    if phase == "stage2":
        image = host_image(batch, cfg.stage2.preprocessing, resolved_raw_bits(cfg))
        if image is not None:
            out["image"] = image
    return out


def make_loader(dataset, indices, batch_size: int, seed: int, train: bool, cfg: Config):
    """A `data.loader.Loader` over `indices` for this process (global batch / process count)."""
    from irdepth_jax.data.loader import Loader

    per_process = batch_size // jax.process_count()
    return Loader(dataset, indices, batch_size=per_process, seed=seed, shuffle=train,
                  drop_remainder=train, augment=train and cfg.data.augment,
                  process_index=jax.process_index(), process_count=jax.process_count())


class BatchStream:
    """Endless batches of a `Loader`, epoch after epoch, with a resumable position."""

    def __init__(self, loader):
        self.loader = loader
        self._it: Iterator | None = None

    def __next__(self) -> dict:
        if self._it is None:
            self._it = iter(self.loader)
        try:
            return next(self._it)
        except StopIteration:
            self._it = iter(self.loader)
            return next(self._it)

    def get_state(self) -> Any:
        return self.loader.get_state()

    def set_state(self, state: Any) -> None:
        self.loader.set_state(state)
        self._it = None
