"""Stage II evaluation: alignment, non-finite predictions and the protocol in the tables."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from irdepth_jax import evaluate, evaluators
from irdepth_jax.config import get_config
from irdepth_jax.train.parallel import DataParallel


def raw_as_depth(cfg, variables, batch):
    """A stand-in Stage II model: depth = raw / 100, NaN where raw is 0."""
    raw = batch["raw14"].astype(jnp.float32)
    return {"depth": jnp.where(raw == 0, jnp.nan, raw / 100.0)}


@pytest.fixture
def fake_model(monkeypatch):
    evaluators._eval_step.cache_clear()  # compiled steps are cached per (dp, kind, cfg)
    monkeypatch.setitem(evaluators._PREDICT, "stage2", raw_as_depth)
    yield
    evaluators._eval_step.cache_clear()


def frame(raw, condition):
    return {"raw14": np.asarray(raw, np.uint16), "depth": np.full((4, 5), 10.0, np.float32),
            "valid": np.ones((4, 5), bool), "condition": condition}


def test_evaluate_stage2_aligns_and_reports_nonfinite_predictions(fake_model):
    broken = np.full((4, 5), 1000)
    broken[2, 3] = 0
    # Predictions: 10 m (exact), 20 m (twice too far), 10 m with one NaN pixel; gt 10 m.
    dataset = [frame(np.full((4, 5), 1000), "day"), frame(np.full((4, 5), 2000), "day"),
               frame(broken, "night")]
    cfg, dp = get_config("tiny"), DataParallel("single")
    plain = evaluators.evaluate_stage2(cfg, None, {}, dataset, [0, 1, 2], dp)
    assert plain["day"]["abs_rel"] == pytest.approx(0.5)
    median = evaluators.evaluate_stage2(cfg, None, {}, dataset, [0, 1, 2], dp, align="median")
    assert median["day"]["abs_rel"] == pytest.approx(0.0) and median["day"]["d1"] == 1.0
    for group in ("all", "night"):
        assert math.isnan(median[group]["abs_rel"]) and math.isnan(median[group]["d1"])
        assert (median[group]["nonfinite_pixels"], median[group]["nonfinite_images"]) == (1, 1)
    assert median["day"]["nonfinite_images"] == 0

    result = {"stage": "stage2", "split": "test_day", "stage1": None, "stage2": median,
              "protocol": {"stride": 10, "frames": 3, "align": "median", "clamp": [1e-3, 80.0]}}
    text = evaluate.format_tables(result)
    assert ("Protocol: 3 images (frames[0:-1:10] of the split); depth: alignment median, "
            "predictions clamped to [0.001, 80] m") in text
    warning = "the model predicted non-finite depth (NaN / inf) on 1 pixels of 1 of 3 images"
    assert evaluate.nonfinite_warning(result).startswith(warning)
    assert f"**Warning: {warning}" in text
    header = next(ln for ln in text.splitlines() if ln.startswith("| condition"))
    assert header.endswith("| silog | nonfinite_pixels | nonfinite_images | images |")
    assert "| night | - |" in text and "| 1 | 1 | 1 |" in text

    clean = evaluators.evaluate_stage2(cfg, None, {}, dataset, [0, 1], dp, align="median")
    result.update(stage2=clean, protocol=dict(result["protocol"], stride=1, frames=2))
    text = evaluate.format_tables(result)
    assert evaluate.nonfinite_warning(result) is None
    assert "nonfinite" not in text and "Warning" not in text and "(every frame of" in text
