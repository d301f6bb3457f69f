"""Our on-disk dataset format: reader (`FolderDataset`) and writer (`write_sample`,
`write_manifest`). The synthetic dataset writer behind `irdepth synth` (`write_synthetic_dataset`)
is `irdepth_jax.data.synthetic_dataset`'s.

## Folder dataset format

A dataset is a directory:

```
DATASET/
  manifest.json            frame list and splits (written last: no manifest = not a dataset)
  raw14/<id>.png           raw LWIR counts, 16-bit single-channel PNG, values 0..16383 (14-bit
                           sensors; 0..65535 for a 16-bit camera, read with raw_bits=16)
  ir8/<id>.png             the camera's 8-bit image, 8-bit single-channel PNG
  depth/<id>.png           depth, 16-bit PNG in 1/256 m (KITTI / MS2 convention), 0 = no depth
  seg/<id>.png             labels, 8-bit PNG: 0 sky, 1 building, 2 car, 3 bicycle, 4 road,
                           5 tree, 255 unlabelled (only for labelled frames)
  rgb/<id>.png             optional aligned visible image, 8-bit 3-channel PNG
  depth_dense/<id>.png     optional dense depth (same encoding as depth/), for evaluation
```

`manifest.json`:

```json
{"format": "irdepth-folder", "version": 1, "height": 256, "width": 320,
 "frames": [{"id": "000000", "split": "train", "seg_split": "train", "condition": "day",
             "labeled": true, "has_rgb": true, "has_depth_dense": true, "max_depth": 79.8}, ...]}
```

- `split` (train / val / test) is the depth (Stage II) split of every frame; `seg_split`
  (train / val / test, or null) is the segmentation (Stage I-2) split of the labelled frames;
  `labeled` says whether `seg/<id>.png` exists. `condition` is free text (day / dusk / night /
  rainy / unknown). `max_depth` (optional) is the largest valid depth of the frame in metres;
  without it the reader opens the depth PNGs when asked for `max_depth()`.
- Ids are file stems: letters, digits, `_`, `-`, `.` (no path separators).
- Depth is stored as round(metres * 256) in uint16, so depths from 1/256 m to 255.99 m are exact
  to 1/512 m; `depth = png / 256`, `valid = png > 0` (`data.depth_png`, which also says what
  happens to a depth over 255.99 m).
- Synthetic datasets (`irdepth synth`) store the LiDAR-like sparse depth in `depth/` (what real
  data provides, used for training and the reported metrics) and the renderer's dense depth
  (sky = 0) in `depth_dense/`.

Every source (this format, MS2, the renderer) yields the same sample dict: `raw14` (H, W) uint16,
`ir8` (H, W) uint8, `rgb` (H, W, 3) uint8 (zeros when absent), `has_rgb` bool, `depth` (H, W)
float32 metres (0 where invalid), `valid` (H, W) bool, `seg` (H, W) uint8 (all 255 when
unlabelled), `labeled` bool, `condition` str, `id` str.
"""

from __future__ import annotations

import json
import pathlib
import re

import cv2
import numpy as np

from irdepth_jax.config import IGNORE_LABEL
from irdepth_jax.data.depth_png import DEPTH_SCALE, decode_depth, encode_depth
from irdepth_jax.data.rawio import accepted_bits
from irdepth_jax.errors import IrdepthError
from irdepth_jax.fileio import make_dirs, write_bytes, write_png
from irdepth_jax.imaging.raw import check_raw

FORMAT_NAME = "irdepth-folder"
FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
MAP_FOLDERS = ("raw14", "ir8", "depth", "seg", "rgb", "depth_dense")
"""The per-frame PNG folders of a dataset."""

_ID = re.compile(r"^[A-Za-z0-9_.\-]+$")
_RECORD_KEYS = ("id", "split", "seg_split", "condition", "labeled")


class DatasetError(IrdepthError):
    """A dataset file or directory is missing, corrupt or inconsistent (the message names it)."""


class DatasetWarning(UserWarning):
    """A dataset is read with parts left out (e.g. MS2 sequences not downloaded); one line."""


# ----------------------------------------------------------------------------- PNG helpers


