"""Raw thermal frames from files (what `irdepth predict` reads) and the bit depth of a dataset.

Formats, by suffix (`RAW_SUFFIXES`):

* ``.png``: 16-bit single-channel PNG (OpenCV).
* ``.tif`` / ``.tiff``: 16-bit single-channel TIFF, one frame per page (multi-page stacks too;
  reduced-resolution thumbnail pages are left out). Read with tifffile (+ imagecodecs for LZW /
  deflate compressed files, which radiometric cameras write), not OpenCV, whose libtiff prints
  a warning on stderr for every private camera tag.
* ``.npy``: an integer array (H, W) or a stack (N, H, W).
* ``.fff`` / ``.seq``: FLIR raw files (one frame / a sequence of frames), through the optional
  `flirpy` package (``pip install 'irdepth_jax[flir]'``): the sensor counts, not temperatures.
* ``.jpg`` / ``.jpeg``: FLIR radiometric JPEGs and DJI R-JPEGs (their raw counts, parsed by
  `irdepth_jax.data.thermal_jpeg`); a JPEG without raw counts is a visible photo.
* ``.bag`` and ROS 2 bag folders: the mono16 ``sensor_msgs/msg/Image`` messages of one topic
  (`irdepth_jax.data.rosbag`, through the optional `rosbags` package: ``pip install
  'irdepth_jax[rosbag]'``).

A file holding one frame gives one frame named by the file stem; a stack gives frames named
``STEM_p0000``, ``STEM_p0001``, ... (page / frame index from 0).

Every frame is checked to be integer counts of the run's bit depth (14 or 16,
`irdepth_jax.imaging.raw.check_raw`). An 8-bit or colour image raises `NotThermalError` (a
folder that mixes thermal and visible frames can skip those); anything else that is not a raw
frame raises `RawFileError`. Both are one-line ValueErrors naming the file.

`detect_raw_bits` resolves ``data.raw_bits=auto`` from a dataset's training frames.
"""

from __future__ import annotations

import os
import typing

import numpy as np

from irdepth_jax.config_schema import RawBits
from irdepth_jax.errors import IrdepthError
from irdepth_jax.imaging.raw import RAW_MAX, check_raw

RAW_SUFFIXES = (".png", ".tif", ".tiff", ".npy", ".fff", ".seq", ".jpg", ".jpeg", ".bag")
"""File suffixes `read_frames` reads (lower case; matched case-insensitively)."""

RAW_BITS_SETTINGS = typing.get_args(RawBits)
"""Values of `DataConfig.raw_bits`."""

AUTO_SAMPLE = 256
"""Most training frames `detect_raw_bits` reads (evenly spaced over the split)."""


class RawFileError(IrdepthError, ValueError):
    """A file that is not a readable raw thermal frame (one line naming the file and why)."""


class NotThermalError(RawFileError):
    """An 8-bit or colour image: a visible / NIR / display frame, not raw thermal counts."""


def accepted_bits(raw_bits: int | str) -> int:
    """The bit depth frames are checked against for a `raw_bits` setting: 14 or 16 as given,
    16 for 'auto' (any count a 16-bit container holds, until the run resolves it). ValueError
    for any other setting."""
    if raw_bits not in RAW_BITS_SETTINGS:
        raise ValueError(f"data.raw_bits {raw_bits!r}: choose 14, 16 or auto")
    return 16 if raw_bits == "auto" else int(raw_bits)


def detect_raw_bits(dataset, indices, max_frames: int = AUTO_SAMPLE) -> int:
    """``data.raw_bits=auto`` resolved: 16 when a training frame has a count over 2^14 - 1,
    else 14.

    Args:
      dataset: a dataset with ``raw(i)`` -> (H, W) uint16 counts (`FolderDataset`, `MS2Dataset`).
      indices: (N,) the training frames.
      max_frames: read every frame when N <= max_frames, else `max_frames` evenly spaced ones
        (a bounded sample: a 16-bit camera's offset puts most frames over 14 bits; a frame over
        14 bits that the sample missed still stops the run when it is loaded, since the run's
        frames are then checked against the resolved 14 bits).
    Returns:
      14 or 16.
    """
    indices = np.asarray(indices)
    if len(indices) > max_frames:
        indices = indices[np.linspace(0, len(indices) - 1, max_frames).round().astype(int)]
    return 16 if any(int(dataset.raw(int(i)).max()) > RAW_MAX for i in indices) else 14


