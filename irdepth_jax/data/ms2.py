"""MS2 (Multi-Spectral Stereo, CVPR 2023) thermal depth data as irdepth sample dicts.

Layout read (only the parts thermal monocular depth needs):

```
ROOT/
  train_list.txt  val_list.txt  test_day_list.txt  test_night_list.txt  test_rainy_list.txt
                                  one sequence name per line (names start with '_')
  sync_data/<seq>/thr/img_left/<name>.png             16-bit raw thermal (counts ~3000-6000)
  proj_depth/<seq>/thr/depth_filtered/<name>.png      uint16 depth, metres * 256, 0 = none
```

Splits: 'train', 'val', 'test_day', 'test_night', 'test_rainy', and 'test' (the three test
lists together). The condition of a frame comes from the test list holding its sequence
('day', 'night', 'rainy'); train / val sequences are not labelled by MS2, so their condition is
the one of a test list naming the same sequence, else the `conditions` mapping given to the
constructor, else 'unknown'.

Frames are the img_left PNGs that have a depth_filtered file (others are skipped, counted in
`skipped` and in one `DatasetWarning`; `strict=True` raises `MissingDepthError` instead), sorted
by sequence (in list order) then name. A partial download is read as it is:
sequences of the lists without sync_data/<seq>/thr/img_left are skipped with one
`DatasetWarning` naming them (kept in `missing`); `strict=True` raises `MissingSequencesError`
instead. The MS2 test protocol evaluates `subsample(ds.indices(), 10)`: the official loader's
`frames[0:-1:10]` over the frames of the whole split (all its sequences concatenated).

Raw counts are checked against `raw_bits` (MS2's sensor is 14-bit, the default): a frame with a
count over it raises DatasetError naming the file. `ir8` is `camera_like(raw)`; MS2 has no
aligned RGB or segmentation here: rgb zeros (has_rgb False), seg all 255 (labeled False).
"""

from __future__ import annotations

import pathlib
import warnings

import numpy as np

from irdepth_jax.config import IGNORE_LABEL, MS2_DEPTH_LABELS
from irdepth_jax.data.depth_png import DEPTH_SCALE, decode_depth
from irdepth_jax.data.folder import DatasetError, DatasetWarning, read_png
from irdepth_jax.data.rawio import accepted_bits
from irdepth_jax.imaging.raw import check_raw

LIST_FILES = {"train": "train_list.txt", "val": "val_list.txt", "test_day": "test_day_list.txt",
              "test_night": "test_night_list.txt", "test_rainy": "test_rainy_list.txt"}
_TEST_CONDITION = {"test_day": "day", "test_night": "night", "test_rainy": "rainy"}
SPLITS = tuple(LIST_FILES) + ("test",)


DEPTH_LABELS = MS2_DEPTH_LABELS


class MissingSequencesError(DatasetError):
    """strict=True: sequences named by a split list are not on disk."""


class MissingDepthError(DatasetError):
    """strict=True: thermal frames of a split have no depth_filtered file."""


