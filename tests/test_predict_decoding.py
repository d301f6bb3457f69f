"""`irdepth predict` decodes each input frame once (issue 42: every file was decoded by the input
check and again for the model), and writes depth beyond what a depth PNG holds with one counted
warning. A stand-in model (no UNet, depth from the counts): these tests check the data path."""

import collections
import dataclasses
import os

import cv2
import numpy as np
import pytest
import tifffile

from irdepth_jax import cli
from irdepth_jax.config import get_config
from irdepth_jax.data import inputs, rawio
from irdepth_jax.models import pipeline
from irdepth_jax.runs import variables

CFG = dataclasses.replace(get_config("tiny"), stage2=dataclasses.replace(
    get_config("tiny").stage2, preprocessing="he", sky_loss=False))


@pytest.fixture
def stand_in_model(monkeypatch):
    """A Stage II model whose depth is its input image's first channel x `scale` metres."""
    monkeypatch.setattr(variables, "load_model",
                        lambda path, overrides=(): (CFG, "stage2", {"unet": None, "depth": {}, "warnings": []}))
    scale = {"metres": 10.0}
    monkeypatch.setattr(pipeline, "run_pipeline", lambda unet, params, raw, cfg, image: {
        "depth": np.asarray(image)[..., 0] * scale["metres"] + 0.5, "rgb": image, "hsv": None})
    return scale


@pytest.fixture
def decodes(monkeypatch):
    """{file name: decodes} counted at the PNG, TIFF and .npy decoders of `data.rawio`."""
    counts = collections.Counter()
    for reader in ("_png", "_tiff", "_npy"):
        real = getattr(rawio, reader)

        def counted(path, real=real):
            counts[os.path.basename(path)] += 1
            return real(path)

        monkeypatch.setattr(rawio, reader, counted)
    return counts


@pytest.fixture
def sources(tmp_path):
    """A folder of three 16-bit PNGs and a 2-frame .npy stack, and a 3-page TIFF."""
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name in ("a", "b", "c"):
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(3000, 9000, (24, 32)).astype(np.uint16))
    np.save(folder / "d.npy", rng.integers(3000, 9000, (2, 24, 32)).astype(np.uint16))
    tifffile.imwrite(tmp_path / "burst.tif", rng.integers(3000, 9000, (3, 24, 32)).astype(np.uint16),
                     photometric="minisblack")
    return folder, tmp_path / "burst.tif"


def predict(argv, capsys):
    """`irdepth predict` of the stand-in model (its --checkpoint: the inputs' folder, unread)."""
    code = cli.main(["predict", "--checkpoint", str(argv[-1]).rsplit(os.sep, 1)[0], "--no-progress",
                     *map(str, argv)])
    return code, capsys.readouterr().err


def test_each_frame_is_decoded_once(stand_in_model, decodes, sources, tmp_path, capsys):
    folder, tiff = sources
    out = tmp_path / "out"
    code, err = predict(["--out", out, "--batch-size", "2", folder, tiff], capsys)
    assert code == 0, err
    assert decodes == {"a.png": 1, "b.png": 1, "c.png": 1, "d.npy": 1, "burst.tif": 1}
    frames = ["a", "b", "c", "d_p0000", "d_p0001", "burst_p0000", "burst_p0001", "burst_p0002"]
    assert sorted(os.listdir(out)) == sorted(f"{f}_{kind}.png" for f in frames
                                             for kind in ("depth", "depth_color"))


def test_each_frame_of_a_video_is_decoded_once(stand_in_model, decodes, sources, tmp_path, capsys):
    folder, tiff = sources
    code, err = predict(["--out", tmp_path / "out", "--video", "--depth-png", tiff], capsys)
    assert code == 0, err
    assert decodes == {"burst.tif": 1}
    assert (tmp_path / "out" / "burst.mp4").exists()


