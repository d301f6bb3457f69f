"""Every checkpoint records what it was trained on; predict and eval say it, and warn when their
inputs differ in kind (a synthetic-trained model on real frames, a frame size far from the
training frames'); the quickstart ends with the commands for a real model."""

import json
import shlex

import numpy as np
from ms2_layout import LIST_NAMES, partial_ms2
from trained_runs import DATA, STEPS

from irdepth_jax import cli
from irdepth_jax.cli.quickstart import quickstart_next_steps
from irdepth_jax.config import get_config
from irdepth_jax.runs.variables import load_model


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_checkpoints_record_what_they_were_trained_on(stage2_run, synthetic_data):
    _, _, model = load_model(str(stage2_run))
    record = model["trained_on"]
    data = {"kind": "synthetic", "format": "folder", "path": str(synthetic_data.resolve()),
            "frame_size": [DATA["height"], DATA["width"]]}
    assert record["data"] == data and record["steps"] == {"stage2": STEPS["stage2"]}
    assert record["depth_network"]["backbone"].startswith("random init")
    assert record["stage1"]["data"] == data
    assert record["stage1"]["steps"] == {"stage1_i1": STEPS["stage1"], "stage1_i2": STEPS["stage1"]}


def test_predict_on_real_frames_warns_naming_the_training_data(stage2_run, realdata, tmp_path,
                                                               capsys):
    frame = realdata / "ms2_sample" / "left" / "000011_thr.png"
    code, _, err = run(["predict", "--checkpoint", stage2_run, "--out", tmp_path, frame], capsys)
    assert code == 0, err
    assert f"trained on synthetic frames, {DATA['height']}x{DATA['width']}" in err
    warnings = [line for line in err.splitlines() if line.startswith("irdepth: WARNING: ")]
    assert len(warnings) == 2, err
    assert "trained on synthetic frames only" in warnings[0]
    assert "frames of 256x640 are far from the 32x48 frames" in warnings[1]
    assert "depth network backbone: random init" in err


def test_eval_on_real_data_warns(stage2_run, tmp_path, capsys):
    lists = tmp_path / "lists"
    lists.mkdir()
    for name, seq in zip(LIST_NAMES, ("_tr", "_va", "_day", "_night", "_rain")):
        (lists / name).write_text(seq + "\n")
    root = partial_ms2(lists, tmp_path / "MS2", ["_day"], size=(DATA["height"], DATA["width"]))
    code, out, err = run(["eval", "--workdir", stage2_run, "--data", root, "--split", "test_day",
                          "--out", tmp_path / "eval"], capsys)
    assert code == 0, err
    result = json.loads((tmp_path / "eval" / "eval_test_day.json").read_text())
    assert result["trained_on"]["data"]["kind"] == "synthetic"
    assert len(result["warnings"]) == 1 and "synthetic frames only" in result["warnings"][0]
    assert "Model: trained on synthetic frames" in out
    assert "irdepth: WARNING: this model was trained on synthetic frames only" in err


def test_quickstart_ends_with_runnable_next_steps():
    lines = quickstart_next_steps("qs", get_config("tiny"))
    assert "means nothing" in lines[0]
    commands = [shlex.split(line)[1:] for line in lines if line.startswith("  irdepth ")]
    assert [c[0] for c in commands] == ["train", "train", "eval", "predict"]
    assert any("depth.checkpoint=depth_anything_v2_metric_vkitti_vits.pth" in c for c in commands)
    parser = cli.build_parser()
    for argv in commands:
        args, extra = parser.parse_known_args(argv)
        assert all("=" in item for item in extra), argv
    assert np.all([c[c.index("--data") + 1] == "MS2_ROOT" for c in commands if "--data" in c])