def subsample(indices: np.ndarray, stride: int) -> np.ndarray:
    """The MS2 protocol's frame subsampling, as the official loader (UkcheolShin/SupDepth4Thermal
    `DataLoader_MS2.crawl_folders_depth`) does it over the concatenated frames of a split.

    Args:
      indices: (N,) frame indices of the split, in order.
      stride: 1 keeps every frame; N > 1 keeps `indices[0:-1:N]` (the last frame is never
        picked, also when (len - 1) is a multiple of N). The test protocol uses 10.
    Returns:
      (M,) the kept indices.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    return indices if stride == 1 else indices[0:-1:stride]


def _read_list(path: pathlib.Path) -> list[str]:
    if not path.is_file():
        raise DatasetError(f"{path}: missing split list")
    try:
        return [line.strip() for line in path.read_text().splitlines() if line.strip()]
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text file") from None


class MS2Dataset:
    """Reader of one MS2 split; `ds[i]` -> sample dict (keys as `FolderDataset`).

    Args:
      root: MS2 root (holding the *_list.txt files, sync_data/ and proj_depth/).
      split: one of SPLITS.
      conditions: optional {sequence: condition} for sequences no test list names.
      strict: raise `MissingSequencesError` when a listed sequence is not on disk (default:
        skip it, with one `DatasetWarning` naming the missing ones, listed in `missing`), and
        `MissingDepthError` when a thermal frame has no depth file (default: skip it, with one
        `DatasetWarning` counting them).
      raw_bits: bit depth the raw counts are checked against when a frame is read: 14, 16 or
        'auto' (up to 16, until a run resolves it).
      depth_label: which depth label version is the ground truth (`DEPTH_LABELS`).
    """

    def __init__(self, root, split: str, conditions: dict | None = None, strict: bool = False,
                 raw_bits: int | str = 14, depth_label: str = "depth_filtered"):
        if depth_label not in DEPTH_LABELS:
            raise ValueError(f"MS2 depth label {depth_label!r}: choose one of "
                             f"{', '.join(DEPTH_LABELS)}")
        self.depth_label = depth_label
        self.root = pathlib.Path(root)
        self.raw_bits = accepted_bits(raw_bits)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a directory")
        if not (self.root / "sync_data").is_dir():
            raise DatasetError(f"{self.root}: not an MS2 root (no sync_data/ directory)")
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        self.split = split
        known = dict(conditions or {})
        for name, cond in _TEST_CONDITION.items():
            path = self.root / LIST_FILES[name]
            if path.is_file():
                known.update({seq: cond for seq in _read_list(path)})
        parts = list(_TEST_CONDITION) if split == "test" else [split]
        self.records: list[dict] = []
        self.missing: list[str] = []
        self.skipped = listed = 0
        for part in parts:
            sequences = _read_list(self.root / LIST_FILES[part])
            listed += len(sequences)
            for seq in sequences:
                img_dir = self.root / "sync_data" / seq / "thr" / "img_left"
                if not img_dir.is_dir():
                    self.missing.append(seq)
                    continue
                cond = _TEST_CONDITION.get(part) or known.get(seq, "unknown")
                for img in sorted(img_dir.glob("*.png")):
                    depth = (self.root / DEPTH_LABELS[depth_label] / seq / "thr" / depth_label
                             / img.name)
                    if not depth.is_file():
                        self.skipped += 1
                        continue
                    self.records.append(dict(id=f"{seq}/{img.stem}", split=split, seg_split=None,
                                             condition=cond, labeled=False, raw_path=str(img),
                                             depth_path=str(depth)))
        if self.missing:
            what = (f"{self.root}: {len(self.missing)} of {listed} sequences of "
                    f"{', '.join(LIST_FILES[p] for p in parts)} are not on disk "
                    "(no sync_data/<seq>/thr/img_left)")
            names = ", ".join(self.missing)
            if strict or not self.records:
                raise (MissingSequencesError if strict else DatasetError)(f"{what}: {names}")
            warnings.warn(f"{what}, skipped: {names}", DatasetWarning, stacklevel=2)
        if self.skipped:
            what = (f"{self.root}: {self.skipped} of {self.skipped + len(self.records)} thermal "
                    f"frames of split {split!r} have no depth file "
                    "(proj_depth/<seq>/thr/depth_filtered/<name>.png)")
            if strict:
                raise MissingDepthError(what)
            if self.records:
                warnings.warn(f"{what}, skipped", DatasetWarning, stacklevel=2)
        if not self.records:
            raise DatasetError(f"{self.root}: no thermal frames with depth in split {split!r} "
                               f"({DEPTH_LABELS[depth_label]}/<seq>/thr/{depth_label})")
        self._max_depth: float | None = None

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, i: int) -> dict:
        """Sample dict of frame i: raw14, ir8, rgb (zeros), has_rgb, depth, valid, seg, labeled,
        condition, id."""
        from irdepth_jax.imaging.tonemap import camera_like

        r = self.records[i]
        raw = self.raw(i)
        counts = read_png(r["depth_path"], np.uint16, 1)
        if counts.shape != raw.shape:
            raise DatasetError(
                f"{r['depth_path']}: shape {counts.shape}, thermal frame {raw.shape}")
        depth, valid = decode_depth(counts)
        return dict(raw14=raw, ir8=np.asarray(camera_like(raw, bits=self.raw_bits), np.uint8),
                    rgb=np.zeros(raw.shape + (3,), np.uint8), has_rgb=False,
                    depth=depth, valid=valid,
                    seg=np.full(raw.shape, IGNORE_LABEL, np.uint8), labeled=False,
                    condition=r["condition"], id=r["id"])

    def raw(self, i: int) -> np.ndarray:
        """Raw counts (H, W) uint16 of frame i, checked against `raw_bits`."""
        path = self.records[i]["raw_path"]
        raw = read_png(path, np.uint16, 1)
        try:
            check_raw(raw, self.raw_bits)
        except ValueError as err:
            raise DatasetError(f"{path}: {err}") from None
        return raw

    def indices(self, split: str | None = None, labeled: bool | None = None,
                seg_split: str | None = None) -> np.ndarray:
        """Frame indices matching the filters; this dataset holds one split and no labels, so
        `split` must be None or this split, labeled=True or a seg_split give no frames."""
        if split is not None and split != self.split:
            raise ValueError(f"this MS2Dataset holds split {self.split!r}, asked for {split!r}")
        if labeled or seg_split is not None:
            return np.zeros(0, np.int64)
        return np.arange(len(self.records), dtype=np.int64)

    def max_depth(self, split: str | None = None) -> float:
        """Largest valid depth (metres) over the frames (reads every depth PNG once; cached)."""
        self.indices(split=split)
        if self._max_depth is None:
            self._max_depth = max(float(read_png(r["depth_path"], np.uint16, 1).max())
                                  for r in self.records) / DEPTH_SCALE
        return self._max_depth