def test_frames_beyond_the_kept_bytes_are_decoded_again_with_the_same_outputs(
        stand_in_model, decodes, sources, tmp_path, capsys, monkeypatch):
    """Only KEPT_BYTES of decoded frames wait for the run: a long sequence is streamed (read
    again when its turn comes), not held in memory; the outputs do not depend on it."""
    folder, _ = sources
    assert predict(["--out", tmp_path / "kept", folder], capsys)[0] == 0
    decodes.clear()
    monkeypatch.setattr(inputs, "KEPT_BYTES", 2 * 24 * 32 * 2)  # a.png and b.png fit
    assert predict(["--out", tmp_path / "streamed", folder], capsys)[0] == 0
    assert decodes == {"a.png": 1, "b.png": 1, "c.png": 2, "d.npy": 2}
    for name in os.listdir(tmp_path / "kept"):
        np.testing.assert_array_equal(cv2.imread(str(tmp_path / "streamed" / name), cv2.IMREAD_UNCHANGED),
                                      cv2.imread(str(tmp_path / "kept" / name), cv2.IMREAD_UNCHANGED))


@pytest.mark.parametrize("video", [False, True])
def test_depth_over_the_png_range_is_written_as_the_largest_with_one_warning(
        stand_in_model, sources, tmp_path, capsys, video):
    """Depth up to 1000 m (was clipped without a word): saturated at 65535 counts and counted
    in one warning line at the end, in PNG mode and in the depth PNGs of a video."""
    _, tiff = sources
    stand_in_model["metres"] = 1000.0
    out = tmp_path / "out"
    code, err = predict(["--out", out, *(["--video", "--depth-png"] if video else []), tiff], capsys)
    assert code == 0, err
    depth = np.stack([cv2.imread(str(out / f"burst_p{k:04d}_depth.png"), cv2.IMREAD_UNCHANGED)
                      for k in range(3)])
    over = int((depth == 65535).sum())
    assert over > 0
    [warning] = [line for line in err.splitlines() if "WARNING" in line]
    assert warning.startswith(f"irdepth: WARNING: {over} depth values of 3 depth maps (the first: "
                              "frame burst_p0000) are over 255.996 m (up to "), warning
    assert warning.endswith("the most a 16-bit depth PNG holds: written as 255.996 m")


@pytest.mark.parametrize("video", [False, True])
def test_nearly_black_pseudo_rgb_images_are_counted_in_one_warning(tmp_path, capsys, monkeypatch,
                                                                   video):
    """A Stage I model that makes almost no texture of the frames (a synthetic-trained model on
    real MS2 counts: mean 1 of 255) leaves the depth network almost no image: one warning at the
    end counts those pseudo-RGB images and names the first; the brighter frame is not counted."""
    cfg = get_config("tiny")  # stage2.preprocessing=hsv: the pseudo-RGB is the depth input
    monkeypatch.setattr(variables, "load_model", lambda path, overrides=(): (
        cfg, "stage2", {"unet": {}, "depth": {}, "warnings": []}))

    def stand_in(unet, params, raw, cfg, image=None):  # pseudo-RGB = counts / 2^14, grey
        rgb = np.repeat(np.asarray(raw, np.float32)[..., None] / 2**14, 3, axis=-1)
        return {"depth": np.full(raw.shape, 5.0, np.float32), "rgb": rgb, "hsv": rgb}

    monkeypatch.setattr(pipeline, "run_pipeline", stand_in)
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name, low in (("bright", 8000), ("dark", 100)):  # means 0.49 and 0.009 of white
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(low, low + 100, (24, 32)).astype(np.uint16))
    code, err = predict(["--out", tmp_path / "out", *(["--video"] if video else []), folder], capsys)
    assert code == 0, err
    [warning] = [line for line in err.splitlines() if "WARNING" in line]
    assert warning.startswith("irdepth: WARNING: 1 of 2 pseudo-RGB images are nearly black (mean "
                              "under 2% of white; the first: frame dark): "), warning
    assert "depth from it is not to be trusted" in warning
