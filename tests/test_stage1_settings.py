"""Stage II takes the settings that define the Stage I model (raw normalisation, bit depth, UNet
sizes and switches) from its --stage1-checkpoint: stored in its config, so predict rebuilds the
Stage I model it was trained on; a conflicting key=value is refused by name."""

import dataclasses
import json

import numpy as np
import pytest
from trained_runs import QUICK

from irdepth_jax import cli
from irdepth_jax.config import STAGE1_MODEL_KEYS
from irdepth_jax.data.rawio import read_frames
from irdepth_jax.predict_runner import Predictor
from irdepth_jax.runs.variables import load_model


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def hsv_of(path, raw, **replace_unet):
    """The HSV image (B, H, W, 3) the model at `path` computes from raw (B, H, W)."""
    cfg, _, model = load_model(str(path))
    if replace_unet:
        cfg = dataclasses.replace(cfg, unet=dataclasses.replace(cfg.unet, **replace_unet))
    predictor = Predictor(cfg, model, cfg.data.raw_bits)
    return predictor.fetch(predictor.dispatch(raw))["hsv"]


def test_stage2_uses_the_stage1_normalisation(synthetic_data, tmp_path, capsys):
    stage1, stage2 = tmp_path / "s1", tmp_path / "s2"
    # Stage I-1 alone, so Stage II without the (untrained) segmentation: the fewest compiles
    code, _, err = run(["train", "stage1", "--data", synthetic_data, "--workdir", stage1, *QUICK,
                        "stage1.steps_i1=1", "stage1.steps_i2=0", "unet.raw_scale=fixed"], capsys)
    assert code == 0, err
    code, _, err = run(["train", "stage2", "--data", synthetic_data, "--workdir", stage2,
                        "--steps", 1, "--stage1-checkpoint", stage1, *QUICK,
                        "stage2.hue_mode=constant", "stage2.sky_loss=false"], capsys)
    assert code == 0, err
    assert "Stage II uses the Stage I model's unet.raw_scale=fixed" in err
    assert json.loads((stage2 / "config.json").read_text())["unet"]["raw_scale"] == "fixed"
    raw = np.stack([r for _, r in read_frames(str(next((synthetic_data / "raw14").iterdir())), 14)])
    expected = hsv_of(stage1, raw)[..., 1:]  # S, V (Stage II's hue is constant here)
    np.testing.assert_array_equal(hsv_of(stage2, raw)[..., 1:], expected)
    # the settings matter: the same Stage I model with the preset's percentile normalisation
    assert np.abs(hsv_of(stage1, raw, raw_scale="percentile")[..., 1:] - expected).mean() > 0.01


def test_untrained_segmentation_branch_is_refused_or_switched_off(synthetic_data, tmp_path, capsys):
    """Stage II refuses the Hue and sky of a segmentation branch no labelled frame trained
    (stage1.seg_labels=none: the same branch as on data without labels) and trains with them
    switched off, saying so. Stage I-1 alone and Stage II with a constant hue: the programs of
    test_stage2_uses_the_stage1_normalisation above, taken from the compilation cache."""
    s1 = tmp_path / "s1"
    assert cli.main(["train", "stage1", "--data", str(synthetic_data), "--workdir", str(s1), *QUICK,
                     "stage1.steps_i1=1", "stage1.steps_i2=0", "stage1.seg_labels=none",
                     "unet.raw_scale=fixed"]) == 0
    assert "segmentation_labels" in capsys.readouterr().err
    code = cli.main(["train", "stage2", "--data", str(synthetic_data), "--workdir",
                     str(tmp_path / "s2"), "--stage1-checkpoint", str(s1), "--steps", "1",
                     *QUICK])
    err = capsys.readouterr().err
    assert code == 2 and "never trained" in err
    assert "stage2.hue_mode=constant" in err and "stage2.sky_loss=false" in err
    s2 = tmp_path / "s2ok"
    assert cli.main(["train", "stage2", "--data", str(synthetic_data), "--workdir", str(s2),
                     "--stage1-checkpoint", str(s1), "--steps", "1", *QUICK,
                     "stage2.hue_mode=constant", "stage2.sky_loss=false"]) == 0
    err = capsys.readouterr().err
    assert "segmentation_branch" in err and "'labeled_frames': 0" in err
    with open(s2 / "metrics.jsonl") as f:
        info = {k: v for ln in f if '"info"' in ln for k, v in json.loads(ln).items()}
    assert info["segmentation_branch"]["labeled_frames"] == 0 and info["sky_loss"] == "off"
    # ... and its evaluation says so too
    assert cli.main(["eval", "--workdir", str(s2), "--data", str(synthetic_data)]) == 0
    assert "segmentation branch of this model was never trained" in capsys.readouterr().out
    with open(s2 / "eval_test.json") as f:
        assert json.load(f)["segmentation_branch"]["labeled_frames"] == 0


@pytest.mark.parametrize("override, stored", [("unet.raw_scale=fixed", "percentile"),
                                              ("unet.use_rgg=false", "true"),
                                              ("unet.widths=(4, 8)", "(4, 4)"),
                                              ("data.raw_bits=16", "14-bit")])
def test_stage2_refuses_another_stage1_setting(stage1_run, synthetic_data, tmp_path, capsys,
                                               override, stored):
    key = override.split("=")[0]
    assert key in STAGE1_MODEL_KEYS
    work = tmp_path / "s2"
    code, _, err = run(["train", "stage2", "--data", synthetic_data, "--workdir", work,
                        "--steps", 1, "--stage1-checkpoint", stage1_run, *QUICK, override], capsys)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("irdepth: error: "), err
    assert str(stage1_run) in lines[0] and override.replace(" ", "") in lines[0].replace(" ", "")
    assert stored in lines[0], lines[0]
    assert not work.exists()
