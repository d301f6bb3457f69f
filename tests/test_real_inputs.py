"""Real raw inputs end to end: a 16-bit dataset trained with data.raw_bits=auto, and `irdepth
predict` on real camera files (MS2 PNGs, a radiometric TIFF, FLIR .fff), stacks and mixed
folders."""

import importlib.util
import json
import shutil

import cv2
import numpy as np
import pytest
import tifffile
from trained_runs import DATA, copy_run

from irdepth_jax import cli
from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset
from irdepth_jax.predict import predict_files
from irdepth_jax.runs.variables import load_model

QUICK = ["--no-progress", "--devices", "1", "log_every=1", "checkpoint_every=50", "eval_every=0"]
H, W = 32, 48
needs_flirpy = pytest.mark.skipif(importlib.util.find_spec("flirpy") is None,
                                  reason="flirpy is not installed (pip install 'irdepth_jax[flir]')")


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(code, err, *needles):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("irdepth: error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def without_provenance(err):
    """stderr without predict's lines on what the model is and was trained on (its warnings for
    camera frames given to this synthetic-trained model: tests/test_provenance.py; the note that
    this Stage I model has no depth: tests/test_surfaces.py)."""
    return "\n".join(ln for ln in err.splitlines()
                     if not ln.startswith(("irdepth: model ", "irdepth: WARNING: "))
                     and "is a Stage I model, it has no depth output" not in ln)


def outputs(folder):
    return sorted(p.name for p in folder.iterdir())


@pytest.fixture(scope="module")
def run16(synthetic_data, tmp_path_factory):
    """Stage I-1 (2 steps; I-2 adds nothing here) on a folder dataset of a 16-bit camera
    (counts up to ~32000: the session's shared dataset, copied, its counts x 4), trained with
    data.raw_bits=auto (its own run: the shared ones are 14-bit)."""
    data = copy_run(synthetic_data, tmp_path_factory.mktemp("data16") / "ds")
    assert (H, W) == (DATA["height"], DATA["width"])
    for png in (data / "raw14").iterdir():
        raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(png), raw * np.uint16(4))
    work = tmp_path_factory.mktemp("s1") / "run16"
    assert cli.main(["train", "stage1", "--data", str(data), "--workdir", str(work), *QUICK,
                     "stage1.steps_i1=2", "stage1.steps_i2=0", "data.raw_bits=auto"]) == 0
    return work


def test_auto_resolves_to_16_bits(run16):
    assert json.loads((run16 / "config.json").read_text())["data"]["raw_bits"] == 16
    rows = [json.loads(line) for line in (run16 / "metrics.jsonl").read_text().splitlines()]
    assert [r["raw_bits"] for r in rows if r.get("kind") == "info" and "raw_bits" in r] == [16]
    cfg, stage, _ = load_model(str(run16))
    assert stage == "stage1_i1" and cfg.data.raw_bits == 16


def test_stage2_refuses_a_stage1_of_another_bit_depth(run16, tmp_path, capsys):
    data = tmp_path / "ds14"
    write_synthetic_dataset(data, n=6, labeled=0, height=H, width=W, seed=2, progress=False)
    work = tmp_path / "s2"
    code, _, err = run(["train", "stage2", "--data", data, "--workdir", work, "--steps", "1",
                        "--stage1-checkpoint", run16, *QUICK, "data.raw_bits=14"], capsys)
    one_line_error(code, err, str(run16), "trained on 16-bit raw counts", "data.raw_bits=14")
    assert not work.exists()


def test_predict_real_camera_files(run16, realdata, tmp_path, capsys):
    """The model trained on 16-bit counts takes the 14-bit MS2 frames, the radiometric TIFF and
    a 16-bit camera's counts alike (no --raw-bits needed: it is the run's)."""
    ms2 = realdata / "ms2_sample"
    for side in ("left", "right"):  # same file names on both sides: separate --out folders
        out = tmp_path / side
        code, _, err = run(["predict", "--checkpoint", run16, "--out", out,
                            *sorted((ms2 / side).glob("*_thr.png"))], capsys)
        assert code == 0 and "skipped" not in err, err
        assert outputs(out) == [f"{i}_thr_{k}.png" for i in ("000011", "002079")
                                for k in ("hsv", "rgb")]
    rgb = cv2.imread(str(tmp_path / "left" / "000011_thr_rgb.png"))
    assert rgb.shape == (256, 640, 3) and rgb.dtype == np.uint8
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "tiff",
                        "--no-progress", realdata / "flir" / "duopror_radiometric.tiff"], capsys)
    assert code == 0 and without_provenance(err) == "", err  # no OpenCV TIFF-tag warning
    assert outputs(tmp_path / "tiff") == ["duopror_radiometric_hsv.png",
                                          "duopror_radiometric_rgb.png"]


