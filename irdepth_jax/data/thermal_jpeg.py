"""Raw counts from the files thermal cameras write besides TIFFs: FLIR radiometric JPEGs, DJI
R-JPEGs and FLIR ``.fff`` records, parsed directly (a few lines each; no camera SDK).

* FLIR radiometric JPEG (most handheld FLIR cameras): the visible-looking JPEG carries an FFF
  record split over APP1 segments that start with ``FLIR\\0``, a version byte, the segment's
  index and the last index; their payloads joined are the record (`flir_jpeg_record`).
* FLIR FFF record (a ``.fff`` file is one): a header (``FFF\\0``, creator, version, index
  offset, entry count; big-endian, little-endian from some PC software) and 32-byte index
  entries; entry type 1 is the raw image, whose
  little-endian header gives width (offset 2) and height (offset 4) and whose pixels start at
  offset 32: uncompressed little-endian uint16, or a PNG whose 16-bit values are byte-swapped
  (`fff_raw_image`).
* DJI R-JPEG (thermal drones): the raw counts are APP3 segments, joined, little-endian uint16
  of the JPEG's frame size or of its half / quarter (the M30T shows 640x512 counts as a
  1280x1024 JPEG) (`dji_rjpeg_raw`).

`read_thermal_jpeg` reads either kind of JPEG; a JPEG with neither raises `NoRawCountsError`
(a visible photo). Errors are one-line ValueErrors naming the file (`data.rawio` turns them into
its own: this module imports nothing of the package).
"""

from __future__ import annotations

import struct

import numpy as np

from irdepth_jax.errors import IrdepthError


class ThermalFileError(IrdepthError, ValueError):
    """A file that is not a readable thermal JPEG / FFF record (one line naming it and why)."""


class NoRawCountsError(ThermalFileError):
    """A JPEG that holds no raw counts: a visible photo, not a thermal camera's file."""

FLIR_SEGMENT = b"FLIR\x00"
FFF_MAGIC = b"FFF\x00"
FFF_RAW_IMAGE = 1
"""Index entry type of the raw sensor image in an FFF record."""
RAW_PIXELS_OFFSET = 32
"""Where the pixels start in an FFF raw-image entry (after its header)."""


def jpeg_segments(data: bytes, where: str) -> list[tuple[int, bytes]]:
    """(marker, payload) of each segment of a JPEG before its image data (start of scan).
    ThermalFileError naming `where` when `data` is not a JPEG or a segment runs past its end."""
    if data[:2] != b"\xff\xd8":
        raise ThermalFileError(f"{where}: not a JPEG file")
    segments, i = [], 2
    while i + 4 <= len(data) and data[i] == 0xFF:
        marker = data[i + 1]
        if marker in (0xD9, 0xDA):  # end of image, start of scan
            break
        if marker == 0xFF or 0xD0 <= marker <= 0xD7:  # fill byte, restart markers: no length
            i += 1 if marker == 0xFF else 2
            continue
        (length,) = struct.unpack(">H", data[i + 2:i + 4])
        if length < 2 or i + 2 + length > len(data):
            raise ThermalFileError(f"{where}: a JPEG segment runs past the end of the file")
        segments.append((marker, data[i + 4:i + 2 + length]))
        i += 2 + length
    return segments


def flir_jpeg_record(segments: list[tuple[int, bytes]], where: str) -> bytes | None:
    """The FFF record of a FLIR radiometric JPEG (its ``FLIR\\0`` APP1 segments joined in
    index order), or None when the JPEG has none. ThermalFileError for a missing part."""
    parts = {}
    last = None
    for marker, payload in segments:
        if marker == 0xE1 and payload.startswith(FLIR_SEGMENT) and len(payload) >= 8:
            parts[payload[6]] = payload[8:]
            last = payload[7]
    if not parts:
        return None
    if sorted(parts) != list(range(last + 1)):
        raise ThermalFileError(f"{where}: FLIR record parts {sorted(parts)} of {last + 1}: some are "
                           "missing")
    return b"".join(parts[k] for k in range(last + 1))


