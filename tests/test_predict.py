"""`irdepth predict`: batching by frame size, depth videos, and what it writes matches the one
inference path (`run_pipeline`). An untrained tiny model (`evaluate.save_model`): these tests
check the data path, not what the model learnt."""

import os

import cv2
import numpy as np
import pytest
import tifffile

from irdepth_jax import cli
from irdepth_jax.config import get_config
from irdepth_jax.data.depth_png import encode_depth
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.depth_colours import BAR_HEIGHT, LABEL_HEIGHT
from irdepth_jax.models.pipeline import run_pipeline

CFG = get_config("tiny")
COLOUR_BAR = BAR_HEIGHT + LABEL_HEIGHT
"""Rows of the colour bar under a video's panels."""


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def read(path):
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return image


@pytest.fixture(scope="module")
def model(untrained_model):
    """(workdir, unet variables, depth params) of an untrained tiny Stage II model."""
    return untrained_model


@pytest.fixture(scope="module")
def mixed_inputs(tmp_path_factory):
    """A folder of 5 frames 40x56 and 3 frames 32x48 (interleaved), and a 3-page 40x56 TIFF."""
    root = tmp_path_factory.mktemp("mixed")
    folder = root / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(8):
        shape = (40, 56) if k % 3 != 2 else (32, 48)
        cv2.imwrite(str(folder / f"f{k}.png"), rng.integers(3000, 9000, shape).astype(np.uint16))
    tifffile.imwrite(root / "burst.tif", rng.integers(3000, 9000, (3, 40, 56)).astype(np.uint16),
                     photometric="minisblack")
    return [folder, root / "burst.tif"]


def test_batched_predict_writes_the_same_pngs_as_batch_1(model, mixed_inputs, tmp_path, capsys):
    """Batches group frames by size (no padding error); outputs do not depend on the batch size
    beyond float32 summation order: at most 1/256 m on a few pixels of the 16-bit depth."""
    work, unet, depth = model
    outs = {}
    for batch in (1, 4):
        outs[batch] = tmp_path / f"b{batch}"
        code, stdout, err = run(["predict", "--checkpoint", work, "--out", outs[batch],
                                 "--batch-size", batch, *mixed_inputs], capsys)
        assert code == 0, err
        assert "wrote 44 files" in stdout  # 11 frames x depth, depth_color, rgb, hsv
    names = sorted(os.listdir(outs[1]))
    assert names == sorted(os.listdir(outs[4])) and len(names) == 44
    for name in names:
        a, b = read(outs[1] / name).astype(np.int64), read(outs[4] / name).astype(np.int64)
        assert a.shape == b.shape
        assert np.abs(a - b).max() <= (1 if name.endswith("_depth.png") else 8), name
        # XLA:CPU picks kernels (and summation orders) by batch size: a ~1e-6 difference moves
        # a few % of the 16-bit depth levels (1/256 m) across a rounding boundary
        assert np.mean(a == b) > (0.95 if name.endswith("_depth.png") else 0.99), name
    # the PNG holds run_pipeline's depth, round(metres x 256)
    raw = read(mixed_inputs[0] / "f2.png")
    want = encode_depth(np.asarray(run_pipeline(unet, depth, raw[None], CFG)["depth"])[0])
    assert np.abs(read(outs[1] / "f2_depth.png").astype(int) - want).max() <= 1


def test_progress_bar_counts_frames(model, mixed_inputs, tmp_path, capsys):
    code, _, err = run(["predict", "--checkpoint", model[0], "--out", tmp_path / "p",
                        "--batch-size", "8", mixed_inputs[1]], capsys)
    assert code == 0, err
    assert "3/3" in err and "frame/s" in err
    code, _, err = run(["predict", "--checkpoint", model[0], "--out", tmp_path / "q",
                        "--no-progress", mixed_inputs[1]], capsys)
    assert code == 0 and "frame/s" not in err


def test_video_of_synthetic_frames(model, tmp_path, capsys):
    """8 rendered frames in a folder -> one MP4 of 8 frames, raw | pseudo-RGB | depth side by
    side, plus the frames' 16-bit depth PNGs (--depth-png), equal to run_pipeline's depth."""
    from irdepth_jax.video import read_video, video_info

    work, unet, depth = model
    height, width = 48, 64
    folder = tmp_path / "drive"
    folder.mkdir()
    raws = [render_scene(k, "day", height, width)["raw14"] for k in range(8)]
    for k, raw in enumerate(raws):
        cv2.imwrite(str(folder / f"{k:04d}.png"), raw)
    out = tmp_path / "video"
    code, stdout, err = run(["predict", "--checkpoint", work, "--out", out, "--video",
                             "--depth-png", "--fps", "10", "--batch-size", "3", folder], capsys)
    assert code == 0, err
    assert "wrote 1 video and 8 files" in stdout
    assert video_info(out / "drive.mp4") == {"frames": 8, "height": height + COLOUR_BAR,
                                             "width": 3 * width, "fps": 10.0}
    assert sorted(os.listdir(out)) == [f"{k:04d}_depth.png" for k in range(8)] + ["drive.mp4"]
    result = run_pipeline(unet, depth, np.stack(raws), CFG)
    for k in range(8):
        want = encode_depth(np.asarray(result["depth"])[k])
        assert np.abs(read(out / f"{k:04d}_depth.png").astype(int) - want).max() <= 1
    frames = read_video(out / "drive.mp4").astype(np.float64)
    pseudo_rgb = np.asarray(result["rgb"]) * 255
    assert np.abs(frames[:, :height, width:2 * width] - pseudo_rgb).mean() < 6  # H.264, crf 18


def test_video_refuses_what_is_not_a_sequence(model, mixed_inputs, tmp_path, capsys):
    single = tmp_path / "one.npy"
    np.save(single, np.full((40, 56), 5000, np.uint16))
    for inputs, message in (([single], "holds one frame"),
                            ([mixed_inputs[0]], "has frames of several sizes (32x48, 40x56)")):
        code, _, err = run(["predict", "--checkpoint", model[0], "--out", tmp_path / "v",
                            "--video", *inputs], capsys)
        assert code == 2 and message in err, err
    code, _, err = run(["predict", "--checkpoint", model[0], "--out", tmp_path / "v",
                        "--depth-png", single], capsys)
    assert code == 2 and "--depth-png adds per-frame depth PNGs to --video" in err
    assert not (tmp_path / "v").exists()


def test_video_of_real_ms2_frames(model, realdata, tmp_path, capsys):
    """The MS2 sample folder (thermal frames beside RGB / NIR ones): the thermal ones are the
    sequence, the others are skipped with one line."""
    from irdepth_jax.video import video_info

    code, stdout, err = run(["predict", "--checkpoint", model[0], "--out", tmp_path / "v",
                             "--video", realdata / "ms2_sample" / "left"], capsys)
    assert code == 0, err
    assert "skipped 4 of 6 files" in err
    info = video_info(tmp_path / "v" / "left.mp4")
    assert (info["frames"], info["height"], info["width"]) == (2, 256 + COLOUR_BAR, 3 * 640)