def read_png(path: pathlib.Path, dtype, channels: int) -> np.ndarray:
    """Reads a PNG exactly (no conversion) and checks its dtype and channel count.

    Returns (H, W) for channels == 1, (H, W, 3) RGB for channels == 3.
    Raises DatasetError naming `path` when it is missing, undecodable or of the wrong kind.
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: missing file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: cannot decode PNG")
    got_channels = 1 if img.ndim == 2 else img.shape[2]
    if img.dtype != np.dtype(dtype) or got_channels != channels:
        raise DatasetError(
            f"{path}: expected a {channels}-channel {np.dtype(dtype)} PNG, "
            f"got {got_channels}-channel {img.dtype}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB) if channels == 3 else img


def _write_png(path: pathlib.Path, img: np.ndarray) -> None:
    """Writes an RGB or single-channel image as PNG, completely or not at all
    (`fileio.write_png`; WriteError naming the file)."""
    make_dirs(path.parent)
    write_png(path, cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img)


# ----------------------------------------------------------------------------- writer


def _check_id(sample_id: str) -> str:
    if not isinstance(sample_id, str) or not _ID.match(sample_id):
        raise ValueError(f"sample id {sample_id!r}: use letters, digits, '_', '-', '.' only")
    return sample_id


def write_sample(root, sample_id: str, sample: dict, raw_bits: int = 14) -> dict:
    """Writes one frame's PNGs under `root`.

    Args:
      root: dataset directory (created if needed).
      sample_id: file stem, see the format above.
      sample: dict with raw14 (H, W) uint16, ir8 (H, W) uint8, depth (H, W) float metres and
        optionally valid (H, W) bool (default depth > 0), seg (H, W) uint8 (written only when
        'labeled' is true, default: seg present), rgb (H, W, 3) uint8 (written when present and
        'has_rgb' is not False), depth_dense (H, W) float metres.
      raw_bits: bit depth of the raw14 counts, 14 or 16 (their accepted range 0..2^bits-1).

    Returns:
      the frame's manifest fields this function knows: labeled, has_rgb, has_depth_dense,
      max_depth (largest valid depth in metres, 0 if none).
    """
    root = pathlib.Path(root)
    sid = _check_id(sample_id)
    raw = np.asarray(sample["raw14"])
    if raw.ndim != 2 or not np.issubdtype(raw.dtype, np.integer) or raw.size == 0:
        raise ValueError(
            f"sample {sid}: raw14 must be a 2-D integer array, got {raw.dtype} {raw.shape}")
    top = 2**raw_bits - 1
    if raw.min() < 0 or raw.max() > top:
        raise ValueError(
            f"sample {sid}: raw14 counts must be in 0..{top}, got {raw.min()}..{raw.max()}")
    shape = raw.shape
    maps = {"raw14": raw.astype(np.uint16), "ir8": np.asarray(sample["ir8"])}
    depth = encode_depth(sample["depth"], sample.get("valid"), f"sample {sid}")
    maps["depth"] = depth
    labeled = bool(sample.get("labeled", "seg" in sample))
    if labeled and "seg" not in sample:
        raise ValueError(f"sample {sid}: labeled is true but there is no 'seg' map")
    if labeled:
        maps["seg"] = np.asarray(sample["seg"])
    has_rgb = "rgb" in sample and bool(sample.get("has_rgb", True))
    if has_rgb:
        maps["rgb"] = np.asarray(sample["rgb"])
    if "depth_dense" in sample:
        maps["depth_dense"] = encode_depth(sample["depth_dense"], name=f"sample {sid} depth_dense")
    for name, want in (("ir8", np.uint8), ("seg", np.uint8), ("rgb", np.uint8)):
        if name in maps and maps[name].dtype != want:
            raise ValueError(
                f"sample {sid}: {name} must be {np.dtype(want)}, got {maps[name].dtype}")
    for name, img in maps.items():
        if img.shape[:2] != shape or (name == "rgb") != (img.ndim == 3):
            raise ValueError(f"sample {sid}: {name} has shape {img.shape}, raw14 has {shape}")
        _write_png(root / name / f"{sid}.png", img)
    return dict(labeled=labeled, has_rgb=has_rgb, has_depth_dense="depth_dense" in maps,
                max_depth=float(depth.max()) / DEPTH_SCALE)


def write_manifest(root, records: list[dict], height: int, width: int, **meta) -> pathlib.Path:
    """Writes `root/manifest.json` (atomically: a temporary file renamed into place).

    Args:
      records: one dict per frame with at least id, split, seg_split, condition, labeled
        (plus optional has_rgb, has_depth_dense, max_depth).
      height, width: frame size.
      meta: extra JSON-able top-level fields (e.g. source, seed).
    """
    root = pathlib.Path(root)
    for r in records:
        _validate_record(r, root / "manifest.json")
    doc = dict(format=FORMAT_NAME, version=FORMAT_VERSION, height=int(height), width=int(width),
               **meta, frames=list(records))
    make_dirs(root)
    write_bytes(root / "manifest.json", json.dumps(doc, indent=1).encode())
    return root / "manifest.json"


def _validate_record(r, where) -> None:
    missing = [k for k in _RECORD_KEYS if not isinstance(r, dict) or k not in r]
    if missing:
        raise DatasetError(f"{where}: frame record {r!r} lacks {missing}")
    _check_id(r["id"])
    if r["split"] not in SPLITS:
        raise DatasetError(f"{where}: frame {r['id']}: split {r['split']!r} not in {SPLITS}")
    if r["seg_split"] is not None and r["seg_split"] not in SPLITS:
        raise DatasetError(
            f"{where}: frame {r['id']}: seg_split {r['seg_split']!r} not in {SPLITS} or null")
    if r["seg_split"] is not None and not r["labeled"]:
        raise DatasetError(f"{where}: frame {r['id']}: seg_split set on an unlabelled frame")


# ----------------------------------------------------------------------------- reader


class FolderDataset:
    """Random-access reader of a folder dataset (format in the module docstring).

    `ds[i]` -> sample dict; `ds.records[i]` -> manifest record; `len(ds)` frames.
    With `with_dense=True` samples also hold `depth_dense` (H, W) float32 (frames without the
    file raise DatasetError). `raw_bits` (14, 16 or 'auto': up to 16) is the bit depth the raw
    counts are checked against when a frame is read; a frame over it raises DatasetError.
    """

    def __init__(self, root, with_dense: bool = False, raw_bits: int | str = 14):
        self.root = pathlib.Path(root)
        self.with_dense = with_dense
        self.raw_bits = accepted_bits(raw_bits)
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: not a directory")
        path = self.root / "manifest.json"
        if not path.is_file():
            raise DatasetError(f"{self.root}: not an irdepth folder dataset (no manifest.json)")
        try:
            doc = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise DatasetError(f"{path}: not valid JSON ({e})") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
            raise DatasetError(
                f"{path}: not an irdepth folder manifest (format != {FORMAT_NAME!r})")
        if doc.get("version") != FORMAT_VERSION:
            raise DatasetError(f"{path}: format version {doc.get('version')!r}, "
                               f"this reader reads {FORMAT_VERSION}")
        frames = doc.get("frames")
        if not isinstance(frames, list):
            raise DatasetError(f"{path}: 'frames' must be a list")
        for r in frames:
            _validate_record(r, path)
        self.height, self.width = int(doc["height"]), int(doc["width"])
        self.meta = {k: v for k, v in doc.items() if k != "frames"}
        self.records: list[dict] = frames
        self._max_depth: dict = {}

    def __len__(self) -> int:
        return len(self.records)

    def _png(self, field: str, sid: str, dtype, channels: int) -> np.ndarray:
        path = self.root / field / f"{sid}.png"
        img = read_png(path, dtype, channels)
        if img.shape[:2] != (self.height, self.width):
            raise DatasetError(f"{path}: size {img.shape[1]}x{img.shape[0]}, manifest says "
                               f"{self.width}x{self.height}")
        return img

    def __getitem__(self, i: int) -> dict:
        """Sample dict of frame i (keys in the module docstring)."""
        r = self.records[i]
        sid = r["id"]
        raw = self.raw(i)
        depth, valid = decode_depth(self._png("depth", sid, np.uint16, 1))
        has_rgb = bool(r.get("has_rgb", False))
        hw = (self.height, self.width)
        sample = dict(
            raw14=raw,
            ir8=self._png("ir8", sid, np.uint8, 1),
            rgb=self._png("rgb", sid, np.uint8, 3) if has_rgb else np.zeros(hw + (3,), np.uint8),
            has_rgb=has_rgb,
            depth=depth,
            valid=valid,
            seg=(self._png("seg", sid, np.uint8, 1) if r["labeled"]
                 else np.full(hw, IGNORE_LABEL, np.uint8)),
            labeled=bool(r["labeled"]),
            condition=str(r["condition"]),
            id=sid,
        )
        if self.with_dense:
            sample["depth_dense"] = decode_depth(self._png("depth_dense", sid, np.uint16, 1))[0]
        return sample

    def raw(self, i: int) -> np.ndarray:
        """Raw counts (H, W) uint16 of frame i, checked against `raw_bits`."""
        sid = self.records[i]["id"]
        raw = self._png("raw14", sid, np.uint16, 1)
        try:
            check_raw(raw, self.raw_bits)
        except ValueError as err:
            raise DatasetError(f"{self.root / 'raw14' / (sid + '.png')}: {err}") from None
        return raw

    def indices(self, split: str | None = None, labeled: bool | None = None,
                seg_split: str | None = None) -> np.ndarray:
        """Frame indices (int64, ascending) matching every filter given (None = any)."""
        for name, value in (("split", split), ("seg_split", seg_split)):
            if value is not None and value not in SPLITS:
                raise ValueError(f"{name} must be one of {SPLITS} or None, got {value!r}")
        keep = [i for i, r in enumerate(self.records)
                if (split is None or r["split"] == split)
                and (labeled is None or bool(r["labeled"]) == labeled)
                and (seg_split is None or r["seg_split"] == seg_split)]
        return np.asarray(keep, np.int64)

    def max_depth(self, split: str | None = "train") -> float:
        """Largest valid depth (metres) over the frames of `split` (None = all frames).

        Uses the manifest's per-frame `max_depth` when every frame has it, else reads the
        depth PNGs (once; cached).
        """
        if split not in self._max_depth:
            idx = self.indices(split=split)
            if len(idx) == 0:
                raise DatasetError(f"{self.root}: no frames in split {split!r}")
            if all("max_depth" in self.records[i] for i in idx):
                value = max(float(self.records[i]["max_depth"]) for i in idx)
            else:
                value = max(float(self._png("depth", self.records[i]["id"], np.uint16, 1).max())
                            for i in idx) / DEPTH_SCALE
            self._max_depth[split] = value
        return self._max_depth[split]