@needs_flirpy
def test_predict_fff_files(run16, realdata, tmp_path, capsys):
    flir = realdata / "flir"
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "p",
                        flir / "duopror_frame_000000.fff", flir / "le_frame_000000.fff"], capsys)
    assert code == 0, err
    assert outputs(tmp_path / "p") == [f"{n}_{k}.png" for n in ("duopror_frame_000000",
                                                                  "le_frame_000000")
                                       for k in ("hsv", "rgb")]
    assert cv2.imread(str(tmp_path / "p" / "le_frame_000000_rgb.png")).shape == (240, 320, 3)
    # declared as 14-bit, the 16-bit camera's frame is refused, naming the file and the fix
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "q",
                        "--raw-bits", "14", flir / "le_frame_000000.fff"], capsys)
    one_line_error(code, err, "le_frame_000000.fff", "exceed 14 bits", "--raw-bits 16")
    assert not (tmp_path / "q").exists()


def test_predict_mixed_folder(run16, realdata, tmp_path, capsys):
    left = realdata / "ms2_sample" / "left"
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "a",
                        "--no-progress", left], capsys)
    assert code == 0, err
    assert without_provenance(err).strip() == (
        "irdepth: skipped 4 of 6 files that are not raw thermal frames (8-bit or colour): "
        "000011_nir.png, 000011_rgb.png, 002079_nir.png, 002079_rgb.png")
    assert len(outputs(tmp_path / "a")) == 4
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "b", "--strict",
                        left], capsys)
    one_line_error(code, err, "000011_nir.png", "8-bit", "--glob")
    assert not (tmp_path / "b").exists()
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "c", "--strict",
                        "--glob", "*_thr.png", left], capsys)
    assert code == 0 and "skipped" not in err, err
    assert outputs(tmp_path / "c") == outputs(tmp_path / "a")
    # a visible frame named explicitly is an error; so is a folder without any thermal frame
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "d",
                        left / "000011_rgb.png"], capsys)
    one_line_error(code, err, "000011_rgb.png", "colour image")
    visible = tmp_path / "visible"
    visible.mkdir()
    for name in ("000011_rgb.png", "000011_nir.png"):
        shutil.copy(left / name, visible / name)
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "d", visible],
                       capsys)
    one_line_error(code, err, str(visible), "none of its 2 files is a raw thermal frame")
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "d", "--glob",
                        "*.tif", left], capsys)
    one_line_error(code, err, str(left), "no file matches --glob '*.tif'")
    assert not (tmp_path / "d").exists()


def test_predict_multipage_16bit_tiff(run16, tmp_path, capsys):
    rng = np.random.default_rng(0)
    stack = rng.integers(20000, 30000, (3, H, W)).astype(np.uint16)
    tifffile.imwrite(tmp_path / "burst.tif", stack, photometric="minisblack")
    code, _, err = run(["predict", "--checkpoint", run16, "--out", tmp_path / "p",
                        tmp_path / "burst.tif"], capsys)
    assert code == 0, err
    assert outputs(tmp_path / "p") == [f"burst_p{k:04d}_{kind}.png" for k in range(3)
                                       for kind in ("hsv", "rgb")]


def test_predict_notes_a_bit_depth_the_fixed_scale_model_did_not_see(run16, tmp_path, capsys):
    np.save(tmp_path / "f.npy", np.full((H, W), 9000, np.uint16))
    written = predict_files(str(run16), [str(tmp_path / "f.npy")], str(tmp_path / "p"),
                            overrides=["unet.raw_scale=fixed"], raw_bits=14).written
    assert len(written) == 2
    err = capsys.readouterr().err
    assert "trained on 16-bit counts with unet.raw_scale=fixed; --raw-bits 14 feeds it " \
           "counts / 16383" in err