def fff_raw_image(record: bytes, where: str) -> np.ndarray:
    """The raw sensor counts (H, W) uint16 of an FFF record (a ``.fff`` file or the record of a
    FLIR JPEG). ThermalFileError when it has no readable raw image."""
    if record[:4] != FFF_MAGIC or len(record) < 32:
        raise ThermalFileError(f"{where}: not a FLIR FFF record")
    # big-endian from cameras; little-endian from some PC software (ResearchIR): the version
    # (100, 101, ...) tells which
    order = ">" if struct.unpack(">I", record[20:24])[0] < 0x10000 else "<"
    offset, count = struct.unpack(order + "II", record[24:32])
    for k in range(count):
        entry = record[offset + 32 * k:offset + 32 * (k + 1)]
        if len(entry) < 20:
            break
        kind, _, _, _, start, length = struct.unpack(order + "HHIIII", entry[:20])
        if kind != FFF_RAW_IMAGE or start + length > len(record):
            continue
        return _raw_entry(record[start:start + length], where)
    raise ThermalFileError(f"{where}: the FLIR record holds no raw image")


def _raw_entry(entry: bytes, where: str) -> np.ndarray:
    width, height = struct.unpack("<HH", entry[2:6])
    pixels = entry[RAW_PIXELS_OFFSET:]
    if pixels[:4] == b"\x89PNG":
        import cv2

        image = cv2.imdecode(np.frombuffer(pixels, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None or image.dtype != np.uint16 or image.shape != (height, width):
            raise ThermalFileError(f"{where}: the FLIR raw image is not a {width}x{height} 16-bit PNG")
        return image.byteswap()  # FLIR stores the PNG's 16-bit values byte-swapped
    if len(pixels) < 2 * width * height:
        raise ThermalFileError(f"{where}: the FLIR raw image holds {len(pixels)} bytes, not "
                           f"{width}x{height} 16-bit counts")
    return np.frombuffer(pixels[:2 * width * height], "<u2").reshape(height, width).copy()


def dji_rjpeg_raw(segments: list[tuple[int, bytes]], where: str) -> np.ndarray | None:
    """The raw counts (H, W) uint16 of a DJI R-JPEG (its APP3 segments joined: little-endian
    uint16 at the JPEG's frame size), or None when the JPEG has no APP3 segment."""
    raw = b"".join(payload for marker, payload in segments if marker == 0xE3)
    if not raw:
        return None
    frame = next((p for m, p in segments if m in (0xC0, 0xC1, 0xC2)), None)
    if frame is None:
        raise ThermalFileError(f"{where}: a JPEG without a frame header")
    height, width = struct.unpack(">HH", frame[1:5])
    # the displayed image may be the sensor's size or an upscale of it (M30T: 1280x1024 of 640x512)
    for scale in (1, 2, 4):
        if height % scale == 0 and width % scale == 0 and \
                len(raw) == 2 * (height // scale) * (width // scale):
            return np.frombuffer(raw, "<u2").reshape(height // scale, width // scale).copy()
    raise ThermalFileError(f"{where}: its APP3 segments hold {len(raw)} bytes, not the 16-bit counts "
                       f"of a {width}x{height} DJI R-JPEG or of a half / quarter of it")


def read_thermal_jpeg(path: str) -> np.ndarray:
    """The raw counts (H, W) uint16 of a FLIR radiometric JPEG or a DJI R-JPEG.

    Raises NoRawCountsError for a JPEG with neither (a visible photo), ThermalFileError for a
    file that is not a JPEG or whose raw record is damaged."""
    with open(path, "rb") as f:
        data = f.read()
    segments = jpeg_segments(data, path)
    record = flir_jpeg_record(segments, path)
    if record is not None:
        return fff_raw_image(record, path)
    raw = dji_rjpeg_raw(segments, path)
    if raw is not None:
        return raw
    raise NoRawCountsError(f"{path}: a JPEG without raw counts (neither a FLIR radiometric JPEG "
                          "nor a DJI R-JPEG), not a raw thermal frame")
