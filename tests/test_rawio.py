"""Raw frame readers (`data.rawio.read_frames`): every format, stacks, and one-line errors."""

import importlib.util
import sys

import cv2
import numpy as np
import pytest
import tifffile

from irdepth_jax.data.rawio import NotThermalError, RawFileError, read_frames

needs_flirpy = pytest.mark.skipif(
    importlib.util.find_spec("flirpy") is None,
    reason="flirpy is not installed (pip install 'irdepth_jax[flir]')")


def _counts(shape, seed=0, high=2**14):
    return np.random.default_rng(seed).integers(1000, high, shape).astype(np.uint16)


def test_png_npy_and_tiff_frames(tmp_path):
    frame = _counts((12, 16))
    cv2.imwrite(str(tmp_path / "a.png"), frame)
    np.save(tmp_path / "b.npy", frame.astype(np.int32))
    tifffile.imwrite(tmp_path / "c.TIFF", frame, compression="zlib")  # needs imagecodecs
    for name in ("a.png", "b.npy", "c.TIFF"):
        [(stem, got)] = read_frames(str(tmp_path / name))
        assert stem == name.split(".")[0] and got.dtype == np.uint16
        np.testing.assert_array_equal(got, frame)


def test_stacks_give_one_frame_per_page(tmp_path):
    stack = _counts((3, 10, 14), high=2**16)
    tifffile.imwrite(tmp_path / "pages.tif", stack, photometric="minisblack")
    np.save(tmp_path / "stack.npy", stack)
    for name in ("pages.tif", "stack.npy"):
        frames = read_frames(str(tmp_path / name), bits=16)
        stem = name.split(".")[0]
        assert [n for n, _ in frames] == [f"{stem}_p0000", f"{stem}_p0001", f"{stem}_p0002"]
        for (_, got), want in zip(frames, stack):
            np.testing.assert_array_equal(got, want)


def test_bit_depth(tmp_path):
    frame = _counts((8, 8))
    frame[0, 0] = 40000
    np.save(tmp_path / "f.npy", frame)
    with pytest.raises(RawFileError, match=r"f\.npy: raw counts exceed 14 bits: maximum 40000 "
                                           r".*--raw-bits 16"):
        read_frames(str(tmp_path / "f.npy"))
    np.testing.assert_array_equal(read_frames(str(tmp_path / "f.npy"), bits=16)[0][1], frame)


@pytest.mark.parametrize("make, match", [
    (lambda p: cv2.imwrite(str(p / "x.png"), np.full((8, 8), 9, np.uint8)), "8-bit image"),
    (lambda p: cv2.imwrite(str(p / "x.png"), np.zeros((8, 8, 3), np.uint16)), "colour image"),
    (lambda p: tifffile.imwrite(p / "x.tif", np.zeros((8, 8, 3), np.uint8)), "colour TIFF"),
    (lambda p: np.save(p / "x.npy", np.zeros((8, 8), np.uint8)), "8-bit image"),
])
def test_not_thermal(tmp_path, make, match):
    make(tmp_path)
    [path] = tmp_path.iterdir()
    with pytest.raises(NotThermalError, match=f"{path.name}: {match}"):
        read_frames(str(path))


@pytest.mark.parametrize("name, content, match", [
    ("x.png", b"not an image", "not a readable PNG"),
    ("x.tif", b"not a tiff", "not a readable TIFF"),
    ("x.npy", b"not an array", "not a readable .npy"),
    ("x.jpg", b"", "x.jpg: not a JPEG file"),
    ("x.bmp", b"", "unknown raw frame type '.bmp'"),
])
def test_unreadable_files(tmp_path, name, content, match):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(RawFileError, match=match) as err:
        read_frames(str(tmp_path / name))
    assert not isinstance(err.value, NotThermalError) and "\n" not in str(err.value)


def test_npy_errors(tmp_path):
    np.save(tmp_path / "f.npy", np.zeros((8, 8), np.float32))
    with pytest.raises(RawFileError, match=r"f\.npy: expected a raw 14-bit frame .*float32"):
        read_frames(str(tmp_path / "f.npy"))
    np.save(tmp_path / "g.npy", np.zeros((2, 2, 8, 8), np.uint16))
    with pytest.raises(RawFileError, match=r"g\.npy: shape \(2, 2, 8, 8\)"):
        read_frames(str(tmp_path / "g.npy"))


def test_radiometric_tiff_reads_silently(realdata, capfd):
    """OpenCV's libtiff warns on stderr about the camera's private tags; tifffile does not."""
    [(name, raw)] = read_frames(str(realdata / "flir" / "duopror_radiometric.tiff"))
    assert name == "duopror_radiometric" and raw.shape == (512, 640)
    assert (raw.min(), raw.max()) == (6743, 7077)
    assert capfd.readouterr().err == ""


@needs_flirpy
def test_fff_is_flirpys_raw_array(realdata):
    flir = realdata / "flir"
    [(name, raw)] = read_frames(str(flir / "duopror_frame_000000.fff"))
    assert name == "duopror_frame_000000"
    np.testing.assert_array_equal(raw, np.load(flir / "duopror_frame_000000_raw.npy"))
    with pytest.raises(RawFileError, match=r"le_frame_000000\.fff: raw counts exceed 14 bits"):
        read_frames(str(flir / "le_frame_000000.fff"))
    [(_, le)] = read_frames(str(flir / "le_frame_000000.fff"), bits=16)
    assert le.shape == (240, 320) and (le.min(), le.max()) == (17899, 19192)


@needs_flirpy
def test_seq_gives_its_frames(realdata, tmp_path):
    """A .seq file is FLIR frames back to back (here two .fff frames)."""
    fff = (realdata / "flir" / "duopror_frame_000000.fff").read_bytes()
    (tmp_path / "flight.seq").write_bytes(fff + fff)
    frames = read_frames(str(tmp_path / "flight.seq"))
    assert [n for n, _ in frames] == ["flight_p0000", "flight_p0001"]
    want = np.load(realdata / "flir" / "duopror_frame_000000_raw.npy")
    for _, raw in frames:
        np.testing.assert_array_equal(raw, want)
    (tmp_path / "bad.fff").write_bytes(b"FFF\0" + bytes(100))
    with pytest.raises(RawFileError, match=r"bad\.fff: not a readable FLIR file"):
        read_frames(str(tmp_path / "bad.fff"))


def test_flir_without_flirpy_names_the_extra(tmp_path, monkeypatch):
    (tmp_path / "x.fff").write_bytes(b"")
    for name in ["flirpy", *(m for m in sys.modules if m.startswith("flirpy."))]:
        monkeypatch.setitem(sys.modules, name, None)  # as if it were not installed
    with pytest.raises(RawFileError, match=r"x\.fff: reading FLIR \.fff / \.seq files needs the "
                                           r"flirpy package: pip install 'irdepth_jax\[flir\]'"):
        read_frames(str(tmp_path / "x.fff"))