def read_frames(path: str, bits: int = 14, topic: str | None = None
                ) -> list[tuple[str, np.ndarray]]:
    """The raw frames of one file (formats in the module docstring).

    Args:
      path: the file (or a ROS 2 bag's folder).
      bits: bit depth of the counts, 14 or 16: a count over 2^bits - 1 is an error.
      topic: a ROS bag's image topic (`data.rosbag.read_bag`; None: its one image topic).
    Returns:
      [(name, (H, W) uint16 counts)]: one entry named by the file stem for a single frame, or
      ``STEM_pNNNN`` per frame of a stack.
    Raises:
      NotThermalError: an 8-bit or colour image.
      RawFileError: an unknown suffix, an unreadable file, a float / negative / over-`bits`
        frame, or a FLIR file without flirpy installed.
    """
    from irdepth_jax.data.rosbag import BagError, is_bag, read_bag

    stem, suffix = os.path.splitext(os.path.basename(os.path.normpath(path)))
    suffix = suffix.lower()
    readers = {".png": _png, ".tif": _tiff, ".tiff": _tiff, ".npy": _npy, ".fff": _flir,
               ".seq": _flir, ".jpg": _thermal_jpeg, ".jpeg": _thermal_jpeg}
    if is_bag(path):
        try:
            arrays = read_bag(path, topic)
        except BagError as err:
            raise RawFileError(str(err)) from None
    elif suffix in readers:
        arrays = readers[suffix](path)
    else:
        raise RawFileError(f"{path}: unknown raw frame type {suffix or '(no suffix)'!r} "
                           f"(read: {', '.join(RAW_SUFFIXES)})")
    if not arrays:
        raise RawFileError(f"{path}: holds no frame")
    if len(arrays) == 1:
        return [(stem, _frame(path, arrays[0], bits))]
    return [(f"{stem}_p{k:04d}", _frame(f"{path} (frame {k})", a, bits))
            for k, a in enumerate(arrays)]


def _frame(where: str, arr: np.ndarray, bits: int) -> np.ndarray:
    """One frame checked: (H, W) (or (H, W, 1)) integer counts of `bits` bits -> uint16."""
    if arr.ndim == 3 and arr.shape[-1] == 1:
        arr = arr[..., 0]
    if arr.ndim == 3 and arr.shape[-1] in (3, 4):
        raise NotThermalError(f"{where}: colour image {arr.shape}, not a raw thermal frame")
    if arr.ndim != 2:
        raise RawFileError(f"{where}: shape {arr.shape}, expected a single-channel frame (H, W)")
    if arr.dtype in (np.uint8, np.int8):
        raise NotThermalError(f"{where}: 8-bit image, not raw thermal counts (16-bit PNG / "
                              "TIFF, .npy or FLIR .fff / .seq)")
    try:
        check_raw(arr, bits)
    except ValueError as err:
        raise RawFileError(f"{where}: {err}") from None
    return arr.astype(np.uint16)


def _png(path: str) -> list[np.ndarray]:
    import cv2

    img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise RawFileError(f"{path}: not a readable PNG image")
    return [img]


def _tiff(path: str) -> list[np.ndarray]:
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            pages = [(page.samplesperpixel, page.asarray()) for page in tif.pages
                     if not page.is_reduced]
    except (tifffile.TiffFileError, ValueError, OSError, RuntimeError) as err:
        # RuntimeError: imagecodecs' decoders (e.g. corrupt LZW data), a message without the file
        raise RawFileError(f"{path}: not a readable TIFF ({err})") from None
    for k, (samples, _) in enumerate(pages):
        if samples > 1:
            raise NotThermalError(f"{path}: colour TIFF (page {k} has {samples} samples per "
                                  "pixel), not a raw thermal frame")
    return [arr for _, arr in pages]


def _npy(path: str) -> list[np.ndarray]:
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:  # EOFError: an empty file
        raise RawFileError(f"{path}: not a readable .npy array ({err})") from None
    if arr.ndim not in (2, 3):
        raise RawFileError(f"{path}: shape {arr.shape}, expected a frame (H, W) or a stack "
                           "(N, H, W)")
    return [arr] if arr.ndim == 2 else list(arr)


def _thermal_jpeg(path: str) -> list[np.ndarray]:
    """A FLIR radiometric JPEG's or a DJI R-JPEG's raw counts (`data.thermal_jpeg`)."""
    from irdepth_jax.data.thermal_jpeg import NoRawCountsError, ThermalFileError, read_thermal_jpeg

    try:
        return [read_thermal_jpeg(path)]
    except NoRawCountsError as err:
        raise NotThermalError(str(err)) from None
    except (ThermalFileError, OSError) as err:
        raise RawFileError(str(err)) from None


def _flir(path: str) -> list[np.ndarray]:
    try:
        from flirpy.io.fff import Fff
        from flirpy.io.seq import Seq
    except ImportError:
        raise RawFileError(f"{path}: reading FLIR .fff / .seq files needs the flirpy package: "
                           "pip install 'irdepth_jax[flir]'") from None
    try:
        if path.lower().endswith(".fff"):
            return [Fff(str(path)).get_image()]
        seq = Seq(str(path))
        return [seq[k].get_image() for k in range(len(seq))]
    # flirpy parses the binary layout directly: a file it cannot parse surfaces as struct,
    # index, attribute or value errors from deep inside it.
    except Exception as err:  # noqa: BLE001
        raise RawFileError(f"{path}: not a readable FLIR file ({type(err).__name__}: "
                           f"{err})") from None
