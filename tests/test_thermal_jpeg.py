"""FLIR radiometric JPEGs and DJI R-JPEGs read to their raw counts (`data.thermal_jpeg`), on the
real files of ../shared/realdata (skipped without them) and on JPEGs built from a real .fff."""

import struct

import cv2
import numpy as np
import pytest

from irdepth_jax.data.rawio import NotThermalError, RawFileError, read_frames
from irdepth_jax.data.thermal_jpeg import fff_raw_image


def flir_jpeg(record: bytes, part_size: int = 60000) -> bytes:
    """A JPEG holding an FFF record in FLIR's APP1 segments (FLIR\\0, version 1, index, last)."""
    parts = [record[i:i + part_size] for i in range(0, len(record), part_size)]
    segments = b""
    for k, part in enumerate(parts):
        payload = b"FLIR\x00\x01" + bytes([k, len(parts) - 1]) + part
        segments += b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    return b"\xff\xd8" + segments + b"\xff\xd9"


def fff_record(counts: np.ndarray) -> bytes:
    """An FFF record (as FLIR cameras write it) whose raw image is a PNG of byte-swapped counts."""
    ok, png = cv2.imencode(".png", counts.byteswap())
    assert ok
    height, width = counts.shape
    entry = struct.pack("<HHH", 2, width, height).ljust(32, b"\0") + png.tobytes()
    header = b"FFF\0" + b"\0" * 16 + struct.pack(">III", 100, 64, 1)
    index = struct.pack(">HHIIIIIII", 1, 3, 100, 1, 96, len(entry), 0, 0, 0)
    return header.ljust(64, b"\0") + index + entry


@pytest.mark.parametrize("name, shape, low, high", [
    ("flir/ax8_radiometric.jpg", (60, 80), 16711, 16876),
    ("flir/flir_example_radiometric.jpg", (320, 240), 12501, 20042),
    ("dji/m30t_DJI_0001_R.JPG", (512, 640), 18452, 18988),
    ("dji/h20t_DJI_0001_R.JPG", (512, 640), 13537, 20670),
])
def test_real_thermal_jpegs(realdata, name, shape, low, high):
    [(stem, raw)] = read_frames(str(realdata / name), 16)
    assert raw.shape == shape and raw.dtype == np.uint16
    assert (int(raw.min()), int(raw.max())) == (low, high)
    # a scene's counts vary smoothly: the neighbouring pixels of a wrongly ordered byte pair
    # (or a wrong width) would differ by thousands
    assert np.median(np.abs(np.diff(raw.astype(np.int64), axis=1))) < 50


def test_a_flir_jpeg_of_a_real_fff_record_reads_as_the_fff(realdata, tmp_path):
    fff = realdata / "flir" / "duopror_frame_000000.fff"
    want = np.load(realdata / "flir" / "duopror_frame_000000_raw.npy")  # flirpy's reading
    assert np.array_equal(fff_raw_image(fff.read_bytes(), str(fff)), want)
    jpeg = tmp_path / "duopror.jpg"
    jpeg.write_bytes(flir_jpeg(fff.read_bytes()))  # 11 APP1 parts, uncompressed raw image
    [(_, raw)] = read_frames(str(jpeg), 14)
    np.testing.assert_array_equal(raw, want)
    # the PNG form the cameras' JPEGs use: 16-bit values stored byte-swapped
    png_jpeg = tmp_path / "duopror_png.jpg"
    png_jpeg.write_bytes(flir_jpeg(fff_record(want), part_size=4000))
    [(_, raw)] = read_frames(str(png_jpeg), 14)
    np.testing.assert_array_equal(raw, want)


def test_little_endian_fff(realdata):
    fff = realdata / "flir" / "le_frame_000000.fff"
    raw = fff_raw_image(fff.read_bytes(), str(fff))
    assert raw.shape == (240, 320) and (int(raw.min()), int(raw.max())) == (17899, 19192)


def test_jpegs_without_raw_counts(tmp_path):
    photo = tmp_path / "photo.jpg"
    cv2.imwrite(str(photo), np.full((8, 8, 3), 100, np.uint8))
    with pytest.raises(NotThermalError, match="photo.jpg: a JPEG without raw counts"):
        read_frames(str(photo))
    counts = np.arange(12, dtype=np.uint16).reshape(3, 4) + 3000
    broken = tmp_path / "broken.jpg"
    record = fff_record(counts)
    broken.write_bytes(flir_jpeg(record, part_size=100)[:-300] + b"\xff\xd9")
    with pytest.raises(RawFileError, match="broken.jpg"):
        read_frames(str(broken))
    whole = tmp_path / "whole.jpg"
    whole.write_bytes(flir_jpeg(record, part_size=100))
    np.testing.assert_array_equal(read_frames(str(whole))[0][1], counts)
