"""What `irdepth predict` and `eval` write says what it is: the HSV PNG holds H, S, V in channel
order (read as any image library reads it); a relative-depth model's outputs are named so and
evaluated aligned. An untrained tiny model (`save_model`): these tests check
the files, not what a model learnt."""

import json
import shutil

import cv2
import numpy as np
import pytest
from ms2_layout import LIST_NAMES, partial_ms2
from PIL import Image

from irdepth_jax import cli
from irdepth_jax.config import apply_overrides, get_config
from irdepth_jax.data.synthetic import render_scene
from irdepth_jax.depth_colours import BAR_HEIGHT, LABEL_HEIGHT
from irdepth_jax.fileio import write_png
from irdepth_jax.models.pipeline import run_pipeline
from irdepth_jax.runs.variables import init_unet, random_depth
from irdepth_jax.train.state import save_model

CFG = get_config("tiny")
H, W = 40, 56


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def model(untrained_model):
    """(workdir, unet variables, depth params) of an untrained tiny Stage II model."""
    return untrained_model


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


@pytest.fixture(scope="module")
def relative_model(tmp_path_factory):
    """Workdir of an untrained tiny Stage II model with the relative head (depth.metric=false)."""
    work = tmp_path_factory.mktemp("relative") / "run"
    cfg = apply_overrides(CFG, ["depth.metric=false"])
    save_model(str(work), cfg, init_unet(cfg), random_depth(cfg))
    return work


def test_relative_depth_is_labelled_as_such(relative_model, frame, tmp_path, capsys):
    code, _, err = run(["predict", "--checkpoint", relative_model, "--out", tmp_path,
                        frame[1]], capsys)
    assert code == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "scene_depth_relative.png", "scene_depth_relative_color.png", "scene_hsv.png",
        "scene_rgb.png"]
    assert "predicts relative depth (depth.metric=false)" in err and "not metres" in err


def test_relative_depth_is_evaluated_aligned(relative_model, synthetic_data, tmp_path, capsys):
    argv = ["eval", "--checkpoint", relative_model, "--data", synthetic_data, "--out", tmp_path]
    code, _, err = run([*argv, "--align", "none"], capsys)
    assert code == 2 and "relative-depth model" in err and "--align median" in err, err
    code, out, err = run(argv, capsys)
    assert code == 0, err
    protocol = json.loads((tmp_path / "eval_test.json").read_text())["protocol"]
    assert protocol["align"] == "median" and protocol["depth"] == "relative"
    assert "alignment median (a relative-depth model" in out


@pytest.fixture(scope="module")
def ms2_root(tmp_path_factory):
    """A small MS2 root: split lists of its own, one test_day sequence of 3 frames 32x48."""
    lists = tmp_path_factory.mktemp("lists")
    for name, seq in zip(LIST_NAMES, ("_tr", "_va", "_day", "_night", "_rain")):
        (lists / name).write_text(seq + "\n")
    return partial_ms2(lists, tmp_path_factory.mktemp("ms2") / "MS2", ["_day"], size=(32, 48))


def test_ms2_eval_leaves_out_psnr_against_our_own_tone_map(model, ms2_root, tmp_path, capsys):
    code, out, err = run(["eval", "--checkpoint", model[0], "--data", ms2_root, "--split",
                          "test_day", "--out", tmp_path], capsys)
    assert code == 0, err
    result = json.loads((tmp_path / "eval_test_day.json").read_text())
    assert result["stage1"]["all"].keys() >= {"entropy", "miou"}
    assert not {"psnr", "ssim"} & result["stage1"]["all"].keys()
    assert result["protocol"]["reconstruction"] is None
    assert "psnr" not in out.split("PSNR / SSIM left out")[0].lower()
    assert "PSNR / SSIM left out: this dataset has no 8-bit camera image" in out


def test_ms2_eval_names_its_depth_label_version(model, ms2_root, synthetic_data, tmp_path,
                                                capsys):
    root = tmp_path / "MS2"
    shutil.copytree(ms2_root, root)
    filtered = root / "proj_depth" / "_day" / "thr" / "depth_filtered"
    labels = root / "sync_data" / "_day" / "thr" / "depth_gt"
    labels.mkdir()
    for png in filtered.iterdir():  # another version: the same points, twice as far
        depth = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(labels / png.name), np.minimum(depth.astype(np.int64) * 2, 65535)
                    .astype(np.uint16))
    tables = {}
    for gt in (None, "depth_gt"):
        out = tmp_path / f"eval_{gt}"
        code, stdout, err = run(["eval", "--checkpoint", model[0], "--data", root, "--split",
                                 "test_day", "--out", out] + (["--gt", gt] if gt else []), capsys)
        assert code == 0, err
        name = gt or "depth_filtered"
        assert f"ground truth: MS2 {name}." in stdout
        tables[name] = json.loads((out / "eval_test_day.json").read_text())
        assert tables[name]["protocol"]["ground_truth"] == f"MS2 {name}"
    assert tables["depth_gt"]["stage2"]["all"]["abs_rel"] != \
        tables["depth_filtered"]["stage2"]["all"]["abs_rel"]
    code, _, err = run(["eval", "--checkpoint", model[0], "--data", root, "--split", "test_day",
                        "--gt", "depth_multi", "--out", tmp_path / "m"], capsys)
    assert code == 2 and "proj_depth/<seq>/thr/depth_multi" in err, err
    code, _, err = run(["eval", "--checkpoint", model[0], "--data", synthetic_data, "--gt",
                        "depth_gt", "--out", tmp_path / "f"], capsys)
    assert code == 2 and "--gt depth_gt: depth label versions are MS2's" in err, err


