"""What `irdepth predict` writes says what it is: the HSV PNG holds H, S, V in channel order
(read as any image library reads it). An untrained tiny model (`save_model`): these tests check
the files, not what a model learnt."""

import numpy as np
import pytest
from PIL import Image

from irdepth_jax import cli
from irdepth_jax.config import get_config
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.fileio import write_png
from irdepth_jax.models.pipeline import run_pipeline
from irdepth_jax.train.variables import init_unet, random_depth, save_model

CFG = get_config("tiny")
H, W = 40, 56


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """(workdir, unet variables, depth params) of an untrained tiny Stage II model."""
    work = tmp_path_factory.mktemp("untrained") / "run"
    unet, depth = init_unet(CFG), random_depth(CFG)
    save_model(str(work), CFG, unet, depth)
    return work, unet, depth


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """A rendered raw frame (H, W) uint16 and its 16-bit PNG."""
    raw = render_scene(3, "day", H, W)["raw14"]
    path = tmp_path_factory.mktemp("frame") / "scene.png"
    write_png(str(path), raw)
    return raw, path


def test_hsv_png_holds_h_s_v_in_channel_order(model, frame, tmp_path, capsys):
    work, unet, depth = model
    raw, path = frame
    code, _, err = run(["predict", "--checkpoint", work, "--out", tmp_path, path], capsys)
    assert code == 0, err
    result = run_pipeline(unet, depth, raw[None], CFG)
    for kind in ("hsv", "rgb"):
        with Image.open(tmp_path / f"scene_{kind}.png") as image:
            assert image.mode == "RGB"
            stored = np.asarray(image).astype(np.float64) / 255
        want = np.asarray(result[kind])[0]
        assert np.abs(stored - want).max() <= 0.5 / 255 + 1e-6, kind
