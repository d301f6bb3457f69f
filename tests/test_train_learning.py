"""The method learns: `workflow.train_and_evaluate` (what `irdepth quickstart` runs) improves
Stage I PSNR / SSIM / mIoU and Stage II d1 / AbsRel clearly over the same models untrained.

The fast test (default suite) checks the session's shortened tiny run (conftest `learned_run`,
also what the quickstart notebook test shows); the slow one
(`python -m pytest -m slow tests/test_train_learning.py`, 2-4 minutes) the whole `tiny` preset,
as the quickstart does.
"""

import pytest

from irdepth_jax.config import get_config
from irdepth_jax.workflow import train_and_evaluate


def learned(cfg, workdir):
    """(before, after) test-split metrics of Stage I and Stage II."""
    result = train_and_evaluate(cfg, str(workdir), devices=1, progress=False,
                                log=lambda line: None)
    return result["before"], result["after"]


def test_shortened_tiny_run_learns(learned_run):
    """`trained_runs.LEARNING`: 48 frames of 32x48, 4 epochs per phase (the session's run)."""
    _, result = learned_run
    before, after = result["before"], result["after"]
    # Measured (seed 0): PSNR 13.6 -> 16.2 dB, SSIM 0.23 -> 0.54, mIoU 0.017 -> 0.16,
    # d1 0.08 -> 0.51, AbsRel 4.0 -> 0.28.
    assert after["stage1"]["psnr"] > before["stage1"]["psnr"] + 1.5
    assert after["stage1"]["ssim"] > before["stage1"]["ssim"] + 0.15
    assert after["stage1"]["miou"] > before["stage1"]["miou"] + 0.08
    assert after["stage2"]["d1"] > before["stage2"]["d1"] + 0.25
    assert after["stage2"]["abs_rel"] < 0.5 * before["stage2"]["abs_rel"]


@pytest.mark.slow
def test_tiny_preset_learns(tmp_path):
    before, after = learned(get_config("tiny"), tmp_path / "w")
    # Measured (seed 0): PSNR 14.8 -> 18.0 dB, SSIM 0.43 -> 0.71, mIoU 0.02 -> 0.40,
    # d1 0.08 -> 0.64. Thresholds leave room for run-to-run and platform differences.
    assert after["stage1"]["psnr"] > before["stage1"]["psnr"] + 2.0
    assert after["stage1"]["ssim"] > before["stage1"]["ssim"] + 0.15
    assert after["stage1"]["miou"] > before["stage1"]["miou"] + 0.2
    assert after["stage2"]["d1"] > before["stage2"]["d1"] + 0.35
    assert after["stage2"]["abs_rel"] < 0.5 * before["stage2"]["abs_rel"]