def read_ply(path):
    """(points (N, 3), colours (N, 3)) of a binary PLY written by `pointcloud.ply_bytes`."""
    data = path.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    count = int(next(ln for ln in header.decode().splitlines()
                     if ln.startswith("element vertex")).split()[-1])
    vertex = np.frombuffer(body, [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"),
                                  ("g", "u1"), ("b", "u1")], count=count)
    assert len(body) == vertex.nbytes
    return (np.stack([vertex[c] for c in "xyz"], -1),
            np.stack([vertex[c] for c in "rgb"], -1))


def test_pointcloud_one_point_per_valid_pixel(model, frame, tmp_path, capsys):
    work, unet, depth = model
    raw, path = frame
    fx, fy, cx, cy = 50.0, 40.0, 27.5, 19.5
    calib = tmp_path / "calib.npy"  # MS2's form: a pickled dict of matrices
    np.save(calib, {"K_thrL": np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]),
                    "K_rgbL": np.eye(3)}, allow_pickle=True)
    want_depth = np.asarray(run_pipeline(unet, depth, raw[None], CFG)["depth"])[0]
    rgb = np.asarray(run_pipeline(unet, depth, raw[None], CFG)["rgb"])[0]
    valid = want_depth > 0
    for spec in (f"{fx},{fy},{cx},{cy}", str(calib)):
        out = tmp_path / f"out_{len(spec)}"
        code, _, err = run(["predict", "--checkpoint", work, "--out", out, "--pointcloud",
                            "--intrinsics", spec, path], capsys)
        assert code == 0, err
        points, colours = read_ply(out / "scene.ply")
        assert len(points) == valid.sum() > 0
        v, u = np.nonzero(valid)
        z = want_depth[valid]
        np.testing.assert_allclose(points[:, 2], z, rtol=1e-4)
        np.testing.assert_allclose(points[:, 0], (u - cx) * z / fx, rtol=1e-3, atol=1e-4)
        np.testing.assert_allclose(points[:, 1], (v - cy) * z / fy, rtol=1e-3, atol=1e-4)
        assert np.abs(colours / 255 - rgb[valid]).max() <= 0.5 / 255 + 1e-6
    for argv, message in ((["--pointcloud"], "--pointcloud needs --intrinsics"),
                          (["--pointcloud", "--intrinsics", "1,2,3"], "expected fx,fy,cx,cy")):
        code, _, err = run(["predict", "--checkpoint", work, "--out", tmp_path / "bad", *argv,
                            path], capsys)
        assert code == 2 and message in err, err


def test_coloured_depth_has_a_colour_bar(model, frame, tmp_path, capsys):
    from matplotlib import colormaps

    work, unet, depth = model
    raw, path = frame
    code, _, err = run(["predict", "--checkpoint", work, "--out", tmp_path, "--depth-range",
                        "0:40", "--cmap", "viridis", path], capsys)
    assert code == 0, err
    with Image.open(tmp_path / "scene_depth_color.png") as image:
        stored = np.asarray(image)
    assert stored.shape == (H + BAR_HEIGHT + LABEL_HEIGHT, W, 3)
    want = np.asarray(run_pipeline(unet, depth, raw[None], CFG)["depth"])[0]
    viridis = (colormaps["viridis"](1 - np.clip(want / 40, 0, 1))[..., :3] * 255).astype(np.uint8)
    assert np.abs(stored[:H].astype(int) - viridis).max() <= 1
    bar = stored[H:H + BAR_HEIGHT].astype(int)
    near, far = (np.asarray(colormaps["viridis"](x)[:3]) * 255 for x in (1.0, 0.0))
    assert np.abs(bar[:, 0] - near).max() <= 2 and np.abs(bar[:, -1] - far).max() <= 2
    assert stored[H + BAR_HEIGHT:].max() == 255  # the labels are drawn
    for argv, message in ((["--depth-range", "5:1"], "--depth-range 5:1: expected auto or MIN:MAX"),
                          (["--cmap", "nope"], "--cmap nope: not a matplotlib colour map")):
        code, _, err = run(["predict", "--checkpoint", work, "--out", tmp_path / "bad", *argv,
                            path], capsys)
        assert code == 2 and message in err, err
